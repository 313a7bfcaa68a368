"""The errors dbf_hpc raises on purpose.

Each carries one line for the user: what is wrong and what to change. The command prints that line
and exits non-zero; anything else is a bug and ends the whole MPI job. Nothing here is
collective but decided_on_rank0, from_rank0, agreed and wait_for_rank0: whoever raises makes sure every rank
raises the same error on the same path.
"""
import contextlib
import math
import numbers
import os
import sys


class DbfError(Exception):
    """An error the user can act on (bad input, a failed solve). Raised on every rank alike."""


class InputError(DbfError):
    """Bad input: a scene, a matrix file, an option."""


class Unresumable(InputError):
    """A checkpoint that is valid for this run, but whose .partial output cannot be continued (a
    failed write damaged it, or its samples are not the checkpoint's): only a fresh start helps."""


class SolverError(DbfError):
    """A numerical failure: non-convergence, breakdown, a diverged step."""


class WriteFailed(SolverError):
    """A write of the output or its checkpoint failed during the integration (a full disk): the file
    is parked, not closed (errors.park)."""


class Interrupted(SolverError):
    """A run stopped by a termination signal after writing its checkpoint: rerun to continue."""


def termination_signals() -> tuple:
    """The signals that stop a run as a batch system's time limit does (checkpoint, then one line):
    SIGTERM, and SIGINT (Ctrl-C) unless the process started with it ignored (a background job, as
    ranks under some launchers are). Red team: Ctrl-C during a run printed a KeyboardInterrupt
    traceback from the integrator's callback."""
    import signal

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        return (signal.SIGTERM,)
    return (signal.SIGTERM, signal.SIGINT)


class _Termination:
    """Whether this process received a termination signal during the integration under way: run.py's
    handlers set it on every rank (rank 0's also asks its own checkpoint), and the integrations tell
    rank 0 of another rank's (fom_integrator's control points, run.RemoteStop; a sweep's ranks tell
    each other, sweep._Stop). Red team: a SIGTERM to
    rank 1 alone of a 2-rank run was ignored, and the job ran on to its end."""

    requested = False
    # The command's output is complete, and every rank knows it (run.run, sweep.run_sweep): a termination
    # signal from now on is not acted on, the command ends at once (cli._terminated)
    finished = False


TERMINATION = _Termination()


class RankFailed(Exception):
    """Another rank's exception that could not be copied (errors.decided_on_rank0, agreed): its type and
    line. Not a DbfError: like the exception it stands for, it is a bug's, and ends the job."""


def _portable(exc: BaseException) -> bytes:
    """`exc` as bytes another rank rebuilds (_rebuilt): its class (by reference), args and attributes;
    where those do not survive the round trip, a RankFailed naming it. Not collective."""
    import pickle

    try:
        args = exc.args
        if isinstance(exc, OSError) and exc.filename is not None:   # (not in its args)
            args = (exc.errno, exc.strerror, exc.filename, *(() if exc.filename2 is None else (None, exc.filename2)))
        payload = pickle.dumps((type(exc), args, dict(getattr(exc, "__dict__", {}))))
        _rebuilt(payload, 0)   # checked here: a payload the other ranks cannot rebuild would fail there alone
        return payload
    except Exception:
        text = (str(exc).splitlines() or [""])[0]
        return pickle.dumps((RankFailed, (f"{type(exc).__name__}{': ' + text if text else ''}",), {}))


def _rebuilt(payload: bytes, origin: int) -> BaseException:
    """The exception _portable made bytes of, as rank `origin` raised it: same class, args and attributes
    (an exception class whose __init__ takes other arguments, such as modes.RepeatedCut, is made
    without calling it),
    marked with dbf_hpc_origin = origin (cli.main: the rank that raised it reports it). Not collective."""
    import pickle

    cls, args, state = pickle.loads(payload)
    try:
        exc = cls(*args)
    except TypeError:   # another __init__: made without it, its attributes set below
        exc = cls.__new__(cls, *args)
        exc.args = args
    try:
        exc.__dict__.update(state)
        exc.dbf_hpc_origin = origin
    except AttributeError:   # an exception type without a __dict__: its class and args are all it has
        pass
    return exc


def decided_on_rank0(comm, decide, *args):
    """decide(*args) on rank 0 of `comm` (petsc4py or mpi4py), its value given to every rank, or its
    exception raised on every rank: a check of files that each rank made itself could differ between
    the ranks' looks (a file edited or replaced meanwhile, a node that cannot read it), and one rank's
    refusal left the others waiting in their next collective call. Rank 0 raises its own exception;
    the others a copy of it (_rebuilt: the same class, message and attributes), so that every rank
    takes the same `except` clause: an InputError is every rank's one line, and an OSError, ValueError
    or KeyError (a bug, or an OS failure no check foresaw) ends the job on every rank (red team: only
    an InputError reached the other ranks; any other exception on rank 0 left them waiting in the
    broadcast for ever). Collective."""
    world = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
    value, caught = None, []
    if world.rank == 0:
        try:
            value = decide(*args)
        except BaseException as e:   # whatever it is, the other ranks hear of it
            caught.append(e)
    return from_rank0(world, value, caught)


def from_rank0(comm, value=None, caught: list | None = None):
    """The end of a block rank 0 of `comm` (petsc4py or mpi4py) ran alone: rank 0's `value` on every
    rank, or the exception rank 0 caught in it raised on every rank, as decided_on_rank0 does (rank 0
    its own, the others a copy: _rebuilt). `caught`: a list holding that exception on rank 0 (empty
    where there was none; the other ranks' is not looked at), emptied here: an exception kept in a variable of a
    frame its own traceback holds is a reference cycle, freed only by a garbage collection, on rank 0
    alone, and with it the PETSc objects those frames hold (red team: a full-order run's, freed as the
    process ended, on rank 0 alone, and PETSc's collective clean-up of its garbage hung the job's end).
    For a block that cannot be one decide() call, as the other ranks take part in it (cache.save: their
    rows sent to rank 0) or wait in their own way (run._run_reduced). Red team: such blocks passed on a
    DbfError or a write error, and any other exception (a bug, an h5py ValueError) left rank 0 alone
    with it and the others waiting in the broadcast after the block for ever (the Python API and a
    2-rank pytest pass do not abort the job as `python -m mpi4py` does). Collective."""
    world = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
    failure = caught.pop() if caught and world.rank == 0 else None
    try:
        value, payload = world.bcast((None, _portable(failure)) if failure is not None else (value, None), root=0)
        if failure is not None:
            raise failure
        if payload is not None:
            raise _rebuilt(payload, 0) from None
        return value
    finally:
        failure = None   # (the cycle above)


def agreed(comm, work, *args):
    """work(*args) on every rank of `comm` (petsc4py or mpi4py), each rank's value returned to it, or
    the first failing rank's exception, in rank order, raised on every rank (that rank's own, a copy
    elsewhere: decided_on_rank0). For what each rank must read itself (its rows of a file every rank
    parses): a file one node cannot see, or one replaced while the ranks read it, was that rank's error
    alone, and the others waited in the next collective call for ever (red team: a stiffness file
    missing on rank 1's view; and any exception but an InputError still was). Collective."""
    world = comm.tompi4py() if hasattr(comm, "tompi4py") else comm
    value = failure = None
    try:
        value = work(*args)
    except BaseException as e:
        failure = e
    payloads = world.allgather(None if failure is None else _portable(failure))
    origin = next((rank for rank, p in enumerate(payloads) if p is not None), None)
    if origin is None:
        return value
    try:
        if origin == world.rank:
            raise failure
        raise _rebuilt(payloads[origin], origin) from None
    finally:
        failure = None   # (a reference cycle otherwise: from_rank0)


def wait_for_rank0(world) -> None:
    """Block until rank 0 of the mpi4py communicator `world` arrives, sleeping instead of spinning (its
    integration may be long). Collective."""
    import time

    request = world.Ibarrier()
    while not request.Test():
        time.sleep(0.02)


# What writing a file can raise: the OS's errors, and h5py's RuntimeError when HDF5 cannot flush (a
# full disk shows as "errno = 28, error message = 'No space left on device'" inside it).
WRITE_ERRORS = (OSError, RuntimeError)


# The lists recording() yields: each warning is appended to every one open, on every rank
_RECORDINGS = []


@contextlib.contextmanager
def recording():
    """A list of the messages warn() gives while the block runs, on every rank alike (run.run: its
    output stores them, and a --resume of it shows them again)."""
    log = []
    _RECORDINGS.append(log)
    try:
        yield log
    finally:
        # this very list, by identity: list.remove compares by ==, and an inner recording that holds what the
        # outer one holds (both empty) removed the outer one (red team: the outer missed every later warning,
        # and its own exit raised "ValueError: list.remove(x): x not in list", a rerun sweep's internal error)
        del _RECORDINGS[next(i for i in range(len(_RECORDINGS) - 1, -1, -1) if _RECORDINGS[i] is log)]


def recorded() -> list:
    """The messages warned so far in the innermost recording() open, or [] outside one."""
    return list(_RECORDINGS[-1]) if _RECORDINGS else []


# The control characters one_line writes as escapes (all but the tab): a line break would split the one line, and
# a NUL or an escape sequence quoted from a name would reach the terminal or a log raw (red team: a sweep's axis
# "damping.zeta\u0000" was refused as "unknown key 'zeta<NUL>'", the NUL byte written to stderr)
_CONTROLS = {c: f"\\x{c:02x}" for c in [*range(0x09), *range(0x0b, 0x20), 0x7f]}
_CONTROLS.update({ord("\n"): "\\n", ord("\r"): "\\r"})


def one_line(text) -> str:
    """`text` on one line: a line break in it (a file name holding one, which a message quotes as given)
    written as \\n (\\r), any other control character but the tab as \\xNN, so that an error or a warning
    stays the one line of text the command promises. Not collective."""
    return str(text).translate(_CONTROLS)


def warn(message: str, comm, record: bool = True) -> None:
    """`dbf-hpc: warning: message` on stderr, from rank 0 of `comm` (petsc4py or mpi4py); stdout
    keeps the progress and the results. Not collective: every rank calls it on the same path (and
    records it in any recording() open, unless record is False: a line of the installation, not of
    the result, rom_integrator.say_fallback)."""
    for log in _RECORDINGS if record else ():
        log.append(message)
    rank = comm.getRank() if hasattr(comm, "getRank") else comm.rank
    if rank == 0:
        sys.stdout.flush()   # after the progress lines already printed
        print(f"dbf-hpc: warning: {one_line(message)}", file=sys.stderr, flush=True)


def is_number(value) -> bool:
    """A real number (numpy's too), not a bool; finite or not."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def check_number(where: str, value, minimum: float | None = None, above: bool = False, integer: bool = False):
    """`value` as a float (an int with integer=True), or one InputError naming `where` (e.g.
    "IntegratorSettings t_end"): a finite number (not a bool or a string), at least `minimum` (above
    it, with above=True). The Python API's dataclasses check what they are given with it; scenes are
    checked before they reach them."""
    kind = numbers.Integral if integer else numbers.Real
    if isinstance(value, bool) or not isinstance(value, kind) or not math.isfinite(value):
        raise InputError(f"{where} must be {'an integer' if integer else 'a finite number'}, got {value!r}")
    if minimum is not None and (value <= minimum if above else value < minimum):
        raise InputError(f"{where} must be {'above' if above else 'at least'} {minimum:g}, got {value!r}")
    return int(value) if integer else float(value)


# HDF5 locks the files it opens; where the file system refuses locks (some NFS and Lustre mounts)
# every open fails with ENOLCK, which read as "not an HDF5 file" (red team)
LOCK_HINT = ("the file system refuses HDF5's file locks: set HDF5_USE_FILE_LOCKING=FALSE in the environment "
             "(dbf-hpc's own .lock files still keep two jobs off one output)")


# HDF5's lock refused because another process holds the file open for writing (errno 11, EAGAIN):
# the locks work. Red team: a second run on an output being written, and `info` on a killed job's
# .partial while its rank was still exiting, read "the file system refuses HDF5's file locks: set
# HDF5_USE_FILE_LOCKING=FALSE", advice that lets a reader see a file half written.
BUSY_HINT = ("another process has it open for writing (a run still going, or a killed run's rank not yet "
             "ended): wait for it to end, then retry")


def lock_problem(exc: Exception) -> str | None:
    """Why an HDF5 open failed on its file lock (BUSY_HINT or LOCK_HINT), or None if it did not."""
    text = str(exc)
    if "unable to lock file" not in text:
        return None
    return BUSY_HINT if "errno = 11," in text else LOCK_HINT


def refused_lock(exc: Exception) -> bool:
    """Whether an HDF5 open failed on its file lock: the file system refused it, or another process
    holds the file (lock_problem says which)."""
    return lock_problem(exc) is not None


def write_failure(exc: Exception) -> str:
    """One line saying why a write failed."""
    if refused_lock(exc):
        return lock_problem(exc)
    text = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
    return "No space left on device" if "errno = 28" in text or "No space left" in text else text.splitlines()[0]


def temporary_tag(pid: int | str | None = None) -> str:
    """<host>-<pid> of this process (or of `pid`), for a temporary file's name: jobs on two hosts sharing
    a directory (a parallel file system) may have one pid (red team). Not collective."""
    import re
    import socket

    return f"{re.sub(r'[^A-Za-z0-9.-]', '_', socket.gethostname())}-{os.getpid() if pid is None else pid}"


def temporary_path(path: str, suffix: str = "", pid: int | str | None = None) -> str:
    """The temporary file `replacing` writes beside `path` (of this process, or of `pid`: the longest
    a name check must allow for is output.LONGEST_PID's)."""
    return f"{path}.tmp-{temporary_tag(pid)}{suffix}"


def not_a_regular_file(path: str) -> str | None:
    """Why `path` is no regular file to read, in words that follow it ("does not exist", "is a named
    pipe", "is a directory" ...), or None when it is one. A path that names a file and ends in '/' is
    said so. Not collective. Red team: `info` on a named pipe, a device or a broken link said "does not
    exist", and opening a named pipe waits for a writer for ever."""
    import stat

    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "is a symbolic link to a missing file" if os.path.islink(path) else "does not exist"
    except NotADirectoryError:
        trimmed = path.rstrip(os.sep)
        return (f"ends in {os.sep!r} but {trimmed!r} is a file" if path.endswith(os.sep) and os.path.isfile(trimmed)
                else "does not exist (a folder on its path is a file)")
    except (OSError, ValueError) as e:   # no permission on a folder, a loop of links, a name too long
        return f"cannot be looked at ({getattr(e, 'strerror', None) or e})"
    for test, kind in ((stat.S_ISREG, None), (stat.S_ISDIR, "is a directory"), (stat.S_ISFIFO, "is a named pipe"),
                       (stat.S_ISSOCK, "is a socket"), (stat.S_ISCHR, "is a character device"),
                       (stat.S_ISBLK, "is a block device")):
        if test(mode):
            return kind
    return "is not a regular file"


def read_regular_file(path: str) -> bytes:
    """The bytes of the regular file `path`, or an OSError (as open() raises, and one whose strerror
    says what the path is instead: a named pipe, a directory, a device). Never waits on a named pipe:
    it is opened without blocking and refused (red team: `dbf-hpc run FIFO` waited for a writer for
    ever). Not collective."""
    import errno
    import stat

    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = not_a_regular_file(path) or "is not a regular file"
            raise OSError(errno.EISDIR if stat.S_ISDIR(mode) else errno.EINVAL,
                          f"{kind.removeprefix('is ')}, not a regular file")
        with os.fdopen(fd, "rb") as f:
            fd = None
            return f.read()
    finally:
        if fd is not None:
            os.close(fd)


def process_gone(pid: int) -> bool:
    """Whether no process `pid` runs on this host (none, or a zombie: a killed job's rank can stay one
    where nothing reaps it)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except OSError:      # another user's process: it exists
        return False
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except (OSError, IndexError):
        return False


# A temporary file of the older name, PATH.tmp-<pid> (no host), untouched this long and whose pid is gone
# here is a killed job's; another host's job cannot be told from it, so a younger one is kept
STALE_TEMPORARY_S = 600.0


def remove_dead_temporaries(path: str, suffix: str = "") -> None:
    """Remove the temporary files of `path` (PATH.tmp-<host>-<pid>SUFFIX, as replacing names them) that a
    process of this host wrote and that is gone: a SIGKILL leaves them, as no `finally` runs (red team:
    `basis --xdmf` killed while writing left SHAPES.h5.tmp-<pid>). Files of a live process, of another
    host, or named otherwise are kept. Not collective."""
    import re

    remove_dead_temporaries_in(os.path.dirname(os.path.abspath(path)), re.escape(os.path.basename(path)),
                               re.escape(suffix))


def remove_dead_temporaries_in(folder: str, names: str, suffix: str = "") -> None:
    """remove_dead_temporaries for every file of `folder` whose name matches the regular expression
    `names` (and `suffix`, also one), listing the folder once: a sweep's case records
    (sweep._sweep). Not collective."""
    import re
    import time

    host = temporary_tag().rsplit("-", 1)[0]
    try:
        listed = os.listdir(folder)
    except OSError:
        return
    for name in listed:
        match = re.fullmatch(rf"(?:{names})\.tmp-(?:(.+)-)?(\d+)(?:{suffix})", name)
        if match is None:
            continue
        tmp = os.path.join(folder, name)
        try:
            ours = (match.group(1) == host if match.group(1) is not None
                    else time.time() - os.stat(tmp).st_mtime > STALE_TEMPORARY_S)
            if ours and process_gone(int(match.group(2))) and os.path.isfile(tmp):
                os.remove(tmp)
        except OSError:   # gone meanwhile, or not ours to remove: the write goes on
            pass


@contextlib.contextmanager
def replacing(path: str, suffix: str = "", clean: bool = True):
    """A temporary path beside `path` (ending in `suffix`) to write; when the block ends it replaces
    `path` by an atomic rename. On a failure the temporary file is removed, and a write error (a full
    disk, a read-only directory) becomes one DbfError naming `path` and the cause. With `clean`,
    temporary files of `path` that killed processes of this host left are removed first
    (remove_dead_temporaries: it lists the folder, which a writer of many small files in one folder,
    a sweep's case records, does not want per file)."""
    if clean:
        remove_dead_temporaries(path, suffix)
    tmp = temporary_path(path, suffix)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.remove(tmp)
        except OSError:
            pass
        if isinstance(e, OSError):
            raise DbfError(f"cannot write {path}: {write_failure(e)}") from None
        raise


def petsc_failure(exc: Exception) -> str:
    """One line from a petsc4py error: its code, the innermost PETSc function and PETSc's message
    (str(exc) is "error code N" and then PETSc's traceback, innermost last, message last)."""
    lines = [line.split("] ", 1)[-1].strip() for line in str(exc).splitlines()]
    code = getattr(exc, "ierr", None) or (lines[0] if lines else "?")
    calls = [line.split(" at ")[0] for line in lines[1:] if " at " in line and line.split(" at ")[0].endswith(")")]
    notes = [line for line in lines[1:] if line and " at " not in line]
    message = notes[-1] if notes else ""
    where = f" in {calls[-1]}" if calls else ""
    return f"PETSc error {code}{where}" + (f": {message}" if message else "")


# HDF5 1.10 (Debian 12) crashes when an h5py object whose file failed to flush is freed (measured:
# a full disk, then any close or garbage collection segfaults). Objects of a failed write are kept
# here instead, and the command exits without tearing h5py down (cli.main).
PARKED = []


def park(*objects) -> None:
    """Keep the h5py objects of a failed write alive for the rest of the process."""
    PARKED.extend(o for o in objects if o is not None)   # None: a file that never opened (nothing to keep)
