"""Where a run's samples go: an HDF5 file (the layout of layout.py is a contract, see README
"Outputs") or memory (the Python API).

The HDF5 file is written by rank 0 under a temporary name `OUT.h5.partial` while the run goes,
samples streamed in blocks (memory stays flat however long the run), and renamed to OUT.h5 only
when it is complete: a crash leaves a `.partial` file, never one that looks finished, and never
touches an existing OUT.h5 (a successful rerun replaces it).
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import socket
import time

import h5py
import numpy as np

from . import __version__, layout
from .errors import (PARKED, WRITE_ERRORS, InputError, lock_problem, not_a_regular_file, park, process_gone,
                     temporary_path)

BLOCK = 1024  # samples buffered between writes


def check_output_path(path: str, inputs=(), replaceable=None, kind: str = "a dbf-hpc output",
                      beside: str | None = None) -> str:
    """Refuse, before any work, an output that cannot or must not be written: a directory, a file in
    a missing or read-only directory, one of the run's inputs ((what, path) pairs), or an existing
    file that `replaceable(path)` (default: is_dbf_output) does not accept: a successful run
    replaces only its own kind of file (`kind`, as the refusal names it). replaceable=False accepts any
    existing regular file (CSV, PNG); a pipe, socket or device is never replaced. `beside`: the output
    that `path` is written beside (OUT.h5 of OUT.h5.partial), which the refusal of a directory names."""
    folder = os.path.dirname(os.path.abspath(path))
    if beside is not None and os.path.isdir(path):   # red team: "give a file name, e.g. 'OUT.h5.partial/out.h5'"
        raise InputError(f"output {beside!r}: {path!r}, which the run writes beside it, is a directory: remove it or "
                         f"choose another output name")
    if os.path.isdir(path):
        raise InputError(f"output {path!r} is a directory: give a file name, e.g. {os.path.join(path, 'out.h5')!r}")
    if path.endswith(os.sep):   # red team: "out.h5/" was refused as "'out.h5/.partial': directory 'out.h5' does not exist"
        raise InputError(f"output {path!r} ends in {os.sep!r}, as a directory's name does: give a file name, e.g. "
                         f"{path.rstrip(os.sep) or 'out.h5'!r}")
    if os.path.exists(folder) and not os.path.isdir(folder):   # red team: "directory 'x.h5' does not exist"
        raise InputError(f"output {path!r}: {folder!r} is not a directory")
    if not os.path.isdir(folder):
        raise InputError(f"output {path!r}: directory {folder!r} does not exist")
    if not os.access(folder, os.W_OK):
        raise InputError(f"output {path!r}: directory {folder!r} is not writable")
    if not os.path.exists(path):
        return path
    if not os.path.isfile(path):   # red team: a named pipe there hung the look below (its open waits for a writer)
        raise InputError(f"output {path!r} exists and is not a regular file (a pipe, socket or device): choose another "
                         f"name")
    if not os.access(path, os.R_OK):   # red team: another user's output "is not a dbf-hpc output: remove it"
        raise InputError(f"output {path!r} exists and this user may not read it (permission denied), so whether "
                         f"dbf-hpc wrote it cannot be told: choose another name, or ask its owner")
    for what, source in inputs:
        if source and os.path.exists(source) and os.path.samefile(path, source):
            raise InputError(f"output {path!r} is the {what} this run reads: choose another output name")
    if replaceable is not False and not (replaceable or is_dbf_output)(path):
        shapes = (" (it holds the mode shapes of a `dbf-hpc basis --xdmf`)"
                  if replaceable is None and is_dbf_shapes(path) else "")
        raise InputError(f"output {path!r} exists and is not {kind}{shapes}: remove it or choose another name")
    return path


# The largest pid Linux gives (pid_max's limit, 2**22): a name holding a pid is at most this long
LONGEST_PID = "4194304"


def check_name_length(path: str, beside: list, what: str = "output") -> None:
    """Refuse, before any work, an output whose name fits its folder but one of the names `beside` (the
    files written next to it: OUT.h5.checkpoint.tmp ...) would not (longer than the folder's NAME_MAX,
    in bytes). Red team: a 241-byte output name was accepted, and every run of it (--resume too) failed at
    its first checkpoint, "File name too long"."""
    folder = os.path.dirname(os.path.abspath(path))
    try:
        limit = os.pathconf(folder, "PC_NAME_MAX")
    except (OSError, ValueError):
        limit = 255
    size = len(os.fsencode(os.path.basename(path)))
    longest = max(beside, key=lambda name: len(os.fsencode(os.path.basename(name))))
    over = len(os.fsencode(os.path.basename(longest))) - limit
    if over > 0:
        raise InputError(f"{what} {path!r}: a name of {size} bytes, too long for the files written beside it "
                         f"({os.path.basename(longest)[size:]!r} added to it would exceed the {limit} bytes a name "
                         f"may have there): give a name of at most {size - over} bytes")


def check_replaced_name(path: str, suffix: str = "", what: str = "output") -> None:
    """Refuse, before any work, an output written through a temporary file (errors.replacing: a CSV, a
    PNG, an XDMF file) whose temporary name would be too long for its folder. Red team: `stiffness -o`
    and `--plot`, `basis --xdmf` with a 245-byte name solved everything, then failed "File name too
    long". Not collective."""
    check_name_length(path, [temporary_path(path, suffix, pid=LONGEST_PID)], what)


def free_bytes(folder: str) -> int:
    stat = os.statvfs(folder)
    return stat.f_bavail * stat.f_frsize


def check_free_space(path: str, needed: float, what: str = "output") -> None:
    """An InputError before writing `needed` bytes to `path` if its file system has not that much
    free (with 10 % and 1 MiB to spare): a disk that fills while HDF5 writes cannot be recovered from
    cleanly."""
    folder = os.path.dirname(os.path.abspath(path))
    free = free_bytes(folder)
    # the line gives what is asked with its room to spare (red team: "needs about 1.84 MiB and ... has
    # 2.99 MiB free" refused a run, the free space more than the need it named)
    asked = 1.1 * needed + 2**20
    if free < asked:
        raise InputError(f"{what} {path!r} needs about {needed / 2**20:.3g} MiB, {asked / 2**20:.3g} MiB with "
                         f"room to spare, and {folder!r} has {free / 2**20:.3g} MiB free: free some space, write "
                         f"elsewhere, or sample less often ([output] sample_dt)")


# Per snapshot, besides its values: one dataset of node vectors (its HDF5 header) and its XDMF grid
SNAPSHOT_OVERHEAD_BYTES = 2 * 2**10


def output_bytes(samples: int, constraint_values: int, probes: int, r: int, snapshots: int, field: int) -> float:
    """The size of a run's output: its series, snapshots (the field's values and its node vectors,
    at most 3 a point, each snapshot a dataset) and fixed data (8 bytes a value). Red team: without
    the node vectors and headers, 5000 snapshots of the paper's beam were estimated at 5.7 MB and
    took 23 MB."""
    per_sample = 1 + 4 * constraint_values + probes + 2 * r
    return (8.0 * (samples * per_sample + 4 * snapshots * field + r * r * 3 + 64 * constraint_values)
            + snapshots * SNAPSHOT_OVERHEAD_BYTES + 64 * 2**10)


def has_hdf5_signature(path: str) -> bool:
    """Whether the file starts with HDF5's signature: a damaged HDF5 file does, another kind does not."""
    if not os.path.isfile(path):   # a named pipe's open waits for a writer for ever
        return False
    try:
        with open(path, "rb") as f:
            return f.read(8) == b"\x89HDF\r\n\x1a\n"
    except OSError:
        return False


def _written_by_us(path: str, ours, damaged: bool = False) -> bool:
    """Whether `path` is an HDF5 file that `ours` (given the open file) accepts; with `damaged`, also a
    damaged HDF5 file (a write that failed on a full disk: a run's own .partial or checkpoint).
    Another kind of file is not ours. A file system that refuses locks is one line, never "not ours"
    (that would advise removing a good file). A file that opens but whose metadata `ours` cannot read
    (h5py's RuntimeError: "Unable to get link info (bad local heap signature)") is a damaged one:
    red team, a rerun onto a damaged output was "internal error (RuntimeError)". A path that is not a
    regular file is not ours, and is not opened (red team: a named pipe at a checkpoint hung --resume in
    the open, which waits for a writer)."""
    if not os.path.isfile(path):
        return False
    try:
        with h5py.File(path, "r") as f:
            try:
                return bool(ours(f))
            except (RuntimeError, KeyError):
                return damaged
    except (OSError, ValueError) as e:
        if lock_problem(e):
            raise InputError(f"cannot open {path!r}: {lock_problem(e)}") from None
        return damaged and has_hdf5_signature(path)


def is_dbf_output(path: str) -> bool:
    """Whether `path` is an HDF5 file dbf-hpc wrote as a run's output or a sweep summary (not the
    mode shapes of `basis --xdmf`: a run must not replace those)."""
    return _written_by_us(path, lambda f: ("dbf_hpc_version" in f.attrs or "sweep" in f.attrs)
                          and not _shapes(f))


def is_dbf_shapes(path: str) -> bool:
    """Whether `path` is the HDF5 file of an earlier `basis --xdmf` (its mode shapes)."""
    return _written_by_us(path, _shapes)


def _shapes(f) -> bool:
    return "dbf_hpc_version" in f.attrs and "shapes" in f and "time" not in f


def is_dbf_partial(path: str) -> bool:
    """Whether `path` can be a run's unfinished output (OUT.h5.partial) dbf-hpc wrote."""
    return _written_by_us(path, lambda f: "complete" in f.attrs or "dbf_hpc_version" in f.attrs, damaged=True)


def is_dbf_checkpoint(path: str) -> bool:
    """Whether `path` can be a checkpoint (OUT.h5.checkpoint) dbf-hpc wrote: sealed as one (read
    without HDF5, which may crash on a damaged file), or an older one's attributes."""
    from .checkpoint import SEAL

    if not os.path.isfile(path):   # a named pipe's open waits for a writer for ever
        return False
    try:
        with open(path, "rb") as f:
            if f.read(len(SEAL)) == SEAL:
                return True
    except OSError:
        pass
    return _written_by_us(path, lambda f: str(f.attrs.get("format", "")).startswith("dbf-hpc-checkpoint"),
                          damaged=True)


def series_shapes(constraint_shape: tuple, n_probes: int, r: int) -> dict:
    """The shape of one sample of each series (constraint_shape: (N_L,) or (N_L, d); n_probes: P,
    or the shape (P, 2) of the probes of a beam of two planes)."""
    probe_shape = (n_probes,) if isinstance(n_probes, (int, np.integer)) else tuple(n_probes)
    shapes = {layout.TIME: (), layout.PROBE_DISPLACEMENT: probe_shape, layout.REDUCED_Q: (r,),
              layout.REDUCED_QDOT: (r,)}
    for name in (layout.CONSTRAINT_DISPLACEMENT, layout.CONSTRAINT_VELOCITY, layout.CONSTRAINT_FORCE,
                 layout.CONSTRAINT_FORCE_PEAK):
        shapes[name] = tuple(constraint_shape)
    return shapes


# The locks this process holds (OutputLock.acquire adds, release removes): the command removes them
# before it aborts the job (cli: a termination signal outside an integration on several ranks, a
# rank's error while another is stuck), where no `finally` runs (red team: SIGTERM during the basis
# on 2 ranks left OUT.h5.lock beside the output)
HELD: dict = {}


def release_held_locks(others: bool = True) -> None:
    """Remove every lock this process holds (its own only: the file still names this process), and
    with `others` those rank 0 of this job holds that this rank knows of (OutputLock.expect: a rank
    that aborts the job ends rank 0 too, which may be stuck where it cannot remove its own). Not
    collective."""
    for lock in list(HELD.values()):
        if others or not lock.shared:
            lock.release()


def _process_start(pid: int) -> str | None:
    """When process `pid` of this host started, as "BOOT/TICKS" (the kernel's boot id and the process's
    start in clock ticks since that boot: /proc), or None where that cannot be read (not Linux, no
    such process). Two processes that ever held one pid on one host differ in it: a lock's job is
    told from a later process that was given its pid, also after a reboot (red team: a lock naming a
    killed job's pid blocked every later job for as long as another process had that pid)."""
    try:
        with open("/proc/sys/kernel/random/boot_id") as f:
            boot = f.read().strip()
        with open(f"/proc/{int(pid)}/stat") as f:
            ticks = f.read().rsplit(")", 1)[1].split()[19]   # field 22, starttime (the fields after comm from 3)
        return f"{boot}/{ticks}"
    except (OSError, IndexError, ValueError):
        return None


def lock_owner() -> str:
    """What this process writes into the locks it takes: "HOST PID START\n" (START: _process_start,
    "-" where unknown). Every rank of a job learns rank 0's before rank 0 takes a lock
    (OutputLock.expect)."""
    return f"{socket.gethostname()} {os.getpid()} {_process_start(os.getpid()) or '-'}\n"


# s after which a lock with no content counts as stale: acquire writes the host and pid the moment it
# creates the file, so an empty one that old was left by a job killed in between (SIGKILL)
EMPTY_LOCK_AGE = 60.0


def _lock_text(path: str) -> str:
    """A lock file's text; an OSError where it is not a regular file: opening a named pipe there waited
    for a writer for ever (red team: a FIFO at OUT.h5.lock hung the run before any work)."""
    if not os.path.isfile(path):
        raise OSError(errno.EINVAL, f"{path} is not a regular file")
    with open(path) as f:
        return f.read()


class OutputLock:
    """An exclusive claim on an output: `PATH.lock`, created atomically (O_CREAT | O_EXCL works on
    NFS and Lustre, where HDF5's own file locking is often switched off), holding the host and pid
    of the job and when its process started (lock_owner). A second job on the same output is refused;
    a lock whose job is gone (same host, no such process, or another process started since under its
    pid) is taken over. Rank 0 only. A lock made is registered in HELD at once (before its content is
    written), so that a stop at any point removes it; the other ranks know it before it is made
    (expect)."""

    def __init__(self, path: str, what: str = "output"):
        self.path, self.lock, self.what = path, f"{path}.lock", what
        self.held, self.owner, self.written, self.shared = False, None, False, False

    def expect(self, comm) -> None:
        """Every rank of `comm` learns the lock rank 0 is about to take (collective, before rank 0's
        acquire): the content rank 0 will write (lock_owner). A rank that aborts the job removes the
        lock if it holds that content (release_held_locks), as rank 0 may not get to: it may be
        blocked in a collective call, where its signal handler does not run, until mpirun kills it.
        Red team: when the lock was shared only after rank 0 took it, a SIGTERM to rank 1 just before
        (a job's first seconds) left OUT.h5.lock behind. If rank 0 does not get the lock, the other
        ranks forget() it; a lock another job holds names that job, so it is never removed. Rank 0's
        own release stays the normal way; the others end with forget()."""
        world = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
        # an allgather, not a bcast: rank 0 goes on to take the lock only once every rank has it (a
        # bcast's root returns at once, and a rank stopped before it never learnt it: red team, measured)
        owner = world.allgather(lock_owner() if world.rank == 0 else None)[0]
        if world.rank != 0:
            self.held, self.owner, self.written, self.shared = True, owner, True, True
            HELD[id(self)] = self

    def forget(self) -> None:
        """Stop knowing a lock another rank holds (expect), without touching it."""
        HELD.pop(id(self), None)
        self.held = self.shared = False

    def acquire(self) -> None:
        owner = lock_owner()
        for _ in range(3):
            try:
                fd = os.open(self.lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                stale = self._stale()
                if stale is not None:   # "" too: an empty lock
                    self._take_over(stale)
                    continue
                raise InputError(self._not_a_lock() or self._busy(self._holder())) from None
            except OSError as e:
                raise InputError(f"{self.what} {self.path!r}: cannot create {self.lock}: {e.strerror or e}") from None
            self.held, self.owner, self.written = True, owner, False
            HELD[id(self)] = self
            try:
                with os.fdopen(fd, "w") as f:
                    f.write(owner)
                self.written = True
            except OSError as e:
                self.release()
                raise InputError(f"{self.what} {self.path!r}: cannot write {self.lock}: {e.strerror or e}") from None
            except BaseException:   # a termination signal (errors.Interrupted) between the create and the write
                self.release()
                raise
            return
        raise InputError(f"{self.what} {self.path!r}: cannot take the lock {self.lock}; remove it if no job runs")

    def _not_a_lock(self) -> str | None:
        """The refusal of a lock path that is no regular file (a directory, a link to a missing file): no
        job made it. Red team: it was "being written by another job (unknown job)"."""
        kind = not_a_regular_file(self.lock)
        if kind is None or kind.startswith("does not exist"):
            return None
        return f"{self.what} {self.path!r}: its lock {self.lock!r} {kind}, which no dbf-hpc job made: remove {self.lock}"

    def _busy(self, holder: str) -> str:
        return (f"{self.what} {self.path!r} is being written by another job ({holder}); wait for it, or remove "
                f"{self.lock} if that job is gone")

    def refuse_if_held(self) -> None:
        """An InputError naming the holder (acquire's line) if a live job holds the lock. For a look at
        the output's files before acquire: HDF5's own lock refuses to open the .partial the holder is
        writing, and that line named neither the job nor its lock (red team). Not collective."""
        holder = self.live_holder()
        if holder is not None:
            raise InputError(self._busy(holder))

    def _holder(self) -> str:
        try:
            text = _lock_text(self.lock)
            if not text.strip():
                return (f"an empty lock, made by a job now starting or killed as it made it; it counts as gone "
                        f"{EMPTY_LOCK_AGE:g} s after it was made")
            host, pid = text.split()[:2]
            return f"pid {int(pid)} on {host}"
        except (OSError, ValueError):
            return "unknown job"

    def live_holder(self) -> str | None:
        """The job holding the lock ("pid N on HOST") if the lock exists and its job is not known to
        be gone (on another host it cannot be told), else None. Not collective."""
        if not os.path.isfile(self.lock) or self._stale() is not None:
            return None
        return self._holder()

    def _stale(self) -> str | None:
        """The lock's content when its job is gone: it ran on this host and its process no longer
        exists, is a zombie (which a killed job's rank can stay as where nothing reaps it), or is
        another process that got its pid later (its start, lock_owner, differs; a lock of an older
        dbf-hpc, "HOST PID", has none to compare)."""
        try:
            text = _lock_text(self.lock)
            if not text.strip():   # made, never written: its job was killed between the two (red team), or is
                # writing it now, which takes microseconds: older than EMPTY_LOCK_AGE it is gone
                return text if time.time() - os.stat(self.lock).st_mtime > EMPTY_LOCK_AGE else None
            host, pid, *start = text.split()
            if host != socket.gethostname() or len(start) > 1:
                return None
            if process_gone(int(pid)):
                return text
            if start and start[0] != "-" and _process_start(int(pid)) not in (None, start[0]):
                return text   # pid reused since (or the host rebooted): the lock's process is gone
            return None
        except (OSError, ValueError):
            return None

    def _take_over(self, stale: str) -> None:
        """Remove the stale lock whose content is `stale`, and only it. Two jobs may find it stale at
        once: the first moves it aside (an atomic rename) and makes its own; the second then moves
        aside the first's live lock, sees that it is not the stale one, and puts it back (red team:
        removing by name, both jobs held the lock once in 40 tries)."""
        aside = f"{self.lock}.stale-{socket.gethostname()}-{os.getpid()}"
        try:
            os.rename(self.lock, aside)
        except FileNotFoundError:   # another job moved it first
            return
        try:
            moved = _lock_text(aside)
            if moved != stale:
                os.link(aside, self.lock)   # a live lock: back in place (fails if yet another was made)
        except OSError:
            pass
        finally:
            os.remove(aside)

    def release(self) -> None:
        """Remove the lock if this process holds it (and its file is still ours: naming this process,
        or not yet written; a lock removed by hand and made again by another job stays, and so does one
        whose text is not even text). Raises nothing: rank 0 releases alone, and the other ranks wait in
        a barrier after it (run.claimed; red team: a lock file replaced by bytes that are not UTF-8
        raised UnicodeDecodeError on rank 0 alone there, and rank 1 waited for ever)."""
        HELD.pop(id(self), None)
        if self.held:
            try:
                ours = _lock_text(self.lock) == self.owner or not self.written
                if ours:
                    os.remove(self.lock)
            except FileNotFoundError:
                pass
            except (OSError, ValueError):   # (UnicodeDecodeError: not text, so not ours)
                pass
        self.held = False


class _Blocks:
    """Samples buffered as blocks of rows (a list of chunks, one array per series in each): a block of
    samples costs no copy until the series are assembled, once (the C callbacks hand over hundreds
    of samples at a time, and at small r the copies, not the arithmetic, are the cost)."""

    def __init__(self, shapes: dict):
        self.shapes = shapes
        self.chunks = []
        self.pending = 0

    def append(self, **values) -> None:
        self.chunks.append({name: np.array(values[name], dtype=float).reshape((1, *shape))
                            for name, shape in self.shapes.items()})
        self.pending += 1

    def append_rows(self, **blocks) -> None:
        """Several samples at once: each value has one row per sample. The arrays are kept, not
        copied: the caller hands them over."""
        count = len(blocks[layout.TIME])
        self.chunks.append({name: np.asarray(blocks[name], dtype=float).reshape((count, *shape))
                            for name, shape in self.shapes.items()})
        self.pending += count

    def series(self, name: str) -> np.ndarray:
        """The buffered samples of one series as one new array."""
        if not self.chunks:
            return np.zeros((0, *self.shapes[name]))
        return np.concatenate([chunk[name] for chunk in self.chunks])

    def clear(self) -> None:
        self.chunks, self.pending = [], 0


class MemoryWriter:
    """Samples kept in memory, for runs from Python (OutputWriter's interface without a file)."""

    def __init__(self, constraint_shape: tuple, n_probes: int, r: int):
        self.shapes = series_shapes(constraint_shape, n_probes, r)
        self.blocks = _Blocks(self.shapes)

    @property
    def count(self) -> int:
        return self.blocks.pending

    @property
    def pending(self) -> int:
        """Samples not yet written: none (memory is where they go)."""
        return 0

    def append(self, **values) -> None:
        self.blocks.append(**values)

    def append_rows(self, **blocks) -> None:
        self.blocks.append_rows(**blocks)

    def flush(self) -> None:
        pass

    def series_data(self, name: str) -> np.ndarray:
        """A new array of the series' samples so far."""
        return self.blocks.series(name)


class OutputWriter:
    """Rank 0's writer of one run's HDF5 output: the series of layout.SERIES streamed, the
    fixed-size data and the attributes at `finish`."""

    def __init__(self, path: str, constraint_shape: tuple, n_probes: int, r: int):
        self.path = path
        self.partial = f"{path}.partial"
        try:
            self.file = h5py.File(self.partial, "w")
        except OSError:   # HDF5 creates the file before it locks it: no empty .partial is left
            if os.path.isfile(self.partial) and os.path.getsize(self.partial) == 0:
                os.remove(self.partial)
            raise
        self.file.attrs["complete"] = False
        shapes = series_shapes(constraint_shape, n_probes, r)
        # Zero-width series (no constraints, no probes) are written empty at the end: HDF5 cannot
        # chunk a zero-size dimension.
        self.empty = [name for name, shape in shapes.items() if 0 in shape]
        self.series = {}
        for name in layout.SERIES:
            if name not in self.empty:
                shape = shapes[name]
                self.series[name] = self.file.create_dataset(name, shape=(0, *shape), maxshape=(None, *shape),
                                                             chunks=(BLOCK, *shape), dtype="f8")
        self.shapes = shapes
        self.blocks = _Blocks({name: shapes[name] for name in self.series})
        self.hashes = {name: hashlib.sha256() for name in self.series}
        self.count = 0
        self.parked = False

    @property
    def pending(self) -> int:
        """Samples buffered, not yet written."""
        return self.blocks.pending

    def append(self, **values) -> None:
        self.blocks.append(**values)
        if self.blocks.pending >= BLOCK:
            self.flush()

    def append_rows(self, **blocks) -> None:
        """Several samples at once: each value has one row per sample."""
        self.blocks.append_rows(**blocks)
        if self.blocks.pending >= BLOCK:
            self.flush()

    def flush(self) -> None:
        n = self.blocks.pending
        if not n:
            return
        for name, dataset in self.series.items():
            block = np.ascontiguousarray(self.blocks.series(name), dtype=np.float64)
            dataset.resize(self.count + n, axis=0)
            dataset[self.count:] = block
            self.hashes[name].update(block.tobytes())
        self.blocks.clear()
        self.count += n
        self.file.flush()

    def digest(self) -> np.ndarray:
        """sha256 of the samples written so far (not those buffered), as 32 bytes: a checkpoint keeps
        it, so that a resume continues these samples and no others."""
        h = hashlib.sha256()
        for name in sorted(self.hashes):
            h.update(name.encode() + self.hashes[name].digest())
        return np.frombuffer(h.digest(), dtype=np.uint8).copy()

    @classmethod
    def reopen(cls, path: str, samples: int, digest) -> "OutputWriter":
        """Continue a .partial file from a checkpoint: keep its first `samples` samples, which must be
        those the checkpoint's run wrote (`digest`, OutputWriter.digest), not another run's or edited
        ones."""
        self = cls.__new__(cls)
        self.path, self.partial = path, f"{path}.partial"
        self.file = h5py.File(self.partial, "r+")
        try:
            if self.file.attrs.get("complete", True):
                raise ValueError("not an incomplete dbf-hpc output")
            self.series, self.empty = {}, []
            for name in layout.SERIES:
                if name not in self.file:  # zero-width series are only written at the end
                    self.empty.append(name)
                    continue
                dataset = self.file[name]
                if dataset.shape[0] < samples:
                    raise ValueError(f"{name} holds {dataset.shape[0]} samples, the checkpoint {samples}")
                self.series[name] = dataset
            if digest is None:
                raise ValueError("its checkpoint was written by an older dbf-hpc, without the samples' checksum")
            # checked before anything is cut: a refused resume leaves the .partial as it was (red team)
            self.hashes = {name: hashlib.sha256() for name in self.series}
            for name, dataset in self.series.items():
                for lo in range(0, samples, 64 * BLOCK):
                    block = dataset[lo:min(lo + 64 * BLOCK, samples)]
                    self.hashes[name].update(np.ascontiguousarray(block, dtype=np.float64).tobytes())
            self.count = samples
            if not np.array_equal(self.digest(), np.asarray(digest, dtype=np.uint8)):
                raise ValueError("its samples are not those its checkpoint's run wrote (another run's, or edited)")
            for dataset in self.series.values():
                dataset.resize(samples, axis=0)
            # what a finish stopped halfway wrote (a full disk): the resumed finish writes it again
            written = []
            self.file.visititems(lambda name, obj: written.append(name)
                                 if isinstance(obj, h5py.Dataset) and name not in self.series else None)
            for name in written:
                del self.file[name]
        except Exception:
            self.file.close()
            raise
        self.blocks = _Blocks({name: self.file[name].shape[1:] for name in self.series})
        self.parked = False
        return self

    def series_data(self, name: str) -> np.ndarray:
        """A series as written so far (rank 0 reads back what it streamed out)."""
        self.flush()
        if name in self.empty:
            return np.zeros((self.count, 0))
        return self.series[name][...]

    def finish(self, datasets: dict, attrs: dict, dataset_attrs: dict | None = None) -> None:
        """Write the fixed-size data and the attributes (every dataset with its unit and meaning),
        close, and rename into place."""
        self.flush()
        for name in self.empty:
            self.file.create_dataset(name, shape=(self.count, 0), dtype="f8")
        for name, value in datasets.items():
            self.file.create_dataset(name, data=np.asarray(value))
        for name, (unit, meaning) in layout.DATASETS.items():
            if name in self.file:      # a dataset, or a group of datasets (the snapshots' vectors)
                self.file[name].attrs.update({"unit": unit, "description": meaning})
                if isinstance(self.file[name], h5py.Group):   # and each of its datasets (docs/outputs.md: every
                    for member in self.file[name].values():    # dataset; new-user pass: these had none)
                        member.attrs.update({"unit": unit, "description": meaning})
        for name, extra in (dataset_attrs or {}).items():
            self.file[name].attrs.update(extra)
        for key, value in attrs.items():
            self.file.attrs[key] = value if isinstance(value, (str, int, float, bool, np.number)) else json.dumps(value)
        self.file.attrs["dbf_hpc_version"] = __version__
        self.file.attrs["complete"] = True
        try:
            self.file.close()
        except WRITE_ERRORS:   # a full disk at the last flush: a second close crashed HDF5 (signal 11)
            self._park()
            raise
        os.replace(self.partial, self.path)

    def discard(self) -> None:
        """Close and remove the .partial without finishing it (a sweep's case whose output is not
        kept). A write that fails (a full disk) parks it (errors.park) and raises."""
        try:
            self.flush()
            self.file.close()
        except WRITE_ERRORS:
            self._park()
            raise
        os.remove(self.partial)

    def _park(self) -> None:
        park(self, self.file, self.series)
        self.series, self.blocks, self.parked = {}, _Blocks({}), True

    def abort(self, failed_write: bool = False) -> None:
        """Close after a failure, leaving only the .partial file (it says complete = False). If the
        file cannot be closed (a full disk), its objects are parked (errors.park). After a failed
        write (`failed_write`, or any HDF5 object parked in this process) it is parked, not closed: a
        close whose flush failed crashed HDF5 then (signal 11; red team, sweeps on a 3 MB tmpfs)."""
        if self.parked:
            return
        if failed_write or PARKED:
            self._park()
            return
        try:
            self.flush()
            self.file.close()
        except WRITE_ERRORS:  # the run already failed; keep its error, not this one
            self._park()
