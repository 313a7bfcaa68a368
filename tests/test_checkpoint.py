"""Checkpoints (checkpoint.py, run.py): a resume continues only the run that wrote the checkpoint,
from data that is what was written. Corrupt, crafted or foreign checkpoints are refused in one line
naming the cause; nothing read from disk is trusted unchecked."""
import json
import os
import re
import shutil
import signal
import threading
import time

import h5py
import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

from conftest import assert_all, ends_a_hang, fifo_at, tmpfs_disk
from dbf_hpc import sealed
from dbf_hpc.checkpoint import SEAL
from dbf_hpc.errors import InputError, SolverError
from dbf_hpc.run import run
from dbf_hpc.scene import load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER = os.path.join(ROOT, "jobs", "paper_beam.toml")


def interrupted_run(scene, out, signum=signal.SIGTERM):
    """Run until the first checkpoint exists, then SIGTERM rank 0 (a batch system's time limit; or
    `signum`): the run checkpoints and stops. Returns the checkpoint's path."""
    checkpoint = out + ".checkpoint"

    def terminate():
        while not os.path.exists(checkpoint):
            time.sleep(0.01)
        os.kill(os.getpid(), signum)

    if MPI.COMM_WORLD.rank == 0:
        threading.Thread(target=terminate, daemon=True).start()
    with pytest.raises(SolverError, match="stopped by a termination signal"):
        run(scene, out, progress=False)
    return checkpoint


@pytest.fixture
def stopped(shared_tmp_path):
    """A paper-beam run stopped at a checkpoint; its scene overrides and output path."""
    sets = ["integrator.t_end=2.0", "output.checkpoint_dt=0.05", f"basis.cache={shared_tmp_path / 'cache'}"]
    out = str(shared_tmp_path / "run.h5")
    checkpoint = interrupted_run(load_scene(PAPER, sets), out)
    if MPI.COMM_WORLD.rank == 0:
        shutil.copy(checkpoint, checkpoint + ".good")
    MPI.COMM_WORLD.Barrier()
    return sets, out, checkpoint


def resume(sets, out):
    return run(load_scene(PAPER, sets), out, progress=False, resume=True)


def test_a_flipped_bit_in_the_state_is_refused_not_resumed(stopped):
    sets, out, checkpoint = stopped
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(checkpoint, "r+") as f:
            q = f["q"][...]
            q.view(np.uint64)[0] ^= np.uint64(1 << 20)     # one bit of the mantissa
            f["q"][...] = q
        sealed.seal(checkpoint, SEAL)   # sealed again: the data's own checksum is what this is about
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="is corrupt .* checksum"):
        resume(sets, out)


@pytest.mark.parametrize("offset", [512 + 16, 512 + 136, 512 + 720, 512 + 1088])
def test_a_flipped_bit_in_the_checkpoint_metadata_is_one_line_not_an_hdf5_crash(stopped, offset):
    # Red team: a flipped byte in a checkpoint's HDF5 metadata (bit rot, a bad copy) surfaced as
    # RuntimeError or TypeError tracebacks from h5py ("Object visitation failed ..."), and HDF5 can
    # crash on such damage. The file's seal is checked before HDF5 parses it; a new run without
    # --resume still knows the damaged file for dbf-hpc's own and replaces it.
    sets, out, checkpoint = stopped
    if MPI.COMM_WORLD.rank == 0:
        with open(checkpoint, "r+b") as f:
            f.seek(offset)
            byte = f.read(1)
            f.seek(offset)
            f.write(bytes([byte[0] ^ 0x10]))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="fails its file checksum .*; remove it or rerun without --resume"):
        resume(sets, out)
    summary = run(load_scene(PAPER, sets), out, progress=False)
    assert summary["stats"]["final_time"] == pytest.approx(2.0)


def test_a_crafted_file_in_place_of_the_checkpoint_is_refused(stopped):
    sets, out, checkpoint = stopped
    if MPI.COMM_WORLD.rank == 0:
        with open(checkpoint, "wb") as f:                  # e.g. a pickle that would run code
            f.write(b"\x80\x04\x95cos\nsystem\n(S'echo owned'\ntR.")
    MPI.COMM_WORLD.Barrier()
    # the advice is one that works (new-user pass: it was "or rerun without --resume", and that run
    # refuses a foreign file there too)
    with pytest.raises(InputError, match="has no file checksum \\(.*not by dbf-hpc\\); remove it or choose "
                                         "another output name$"):
        resume(sets, out)
    with pytest.raises(InputError, match="exists and is not a dbf-hpc output"):
        run(load_scene(PAPER, sets), out, progress=False)


def test_a_named_pipe_in_place_of_the_checkpoint_is_refused_not_waited_on(stopped):
    # Red team: a FIFO at OUT.h5.checkpoint hung --resume (rank 0's look at the file opened it, and the
    # open waits for a writer for ever; the other ranks waited for rank 0): one line on every rank now

    sets, out, checkpoint = stopped
    fifo_at(checkpoint)
    with ends_a_hang():
        # (it said "cannot be read (OSError)"; it says what is there)
        with pytest.raises(InputError, match="is a named pipe, not a checkpoint: remove it or choose another output name$"):
            resume(sets, out)
        with pytest.raises(InputError, match="is not a regular file"):   # nor replaced by a run from the start
            run(load_scene(PAPER, sets), out, progress=False)


def test_an_unsealed_checkpoint_of_dbf_hpc_is_refused_and_a_run_from_the_start_replaces_it(stopped):
    # An older version's checkpoint: dbf-hpc's HDF5, without the seal. Its refusal advises a run
    # without --resume, and that run indeed starts from t = 0 over it.
    sets, out, checkpoint = stopped
    if MPI.COMM_WORLD.rank == 0:
        with open(checkpoint, "r+b") as f:
            f.write(b"\0" * len(SEAL))
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="has no file checksum .*; remove it or rerun without --resume$"):
        resume(sets, out)
    summary = run(load_scene(PAPER, sets), out, progress=False)
    assert summary["stats"]["final_time"] == pytest.approx(2.0)


def test_a_changed_scene_or_changed_petsc_options_are_refused_naming_what_differs(stopped):
    sets, out, _ = stopped
    with pytest.raises(InputError, match="written by a different scene or setup \\(.*scene"):
        resume(sets + ["constraint.clearance=2.4e-3"], out)
    options = PETSc.Options()
    options.setValue("rom_snes_rtol", "1e-12")
    try:
        with pytest.raises(InputError, match="options differ"):
            resume(sets, out)
    finally:
        options.delValue("rom_snes_rtol")


def test_samples_in_the_partial_output_that_the_checkpoint_did_not_save_are_refused(stopped):
    # Red team: the checkpoint was checked, the samples already in OUT.h5.partial only counted, so
    # another run's .partial (or an edited sample) went into the finished file under this scene.
    sets, out, _ = stopped
    from dbf_hpc import layout

    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(out + ".partial", "r+") as f:
            f["constraints/displacement"][3, 0] += 1e-3
            for name in layout.SERIES:   # and samples past the checkpoint's, as another run's file has
                if name in f:
                    f[name].resize(f[name].shape[0] + 5, axis=0)
    MPI.COMM_WORLD.Barrier()
    with h5py.File(out + ".partial", "r") as f:
        before = {name: f[name].shape for name in ("time", "constraints/displacement")}
    with pytest.raises(InputError, match="cannot be resumed \\(its samples are not those its checkpoint's run"):
        resume(sets, out)
    with h5py.File(out + ".partial", "r") as f:   # red team: the refusal cut the samples past the checkpoint's
        assert {name: f[name].shape for name in before} == before


def test_the_untouched_checkpoint_resumes_to_the_end(stopped):
    sets, out, checkpoint = stopped
    summary = resume(sets, out)
    assert summary["stats"]["final_time"] == pytest.approx(2.0)
    assert_all(not os.path.exists(checkpoint) and os.path.exists(out))
    with h5py.File(out) as f:
        assert_all(f["time"].shape == (10001,) and bool(f.attrs["complete"]))


def test_what_a_finish_stopped_halfway_wrote_is_written_again_on_resume(stopped):
    # Red team: a full disk (or, before, SIGTERM) stopped the final write halfway; the .partial kept
    # the fixed datasets written so far and --resume failed on "name already exists".
    sets, out, _ = stopped
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(out + ".partial", "r+") as f:
            f["constraints/position"] = [9.0]
            f["snapshots/displacement/000000"] = np.zeros((2, 3))
    MPI.COMM_WORLD.Barrier()
    summary = resume(sets, out)
    assert summary["stats"]["final_time"] == pytest.approx(2.0)
    with h5py.File(out) as f:
        assert_all(f["constraints/position"][:].tolist() == [0.25] and bool(f.attrs["complete"]))
        assert_all(f["snapshots/displacement/000000"].shape != (2, 3))


def test_a_changed_matrix_file_is_refused_even_with_the_same_scene(shared_tmp_path):
    import scipy.io

    from dbf_hpc import Beam, Constraint, FullOrderModel, law
    from test_matrices import to_scipy

    with FullOrderModel.build(Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=30),
                              [Constraint(law("deadband", clearance=2e-4, k=1e6), x=0.25)]) as fom:
        K, M = to_scipy(fom.operators.K), to_scipy(fom.operators.M)
        row, force = int(fom.constraints.flat_rows[0]), int(fom.operators.mesh.row[20, 0])
    text = f"""[structure]
kind = "matrices"
stiffness = "K.mtx"
mass = "M.mtx"
[excitation]
kind = "force"
amplitude = 0.05
frequency_hz = 3.0
dof = {force}
[[constraint]]
dof = {row}
law = "deadband"
clearance = 2e-4
k = 1e6
[integrator]
t_end = 2.0
[output]
checkpoint_dt = 0.05
"""
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(str(shared_tmp_path / "K.mtx"), K, precision=17)
        scipy.io.mmwrite(str(shared_tmp_path / "M.mtx"), M, precision=17)
        (shared_tmp_path / "m.toml").write_text(text)
    MPI.COMM_WORLD.Barrier()
    scene = str(shared_tmp_path / "m.toml")
    sets = [f"basis.cache={shared_tmp_path / 'cache'}"]
    out = str(shared_tmp_path / "m.h5")
    interrupted_run(load_scene(scene, sets), out)
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(str(shared_tmp_path / "K.mtx"), K * (1 + 1e-9), precision=17)   # same scene, new K
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="structure differ"):
        run(load_scene(scene, sets), out, progress=False, resume=True)


@pytest.mark.parametrize("checkpoint_dt,stopped_line", [
    (0.01, r"rerun with --resume to finish from the last checkpoint \(samples so far in .*partial"),
    (1.0, r"rerun it \(it was too short for a checkpoint: --resume starts it over\) \(the samples up to")])
def test_sigterm_during_the_error_estimate_says_so_and_a_resume_finishes_the_run(shared_tmp_path, monkeypatch,
                                                                                 checkpoint_dt, stopped_line):
    # A batch system's time limit can fall after the integration, in the a-posteriori estimate (the
    # statistics' estimate of a long run costs about what the run did). The one line says where the
    # run stopped and that --resume finishes it (not "before the integration began; nothing was
    # written"); the partial output and the checkpoint stay, and the resumed output is the
    # uninterrupted run's. Red team: a run too short to write a checkpoint (checkpoint_dt = 1 s) was told
    # to finish "from the last checkpoint": there is none, and --resume integrates it again from t = 0;
    # its line says so.
    from dbf_hpc import run as run_module

    sets = ["integrator.t_end=0.05", f"output.checkpoint_dt={checkpoint_dt}", f"basis.cache={shared_tmp_path / 'cache'}"]
    whole, out = str(shared_tmp_path / "whole.h5"), str(shared_tmp_path / "stopped.h5")
    run(load_scene(PAPER, sets), whole, progress=False)
    original = run_module._estimate

    def terminated(*args, **kwargs):   # rank 0 only: the estimate is rank 0's
        os.kill(os.getpid(), signal.SIGTERM)
        return original(*args, **kwargs)

    monkeypatch.setattr(run_module, "_estimate", terminated)
    with pytest.raises(SolverError, match="during the error estimates, after the integration; " + stopped_line):
        run(load_scene(PAPER, sets), out, progress=False)
    monkeypatch.setattr(run_module, "_estimate", original)
    checkpointed = checkpoint_dt < 0.05
    assert_all(not os.path.exists(out) and os.path.exists(out + ".checkpoint") == checkpointed
               and (os.path.exists(out + ".partial") or not checkpointed))
    summary = resume(sets, out)
    assert summary["stats"]["final_time"] == pytest.approx(0.05) and "estimated_error" in summary
    MPI.COMM_WORLD.Barrier()
    with h5py.File(whole) as a, h5py.File(out) as b:
        assert bool(b.attrs["complete"]) and a["time"].shape == b["time"].shape
        assert np.array_equal(a["constraints/displacement"][:], b["constraints/displacement"][:])
        assert a.attrs["estimated_error"] == b.attrs["estimated_error"]


def test_a_changed_damping_file_of_a_matrices_structure_is_refused_naming_the_files(shared_tmp_path):
    # Red team: the resume identity held the matrix files' K and M (the basis cache's fingerprint) but
    # not the damping file's bytes: the resumed output was half one damping, half the other.
    import scipy.io
    import scipy.sparse

    n = 60
    K = scipy.sparse.diags([-1e4 * np.ones(n - 1), 2e4 * np.ones(n), -1e4 * np.ones(n - 1)], [-1, 0, 1])
    names = {name: str(shared_tmp_path / name) for name in ("K.mtx", "M.mtx", "C.mtx", "chain.toml")}
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(names["K.mtx"], K.tocoo(), precision=17)
        scipy.io.mmwrite(names["M.mtx"], scipy.sparse.identity(n, format="coo") * 0.01, precision=17)
        scipy.io.mmwrite(names["C.mtx"], (2e-3 * K).tocoo(), precision=17)
        with open(names["chain.toml"], "w") as f:
            f.write('[structure]\nkind = "matrices"\nstiffness = "K.mtx"\nmass = "M.mtx"\ndamping = "C.mtx"\n'
                    '[excitation]\nkind = "force"\ndof = 10\namplitude = 5.0\nfrequency_hz = 3.0\n'
                    '[[constraint]]\ndof = 30\nclearance = 1e-4\nk = 1e5\n[basis]\nmodes = 6\nestimate = false\n'
                    f'cache = "{shared_tmp_path / "cache"}"\n[integrator]\nt_end = 20.0\n[output]\n'
                    'checkpoint_dt = 0.05\n')
    MPI.COMM_WORLD.Barrier()
    out = str(shared_tmp_path / "chain.h5")
    interrupted_run(load_scene(names["chain.toml"]), out)
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(names["C.mtx"], (2e-2 * K).tocoo(), precision=17)
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="written by a different scene or setup \\(files differ"):
        run(load_scene(names["chain.toml"]), out, progress=False, resume=True)


@pytest.fixture
def tiny_disk(tmp_path):
    """A 256 KiB file system of its own, or a skip."""
    with tmpfs_disk(tmp_path, "256k") as mount:
        yield mount


# A checkpoint written on a disk left with `free` bytes, in a process that ends as the command does
# (without tearing h5py down when a failed write's objects were kept, cli.main)
_WRITE_ON_FULL_DISK = """
import os, sys
import numpy as np
from dbf_hpc.checkpoint import Checkpoint
from dbf_hpc.errors import PARKED, WRITE_ERRORS
disk, free = sys.argv[1], int(sys.argv[2])
with open(os.path.join(disk, "filler"), "wb") as f:
    try:
        f.write(bytes(256 * 1024 - free))
    except OSError:
        pass
state = {**{f"q{i}": np.full(50, float(i)) for i in range(20)}, **{f"impacts/s{i}": np.ones(3) for i in range(10)}}
try:
    Checkpoint(os.path.join(disk, "run.h5.checkpoint"), {"scene": "x"}).write(state)
    print("written", flush=True)
except WRITE_ERRORS as e:
    print("refused", flush=True)
if PARKED:
    os._exit(0)
"""


@pytest.mark.launcher
def test_a_checkpoint_the_full_disk_refused_neither_crashes_nor_leaves_a_half_file(tiny_disk):
    # Red team (a sweep on a 3 MB tmpfs that filled while a case wrote its checkpoint): the `with`
    # block closed the HDF5 file after its failed write, and closing or freeing it crashed HDF5 at
    # exit (signal 11, after the error line), and CHECKPOINT.tmp was left on the disk.
    import subprocess
    import sys

    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    outcomes = set()
    for free in range(0, 32 * 1024 + 1, 2048):   # the write fails in the data, the metadata, the close
        for name in os.listdir(tiny_disk):
            os.remove(tiny_disk / name)
        done = subprocess.run([sys.executable, "-c", _WRITE_ON_FULL_DISK, str(tiny_disk), str(free)],
                              capture_output=True, text=True, env=env, timeout=120)
        assert done.returncode == 0, f"{free} bytes free: exit {done.returncode}: {done.stderr[-500:]}"
        outcome = done.stdout.strip()
        outcomes.add(outcome)
        left = sorted(os.listdir(tiny_disk))
        expected = ["filler", "run.h5.checkpoint"] if outcome == "written" else ["filler"]
        assert left == expected, f"{free} bytes free: {outcome}, left {left}"
    assert outcomes == {"written", "refused"}, "the disk's room spans a refused and a written checkpoint"


def _same(a: dict, b: dict) -> bool:
    """Equal summaries, NaN equal to NaN (json writes both as NaN)."""
    import json

    return json.dumps(a, sort_keys=True) == json.dumps(b, sort_keys=True)


@pytest.mark.parametrize("method", ["rom", "full"])
def test_a_resume_of_a_finished_run_computes_nothing_and_returns_its_summary(shared_tmp_path, method):
    # A requeued batch job whose run had finished ran it all again (same result, twice the cost). Its
    # output is kept untouched now, and the summary read back from it is the one the run returned:
    # statistics, solver counters, estimates (a long run's statistics' too) and the final state.
    sets = ["integrator.t_end=1.2" if method == "rom" else "integrator.t_end=0.05", "output.snapshots=3",
            f"basis.cache={shared_tmp_path / 'cache'}"]
    out = str(shared_tmp_path / "run.h5")
    first = run(load_scene(PAPER, sets), out, progress=False, method=method)
    before = os.stat(out).st_mtime_ns
    again = run(load_scene(PAPER, sets), out, progress=False, method=method, resume=True)
    assert_all(os.stat(out).st_mtime_ns == before, "the finished output was written again")
    assert _same(first, again)
    if method == "rom":
        assert {"final_state", "estimated_error", "estimated_statistics"} <= set(again)


def test_a_resume_of_a_finished_run_asked_differently_computes_it_again(shared_tmp_path):
    # What the output answered must be what is asked now: another t_end, another PETSc option, or a
    # missing ParaView file (a full disk stopped its write) is computed again, never taken as done.
    sets = ["integrator.t_end=0.1", "output.snapshots=3", f"basis.cache={shared_tmp_path / 'cache'}"]
    out = str(shared_tmp_path / "run.h5")
    run(load_scene(PAPER, sets), out, progress=False)
    summary = run(load_scene(PAPER, ["integrator.t_end=0.2", *sets[1:]]), out, progress=False, resume=True)
    assert summary["stats"]["final_time"] == pytest.approx(0.2)
    stamp = os.stat(out).st_mtime_ns
    PETSc.Options().setValue("rom_snes_rtol", 1e-9)
    try:
        run(load_scene(PAPER, ["integrator.t_end=0.2", *sets[1:]]), out, progress=False, resume=True)
    finally:
        PETSc.Options().delValue("rom_snes_rtol")
    assert_all(os.stat(out).st_mtime_ns != stamp, "an output of other PETSc options was kept")
    stamp = os.stat(out).st_mtime_ns
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        os.remove(str(shared_tmp_path / "run.xdmf"))
    MPI.COMM_WORLD.Barrier()
    run(load_scene(PAPER, ["integrator.t_end=0.2", *sets[1:]]), out, progress=False, resume=True)
    assert_all(os.stat(out).st_mtime_ns != stamp and os.path.exists(str(shared_tmp_path / "run.xdmf")))



def test_an_earlier_runs_paraview_file_beside_a_rerun_whose_own_was_not_written_is_not_taken_as_finished(
        shared_tmp_path, monkeypatch):
    # A rerun (another t_end) finished its output, and its ParaView file could not be written (a full disk;
    # or a kill after the output's rename): the earlier run's run.xdmf stayed beside it, with that run's
    # snapshot times. A requeued --resume said "already complete" and kept it: ParaView showed the new
    # snapshots at the old times. The sidecar must be the output's own, or the run is computed again.
    import errno

    from dbf_hpc import xdmf

    sets = ["output.snapshots=3", "basis.estimate=false", f"basis.cache={shared_tmp_path / 'cache'}"]
    out, sidecar = str(shared_tmp_path / "run.h5"), str(shared_tmp_path / "run.xdmf")
    run(load_scene(PAPER, ["integrator.t_end=0.1", *sets]), out, progress=False)

    def full_disk(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    longer = load_scene(PAPER, ["integrator.t_end=0.2", *sets])
    with monkeypatch.context() as patched:
        patched.setattr(xdmf, "write", full_disk)
        with pytest.raises(SolverError, match="but not its ParaView file"):
            run(longer, out, progress=False)
    MPI.COMM_WORLD.Barrier()
    summary = run(longer, out, progress=False, resume=True)
    assert summary["stats"]["final_time"] == pytest.approx(0.2)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(out, "r") as f:
            times = f["snapshots/time"][()]
            described = xdmf.describes(sidecar, f)
        with open(sidecar) as f:
            shown = [float(t) for t in re.findall(r'<Time Value="([^"]+)"', f.read())]
    ok = MPI.COMM_WORLD.bcast(described and np.array_equal(shown, times) and times[-1] == 0.2 if
                              MPI.COMM_WORLD.rank == 0 else None, root=0)
    assert ok, "the ParaView file shows the output's own snapshot times"


def test_a_finished_output_whose_statistics_group_is_damaged_is_not_finished_and_raises_nothing(shared_tmp_path):
    # finished_output reads the statistics back (the summary a requeued --resume returns, a sweep's kept case
    # outputs); where the group's link names cannot be read (its local heap damaged) it raised h5py's
    # RuntimeError, an internal error of the command. Such an output is not finished: it is computed again.
    import struct

    from dbf_hpc.run import finished_output

    sets = ["integrator.t_end=0.05", "basis.estimate=false", f"basis.cache={shared_tmp_path / 'cache'}"]
    out = str(shared_tmp_path / "run.h5")
    scene = load_scene(PAPER, sets)
    run(scene, out, progress=False)
    found = None
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(out, "r") as f:
            ident = {"request": json.loads(f.attrs["run_identity"])["request"]}
        assert finished_output(out, ident, scene) is not None
        data = open(out, "rb").read()
        at = data.find(b"HEAP")
        while at >= 0:   # the local heap whose data segment holds the statistics' names
            size, address = struct.unpack("<Q", data[at + 8:at + 16])[0], struct.unpack("<Q", data[at + 24:at + 32])[0]
            if b"impact_duration_max" in data[address:address + size]:
                break
            at = data.find(b"HEAP", at + 4)
        with open(out, "r+b") as f:
            f.seek(at)
            f.write(b"XXXX")
        found = finished_output(out, ident, scene)
    assert MPI.COMM_WORLD.bcast(found, root=0) is None

def test_ctrl_c_checkpoints_and_stops_as_sigterm_does_and_the_resume_is_the_uninterrupted_run(shared_tmp_path):
    # Red team: Ctrl-C (SIGINT to the foreground job) during the integration ended in a
    # KeyboardInterrupt traceback from the integrator's callback, the .partial and checkpoint left
    # unnamed. SIGINT is a termination signal as SIGTERM is: the run checkpoints at the end of the
    # step, stops with one line, and a resume gives the samples of the run never stopped, bit for bit.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)   # as in a terminal (not ignored)
    try:
        sets = ["integrator.t_end=0.5", "output.checkpoint_dt=0.05", "integrator.callbacks=python",
                f"basis.cache={shared_tmp_path / 'cache'}"]
        whole, out = str(shared_tmp_path / "whole.h5"), str(shared_tmp_path / "stopped.h5")
        run(load_scene(PAPER, sets), whole, progress=False)
        interrupted_run(load_scene(PAPER, sets), out, signal.SIGINT)
        assert_all(not os.path.exists(out) and os.path.exists(out + ".partial") and os.path.exists(out + ".checkpoint"))
        resume(sets, out)
    finally:
        signal.signal(signal.SIGINT, previous)
    MPI.COMM_WORLD.Barrier()
    with h5py.File(whole) as a, h5py.File(out) as b:
        assert bool(b.attrs["complete"]) and a["time"].shape == b["time"].shape
        for name in ("time", "constraints/displacement", "constraints/force", "reduced/q"):
            assert np.array_equal(a[name][:], b[name][:]), name


def test_a_checkpoint_left_beside_a_finished_output_does_not_stop_a_requeued_resume(stopped):
    # Red team: a kill between the output's rename and the checkpoint's removal (or during the
    # ParaView file's write) left OUT.h5 complete beside OUT.h5.checkpoint; a requeued --resume then
    # refused with HDF5's "unable to open file ... .partial" and "rerun without --resume", which
    # computes the finished run again. The finished output of the same question is the answer, kept
    # byte for byte, and the checkpoint, which nothing can resume, is removed.
    sets, out, checkpoint = stopped
    resume(sets, out)
    if MPI.COMM_WORLD.rank == 0:
        shutil.copy(checkpoint + ".good", checkpoint)
    MPI.COMM_WORLD.Barrier()
    before = open(out, "rb").read()
    summary = resume(sets, out)
    assert summary["stats"]["final_time"] == pytest.approx(2.0)
    MPI.COMM_WORLD.Barrier()
    assert_all(open(out, "rb").read() == before and not os.path.exists(checkpoint))


def test_a_checkpoint_whose_partial_is_gone_is_refused_naming_the_missing_file(stopped):
    sets, out, checkpoint = stopped
    if MPI.COMM_WORLD.rank == 0:
        os.remove(out + ".partial")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"run\.h5\.partial, the samples its checkpoint continues, is missing: the "
                                          r"checkpoint cannot be resumed; rerun without --resume$"):
        resume(sets, out)
    assert_all(os.path.exists(checkpoint) and not os.path.exists(out))


@pytest.fixture
def cli_signals():
    """SIGTERM outside an integration as the command handles it (cli._terminated), for the block."""
    from dbf_hpc import cli

    previous = signal.signal(signal.SIGTERM, cli._terminated)
    yield
    signal.signal(signal.SIGTERM, previous)


def _terminate_before(module, name, monkeypatch):
    """Rank 0 sends itself SIGTERM as `module.name` begins (it runs on rank 0 alone)."""
    original = getattr(module, name)

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, terminated)


@pytest.mark.parametrize("method", ["rom", "full"])
def test_sigterm_after_the_integration_before_the_output_is_written_says_so_and_resumes(
        shared_tmp_path, monkeypatch, cli_signals, method):
    # Red team: a batch system's time limit after the integration, before the output's write (the
    # snapshots, the samples' statistics), read "stopped ... before the integration began; nothing
    # was written: rerun to start again" while the .partial and the checkpoint stayed; of a full-order
    # run, the other ranks waited in a broadcast for ever. The line says where the run stopped and
    # that --resume finishes it, on every rank, and the resumed output is the uninterrupted run's.
    from dbf_hpc import run as run_module

    sets = ["integrator.t_end=0.05" if method == "rom" else "integrator.t_end=0.01", "output.checkpoint_dt=0.004",
            "basis.estimate=false", "output.snapshots=3", f"basis.cache={shared_tmp_path / 'cache'}"]
    whole, out = str(shared_tmp_path / "whole.h5"), str(shared_tmp_path / "stopped.h5")
    run(load_scene(PAPER, sets), whole, progress=False, method=method)
    _terminate_before(run_module, "finish", monkeypatch)
    with pytest.raises(SolverError, match="after the integration, before its output was written; rerun with --resume "
                                          r"to finish from the last checkpoint \(samples so far in .*partial"):
        run(load_scene(PAPER, sets), out, progress=False, method=method)
    monkeypatch.undo()
    assert_all(not os.path.exists(out) and os.path.exists(out + ".partial") and os.path.exists(out + ".checkpoint"))
    run(load_scene(PAPER, sets), out, progress=False, method=method, resume=True)
    MPI.COMM_WORLD.Barrier()
    with h5py.File(whole) as a, h5py.File(out) as b:
        assert bool(b.attrs["complete"]) and a["time"].shape == b["time"].shape
        for name in ("time", "constraints/displacement", "constraints/force", "snapshots/w"):
            assert np.array_equal(a[name][:], b[name][:]), name


def test_sigterm_while_the_paraview_file_is_written_waits_for_it(shared_tmp_path, monkeypatch, cli_signals, capfd):
    # Red team: a signal between the output's rename and its ParaView file's write read "wrote OUT.h5,
    # but not its ParaView file: ... nothing was written". The output, renamed, is finished: the
    # signal waits for its ParaView file (a few milliseconds), and the run ends complete.
    from dbf_hpc import run as run_module

    sets = ["integrator.t_end=0.05", "basis.estimate=false", "output.snapshots=3",
            f"basis.cache={shared_tmp_path / 'cache'}"]
    out = str(shared_tmp_path / "run.h5")
    _terminate_before(run_module.xdmf, "write", monkeypatch)
    run(load_scene(PAPER, sets), out, progress=False)
    monkeypatch.undo()
    assert_all(os.path.exists(out) and os.path.exists(str(shared_tmp_path / "run.xdmf"))
               and not os.path.exists(out + ".checkpoint") and not os.path.exists(out + ".partial"))
    if MPI.COMM_WORLD.rank == 0:
        assert "a termination signal came while" in capfd.readouterr().err


def test_a_resume_of_another_scene_names_the_scene_not_a_rebuilt_cache(stopped):
    # Red team: a resume with another probe (or another structure) was refused as "(coordinates, scene
    # differ; the basis was rebuilt since (the cache cleared, another rank count) ...)": the
    # explanation of a rebuilt basis belongs to a changed rank count or cache only.
    sets, out, checkpoint = stopped
    with pytest.raises(InputError) as refused:
        resume([*sets, "output.probes=[0.4]"], out)
    assert "scene" in str(refused.value) and "the cache cleared" not in str(refused.value), str(refused.value)


def _signal_rank_1_at(monkeypatch, module, name: str) -> None:
    """Rank 1 sends itself SIGTERM as `module.name` begins; the handler the run installed takes it."""
    original = getattr(module, name)

    def signalled(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        return original(*args, **kwargs)

    if MPI.COMM_WORLD.rank == 1:
        monkeypatch.setattr(module, name, signalled)


def _same_samples(whole: str, out: str, names) -> None:
    MPI.COMM_WORLD.Barrier()
    with h5py.File(whole) as a, h5py.File(out) as b:
        assert bool(b.attrs["complete"]) and a["time"].shape == b["time"].shape
        for name in names:
            assert np.array_equal(a[name][:], b[name][:]), name


def test_sigterm_to_rank_1_alone_stops_a_reduced_run_for_resume(shared_tmp_path, monkeypatch):
    # Red team: rank 0 integrates a reduced run alone, and a SIGTERM to rank 1 alone (a launcher that
    # signals one process, a node's own limit) was ignored: the job ran on. Rank 1 tells rank 0, which
    # checkpoints at the end of its step and stops with the resume line on every rank; the resume is
    # the uninterrupted run, sample for sample.
    if MPI.COMM_WORLD.size < 2:
        pytest.skip("a signal to another rank than 0: run on 2 ranks")
    from dbf_hpc import run as run_module

    sets = ["integrator.t_end=0.2", "output.checkpoint_dt=10", f"basis.cache={shared_tmp_path / 'cache'}"]
    whole, out = str(shared_tmp_path / "whole.h5"), str(shared_tmp_path / "stopped.h5")
    run(load_scene(PAPER, sets), whole, progress=False)
    _signal_rank_1_at(monkeypatch, run_module, "_wait_telling")
    if MPI.COMM_WORLD.rank == 0:
        # rank 0 starts integrating once rank 1's word is on its way (it cannot finish first): waiting
        # for the message itself, not for a time
        begin = run_module.Checkpointing.__init__

        def after_the_word(self, *args, **kwargs):
            while not MPI.COMM_WORLD.iprobe(source=1, tag=run_module.STOP_TAG):
                time.sleep(0.01)
            begin(self, *args, **kwargs)

        monkeypatch.setattr(run_module.Checkpointing, "__init__", after_the_word)
    with pytest.raises(SolverError, match=r"stopped by a termination signal at t = .*rerun with --resume"):
        run(load_scene(PAPER, sets), out, progress=False)
    monkeypatch.undo()
    assert_all(not os.path.exists(out) and os.path.exists(out + ".partial") and os.path.exists(out + ".checkpoint"))
    resume(sets, out)
    _same_samples(whole, out, ("time", "constraints/displacement", "constraints/force", "reduced/q"))


def test_sigterm_to_rank_1_alone_during_the_error_estimate_stops_the_run_for_resume(shared_tmp_path, monkeypatch):
    # Red team: rank 0 makes a reduced run's estimates alone after its integration (a long run's
    # statistics cost about what the run did), and a SIGTERM to rank 1 alone then was not acted on: the
    # job ran on to its end. Rank 1's word now stops the estimate as rank 0's own signal does: the line
    # says so on every rank, the samples and the checkpoint stay, and the resume is the uninterrupted run.
    if MPI.COMM_WORLD.size < 2:
        pytest.skip("a signal to another rank than 0: run on 2 ranks")
    from dbf_hpc import run as run_module

    world, in_estimate = MPI.COMM_WORLD, 7302
    sets = ["integrator.t_end=0.05", "output.checkpoint_dt=0.01", f"basis.cache={shared_tmp_path / 'cache'}"]
    whole, out = str(shared_tmp_path / "whole.h5"), str(shared_tmp_path / "stopped.h5")
    run(load_scene(PAPER, sets), whole, progress=False)
    if world.rank == 0:
        original = run_module._estimate

        def estimate_after_the_word(*args, **kwargs):   # rank 1 is signalled once rank 0 is in its estimate
            world.send(True, dest=1, tag=in_estimate)
            deadline = time.monotonic() + 60   # the alarm raises in this wait (bounded: no hang if it does not)
            while time.monotonic() < deadline:
                time.sleep(0.01)
            return original(*args, **kwargs)

        monkeypatch.setattr(run_module, "_estimate", estimate_after_the_word)
    elif world.rank == 1:
        wait = run_module._wait_telling

        def signalled_in_the_estimate(comm):
            comm.recv(source=0, tag=in_estimate)
            os.kill(os.getpid(), signal.SIGTERM)   # the handler the run installed takes it
            return wait(comm)

        monkeypatch.setattr(run_module, "_wait_telling", signalled_in_the_estimate)
    with pytest.raises(SolverError, match="during the error estimates, after the integration; rerun with --resume "
                                          r"to finish from the last checkpoint \(samples so far in .*partial"):
        run(load_scene(PAPER, sets), out, progress=False)
    monkeypatch.undo()
    assert signal.getsignal(signal.SIGALRM) in (signal.SIG_DFL, None) and signal.getitimer(signal.ITIMER_REAL)[0] == 0
    assert_all(not os.path.exists(out) and os.path.exists(out + ".partial") and os.path.exists(out + ".checkpoint"))
    resume(sets, out)
    _same_samples(whole, out, ("time", "constraints/displacement", "constraints/force", "reduced/q"))
    with h5py.File(whole) as a, h5py.File(out) as b:
        assert a.attrs["estimated_error"] == b.attrs["estimated_error"]


def test_sigterm_to_rank_1_alone_stops_a_full_order_run_for_resume(shared_tmp_path, monkeypatch):
    # Red team: only rank 0's signal stopped a full-order run; every rank integrates it, and rank 1's
    # flag reaches rank 0 at the next control point, where every rank stops after rank 0's checkpoint.
    if MPI.COMM_WORLD.size < 2:
        pytest.skip("a signal to another rank than 0: run on 2 ranks")
    from dbf_hpc import run as run_module

    sets = ["integrator.t_end=0.1", "integrator.dt=1e-4", "basis.estimate=false", "basis.cache=off"]
    whole, out = str(shared_tmp_path / "whole.h5"), str(shared_tmp_path / "stopped.h5")
    run(load_scene(PAPER, sets), whole, progress=False, method="full")
    _signal_rank_1_at(monkeypatch, run_module, "integrate_full")
    with pytest.raises(SolverError, match=r"stopped by a termination signal at t = .*rerun with --resume"):
        run(load_scene(PAPER, sets), out, progress=False, method="full")
    monkeypatch.undo()
    assert_all(not os.path.exists(out) and os.path.exists(out + ".partial") and os.path.exists(out + ".checkpoint"))
    run(load_scene(PAPER, sets), out, progress=False, method="full", resume=True)
    _same_samples(whole, out, ("time", "constraints/displacement", "constraints/force"))


def test_sigterm_during_a_full_order_runs_estimate_resumes_from_the_integrations_end(shared_tmp_path, monkeypatch):
    # Red team: a full-order run stopped in its error estimate (a second integration at a 4 times shorter
    # step) resumed from its last in-run checkpoint, or from t = 0 when the run was too short to write one,
    # and integrated again. The integration's end is checkpointed before the estimate: the resume only
    # redoes the estimate, and its output is the uninterrupted run's, estimate included.
    from dbf_hpc import run as run_module
    from dbf_hpc import fom_integrator

    sets = ["integrator.t_end=0.1", "integrator.dt=1e-4", "basis.cache=off"]
    whole, out = str(shared_tmp_path / "whole.h5"), str(shared_tmp_path / "stopped.h5")
    run(load_scene(PAPER, sets), whole, progress=False, method="full")
    integrate = fom_integrator.integrate_full

    def terminated(*args, **kwargs):   # rank 0's signal, as the estimate's integration begins
        if isinstance(kwargs.get("control"), run_module._EstimateControl):
            os.kill(os.getpid(), signal.SIGTERM)
        return integrate(*args, **kwargs)

    monkeypatch.setattr(run_module, "integrate_full", terminated)
    with pytest.raises(SolverError, match="during the error estimate, after the integration; rerun with --resume"):
        run(load_scene(PAPER, sets), out, progress=False, method="full")
    monkeypatch.undo()
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(out + ".checkpoint", "r") as f:
            assert float(f["t"][()]) == pytest.approx(0.1, rel=1e-12)
    starts = []

    def counted(fom, settings, *args, resume=None, **kwargs):
        starts.append((settings.t_end, None if resume is None else float(resume["t"])))
        return integrate(fom, settings, *args, resume=resume, **kwargs)

    monkeypatch.setattr(run_module, "integrate_full", counted)
    summary = run(load_scene(PAPER, sets), out, progress=False, method="full", resume=True)
    assert starts[0] == (0.1, pytest.approx(0.1, rel=1e-12)), "the resume starts at the integration's end"
    assert len(starts) == 2 and starts[1][0] < 0.1 and starts[1][1] is None, "then only the estimate integrates"
    assert np.isfinite(summary["estimated_error"])
    _same_samples(whole, out, ("time", "constraints/displacement", "constraints/force"))
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(whole) as a, h5py.File(out) as b:
            assert a.attrs["estimated_error"] == b.attrs["estimated_error"]
            assert np.array_equal(a["constraints/stats/impacts"][:], b["constraints/stats/impacts"][:])


def test_a_file_left_at_the_checkpoints_temporary_name_is_replaced_not_written_through(shared_tmp_path):
    # Red team: Checkpoint.write opened OUT.h5.checkpoint.tmp for writing as it found it: a symlink left
    # there had HDF5 overwrite the file it pointed to (a user's file, clobbered). A killed run's file of
    # another scene there is replaced; a directory there is a write error (the run's one line), kept.
    from dbf_hpc.checkpoint import Checkpoint

    ok = True
    if MPI.COMM_WORLD.rank == 0:
        precious = shared_tmp_path / "precious.txt"
        precious.write_text("a user's own file")
        path = str(shared_tmp_path / "x.h5.checkpoint")
        os.symlink(precious, path + ".tmp")
        checkpoint = Checkpoint(path, {"scene": "this one"})
        checkpoint.write({"t": 1.5, "q": np.arange(3.0)})
        ok &= precious.read_text() == "a user's own file" and not os.path.lexists(path + ".tmp")
        ok &= float(checkpoint.read()["t"]) == 1.5
        with open(path + ".tmp", "wb") as f:   # a killed run's half-written checkpoint of another scene
            f.write(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
        checkpoint.write({"t": 2.5, "q": np.arange(3.0)})
        ok &= float(checkpoint.read()["t"]) == 2.5 and not os.path.lexists(path + ".tmp")
        os.mkdir(path + ".tmp")
        from dbf_hpc.errors import PARKED
        parked = len(PARKED)
        with pytest.raises(OSError):
            checkpoint.write({"t": 3.5, "q": np.arange(3.0)})
        ok &= os.path.isdir(path + ".tmp") and float(checkpoint.read()["t"]) == 2.5
        # no file was opened, so none is parked: an entry there (None) had every later failed run in this
        # process keep its .partial open (OutputWriter.abort), and the next run on it failed ("already open")
        ok &= len(PARKED) == parked
    assert_all(ok)
