"""Outputs (output.py, run.py): what is refused before any work, and the lock that keeps two jobs off
one output where HDF5's own file locking is switched off (Lustre, NFS)."""
import os
import re
import socket
import time

import pytest
from mpi4py import MPI

from conftest import assert_all, ends_a_hang, fifo_at, rank0_files
from dbf_hpc.errors import InputError
from dbf_hpc.output import OutputLock, check_output_path
from dbf_hpc.run import run
from dbf_hpc.scene import load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER = os.path.join(ROOT, "jobs", "paper_beam.toml")
SHORT = ["basis.cache=off", "integrator.t_end=0.01"]


def test_an_output_onto_the_scene_itself_is_refused_and_the_scene_survives(shared_tmp_path):
    scene_path = shared_tmp_path / "scene.toml"
    if MPI.COMM_WORLD.rank == 0:
        scene_path.write_text(open(PAPER).read())
    MPI.COMM_WORLD.Barrier()
    before = scene_path.read_bytes()
    with pytest.raises(InputError, match="is the scene this run reads"):
        run(load_scene(str(scene_path), SHORT), str(scene_path), progress=False)
    assert_all(scene_path.read_bytes() == before)


def test_a_directory_as_output_is_refused_before_any_work(shared_tmp_path):
    with pytest.raises(InputError, match="is a directory: give a file name"):
        run(load_scene(PAPER, SHORT), str(shared_tmp_path), progress=False)
    assert_all(not list(shared_tmp_path.glob("*.partial")))


@pytest.mark.parametrize("out", ["", "  "])
def test_an_empty_output_name_is_refused_not_taken_for_the_scenes_output(shared_tmp_path, out, monkeypatch):
    # Red team: run(scene, "") (and `dbf-hpc run SCENE -o ""`) wrote the scene's [output] file, in silence
    monkeypatch.chdir(shared_tmp_path)   # (a blank name is a file of this folder)
    scene = load_scene(PAPER, [*SHORT, f'output.file="{shared_tmp_path / "default.h5"}"'])
    with pytest.raises(InputError, match=f"^output {re.escape(repr(out))} is an empty name: give a file name, or none "
                                         f"for the scene's \\[output\\] file$"):
        run(scene, out, progress=False)
    assert_all(not os.listdir(shared_tmp_path))


@pytest.mark.parametrize("name, refusal", [
    ("out.h5/", "output '{tmp}/out.h5/' ends in '/', as a directory's name does: give a file name, e.g. '{tmp}/out.h5'"),
    ("notes.txt/out.h5", "output '{tmp}/notes.txt/out.h5': '{tmp}/notes.txt' is not a directory")])
def test_an_output_whose_folder_is_not_one_is_refused_saying_so(shared_tmp_path, name, refusal):
    # Red team: "out.h5/" was refused as "output 'out.h5/.partial': directory 'out.h5' does not exist", and
    # an output in a "folder" that is a file said that folder did not exist
    if MPI.COMM_WORLD.rank == 0:
        (shared_tmp_path / "notes.txt").write_text("notes")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=f"^{re.escape(refusal.format(tmp=shared_tmp_path))}$"):
        run(load_scene(PAPER, SHORT), f"{shared_tmp_path}/{name}", progress=False)
    assert_all(sorted(os.listdir(shared_tmp_path)) == ["notes.txt"])


def test_an_output_name_too_long_for_the_files_beside_it_is_refused_before_any_work(shared_tmp_path):
    # Red team: a 241-byte name was accepted, and the run (and every --resume of it) failed at its first
    # checkpoint: "Unable to create file (... OUT.h5.checkpoint.tmp ... File name too long)". The longest
    # name written beside the output decides (the lock a next job sets aside, OUT.h5.lock.stale-HOST-PID).
    import socket

    longest = len(os.fsencode(f".lock.stale-{socket.gethostname()}-4194304"))
    limit = os.pathconf(shared_tmp_path, "PC_NAME_MAX") - longest
    too_long = str(shared_tmp_path / ("c" * (limit + 1 - 3) + ".h5"))
    with pytest.raises(InputError, match=f"a name of {limit + 1} bytes, too long for the files written beside it "
                                         f".* give a name of at most {limit} bytes$"):
        run(load_scene(PAPER, SHORT), too_long, progress=False)
    assert_all(not os.listdir(shared_tmp_path))
    just = str(shared_tmp_path / ("c" * (limit - 3) + ".h5"))
    run(load_scene(PAPER, SHORT), just, progress=False)
    assert_all(os.path.isfile(just))


def test_an_existing_file_that_is_not_a_dbf_output_is_not_replaced(shared_tmp_path):
    target = shared_tmp_path / "notes.h5"
    if MPI.COMM_WORLD.rank == 0:
        target.write_text("my notes")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match="exists and is not a dbf-hpc output"):
        check_output_path(str(target))
    run(load_scene(PAPER, SHORT), str(shared_tmp_path / "ok.h5"), progress=False)
    run(load_scene(PAPER, SHORT), str(shared_tmp_path / "ok.h5"), progress=False)   # a rerun replaces its own
    assert_all(target.read_text() == "my notes")




def test_a_pipe_at_the_output_path_is_refused_not_waited_on(shared_tmp_path):
    # Red team: `-o out.h5` where out.h5 is a named pipe (a FIFO) hung the run before any work, on any
    # rank count: the look at whether the file is dbf-hpc's opened it, and the open waited for a writer
    # for ever. A pipe, socket or device is not a file to replace: refused in one line, left as it is.
    import stat

    target = shared_tmp_path / "out.h5"
    fifo_at(target)
    with ends_a_hang(), pytest.raises(InputError, match="exists and is not a regular file"):
        run(load_scene(PAPER, SHORT), str(target), progress=False)
    assert_all(stat.S_ISFIFO(os.stat(target).st_mode))


def test_a_pipe_at_the_output_lock_is_refused_not_waited_on(shared_tmp_path):
    # Red team: a named pipe at OUT.h5.lock hung the run before any work: the lock exists, so its
    # content was read to tell a live job from a stale one, and the open waited for a writer for ever.
    import stat

    out = shared_tmp_path / "out.h5"
    lock = shared_tmp_path / "out.h5.lock"
    fifo_at(lock)
    with ends_a_hang(), pytest.raises(InputError, match=f"remove {lock}"):
        run(load_scene(PAPER, SHORT), str(out), progress=False)
    assert_all(stat.S_ISFIFO(os.stat(lock).st_mode) and not out.exists())


@pytest.mark.parametrize("what", ["directory", "broken link"])
def test_a_lock_that_no_job_made_is_refused_as_what_it_is_not_as_another_jobs(shared_tmp_path, what):
    # Red team: a directory (or a link to a missing file) at OUT.h5.lock was "being written by another job
    # (unknown job)"
    out, lock = shared_tmp_path / "out.h5", shared_tmp_path / "out.h5.lock"
    if MPI.COMM_WORLD.rank == 0:
        lock.mkdir() if what == "directory" else lock.symlink_to(shared_tmp_path / "gone")
    MPI.COMM_WORLD.Barrier()
    said = "is a directory" if what == "directory" else "is a symbolic link to a missing file"
    with pytest.raises(InputError, match=f"^output {re.escape(repr(str(out)))}: its lock {re.escape(repr(str(lock)))} "
                                         f"{said}, which no dbf-hpc job made: remove {re.escape(str(lock))}$"):
        run(load_scene(PAPER, SHORT), str(out), progress=False)
    assert_all(os.path.lexists(lock) and not out.exists())


@pytest.mark.parametrize("resume", [False, True])
@pytest.mark.parametrize("beside", [".partial", ".checkpoint"])
def test_a_directory_where_the_run_writes_beside_its_output_is_refused_naming_the_output(shared_tmp_path, beside,
                                                                                         resume):
    # Red team: a directory at OUT.h5.partial was refused with "give a file name, e.g. 'OUT.h5.partial/out.h5'",
    # and at OUT.h5.checkpoint (--resume) with "cannot be read (OSError)"
    out = shared_tmp_path / "out.h5"
    if MPI.COMM_WORLD.rank == 0:
        (shared_tmp_path / f"out.h5{beside}").mkdir()
    MPI.COMM_WORLD.Barrier()
    said = (f"{out}.checkpoint is a directory, not a checkpoint: remove it or choose another output name"
            if beside == ".checkpoint" and resume else
            f"output {str(out)!r}: {str(out) + beside!r}, which the run writes beside it, is a directory: remove it or "
            f"choose another output name")
    with pytest.raises(InputError, match=f"^{re.escape(said)}$"):
        run(load_scene(PAPER, SHORT), str(out), progress=False, resume=resume)
    assert_all(rank0_files(shared_tmp_path) == [f"out.h5{beside}"])


@pytest.mark.parametrize("resume", [False, True])
def test_a_rerun_onto_an_output_whose_metadata_is_damaged_is_one_line_and_leaves_it(shared_tmp_path, resume):
    # Red team (bytes flipped across a finished output): where the file opens but its root group's links
    # cannot be read, a rerun onto it, with or without --resume, ended in "internal error (RuntimeError) on
    # rank 0: Unable to get link info (...)", from the look at whether the file is dbf-hpc's. A damaged
    # file is refused as other files that are not a readable output are, before any work, and kept.
    out = shared_tmp_path / "run.h5"
    run(load_scene(PAPER, SHORT), str(out), progress=False)
    if MPI.COMM_WORLD.rank == 0:
        data = out.read_bytes()
        at = data.index(b"HEAP")   # the root group's local heap (its link names), the file's first
        out.write_bytes(data[:at] + b"XXXX" + data[at + 4:])
    MPI.COMM_WORLD.Barrier()
    before = out.read_bytes()
    with pytest.raises(InputError, match="exists and is not a dbf-hpc output: remove it or choose another name"):
        run(load_scene(PAPER, SHORT), str(out), progress=False, resume=resume)
    assert_all(out.read_bytes() == before and not list(shared_tmp_path.glob("run.h5.*")))

def test_a_second_job_on_an_output_being_written_is_refused_naming_the_first(shared_tmp_path, monkeypatch):
    monkeypatch.setenv("HDF5_USE_FILE_LOCKING", "FALSE")
    target = str(shared_tmp_path / "busy.h5")
    lock = OutputLock(target)
    if MPI.COMM_WORLD.rank == 0:
        lock.acquire()                         # the first job (this process: alive)
    MPI.COMM_WORLD.Barrier()
    try:
        with pytest.raises(InputError, match=f"being written by another job \\(pid {os.getpid() if MPI.COMM_WORLD.rank == 0 else ''}"):
            run(load_scene(PAPER, SHORT), target, progress=False)
    finally:
        if MPI.COMM_WORLD.rank == 0:
            lock.release()
    MPI.COMM_WORLD.Barrier()
    run(load_scene(PAPER, SHORT), target, progress=False)
    # rank 0 removes the lock as its run() returns: rank 1, back from the same run, looked before it did
    # (failed on 2 ranks every time on a loaded 2-core machine)
    MPI.COMM_WORLD.Barrier()
    assert_all(os.path.exists(target) and not os.path.exists(target + ".lock"))


def test_an_output_whose_partial_another_process_writes_is_refused_as_busy_not_as_a_lockless_file_system(
        shared_tmp_path, monkeypatch):
    # Red team: with HDF5's file locks working, a second run on an output being written (and `info` on
    # a killed job's .partial while its rank was still exiting) read "the file system refuses HDF5's
    # file locks: set HDF5_USE_FILE_LOCKING=FALSE": a false cause, and advice that lets a reader see a
    # file half written. HDF5's lock is held (errno 11): the refusal says another process writes it.
    import subprocess
    import sys

    monkeypatch.delenv("HDF5_USE_FILE_LOCKING", raising=False)
    target = str(shared_tmp_path / "held.h5")
    holder = None
    if MPI.COMM_WORLD.rank == 0:
        holder = subprocess.Popen(
            [sys.executable, "-c", "import h5py, sys; f = h5py.File(sys.argv[1], 'w'); f.attrs['complete'] = False; "
             "f.flush(); print('open', flush=True); sys.stdin.read()", target + ".partial"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert holder.stdout.readline().strip() == "open"
    MPI.COMM_WORLD.Barrier()
    try:
        with pytest.raises(InputError) as refused:
            run(load_scene(PAPER, SHORT), target, progress=False)
        assert "another process has it open for writing" in str(refused.value), str(refused.value)
        assert "HDF5_USE_FILE_LOCKING" not in str(refused.value)
    finally:
        if holder is not None:
            holder.communicate("", timeout=60)
        MPI.COMM_WORLD.Barrier()
    assert_all(not os.path.exists(target))


def test_every_rank_takes_rank_0s_answer_on_the_output_path(shared_tmp_path, monkeypatch):
    # Red team: each rank checked the output's files itself; when the files changed between the ranks'
    # looks (another job's .partial closed meanwhile), one rank refused and the other waited in the
    # next collective call for ever. Rank 0 (which writes) checks; every rank refuses alike.
    from dbf_hpc import run as run_module

    if MPI.COMM_WORLD.rank == 0:
        def seen_busy(*args):
            raise InputError("rank 0 saw the output busy")
        monkeypatch.setattr(run_module, "output_path", seen_busy)
    with pytest.raises(InputError, match="rank 0 saw the output busy"):
        run(load_scene(PAPER, SHORT), str(shared_tmp_path / "agreed.h5"), progress=False)
    assert_all(not os.path.exists(shared_tmp_path / "agreed.h5.partial"))


def test_info_on_a_partial_its_run_still_writes_says_so_instead_of_advising_a_resume(tmp_path, monkeypatch):
    # Red team: with HDF5_USE_FILE_LOCKING=FALSE, `info` on the .partial of a run still going said "a
    # checkpoint exists: rerun with --resume to continue", which the run's lock refused. A live lock
    # names the run; once its job is gone, the advice to resume comes back.
    import h5py

    from dbf_hpc.report import describe

    monkeypatch.setenv("HDF5_USE_FILE_LOCKING", "FALSE")
    target = str(tmp_path / "going.h5")
    with h5py.File(target + ".partial", "w") as f:
        f.create_dataset("time", data=[0.0, 0.1])
        f.attrs["complete"] = False
    open(target + ".checkpoint", "w").close()
    lock = OutputLock(target)
    lock.acquire()                              # the run (this process: alive)
    try:
        lines = describe(target)
    finally:
        lock.release()
    assert f"being written by a run now (pid {os.getpid()} on" in lines[0] and "--resume" not in " ".join(lines)
    with open(target + ".lock", "w") as f:      # a killed job's lock: no such process
        f.write(f"{socket.gethostname()} {2**22 + 12345}\n")
    lines = describe(target)
    assert "the run did not finish" in lines[0] and "rerun with --resume to continue" in lines[1]


def test_an_empty_lock_of_a_job_killed_as_it_made_it_is_taken_over_once_older_than_any_live_write(tmp_path):
    # red team: SIGKILL between the lock's creation and its write left an empty OUT.h5.lock, refused as
    # "unknown job" for ever; a job writes it within microseconds, so one older than EMPTY_LOCK_AGE is gone
    from dbf_hpc.output import EMPTY_LOCK_AGE

    target = str(tmp_path / "empty.h5")
    open(target + ".lock", "w").close()
    with pytest.raises(InputError, match=r"being written by another job \(an empty lock, made by a job now starting "
                                         r"or killed as it made it; it counts as gone 60 s after it was made\)"):
        OutputLock(target).acquire()
    old = time.time() - EMPTY_LOCK_AGE - 1.0
    os.utime(target + ".lock", (old, old))
    lock = OutputLock(target)
    lock.acquire()
    assert open(target + ".lock").read().split()[1] == str(os.getpid())
    lock.release()
    assert not os.path.exists(target + ".lock")


@pytest.mark.serial
def test_a_held_lock_replaced_by_bytes_that_are_not_text_is_left_and_its_release_raises_nothing(tmp_path):
    # Red team: rank 0 releases the lock alone, then every rank meets in a barrier (run.claimed, the sweep's);
    # a lock file overwritten with bytes that are not UTF-8 made release() raise UnicodeDecodeError on rank 0
    # alone, and the other ranks waited in that barrier for ever. Not text is not ours: it stays.
    target = str(tmp_path / "junk.h5")
    lock = OutputLock(target)
    lock.acquire()
    with open(target + ".lock", "wb") as f:
        f.write(b"\xff\xfe\x00 not a lock of ours")
    lock.release()
    assert not lock.held and open(target + ".lock", "rb").read() == b"\xff\xfe\x00 not a lock of ours"


def test_a_lock_left_by_a_dead_job_on_this_host_is_taken_over(tmp_path):
    target = str(tmp_path / "old.h5")
    dead = 2**22 + 12345                       # above the default pid_max: no such process
    with open(target + ".lock", "w") as f:
        f.write(f"{socket.gethostname()} {dead}\n")
    lock = OutputLock(target)
    lock.acquire()
    assert open(target + ".lock").read().split()[1] == str(os.getpid())
    lock.release()
    with open(target + ".lock", "w") as f:
        f.write(f"another-host {dead}\n")      # another host's job cannot be checked: refused
    with pytest.raises(InputError, match="pid .* on another-host"):
        OutputLock(target).acquire()


def test_a_lock_whose_pid_another_process_got_since_is_taken_over_but_not_a_live_jobs(tmp_path):
    # Red team: a killed job's lock named only its host and pid; once another process had that pid (pids
    # are reused, and start again from 1 after a reboot) the lock blocked every job on the output for as
    # long as that process lived. The lock holds when its process started (boot id, start ticks).
    from dbf_hpc.output import lock_owner

    target = str(tmp_path / "reused.h5")
    host, pid, start = lock_owner().split()
    assert pid == str(os.getpid()) and start != "-"       # Linux: /proc tells when a process started
    boot, ticks = start.split("/")
    for other in (f"{boot}/{int(ticks) + 1}", f"another-boot/{ticks}"):   # this pid, another process's start
        with open(target + ".lock", "w") as f:
            f.write(f"{host} {pid} {other}\n")
        lock = OutputLock(target)
        lock.acquire()
        assert open(target + ".lock").read() == lock_owner()
        lock.release()
    with open(target + ".lock", "w") as f:       # the live job itself (this process): refused, named
        f.write(lock_owner())
    with pytest.raises(InputError, match=f"being written by another job \\(pid {pid} on {host}\\)"):
        OutputLock(target).acquire()
    os.remove(target + ".lock")


def test_the_locks_a_process_holds_are_removed_before_an_abort_but_never_another_jobs(tmp_path):
    # An abort (cli._abort) runs no `finally`: the locks this process holds are released from
    # output.HELD first. Only its own: a lock removed by hand and made again by another job stays.
    from dbf_hpc.output import HELD, release_held_locks

    ours, theirs = OutputLock(str(tmp_path / "a.h5")), OutputLock(str(tmp_path / "b.h5"))
    ours.acquire()
    theirs.acquire()
    os.remove(theirs.lock)
    with open(theirs.lock, "w") as f:
        f.write("another-host 12345\n")
    release_held_locks()
    assert not os.path.exists(ours.lock) and not HELD
    assert open(theirs.lock).read() == "another-host 12345\n"


def test_every_dataset_of_a_run_carries_its_unit(shared_tmp_path):
    import h5py

    run(load_scene(PAPER, SHORT + ["output.snapshots=3", "output.probes=[0.5]"]), str(shared_tmp_path / "u.h5"),
        progress=False)
    if MPI.COMM_WORLD.rank == 0:
        missing = []
        with h5py.File(shared_tmp_path / "u.h5") as f:
            f.visititems(lambda name, obj: missing.append(name) if isinstance(obj, h5py.Dataset) and "unit" not in
                         obj.attrs and "unit" not in obj.parent.attrs else None)
        assert not missing, missing


def test_the_output_reference_in_docs_is_generated_from_the_layout_and_up_to_date():
    from dbf_hpc.layout import reference

    with open(os.path.join(ROOT, "docs", "outputs.md")) as f:
        assert f.read() == reference(), "regenerate it: python -m dbf_hpc.layout > docs/outputs.md"


def test_a_failed_write_leaves_the_old_file_and_no_temporary_one(tmp_path):
    # The writers of tables, figures, XDMF files and sweep records (errors.replacing): a full disk
    # was an internal error that left NAME.tmp-PID beside the file.
    import errno

    from dbf_hpc.errors import DbfError, replacing

    target = tmp_path / "table.csv"
    target.write_text("old")
    with pytest.raises(DbfError, match=f"cannot write {target}: No space left on device"):
        with replacing(str(target)) as tmp:
            open(tmp, "w").write("half")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]
    with replacing(str(target)) as tmp:
        open(tmp, "w").write("new")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]


def test_a_job_that_found_a_lock_stale_leaves_the_live_lock_another_job_took_meanwhile(tmp_path):
    # Red team: two jobs found a dead job's lock stale at once; the second removed the lock the first
    # had just made, and both wrote the output (once in 40 tries).
    import socket

    from dbf_hpc.output import OutputLock, lock_owner

    path = str(tmp_path / "out.h5")
    dead = f"{socket.gethostname()} 999999\n"
    with open(path + ".lock", "w") as f:
        f.write(dead)
    first, second = OutputLock(path), OutputLock(path)
    seen_by_second = second._stale()
    assert seen_by_second == dead
    first.acquire()                       # took the dead job's lock over
    second._take_over(seen_by_second)     # the second job acts on what it saw before
    with open(path + ".lock") as f:
        assert f.read() == lock_owner() and lock_owner().split()[:2] == [socket.gethostname(), str(os.getpid())]
    with pytest.raises(InputError, match="is being written by another job"):
        second.acquire()
    first.release()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_an_output_whose_write_failed_is_kept_open_not_closed(tmp_path):
    # Red team (sweeps on a 3 MB tmpfs): closing an output after its write failed on the full disk
    # crashed HDF5 (signal 11) once another failed file was parked in the process; after a failed write
    # the output is parked (errors.park) and its .partial stays as last flushed.
    from dbf_hpc.errors import PARKED
    from dbf_hpc.output import OutputWriter

    writer = OutputWriter(str(tmp_path / "out.h5"), (1,), 1, 0)
    writer.append(**{"time": 0.0, "constraints/displacement": [0.0], "constraints/velocity": [0.0],
                     "constraints/force": [0.0], "constraints/force_peak": [0.0], "probes/displacement": [0.0],
                     "reduced/q": [], "reduced/qdot": []})
    writer.flush()
    before = len(PARKED)
    writer.abort(failed_write=True)
    try:
        assert writer.parked and writer.file.id.valid, "parked, never closed"
        assert any(obj is writer.file for obj in PARKED[before:])
    finally:
        writer.file.close()
        del PARKED[before:]


def test_reduced_coordinates_carry_the_units_of_an_m_orthonormal_basis(shared_tmp_path):
    # The paper's beam released from 1 mm in its first mode: the M-orthonormal mode is
    # sqrt(2 / (rho A L)) sin(pi x / L) (kg^-1/2), so q_1(0) = 1 mm sqrt(rho A L / 2) (m kg^1/2) and B at
    # x = 0.25 m is sqrt(2 / (rho A L)) sin(pi / 4): w = B q in m, not q in 1 and B in m (red team).
    import h5py
    import numpy as np

    rhoA, L = 11800 * 2.9e-7, 1.0
    path = str(shared_tmp_path / "units.h5")
    run(load_scene(PAPER, SHORT + ["excitation.kind=none", "initial.amplitude=1e-3", "basis.estimate=false"]), path,
        progress=False)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(path, "r") as f:
            q, B = f["reduced/q"], f["reduced/B"]
            assert (q.attrs["unit"], f["reduced/qdot"].attrs["unit"], B.attrs["unit"]) == \
                ("m kg^(1/2)", "m kg^(1/2)/s", "kg^(-1/2)")
            assert abs(abs(q[0, 0]) - 1e-3 * np.sqrt(rhoA * L / 2)) < 1e-6 * 1e-3 * np.sqrt(rhoA * L / 2)
            assert abs(abs(B[0, 0]) - np.sqrt(2 / (rhoA * L)) * np.sin(np.pi / 4)) < 1e-4 * np.sqrt(2 / (rhoA * L))
            assert abs(B[0] @ q[0] - f["constraints/displacement"][0, 0]) < 1e-12


@pytest.mark.parametrize("method", ["rom", "full"])
def test_samples_start_at_0_step_by_sample_dt_and_end_at_t_end_with_its_state(shared_tmp_path, method):
    # sample_dt = 3 ms does not divide t_end = 10 ms: the samples are 0, 3, 6, 9 and 10 ms, the last the state at
    # t_end. Free vibration in the pinned-pinned mode 3 (1 mm, clear of the 2.5 mm stop): w(0.5, t) =
    # -1 mm cos(omega_3 t), omega_3 = (3 pi)^2 sqrt(EI / rho A); cos changes by 1.4e-3 from 9 to 10 ms.
    import h5py
    import numpy as np

    omega = (3 * np.pi) ** 2 * np.sqrt(117e9 * 8.78e-16 / (11800 * 2.9e-7))
    path = str(shared_tmp_path / f"times_{method}.h5")
    run(load_scene(PAPER, SHORT + ["excitation.kind=none", "initial.mode=3", "initial.amplitude=1e-3",
                                   "output.sample_dt=3e-3", "output.probes=[0.5]", "integrator.dt=1e-5",
                                   "basis.estimate=false"]), path, progress=False, method=method)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(path, "r") as f:
            t, w = f["time"][:], f["probes/displacement"][:, 0]
        np.testing.assert_allclose(t, [0.0, 3e-3, 6e-3, 9e-3, 1e-2], rtol=0, atol=1e-15)
        exact = 1e-3 * np.cos(omega * t) * np.sign(w[0])
        assert np.abs(w - exact).max() < 1e-4 * 1e-3, (w, exact)


def test_info_on_a_partial_killed_before_its_first_samples_says_what_left_it_and_what_to_do(tmp_path):
    # it said only "is damaged (truncated file ...)"
    import h5py
    import numpy as np

    from dbf_hpc.report import open_output

    partial = tmp_path / "run.h5.partial"
    with h5py.File(partial, "w") as f:
        f["time"] = np.arange(1000.0)
    partial.write_bytes(partial.read_bytes()[:600])   # HDF5's signature, its data never flushed
    with pytest.raises(InputError, match=r"cannot be read .*killed before HDF5 wrote its first samples.*rerun"):
        open_output(str(tmp_path / "run.h5"))


def test_a_refusal_for_room_names_the_room_it_asks_not_less_than_the_free_space(tmp_path, monkeypatch):
    # Red team: "output 'a.h5' needs about 1.84 MiB and '...' has 2.99 MiB free" refused a run: the check
    # asks 10 % and 1 MiB more than the output's size. The line names what it asks, which the free space
    # falls short of.
    import re

    from dbf_hpc import output

    monkeypatch.setattr(output, "free_bytes", lambda folder: 3.0 * 2**20)
    with pytest.raises(InputError) as refused:
        output.check_free_space(str(tmp_path / "a.h5"), 1.84 * 2**20)
    asked = float(re.search(r"([\d.]+) MiB with room to spare", str(refused.value)).group(1))
    free = float(re.search(r"has ([\d.]+) MiB free", str(refused.value)).group(1))
    assert asked == pytest.approx(1.1 * 1.84 + 1, rel=1e-2) and asked > free
    output.check_free_space(str(tmp_path / "a.h5"), 1.7 * 2**20)   # 2.87 MiB asked: room enough


def test_each_snapshot_vector_dataset_carries_its_own_unit_not_only_its_group(shared_tmp_path):
    # New-user pass: docs/outputs.md says every dataset carries unit and description; the datasets
    # snapshots/displacement/NNNNNN had none (only their group had), so a script reading a dataset's unit
    # found no attribute.
    import h5py

    run(load_scene(PAPER, SHORT + ["output.snapshots=3"]), str(shared_tmp_path / "s.h5"), progress=False)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(shared_tmp_path / "s.h5") as f:
            members = list(f["snapshots/displacement"].values())
            assert len(members) == 3
            for member in members:
                assert member.attrs["unit"] == "m" and "displacement vectors" in member.attrs["description"]
