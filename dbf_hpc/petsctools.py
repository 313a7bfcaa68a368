"""Small PETSc helpers shared by the whole package: layouts, assembly from triplets, direct solvers,
scoped option defaults, reading rows of distributed vectors, and freeing what a caller owns.

Conventions (after petsc4py's demos and Firedrake's petsctools): every solver gets its own options
prefix; the code's defaults are put into the options database only where the user has not set
them and only for as long as the solver reads them (`options_defaults`); whoever creates a PETSc
object destroys it, also on error paths (`destroy`). Each helper's docstring says whether it is
collective (on the communicator of the objects it is given).
"""
from __future__ import annotations

import contextlib
import functools
import os

import numpy as np
from petsc4py import PETSc

from ._petsc import SOLVER_PREFIXES, option_pairs


def petsc_comm(comm, where: str) -> PETSc.Comm:
    """The petsc4py communicator an API call runs on: None is COMM_WORLD, a petsc4py or mpi4py
    intracommunicator is taken as it is (PETSC_COMM_SELF, a Split's sub-communicator for a
    task-parallel study). A null communicator (what MPI.Comm.Split gives a rank it leaves out,
    color = MPI.UNDEFINED) or anything else is an InputError naming `where`. Red team: `comm or
    COMM_WORLD` read a null communicator, which is falsy, as none given, and ran that rank's case
    collectively on COMM_WORLD, which the other ranks, busy on their own communicators, never join
    (a hang); an mpi4py communicator given to run() was a traceback. Not collective."""
    from mpi4py import MPI

    from .errors import InputError

    if comm is None:
        return PETSc.COMM_WORLD
    if isinstance(comm, MPI.Comm) and comm != MPI.COMM_NULL and not comm.Is_inter():
        return PETSc.Comm(comm)
    if isinstance(comm, PETSc.Comm) and comm != PETSc.COMM_NULL and not comm.tompi4py().Is_inter():
        return comm
    what = ("a null communicator (a rank that MPI.Comm.Split left out has no case to run)"
            if isinstance(comm, (MPI.Comm, PETSc.Comm)) and not comm else
            "an intercommunicator" if isinstance(comm, (MPI.Comm, PETSc.Comm)) else type(comm).__name__)
    raise InputError(f"{where}: comm must be a petsc4py or mpi4py communicator (PETSc.COMM_SELF, "
                     f"MPI.COMM_WORLD.Split(...)) or None for COMM_WORLD, got {what}")


def owned_rows(n: int, comm) -> tuple[int, int]:
    """The rows [start, end) this rank owns in PETSc's default layout of n rows. Collective."""
    n_local, _ = PETSc.Sys.splitOwnership(n, comm=comm)
    start = comm.tompi4py().exscan(n_local) or 0
    return start, start + n_local


def aij_from_owned_triplets(comm, n: int, rows, cols, values) -> PETSc.Mat:
    """An assembled n x n AIJ matrix from (row, col, value) triplets of this rank's own rows
    (duplicates are summed). Collective; no values move between ranks."""
    start, end = owned_rows(n, comm)
    rows = np.asarray(rows, dtype=np.int64)
    key, inverse = np.unique((rows - start) * n + np.asarray(cols, dtype=np.int64), return_inverse=True)
    summed = np.bincount(inverse, weights=np.asarray(values, dtype=float), minlength=key.size)
    local_row, col = np.divmod(key, n)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(local_row, minlength=end - start))])
    A = PETSc.Mat().createAIJ(size=((end - start, n), (end - start, n)),
                              csr=(indptr.astype(PETSc.IntType), col.astype(PETSc.IntType), summed),
                              comm=comm)
    A.assemble()
    return A


def direct_solver(ksp: PETSc.KSP, factorization: str = "lu") -> PETSc.KSP:
    """Configure a KSP as a direct solve by MUMPS (required in parallel): preonly + LU or Cholesky.
    Set before setFromOptions, so the user's options still win."""
    ksp.setType(PETSc.KSP.Type.PREONLY)
    pc = ksp.getPC()
    pc.setType(factorization)
    pc.setFactorSolverType("mumps")
    return ksp


@contextlib.contextmanager
def options_defaults(prefix: str, defaults: dict):
    """Put the code's `defaults` (option name -> value) under `prefix` into the options database
    where the user has not set them, for the calls inside the block (setFromOptions, and a solve
    when an option is read at factorization time), and take them out after: the user's options
    always win, and ours never leak into another solver or outlive this one. Yields the prefixed
    options, to read the effective values."""
    options = PETSc.Options(prefix)
    ours = [name for name in defaults if not options.hasName(name)]
    for name in ours:
        options.setValue(name, defaults[name])
    try:
        yield options
    finally:
        for name in ours:
            options.delValue(name)


def values_at(vec: PETSc.Vec, rows) -> np.ndarray:
    """vec[rows] on every rank. Collective."""
    lo, hi = vec.getOwnershipRange()
    rows = np.asarray(rows, dtype=np.int64)
    out = np.zeros(rows.size)
    mine = (rows >= lo) & (rows < hi)
    out[mine] = vec.getArray(readonly=True)[rows[mine] - lo]
    return vec.getComm().tompi4py().allreduce(out)


def on_rank0(vec: PETSc.Vec) -> np.ndarray | None:
    """The whole of a distributed Vec on rank 0 (None elsewhere). Collective."""
    scatter, full = PETSc.Scatter.toZero(vec)
    try:
        scatter.scatter(vec, full, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        return full.getArray(readonly=True).copy() if vec.getComm().rank == 0 else None
    finally:
        destroy(scatter, full)


def unit_vector(template: PETSc.Vec, row: int) -> PETSc.Vec:
    """The unit vector at global `row`, laid out like `template`. Collective."""
    g = template.duplicate()
    g.set(0.0)
    lo, hi = g.getOwnershipRange()
    if lo <= row < hi:
        g.setValue(int(row), 1.0)
    g.assemble()
    return g


def destroy(*objects) -> None:
    """Destroy the given PETSc objects (None is skipped). Collective on each object's communicator."""
    for obj in objects:
        if obj is not None:
            obj.destroy()


def release_frames(exc: BaseException) -> None:
    """Clear the local variables of the finished frames an exception passed through (and those of the
    exceptions it arose from), before the owner of the PETSc objects they refer to destroys them on
    its error path. Those frames hold references to the solver's own objects: the TS or PC petsc4py
    hands a Python callback, an ST or factor got from a solver; kept by the traceback, they outlive the
    owner's destroy, and petsc4py 3.18 then parks each such object (with all it holds: a TS's SNES, KSP
    and matrices) in PETSc's garbage until a collective cleanup: a leak in a long process. Frames still
    running keep their variables. Not collective."""
    import traceback

    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        traceback.clear_frames(exc.__traceback__)
        exc = exc.__context__


def refused_options_line(exc: Exception, what: str | None = None, prefixes: tuple = ()) -> str:
    """One line for a PETSc error that reached the Python API: `what` failed (the stage), PETSc's
    code, function and message (errors.petsc_failure), and the options of the package's solvers
    (_petsc.SOLVER_PREFIXES) in the database, the one whose value PETSc's message quotes (an unknown
    type) first; `prefixes` (e.g. ("rom_",)) are the solvers of the stage. Not collective."""
    from .errors import petsc_failure

    failure = petsc_failure(exc)
    given = {k: v for k, v in sorted(PETSc.Options().getAll().items()) if k.startswith(SOLVER_PREFIXES)}
    words = failure.rsplit(": ", 1)[-1].split()
    quoted = [k for k, v in given.items() if v and v.strip() in words]
    names = " ".join(f"-{k}" + (f" {given[k]}" if given[k] else "")
                     for k in quoted + [k for k in given if k not in quoted])
    if prefixes:
        hint = f"; check the {', '.join(f'-{p}' for p in prefixes)} options" + (f" (given: {names})" if names else "")
    else:
        hint = f"; check the PETSc options given ({names})" if names else ""
    return (f"{what}: " if what else "") + failure + hint


def petsc_errors_as_one_line(what: str | None = None, prefixes: tuple = ()):
    """Decorator for the Python API's entry points: a PETSc error (most often an option PETSc refused,
    -rom_ts_type nonsense) leaves as one SolverError line (refused_options_line), never as PETSc's
    multi-line petsc4py.PETSc.Error; the frames it passed through are released first (their PETSc
    objects are their owners' to destroy). With DBF_HPC_DEBUG set the PETSc error passes as it is.
    Collective as the function is: the ranks meet a refused option alike, and each raises."""
    def wrap(function):
        @functools.wraps(function)
        def api(*args, **kwargs):
            try:
                return function(*args, **kwargs)
            except PETSc.Error as e:
                if os.environ.get("DBF_HPC_DEBUG"):
                    raise
                release_frames(e)
                from .errors import SolverError

                raise SolverError(refused_options_line(e, what, prefixes)) from None
        return api
    return wrap


@contextlib.contextmanager
def frames_released():
    """release_frames on any exception leaving the block (a solve that calls back into Python)."""
    try:
        yield
    except BaseException as e:
        release_frames(e)
        raise


_COMMANDS = []   # the option names ("-name") of each command_options block open, the innermost last


def command_option_names() -> list:
    """The PETSc options ("-name") of the command running now (its command_options block), [] outside one:
    those whose use dbf-hpc checks (unused_options; run.run stores the lines in its output). Not collective."""
    return list(_COMMANDS[-1]) if _COMMANDS else []


@contextlib.contextmanager
def command_options(tokens, at_start: bool, keep: bool = False):
    """One command's PETSc options (tokens as given: -name [value] ...) in the database while it runs,
    so that a later command in the same process (a study script or the tests calling cli.main)
    neither inherits them nor loses its own (red team: a second cli.main ran with the first one's
    -modes_eps_tol 1e-3 and warned its own options unused). The options of the package's solvers
    (_petsc.SOLVER_PREFIXES) go in now, over any value PETSC_OPTIONS or a file gave (the command line
    wins, as in PETSc), and are taken back afterwards, the values from before restored; the others
    (-log_view, -malloc_debug) configure PETSc itself and stay: `at_start`, PETSc was initialized with
    them (_petsc.startup_options), else they go in now. `keep`: the command is the program's (its
    own command line): its options stay for PETSc's finalization, whose -options_left and -log_view
    report them (taken back, -options_left said "There are no unused options" of a misspelled one
    and -log_view's option table lost every solver option; red team). Not collective."""
    options = PETSc.Options()
    pairs = option_pairs(tokens)
    _COMMANDS.append([f"-{name}" for name, _ in pairs])
    before = {}
    for name, _ in pairs:
        if name.startswith(SOLVER_PREFIXES) and name not in before:
            before[name] = options.getString(name) if options.hasName(name) else None
    for name, value in pairs:
        if name.startswith(SOLVER_PREFIXES) or not at_start:
            options.setValue(name, value)
    try:
        yield
    finally:
        _COMMANDS.pop()
        if not keep:
            for name, value in before.items():
                options.delValue(name)
                if value is not None:
                    options.setValue(name, value or None)


def _petsc_library():
    """The loaded libpetsc, through ctypes (petsc4py 3.18 does not expose PetscOptionsUsed), or None."""
    import ctypes

    try:
        with open("/proc/self/maps") as maps:
            path = next(line.split()[-1] for line in maps if "libpetsc" in line and ".so" in line.split()[-1])
        lib = ctypes.CDLL(path)
        lib.PetscOptionsUsed.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.POINTER(ctypes.c_int)]
        return lib
    except (OSError, StopIteration, AttributeError):
        return None


# Options PETSc reads only in PetscFinalize (after the command asks what was used), or consumes at
# start-up without marking them used: never "not used" (red team: -options_left and -options_view
# drew "a misspelling" warnings).
READ_BY_PETSC_ITSELF = ("-options_left", "-options_view", "-options_file")


def _checked(names) -> list:
    return [n for n in names if n.startswith("-") and len(n) > 1 and n not in READ_BY_PETSC_ITSELF]


def options_read_here(names) -> np.ndarray:
    """Per option of `names` (as given, e.g. '-rom_ts_arkimex_typ'; those unused_options checks), 1 where
    a solver on this rank has read it so far (or PETSc cannot tell), else 0. Not collective."""
    import ctypes

    lib = _petsc_library()
    used = []
    for name in _checked(names):
        flag = ctypes.c_int(1)
        if lib is not None and lib.PetscOptionsUsed(None, name.lstrip("-").encode(), ctypes.byref(flag)) != 0:
            flag.value = 1
        used.append(bool(flag.value))
    return np.array(used, dtype=np.int32)


def options_read_anywhere(names, comm) -> np.ndarray:
    """options_read_here of every rank of `comm` combined: 1 where a solver on any rank has read it.
    Collective."""
    from mpi4py import MPI

    here = options_read_here(names)
    anywhere = np.zeros_like(here)
    comm.tompi4py().Allreduce(here, anywhere, op=MPI.MAX)
    return anywhere


def unused_options(names, comm) -> list:
    """The options among `names` (as given, e.g. '-rom_ts_arkimex_typ') that no solver on any rank
    read: a misspelling, or a solver this command does not run (not READ_BY_PETSC_ITSELF).
    Collective; [] where PETSc cannot tell."""
    return [name for name, u in zip(_checked(names), options_read_anywhere(names, comm)) if not u]


def unread_options(names, read) -> list:
    """unused_options where the ranks cannot meet: `read` is options_read_anywhere at an earlier point
    of the command where every rank was present, and this rank's own reads since count too (run.py:
    rank 0 checks as it writes the output, the other ranks done with their solvers and waiting). Not
    collective."""
    here = np.maximum(options_read_here(names), read)
    return [name for name, u in zip(_checked(names), here) if not u]


def unused_option_warning(name: str) -> str:
    """The warning for a PETSc option no solver read (unused_options)."""
    return (f"PETSc option {name} was not used: a misspelling, or a solver this command does not run (prefixes: "
            f"modes_, dbf_, static_, buckling_, rom_, full_)")


def mark_options_read(names) -> None:
    """Read each of `names` once, so that PETSc counts it used: where the run that read them is done
    already (run.run of a finished output, whose stored warnings say which no solver read). Not
    collective."""
    database = PETSc.Options()
    for name in _checked(names):
        database.getString(name.lstrip("-"), "")


def natural_fill_is_small(A: PETSc.Mat) -> bool:
    """Whether Cholesky in the natural ordering keeps the fill within 10 times the lower triangle
    (a beam's banded matrix does; a 3-D mesh does not). Collective."""
    lo, _ = A.getOwnershipRange()
    ia, ja, _ = A.getValuesCSR()
    n = ia.size - 1
    envelope = lower = 0.0
    if n:
        first = np.minimum.reduceat(ja, ia[:-1])
        envelope = float(np.sum(np.maximum(lo + np.arange(n) - first, 0) + 1))
        lower = (ja.size + n) / 2
    envelope, lower = A.getComm().tompi4py().allreduce(np.array([envelope, lower]))
    return envelope <= 10.0 * lower
