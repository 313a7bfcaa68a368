"""Shared test set-up. The suite runs serially and under `mpirun -n 2 python -m mpi4py -m pytest`.

Under MPI every rank runs every test. Rules that keep a failure from hanging the job:
- assert only on values every rank agrees on, or reduce the condition first (`assert_all`);
- use `shared_tmp_path` (rank 0's tmp_path) for files all ranks read or write;
- look at the files a collective call left behind with `rank0_files` (rank 0 writes and removes them).
"""
import contextlib
import os
import subprocess

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc


@pytest.hookimpl(trylast=True)
def pytest_configure(config):
    config.addinivalue_line("markers", "parallel: needs 2 MPI ranks; runs in the 2-rank pass")
    config.addinivalue_line("markers", "launcher: starts its own mpirun jobs; runs in the serial pass")
    config.addinivalue_line("markers", "serial: what it checks is one rank's own computation, which the "
                            "2-rank pass would repeat on every rank (or on rank 0 alone), its collective "
                            "set-up covered by other tests there; runs in the serial pass")
    if MPI.COMM_WORLD.rank > 0:  # one report, from rank 0
        reporter = config.pluginmanager.getplugin("terminalreporter")
        if reporter is not None:
            config.pluginmanager.unregister(reporter)


_failed = []   # this rank's failed tests


def pytest_runtest_logreport(report):
    if report.failed:
        _failed.append(report.nodeid)


def pytest_sessionfinish(session, exitstatus):
    """Rank 0 reports; a test that failed on another rank only is named here (else the pass would
    fail with rank 0's summary saying all passed). Collective."""
    world = MPI.COMM_WORLD
    if world.size < 2:
        return
    everyone = world.gather(sorted(set(_failed)), root=0)
    if world.rank == 0:
        elsewhere = sorted({nodeid for failed in everyone[1:] for nodeid in failed} - set(everyone[0]))
        reporter = session.config.pluginmanager.getplugin("terminalreporter")
        if reporter is not None and elsewhere:
            reporter.ensure_newline()
        for nodeid in elsewhere:
            ranks = [rank for rank, failed in enumerate(everyone) if nodeid in failed]
            line = f"FAILED on rank(s) {ranks} only: {nodeid}"
            reporter.write_line(line) if reporter is not None else print(line)
        if elsewhere:
            session.exitstatus = 1


def pytest_collection_modifyitems(config, items):
    parallel = MPI.COMM_WORLD.size >= 2
    skip_parallel = pytest.mark.skip(reason="needs 2 MPI ranks (runs in the 2-rank pass)")
    skip_launcher = pytest.mark.skip(reason="starts mpirun itself (runs in the serial pass)")
    skip_serial = pytest.mark.skip(reason="one rank's own computation, the same on 2 (runs in the serial pass)")
    for item in items:
        if "parallel" in item.keywords and not parallel:
            item.add_marker(skip_parallel)
        if "launcher" in item.keywords and parallel:
            item.add_marker(skip_launcher)
        if item.get_closest_marker("serial") is not None and parallel:
            item.add_marker(skip_serial)


@pytest.fixture(autouse=True, scope="session")
def private_default_cache(tmp_path_factory):
    """A scene that leaves [basis] cache unset caches its bases in the test run's own folder, not in
    the user's ~/.cache/dbf_hpc: there, other checkouts' test sessions on the same machine (of other
    code, under the same version) and the user's own runs read and wrote one folder with the tests,
    so the basis a test got, and whether it was built or found, depended on what ran before (tests of
    sweeps, of the gyroscopic scenes, ... cached there). The folder is $DBF_HPC_TEST_CACHE
    (scripts/test: one for both passes, removed at its end), else this session's (rank 0's, every
    rank the same). The `dbf-hpc` subprocesses of launcher tests keep their own default; they give
    [basis] cache."""
    import os

    from dbf_hpc import cache, scene

    folder = None
    if MPI.COMM_WORLD.rank == 0:
        folder = os.environ.get("DBF_HPC_TEST_CACHE") or str(tmp_path_factory.mktemp("default-cache"))
    folder = MPI.COMM_WORLD.bcast(folder, root=0)
    types, default = scene.SCHEMA["basis"]["cache"]
    assert default == cache.DEFAULT_DIR, (default, cache.DEFAULT_DIR)
    scene.SCHEMA["basis"]["cache"], cache.DEFAULT_DIR = (types, folder), folder
    try:
        yield folder
    finally:
        scene.SCHEMA["basis"]["cache"], cache.DEFAULT_DIR = (types, default), default


@pytest.fixture
def comm():
    return PETSc.COMM_WORLD


@pytest.fixture
def shared_tmp_path(tmp_path):
    """Rank 0's tmp_path, the same directory on every rank."""
    return MPI.COMM_WORLD.bcast(tmp_path, root=0)


def rank0_files(folder) -> list:
    """The names in `folder` as rank 0 sees them once it is back from the collective call before,
    sorted, the same on every rank. Rank 0 writes and removes a run's files (the output, its .partial
    and checkpoint, the OUT.h5.lock it releases last): rank 1 can return from the same call's error
    before rank 0 has removed them, as no collective follows the release on the error path (a barrier
    there would hang a job where one rank raises alone; run.claimed has one on the normal path only).
    A look from rank 1 then still saw OUT.h5.lock (failed on rank 1 only, under load). Collective."""
    import os

    return MPI.COMM_WORLD.bcast(sorted(os.listdir(folder)) if MPI.COMM_WORLD.rank == 0 else None, root=0)


def assert_all(condition, message=""):
    """Assert a condition that may differ between ranks: fails on every rank if it fails on one."""
    ok = MPI.COMM_WORLD.allreduce(bool(condition), op=MPI.LAND)
    assert ok, message or "failed on at least one rank"


def to_numpy(vec):
    """The whole of a distributed Vec as a numpy array, on every rank. Collective."""
    scatter, full = PETSc.Scatter.toAll(vec)
    scatter.scatter(vec, full, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
    values = full.getArray().copy()
    scatter.destroy()
    full.destroy()
    return values


@contextlib.contextmanager
def petsc_options(**values):
    """PETSc options set for the block (name without its dash: value), removed after it."""
    from petsc4py import PETSc

    options = PETSc.Options()
    for name, value in values.items():
        options.setValue(name, value)
    try:
        yield
    finally:
        for name in values:
            options.delValue(name)


@contextlib.contextmanager
def tmpfs_disk(folder, size: str):
    """A file system of its own (tmpfs of `size`, e.g. "3m") mounted at folder/disk for a real full
    disk, or a skip where this machine cannot mount one (needs root)."""
    mount = folder / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount)], capture_output=True)
    if done.returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], capture_output=True)



ROTOR_SCENE = """[structure]
kind = "matrices"
stiffness = "K.mtx"
mass = "M.mtx"
gyroscopic = "G.mtx"
[excitation]
kind = "force"
dof = 0
amplitude = 1.0
frequency_hz = 5.0
[[constraint]]
dof = 2
law = "deadband"
clearance = 1e-3
k = 1e3
"""


def write_rotor(folder, K, G, scenes: dict) -> None:
    """A 3-DOF rotor (M = I, the given K and gyroscopic G as Matrix Market files) with a 1 N force at
    5 Hz on DOF 0 and a deadband stop on DOF 2, as scenes `name: extra sections` in `folder`
    (rank 0 writes; every rank waits)."""
    import numpy as np
    import scipy.io
    import scipy.sparse

    if MPI.COMM_WORLD.rank == 0:
        for name, mat in (("K", K), ("M", np.eye(3)), ("G", G)):
            scipy.io.mmwrite(str(folder / f"{name}.mtx"), scipy.sparse.csr_matrix(mat), precision=17,
                             symmetry="general")
        for name, extra in scenes.items():
            (folder / name).write_text(ROTOR_SCENE + extra)
    MPI.COMM_WORLD.Barrier()


def petsc_garbage(capfd) -> int:
    """How many PETSc objects wait in PETSc's garbage on COMM_WORLD and COMM_SELF, the same on every
    rank. petsc4py 3.18 parks an object there when a Python wrapper holding its last reference is
    collected (a factor Mat got from a PC whose KSP was destroyed first, say): it is freed only by a
    collective PETSc.garbage_cleanup(), so in one long process (a parameter study) it is a leak. Reads
    PETSc.garbage_view's table (rank 0 prints every rank's). Collective."""
    import re

    capfd.readouterr()
    PETSc.garbage_view(PETSc.COMM_WORLD)
    PETSc.garbage_view(PETSc.COMM_SELF)
    text = capfd.readouterr().out
    count = sum(int(n) for n in re.findall(r"Total entries: (\d+)", text))
    return MPI.COMM_WORLD.bcast(count, root=0)


def undestroyed_petsc_objects() -> int:
    """How many petsc4py objects Python still holds whose PETSc object is not destroyed (after a
    garbage collection). An error path that leaves one alive (e.g. in the frames its traceback keeps)
    counts it; in parallel such objects pile up in PETSc's garbage."""
    import gc

    gc.collect()
    return sum(1 for o in gc.get_objects() if isinstance(o, PETSc.Object) and o.handle)


def twin_chains(directory, copies: int = 2):
    """Operators of two (`copies`) identical, uncoupled spring-mass chains (a symmetric structure that is
    not a beam: every eigenvalue twice, as a square bar's bending pairs) and one chain's dense K and M."""
    import scipy.io
    import scipy.sparse
    from mpi4py import MPI

    from dbf_hpc.matrices import MatrixFiles, load_operators

    n = 10
    K = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr() * 1e5
    M = scipy.sparse.diags(np.linspace(1.0, 2.0, n)).tocsr()
    paths = [str(directory / name) for name in ("K.mtx", "M.mtx")]
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(paths[0], scipy.sparse.block_diag([K] * copies).tocsr(), precision=17)
        scipy.io.mmwrite(paths[1], scipy.sparse.block_diag([M] * copies).tocsr(), precision=17)
    MPI.COMM_WORLD.Barrier()
    return load_operators(MatrixFiles(*paths)), K.toarray(), M.toarray()


def damage_data_address(path, dataset: str) -> None:
    """Point the (contiguous) `dataset` of the HDF5 file `path` at data far beyond the file's end: it
    opens, and its data cannot be read ("Can't read data (addr overflow ...)"), as after damage to
    its layout message. Not collective."""
    import struct

    import h5py

    with h5py.File(path, "r") as f:
        offset = f[dataset].id.get_offset()
    data = open(path, "rb").read()
    needle = struct.pack("<Q", offset)
    assert offset is not None and data.count(needle) == 1, "the data address appears once"
    at = data.index(needle)
    with open(path, "r+b") as f:
        f.seek(at)
        f.write(struct.pack("<Q", offset + 2**40))


def small_mass_chain(folder, atol=None) -> str:
    """A scene of 10 masses of 1e-9 kg joined by 1e-4 N/m springs, a stop 1 um away (dof 5), forced at dof 2:
    a part of small masses and displacements in SI (run.loose_atol). With [integrator] atol, when given.
    The files are written by rank 0; every rank returns after they exist. Returns the scene's path."""
    import scipy.io
    import scipy.sparse

    n, path = 10, os.path.join(str(folder), "chain.toml")
    K = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr() * 1e-4
    M = scipy.sparse.diags(np.linspace(1.0, 2.0, n)).tocsr() * 1e-9
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(os.path.join(str(folder), "K.mtx"), K, precision=17)
        scipy.io.mmwrite(os.path.join(str(folder), "M.mtx"), M, precision=17)
        with open(path, "w") as f:
            f.write('[structure]\nkind = "matrices"\nstiffness = "K.mtx"\nmass = "M.mtx"\n'
                    '[excitation]\nkind = "force"\ndof = 2\namplitude = 5e-10\nfrequency_hz = 10.0\n'
                    '[[constraint]]\ndof = 5\nclearance = 1e-6\nk = 1e-3\n[basis]\nmodes = 4\ncache = "off"\nestimate = false\n'
                    '[output]\nsample_dt = 1e-4\n[integrator]\nt_end = 0.01\n'
                    + (f"atol = {atol!r}\n" if atol is not None else ""))
    MPI.COMM_WORLD.Barrier()
    return path


def recorded_impacts(constraints, t, z, v, by_blocks: bool) -> dict:
    """The impact statistics a SampleRecorder gives for the steps (t, z, v) of `constraints`, fed as one
    block of steps or one step at a time (the two must agree). Not collective."""
    from dbf_hpc.output import MemoryWriter
    from dbf_hpc.recorder import SampleRecorder

    recorder = SampleRecorder(MemoryWriter(constraints.shape, 0, 0), constraints)
    if by_blocks:
        recorder.steps(t, z, v)
    else:
        for i in range(t.size):
            recorder.step(t[i], z[i], v[i])
    return recorder.impacts.result()


def write_binary_vec(vec, path: str) -> None:
    """`vec` as a PETSc binary file at `path`. Collective on vec's communicator."""
    viewer = PETSc.Viewer().createBinary(path, mode="w", comm=vec.getComm())
    vec.view(viewer)
    viewer.destroy()


@contextlib.contextmanager
def ends_a_hang(seconds: float = 120):
    """A hang inside (the bug a test checks for) ends the job after `seconds`, with where it waited
    (faulthandler's traceback), instead of stopping CI."""
    import faulthandler

    faulthandler.dump_traceback_later(seconds, exit=True)
    try:
        yield
    finally:
        faulthandler.cancel_dump_traceback_later()


# Defined in every script two_ranks_of runs: what each rank raised, said by rank 0 in rank order
EVERY_RANK_SAYS = '''
def every_rank_says(act, folder=None):
    """act() on every rank; rank 0 then prints each rank's outcome (no error, or its exception's class,
    message and dbf_hpc_origin) in rank order, and the files in `folder`."""
    import os
    from mpi4py import MPI
    rank = MPI.COMM_WORLD.rank
    try:
        act()
        said = f"rank {rank}: no error"
    except Exception as e:
        said = f"rank {rank}: {type(e).__name__}: {e} (origin {getattr(e, 'dbf_hpc_origin', None)})"
    said = MPI.COMM_WORLD.gather(said, root=0)   # (rank 0 prints: the ranks' own lines interleave)
    if rank == 0:
        for line in said + ([f"files {sorted(os.listdir(folder))}"] if folder is not None else []):
            print(line, flush=True)
'''


def two_ranks_of(script: str, *args, seconds: int = 60):
    """The Python `script` (its text) run by `mpirun -n 2` under `timeout`, this checkout first on the
    path: the finished process (stdout, stderr as text). For a test of what every rank does when one
    rank fails alone: a regression hangs the ranks left waiting, and the timeout ends that job (exit
    124) where a hang inside the 2-rank pass would stop it until the suite's own limit. Mark such a
    test `launcher` (serial pass). The script may call every_rank_says (EVERY_RANK_SAYS)."""
    import sys
    import tempfile

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "OMPI_MCA_orte_execute_quiet": "1", "OMPI_MCA_rmaps_base_oversubscribe": "1",
           "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])}
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
        f.write(EVERY_RANK_SAYS + script)
    try:
        return subprocess.run(["timeout", "--kill-after=10", str(seconds), "mpirun", "-n", "2", sys.executable,
                               f.name, *map(str, args)], capture_output=True, text=True, env=env, cwd=root,
                              timeout=seconds + 30)
    finally:
        os.remove(f.name)


def fifo_at(path) -> None:
    """A named pipe at `path` (what was there removed), made by rank 0; every rank sees it after."""
    if MPI.COMM_WORLD.rank == 0:
        if os.path.lexists(path):
            os.remove(path)
        os.mkfifo(path)
    MPI.COMM_WORLD.Barrier()


# A steel micro-beam 100 um long, free vibration in its first mode (1e-7 m): scales far below the paper's
MICRO_BEAM = """
[structure]
kind = "beam"
length = 1e-4
elements = 20
E = 2e11
I = 8.333e-22
A = 1e-10
rho = 7800.0

[initial]
mode = 1
amplitude = 1e-7
"""
