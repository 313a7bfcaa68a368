"""Parameter studies (sweep.py): cases over the ranks, one basis per distinct structure, a summary
with the impact statistics, resume after a kill, failed cases recorded."""
import json
import os
import re

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from conftest import assert_all, ends_a_hang, fifo_at, rank0_files, two_ranks_of
from dbf_hpc.errors import DbfError, InputError
from dbf_hpc.modes import counters
from dbf_hpc.report import describe
from dbf_hpc.stats import STATISTICS
from dbf_hpc.sweep import load_sweep, run_sweep

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER = os.path.join(ROOT, "jobs", "paper_beam.toml")


def write_sweep(folder, body, scene=PAPER, name="sweep.toml", output="summary.h5"):
    path = folder / name
    # every rank is done with the file this one replaces (red team, 2 ranks on a loaded machine: rank 1 still
    # read the first sweep of a test when rank 0 wrote the second, failed alone, and the job hung)
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(f'scene = "{scene}"\noutput = "{output}"\n' + body)
    MPI.COMM_WORLD.Barrier()
    return str(path)


GRID = '''
[axes]
"excitation.frequency_hz" = [0.9, 1.1]
"constraint.law" = ["deadband", "hertz"]
"integrator.t_end" = [0.5]
[[case]]
"integrator.t_end" = 0.5
"integrator.scheme" = "ars443"
'''


def test_sweep_runs_every_case_shares_one_basis_and_records_failures(shared_tmp_path):
    path = write_sweep(shared_tmp_path, GRID + '[[case]]\n"basis.cache" = "off"\n"integrator.t_end" = 0.5\n')
    before = counters["eigen_solves"]
    result = run_sweep(path, progress=False)
    solves = MPI.COMM_WORLD.allreduce(counters["eigen_solves"] - before, op=MPI.MAX)
    # each rank's own look, right after the return: the summary's lock is gone everywhere
    assert_all("summary.h5.lock" not in os.listdir(shared_tmp_path), "a returned sweep left its lock")
    assert result["cases"] == 6 and result["failed"] == 1
    # the command's one line names the first failure's cause (red team: "6 of 6 cases failed" hid a full disk)
    assert result["first_failure"].startswith("case 5: ") and "ars443" in result["first_failure"]
    assert solves <= 3, "laws and frequencies share one basis: modes, pinned, spring (once)"
    with h5py.File(result["output"]) as f:
        status = [s.decode() for s in f["cases/status"][:]]
        assert status.count("ok") == 5 and status[4] == "failed"
        assert "ars443" in f["cases/error"][4].decode()
        np.testing.assert_array_equal(f["cases/parameters/excitation.frequency_hz"][:4], [0.9, 0.9, 1.1, 1.1])
        for name in STATISTICS:
            assert f[f"cases/stats/{name}"].shape == (6, 1)
        impacts = f["cases/stats/impacts"][:, 0]
        assert np.all(impacts[[0, 1, 2, 3, 5]] >= 1) and np.isnan(impacts[4])
        assert np.all(np.abs(f["cases/stats/displacement_peak"][[0, 2, 5], 0] / 2.5e-3 - 1) < 0.05)


def test_rerunning_a_killed_sweep_skips_the_finished_cases(shared_tmp_path):
    path = write_sweep(shared_tmp_path, GRID)
    first = run_sweep(path, progress=False)
    folder = first["output"] + ".cases"
    kept = os.path.join(folder, "case-00000.json")
    redo = os.path.join(folder, "case-00003.json")
    stamp = os.path.getmtime(kept)
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        os.remove(redo)            # as if the sweep was killed before case 4 finished
        os.remove(first["output"])
    MPI.COMM_WORLD.Barrier()
    second = run_sweep(path, progress=False)
    assert_all(os.path.getmtime(kept) == stamp, "a finished case is not run again")
    assert_all(os.path.exists(redo) and os.path.exists(second["output"]))
    with open(redo) as f:
        assert json.load(f)["status"] == "ok"


def test_a_rerun_removes_the_record_temporaries_a_killed_sweep_left_but_no_live_writers(shared_tmp_path):
    # Red team: a sweep SIGKILLed as a rank wrote its case's record left case-NNNNN.json.tmp-<host>-<pid> in
    # the case folder for good (no `finally` runs, and the record writer does not list the folder per record).
    # A rerun removes those whose process is gone from this host; a live process's (another job's rank
    # writing now), another host's (which cannot be told) and other files are kept.
    import socket
    import subprocess

    from dbf_hpc.errors import temporary_tag

    path = write_sweep(shared_tmp_path, '[axes]\n"integrator.t_end" = [0.05]\n')
    folder = shared_tmp_path / "summary.h5.cases"
    host = temporary_tag().rsplit("-", 1)[0]
    live = None
    if MPI.COMM_WORLD.rank == 0:
        gone = subprocess.Popen(["true"])
        gone.wait()
        live = subprocess.Popen(["sleep", "120"])
        folder.mkdir()
        dead = [f"case-00000.json.tmp-{host}-{gone.pid}", f"case-00007.json.tmp-{host}-{gone.pid}"]
        kept = [f"case-00000.json.tmp-{host}-{live.pid}", f"case-00000.json.tmp-another-host-{gone.pid}",
                f"notes.json.tmp-{host}-{gone.pid}", f"case-00000.json.tmp-{socket.gethostname()}x-{gone.pid}"]
        for name in dead + kept:
            (folder / name).write_text('{"index": 0')   # cut short by the kill
    MPI.COMM_WORLD.Barrier()
    try:
        result = run_sweep(path, progress=False)
        assert result["failed"] == 0
        left = rank0_files(folder)
    finally:
        if live is not None:
            live.kill()
            live.wait()
    expected = MPI.COMM_WORLD.bcast(sorted(["case-00000.json", *kept]) if live is not None else None)
    assert left == expected, left


def _write_record(path: str, record: dict) -> None:
    """A crafted case record with a valid checksum: what the sweep must see through is its content."""
    from dbf_hpc.sweep import record_checksum

    with open(path, "w") as f:
        json.dump({**record, "sha256": record_checksum(record)}, f)


def test_a_changed_digit_in_a_finished_case_record_reruns_the_case(shared_tmp_path):
    # Red team: a record is JSON that passed its shape checks; a changed number (bit rot, an edit) in
    # its statistics went into the summary as the case's result. Its checksum sends the case to run again.
    path, files = _swept(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n'
                                          '"integrator.t_end" = [0.05]\n', 2)
    fresh = [json.load(open(name)) for name in files]
    kept = os.path.getmtime(files[1])
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        with open(files[0], "w") as f:
            json.dump(dict(fresh[0], stats={k: [v[0] * 2] for k, v in fresh[0]["stats"].items()}), f)
    MPI.COMM_WORLD.Barrier()
    result = run_sweep(path, progress=False)
    again = [json.load(open(name)) for name in files]
    assert_all(again[0]["stats"] == fresh[0]["stats"] and os.path.getmtime(files[1]) == kept)
    with h5py.File(result["output"]) as f:
        assert_all(f["cases/stats/displacement_peak"][0, 0] == fresh[0]["stats"]["displacement_peak"][0])


def _swept(folder, body: str, count: int):
    """A sweep file of `body` run once: its path and its cases' record files."""
    path = write_sweep(folder, body)
    output = run_sweep(path, progress=False)["output"]
    return path, [os.path.join(output + ".cases", f"case-{i:05d}.json") for i in range(count)]


def test_a_sweep_rerun_on_another_rank_count_or_callbacks_reruns_its_finished_cases(shared_tmp_path, monkeypatch,
                                                                                   capsys):
    # The reduced model is projected on every rank, and its round-off differs with their number (0.2 % on
    # the chaotic tube between 1 and 2 ranks); the callbacks ("c", "python") differ by round-off too. A
    # sweep resumed on another setup reused the finished cases' records (red team): the summary mixed two
    # setups' answers. Each case's record says its setup; another one reruns it, and the line says why.
    import dbf_hpc.sweep as sweep

    path, files = _swept(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n'
                                          '"integrator.t_end" = [0.05]\n', 2)
    first = [json.load(open(name)) for name in files]
    callbacks = sweep.scene_callbacks(load_sweep(path)["scenes"][0])
    assert_all([(r["ranks"], r["callbacks"]) for r in first] == [(MPI.COMM_WORLD.size, callbacks)] * 2)
    same = run_sweep(path)   # the same setup: reused
    assert_all([json.load(open(name))["identity"] for name in files] == [r["identity"] for r in first])
    capsys.readouterr()
    monkeypatch.setattr(sweep, "_setup", lambda scene: {"ranks": MPI.COMM_WORLD.size + 1, "callbacks": callbacks})
    other = run_sweep(path)
    out = capsys.readouterr().out
    again = [json.load(open(name)) for name in files]
    assert same["failed"] == other["failed"] == 0
    assert_all(all(a["identity"] != r["identity"] and a["ranks"] == MPI.COMM_WORLD.size + 1
                   for a, r in zip(again, first)))
    if MPI.COMM_WORLD.rank == 0:
        assert "2 cases, 0 already done" in out, out
        assert f"2 finished case(s) rerun: they ran on {MPI.COMM_WORLD.size} rank(s) with the {callbacks} callbacks" \
            in out, out


def test_finished_cases_of_another_question_are_not_said_to_rerun_for_the_rank_count(shared_tmp_path, monkeypatch,
                                                                                     capsys):
    # New-user pass: a sweep rerun on 1 rank with --set integrator.t_end=1 (another question) said
    # "18 finished case(s) rerun: they ran on 2 rank(s) ... (rerun on that setup to reuse them)": the
    # rank count was not why they reran, and that setup would not have reused them. Only the cases
    # whose recorded identity their recorded setup reproduces rerun for their setup.
    import dbf_hpc.sweep as sweep

    body = '[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n"integrator.t_end" = [{}]\n'
    path, files = _swept(shared_tmp_path, body.format(0.05), 2)
    first = [json.load(open(name)) for name in files]
    callbacks = sweep.scene_callbacks(load_sweep(path)["scenes"][0])
    assert write_sweep(shared_tmp_path, body.format(0.06)) == path   # the same summary, another t_end
    capsys.readouterr()
    monkeypatch.setattr(sweep, "_setup", lambda scene: {"ranks": MPI.COMM_WORLD.size + 1, "callbacks": callbacks})
    other = run_sweep(path)
    out = capsys.readouterr().out
    assert other["failed"] == 0
    assert_all(all(json.load(open(name))["identity"] != r["identity"] for name, r in zip(files, first)))
    if MPI.COMM_WORLD.rank == 0:
        assert "2 cases, 0 already done" in out, out
        assert "finished case(s) rerun" not in out, out


def test_a_rerun_retries_failed_cases_and_reruns_a_case_file_that_is_not_a_record(shared_tmp_path):
    # Red team: cases that failed on a full disk stayed failed after the disk was freed ("6 already
    # done"), and a case file holding valid JSON that is not a record was an internal error.
    path, files = _swept(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1, 1.3]\n'
                                          '"integrator.t_end" = [0.05]\n', 3)
    kept = os.path.getmtime(files[2])
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        with open(files[0]) as f:
            record = json.load(f)
        record.update(status="failed", error="cannot write case-00000.h5: No space left on device")
        _write_record(files[0], record)
        with open(files[1], "w") as f:
            json.dump([1, 2], f)
    MPI.COMM_WORLD.Barrier()
    second = run_sweep(path, progress=False)
    assert second["failed"] == 0
    statuses = [json.load(open(name))["status"] for name in files]
    assert_all(statuses == ["ok"] * 3 and os.path.getmtime(files[2]) == kept, "only the two bad ones rerun")


def test_a_named_pipe_in_place_of_a_case_record_reruns_the_case_not_waits_on_it(shared_tmp_path):
    # Red team: a FIFO at a case's record hung the rerun of the sweep (rank 0's look at the records
    # opened it, and the open waits for a writer for ever). It is no record: the case runs again.
    import stat

    path, files = _swept(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n'
                                          '"integrator.t_end" = [0.05]\n', 2)
    kept = os.path.getmtime(files[1])
    MPI.COMM_WORLD.Barrier()
    fifo_at(files[0])
    with ends_a_hang():
        second = run_sweep(path, progress=False)
    assert second["failed"] == 0
    assert_all(stat.S_ISREG(os.stat(files[0]).st_mode) and json.load(open(files[0]))["status"] == "ok"
               and os.path.getmtime(files[1]) == kept, "the case of the pipe reran, the other stayed")


def test_a_case_record_the_full_disk_refused_on_one_rank_stops_every_rank_with_one_error(shared_tmp_path,
                                                                                        monkeypatch):
    # Red team (a 3 MB tmpfs filled just before a case's record): the rank whose record failed left
    # the sweep while the others waited in its collective end; the job ended only by the command's
    # 10 s timeout and MPI_Abort, with the summary's lock left behind. Every rank now hears of it.
    import errno

    from dbf_hpc import sweep as sweep_module
    from dbf_hpc.errors import DbfError, replacing

    path = write_sweep(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1, 1.3, 1.5]\n'
                                        '"integrator.t_end" = [0.05]\n')
    world = MPI.COMM_WORLD

    def full_disk(record_path, content):
        with replacing(record_path) as tmp:
            with open(tmp, "w"):
                raise OSError(errno.ENOSPC, "No space left on device")

    if world.rank == world.size - 1:   # one rank's disk write fails, the others' succeed
        monkeypatch.setattr(sweep_module, "_write_json", full_disk)
    with pytest.raises(DbfError, match="case-0000.\\.json: No space left on device; .*free some space, then rerun"):
        run_sweep(path, progress=False)
    world.Barrier()   # the failing rank may raise before rank 0 has released the lock in its own exit
    summary = shared_tmp_path / "summary.h5"
    assert_all(not os.path.exists(f"{summary}.lock"), "the lock is released")
    assert_all(not os.path.exists(summary), "no summary of cases that are not all recorded")
    assert_all(not [p for p in os.listdir(f"{summary}.cases") if ".tmp-" in p], "no temporary record is left")
    monkeypatch.undo()
    result = run_sweep(path, progress=False)
    assert result["cases"] == 4 and result["failed"] == 0, "a rerun with room records every case"


@pytest.fixture
def parked_released():
    """The h5py objects a test's simulated failed write parked (errors.park) are closed after it: a
    parked object makes every later OutputWriter.abort of the process park too."""
    from dbf_hpc.errors import PARKED

    before = len(PARKED)
    yield
    for obj in PARKED[before:]:
        if isinstance(obj, h5py.File) and obj.id.valid:
            obj.close()
    del PARKED[before:]


def test_a_case_whose_hdf5_write_failed_stops_the_sweep_before_another_hdf5_write(shared_tmp_path, monkeypatch,
                                                                                  parked_released):
    # Red team (sweeps of the 2-D tube on a 3 MB tmpfs, 3 runs in 6): after a case's HDF5 write failed
    # on the full disk, the rank's next failed write crashed HDF5 in its close (signal 11): closing the
    # case's output in OutputWriter.abort, or the next case's checkpoint. The failed file is now kept
    # open (errors.park) and the sweep stops on every rank; the case's record names no file it removed.
    from dbf_hpc import output as output_module

    path = write_sweep(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1, 1.3, 1.5]\n'
                                        '"integrator.t_end" = [0.05]\n')
    flush = output_module.OutputWriter.flush

    def full_disk(self):
        if self.path.endswith("case-00000.h5") and self.count:   # case 1 (rank 0), after its first block
            raise RuntimeError("Can't write data (file write failed: errno = 28, error message = 'No space left on "
                               "device')")
        flush(self)

    monkeypatch.setattr(output_module.OutputWriter, "flush", full_disk)
    with pytest.raises(DbfError, match="case 1 failed: cannot write .*case-00000.h5.partial or its checkpoint: No "
                                       "space left on device; the cases recorded so far are kept .* rerun"):
        run_sweep(path, progress=False)
    folder = shared_tmp_path / "summary.h5.cases"
    record = json.load(open(folder / "case-00000.json"))
    assert record["status"] == "failed" and "samples" not in record["error"], "the removed files are not named"
    assert_all(not os.path.exists(folder / "case-00002.json"), "rank 0 started no case after the failed write")
    assert_all(not os.path.exists(shared_tmp_path / "summary.h5"), "no summary after the stop")
    monkeypatch.undo()
    assert run_sweep(path, progress=False)["failed"] == 0, "a rerun with room finishes every case"


def test_a_case_folder_that_cannot_be_made_is_one_line_on_every_rank_and_leaves_no_lock(shared_tmp_path):
    # Red team: a file named like the case folder read "[Errno 17] File exists: '...cases'", and rank 0
    # left the summary's lock behind (a later sweep on another node: "being written by another job").
    path = write_sweep(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9]\n"integrator.t_end" = [0.05]\n')
    if MPI.COMM_WORLD.rank == 0:
        (shared_tmp_path / "summary.h5.cases").write_text("not a folder")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=r"case folder .*summary\.h5\.cases' is a file, not a directory: move it "
                                         r"away, or give the sweep another output"):
        run_sweep(path, progress=False)
    MPI.COMM_WORLD.Barrier()
    assert_all(sorted(os.listdir(shared_tmp_path)) == ["summary.h5.cases", "sweep.toml"], "no lock left behind")


def test_any_exception_as_rank_0_claims_the_summary_ends_the_sweep_on_every_rank_and_leaves_no_lock(shared_tmp_path,
                                                                                                   monkeypatch):
    # Red team: rank 0's claim of the summary (its checks, its lock, the case folder) passed on an InputError or
    # an OSError; anything else (a bug) left the other ranks waiting in the broadcast after it for ever
    from dbf_hpc import sweep as sweep_module

    path = write_sweep(shared_tmp_path, '[axes]\n"integrator.t_end" = [0.01]\n')
    if MPI.COMM_WORLD.rank == 0:
        def looked(*args):
            raise ValueError("rank 0's look went wrong")
        monkeypatch.setattr(sweep_module, "check_output_path", looked)
    with ends_a_hang(60), pytest.raises(ValueError, match="rank 0's look went wrong"):
        run_sweep(path, progress=False)
    assert_all(rank0_files(shared_tmp_path) == ["sweep.toml"])


def test_a_summary_that_would_not_fit_on_the_disk_is_refused_before_hdf5_writes_it(shared_tmp_path, monkeypatch):
    # Red team (a 3 MB tmpfs filled during a case; the failed cases' removed files left a few kB): the
    # summary's write failed, and its close crashed HDF5 (signal 11) because the failed case's file
    # was kept open in the process (errors.park); the .partial and the lock were left behind.
    from dbf_hpc import sweep as sweep_module
    from dbf_hpc.errors import DbfError

    path = write_sweep(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n"integrator.t_end" = [0.05]\n')
    summary = shared_tmp_path / "summary.h5"
    monkeypatch.setattr(sweep_module, "free_bytes", lambda folder: 200 * 2**10)   # what the disk had left
    with pytest.raises(DbfError, match="cannot write the sweep summary .*: No space left on device; the cases are kept"):
        run_sweep(path, progress=False)
    assert rank0_files(shared_tmp_path) == ["summary.h5.cases", "sweep.toml"], "no summary, .partial or lock"
    records = [str(summary) + f".cases/case-0000{i}.json" for i in range(2)]
    stamps = [os.path.getmtime(name) for name in records]
    monkeypatch.undo()
    result = run_sweep(path, progress=False)
    assert result["failed"] == 0 and [os.path.getmtime(name) for name in records] == stamps, \
        "with room, the summary is written from the cases kept"


def test_a_file_left_at_the_summarys_temporary_name_is_replaced_not_written_through(shared_tmp_path):
    # Red team: the summary was written to OUT.h5.partial as found there: a symlink left there had HDF5
    # overwrite the file it pointed to (a user's file clobbered, then renamed over the summary's name as
    # a symlink). It is removed first; a directory there is the write's one line, and stays.
    from dbf_hpc.errors import DbfError

    path = write_sweep(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9]\n"integrator.t_end" = [0.05]\n')
    summary, precious = shared_tmp_path / "summary.h5", shared_tmp_path / "precious.txt"
    if MPI.COMM_WORLD.rank == 0:
        precious.write_text("a user's own file")
        os.symlink(precious, str(summary) + ".partial")
    MPI.COMM_WORLD.Barrier()
    assert run_sweep(path, progress=False)["failed"] == 0
    assert_all(precious.read_text() == "a user's own file" and not os.path.islink(summary)
               and not os.path.lexists(str(summary) + ".partial"))
    with h5py.File(summary) as f:
        assert list(f["cases/status"].asstr()) == ["ok"]
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        os.remove(summary)
        os.mkdir(str(summary) + ".partial")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(DbfError, match="^cannot write the sweep summary .*; the cases are kept in"):
        run_sweep(path, progress=False)
    assert_all(os.path.isdir(str(summary) + ".partial") and not os.path.exists(summary))


def test_a_retried_step_of_a_stepped_sine_reruns_the_steps_after_it(shared_tmp_path):
    # Red team: when step 2 failed, step 3 ran from rest and was kept as ok after step 2's retry.
    path, files = _swept(shared_tmp_path, 'continuation = "excitation.frequency_hz"\n[axes]\n'
                                          '"excitation.frequency_hz" = [0.9, 1.1]\n"integrator.t_end" = [0.05]\n', 4)
    fresh = [json.load(open(name)) for name in files]
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        failed = dict(fresh[0], status="failed", error="No space left on device")
        _write_record(files[0], failed)
        stale = dict(fresh[1], continued=False, stats={k: [v[0] * 2] for k, v in fresh[1]["stats"].items()})
        _write_record(files[1], stale)   # as if it had run from rest after the failure
    MPI.COMM_WORLD.Barrier()
    kept = os.path.getmtime(files[3])
    run_sweep(path, progress=False)
    again = [json.load(open(name)) for name in files]
    assert_all(again[1]["continued"] and again[1]["stats"] == fresh[1]["stats"], "step 2 rerun from step 1")
    assert_all(os.path.getmtime(files[3]) == kept, "the other chain is kept")


def test_a_step_after_a_failed_step_of_a_stepped_sine_is_not_run_from_rest(shared_tmp_path, monkeypatch):
    # Red team: when step 1 of a chain failed (say, a full disk), step 2 ran from rest and was recorded
    # ok: the response of a start from rest, not of the sweep's continuation, under the sweep's name.
    from dbf_hpc import sweep as sweep_module

    real = sweep_module._run_one

    def first_fails(sweep, index, *args):
        record = real(sweep, index, *args)
        return dict(record, status="failed", error="No space left on device") if index == 0 else record

    monkeypatch.setattr(sweep_module, "_run_one", first_fails)
    path = write_sweep(shared_tmp_path, 'continuation = "excitation.frequency_hz"\n[axes]\n'
                                        '"excitation.frequency_hz" = [0.9, 1.1]\n"integrator.t_end" = [0.05]\n')
    result = run_sweep(path, progress=False)
    folder = result["output"] + ".cases"
    records = [json.load(open(os.path.join(folder, f"case-{i:05d}.json"))) for i in range(4)]
    assert result["failed"] == 2 and [r["status"] for r in records] == ["failed", "failed", "ok", "ok"]
    assert records[1]["error"].startswith("not run: case 1, the step before it in its continuation chain, failed")
    assert records[3]["continued"], "the other chain continues as before"
    monkeypatch.undo()
    run_sweep(path, progress=False)
    again = [json.load(open(os.path.join(folder, f"case-{i:05d}.json"))) for i in range(4)]
    assert [r["status"] for r in again] == ["ok"] * 4 and again[1]["continued"], "a rerun runs the chain anew"


def test_a_failed_case_names_the_sweep_rerun_not_a_resume_flag_the_sweep_does_not_take(shared_tmp_path, monkeypatch):
    # Red team: a case's error said "rerun with --resume", which `dbf-hpc sweep` does not take (it
    # resumes its cases itself).
    from dbf_hpc import sweep as sweep_module
    from dbf_hpc.errors import SolverError

    def stopped(*args, **kwargs):
        raise SolverError("cannot finish case.h5: No space left on device; free some space, then rerun with --resume")

    monkeypatch.setattr(sweep_module, "run_case", stopped)
    path = write_sweep(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9]\n"integrator.t_end" = [0.05]\n')
    result = run_sweep(path, progress=False)
    assert result["failed"] == 1 and "--resume" not in result["first_failure"], result["first_failure"]
    assert result["first_failure"].endswith("free some space, then rerun the sweep"), result["first_failure"]


def test_a_bad_case_stops_the_sweep_before_any_work(shared_tmp_path):
    path = write_sweep(shared_tmp_path, '[axes]\n"constraint.clearance" = [1e-3, -1]\n"basis.mode" = [3]\n')
    with pytest.raises(InputError, match="case 1 .*unknown key 'mode' in \\[basis\\]"):
        load_sweep(path)


@pytest.mark.parametrize("key", ["scene", "output"])
def test_a_sweep_file_name_holding_a_nul_character_is_refused_naming_its_key(shared_tmp_path, key):
    # Red team: output = "sw\u0000.h5" (a TOML escape) ended in "internal error (ValueError): embedded null byte"
    body = '[axes]\n"constraint.clearance" = [1e-3]\n'
    path = write_sweep(shared_tmp_path, body, **{key: "a\\u0000b"})
    with pytest.raises(InputError, match=f"^{re.escape(path)}: {key} contains a NUL character, which no file name may "
                                         f"hold; remove it$"):
        load_sweep(path)


@pytest.mark.parametrize("output", ["", " ", "results/"])
def test_a_summary_output_that_names_no_file_is_refused_naming_the_sweep_file(shared_tmp_path, output):
    # Red team: output = "" was refused as "output '/.../' is a directory", naming neither the sweep file
    # nor its output key
    path = write_sweep(shared_tmp_path, '[axes]\n"constraint.clearance" = [1e-3]\n', output=output)
    with pytest.raises(InputError, match=f"^{re.escape(path)}: output {re.escape(repr(output))} names no file: give "
                                         f"the summary's file name, e.g. output = \"sweep.h5\""):
        load_sweep(path)


def test_a_summary_name_too_long_for_its_partial_file_is_refused_before_any_case_runs(shared_tmp_path):
    # Red team: a summary name that left no room for OUT.h5.partial ran every case, then failed to write it
    name = "s" * (os.pathconf(shared_tmp_path, "PC_NAME_MAX") - 5) + ".h5"
    path = write_sweep(shared_tmp_path, '[axes]\n"integrator.t_end" = [0.01]\n', output=name)
    with pytest.raises(InputError, match="^sweep summary .*: a name of .* bytes, too long for the files written "
                                         "beside it"):
        run_sweep(path, progress=False)
    assert_all(rank0_files(shared_tmp_path) == ["sweep.toml"])


def test_a_sweep_file_that_is_a_named_pipe_is_refused_not_waited_on(shared_tmp_path):
    # Red team: `dbf-hpc sweep FIFO` waited for a writer for ever
    path = str(shared_tmp_path / "sweep.toml")
    fifo_at(path)
    with ends_a_hang(60), pytest.raises(InputError, match=f"^cannot read sweep {re.escape(repr(path))}: a named "
                                                          f"pipe, not a regular file$"):
        run_sweep(path, progress=False)


def test_a_listed_case_with_a_nested_table_is_refused_naming_the_sweep_not_a_set(shared_tmp_path):
    # Red team: [[case]] excitation = {frequency_hz = 1.0} was refused as `--set "excitation={...}"`, a flag
    # the command line did not hold
    path = write_sweep(shared_tmp_path, '[[case]]\nexcitation = {frequency_hz = 1.0}\n')
    with pytest.raises(InputError, match=r"sweep.toml: case 1 .*'excitation' must be a scene value written section.key"):
        load_sweep(path)


@pytest.mark.parametrize("value", ['"integrator.t_end" = [0.5, 1e9]', '"excitation.frequency_hz" = [1.0, 1e9]'])
def test_a_case_a_run_would_refuse_as_endless_stops_the_sweep_before_any_work(shared_tmp_path, value):
    # Red team: `dbf-hpc run` refuses 2e10 steps (20 a period of the forcing over t_end) before any work; the same
    # case in a sweep was integrated on and on, holding its rank and the summary behind it
    path = write_sweep(shared_tmp_path, f'[axes]\n{value}\n')
    with pytest.raises(InputError, match="case 2 .*the run would take at least 2e\\+1[01] steps"):
        load_sweep(path)


@pytest.mark.parametrize("values", ["[1.2, 1.0]", "[1.0, 1.1, 1.0]", "[1.0, 1.0]"])
def test_a_continuation_axis_not_in_increasing_order_is_refused_as_its_directions_would_be_mislabelled(
        shared_tmp_path, values):
    # "up" runs the values as listed and "down" reversed: [1.2, 1.0] ran a falling frequency under "up", the
    # hysteresis branches of the summary swapped (red team)
    path = write_sweep(shared_tmp_path, f'continuation = "excitation.frequency_hz"\n[axes]\n'
                                        f'"excitation.frequency_hz" = {values}\n')
    with pytest.raises(InputError, match="continuation 'excitation.frequency_hz' .* in increasing order, each once"):
        load_sweep(path)
    # a value of a law (not a number) runs in the order given
    path = write_sweep(shared_tmp_path, 'continuation = "constraint.law"\n[axes]\n"constraint.law" = ["hertz", '
                                        '"deadband"]\n')
    assert [v["constraint.law"] for v in load_sweep(path)["values"]] == ["hertz", "deadband", "deadband", "hertz"]


@pytest.mark.parametrize("body,message", [
    ('continuation = ["excitation.frequency_hz"]\n', r"continuation must name one of the \[axes\] \(a string\), got "
                                                    r"\['excitation.frequency_hz'\]$"),
    ("continuation = {a = 1}\n", r"continuation must name one of the \[axes\] \(a string\), got \{'a': 1\}$"),
    ('continuation = "excitation.frequency_hz"\ndirections = [[1.0]]\n',
     r'directions must be a list of "up" and/or "down", each once, got \[\[1.0\]\]$'),
    ('continuation = "excitation.frequency_hz"\ndirections = ["up", "up"]\n',
     r"directions must be a list of .*, each once, got \['up', 'up'\]$"),
])
def test_a_continuation_or_directions_of_the_wrong_shape_is_one_line_naming_the_key(shared_tmp_path, body, message):
    # Red team: continuation = ["x"] or directions = [[1.0]] was an internal TypeError (unhashable); directions =
    # ["up", "up"] ran each chain twice, every case of it twice in the summary
    path = write_sweep(shared_tmp_path, body + '[axes]\n"excitation.frequency_hz" = [1.0, 1.1]\n')
    with pytest.raises(InputError, match=rf"^{path}: {message}"):
        load_sweep(path)
    path = write_sweep(shared_tmp_path, 'continuation = "excitation.frequency_hz"\ndirections = ["down"]\n[axes]\n'
                                        '"excitation.frequency_hz" = [1.0, 1.1]\n')
    assert [v["excitation.frequency_hz"] for v in load_sweep(path)["values"]] == [1.1, 1.0]


def test_a_case_whose_fixed_step_cannot_resolve_its_forcing_is_warned_as_a_run_would(shared_tmp_path, capfd):
    # Red team: at a fixed dt of 10 steps a period of the forcing, `dbf-hpc run` warns that the response is
    # wrong; a sweep of the same cases ran them without a word
    path = write_sweep(shared_tmp_path, '[axes]\n"integrator.adaptive" = [false]\n"integrator.dt" = [0.1, 0.001]\n'
                                        '"excitation.frequency_hz" = [1.0]\n"output.sample_dt" = [0.8]\n')
    load_sweep(path)
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert re.search(r"warning: .*: case 1: \[integrator\] dt = 0.1 s takes 10 fixed steps per period", err), err
        assert "case 2: [integrator] dt" not in err
        # the samples alias both cases' response (and their probe peaks): one line names both
        assert re.search(r"warning: .*: cases 1, 2: \[output\] sample_dt = 0.8 s takes 1.2 samples", err), err


def test_a_warning_naming_a_sweep_file_with_a_line_break_in_its_name_stays_one_line(shared_tmp_path, capfd):
    # Red team: a sweep file named "coarse\nsweep.toml" split its cases' warning over two lines; an error
    # or warning is one line, a line break in a name it quotes written \n
    path = write_sweep(shared_tmp_path, '[axes]\n"output.sample_dt" = [0.8]\n"output.snapshots" = [0]\n',
                       name="coarse\nsweep.toml")
    load_sweep(path)
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        lines = [line for line in err.splitlines() if line]
        assert len(lines) == 1 and lines[0].startswith("dbf-hpc: warning: ") and "coarse\\nsweep.toml: case 1:" in lines[0], err


def test_a_case_with_more_snapshots_than_samples_is_warned_as_a_run_would(shared_tmp_path, capfd):
    # the paper scene's 50 snapshots over 0.5 s at 0.05 s are its 11 samples: `dbf-hpc run` says so, a sweep too
    path = write_sweep(shared_tmp_path, '[axes]\n"integrator.t_end" = [0.5]\n"output.sample_dt" = [0.05, 0.001]\n')
    load_sweep(path)
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert re.search(r"warning: .*: case 1: \[output\] snapshots = 50 is more than the 11 output samples", err), err
        assert "case 2: [output] snapshots" not in err, err


@pytest.mark.parametrize("given", ["constraint.clearance=1e-3", "constraint.1.clearance=1e-3"])
def test_a_set_of_a_value_the_cases_set_is_refused_instead_of_silently_replaced(shared_tmp_path, given):
    # each case's own value is applied after --set: the clearance from the axis would replace the one the
    # command line asked for (red team), so the --set is refused before any work
    path = write_sweep(shared_tmp_path, '[axes]\n"constraint.clearance" = [1e-3, 2e-3]\n"integrator.t_end" = [0.5]\n')
    with pytest.raises(InputError, match=f"--set {given}: the sweep .* sets .* in its cases"):
        load_sweep(path, [given])
    # a value no case sets still applies to every case
    sweep = load_sweep(path, ["constraint.1.k=2e6"])
    assert [scene.constraints[0].law.k_plus for scene in sweep["scenes"]] == [2e6, 2e6]


def test_a_set_of_an_axis_of_one_value_shortens_every_case_as_it_shortens_a_run(shared_tmp_path):
    # the shipped sweeps give integrator.t_end as an axis of one value: `--set integrator.t_end=0.1` to try
    # a study quickly was refused (red team). It is every case's simulated time: the --set replaces it,
    # the summary's column says 0.1 s, and the cases' identities change (a finished 0.5 s case is not reused)
    path = write_sweep(shared_tmp_path, '[axes]\n"constraint.clearance" = [1e-3, 2e-3]\n"integrator.t_end" = [0.5]\n')
    plain, short = load_sweep(path), load_sweep(path, ["integrator.t_end=0.1"])
    assert [scene.integrator_settings().t_end for scene in short["scenes"]] == [0.1, 0.1]
    assert [v["integrator.t_end"] for v in short["values"]] == [0.1, 0.1]
    assert [scene.integrator_settings().t_end for scene in plain["scenes"]] == [0.5, 0.5]
    from dbf_hpc.sweep import _identities
    assert not set(_identities(plain, plain["scenes"])) & set(_identities(short, short["scenes"]))
    # an axis of several values, or a [[case]] that sets it, still refuses it
    path = write_sweep(shared_tmp_path, '[axes]\n"integrator.t_end" = [0.5]\n[[case]]\n"integrator.t_end" = 0.2\n')
    with pytest.raises(InputError, match="--set integrator.t_end=0.1: the sweep .* sets integrator.t_end in its cases"):
        load_sweep(path, ["integrator.t_end=0.1"])


@pytest.mark.parametrize("name", sorted(f for f in os.listdir(os.path.join(ROOT, "jobs")) if f.startswith("sweep_")))
def test_the_commands_a_shipped_sweep_shows_name_the_summary_it_writes(name):
    # sweep_steam_generator_2d.toml said `dbf-hpc info steam_generator_2d_sweep.h5` after a sweep run
    # from the top folder, which writes jobs/steam_generator_2d_sweep.h5 (beside the sweep file)
    path = os.path.join(ROOT, "jobs", name)
    comments = "\n".join(line for line in open(path) if line.startswith("#"))
    shown = re.findall(r"dbf-hpc (?:info|plot) (\S+)", comments)
    written = os.path.relpath(load_sweep(path)["output"], ROOT)
    assert all(p == written for p in shown), (shown, written)


def test_continuation_sweeps_up_and_down_each_case_starting_from_the_last(shared_tmp_path):
    path = write_sweep(shared_tmp_path, 'continuation = "excitation.frequency_hz"\n[axes]\n'
                                        '"excitation.frequency_hz" = [0.9, 1.1]\n"integrator.t_end" = [0.4]\n')
    sweep = load_sweep(path)
    assert sweep["chains"] == [[0, 1], [2, 3]]
    assert [v["sweep_direction"] for v in sweep["values"]] == ["up", "up", "down", "down"]
    assert [v["excitation.frequency_hz"] for v in sweep["values"]] == [0.9, 1.1, 1.1, 0.9]
    result = run_sweep(path, progress=False)
    folder = result["output"] + ".cases"
    records = [json.load(open(os.path.join(folder, f"case-{i:05d}.json"))) for i in range(4)]
    assert [r["continued"] for r in records] == [False, True, False, True]
    assert all(r["status"] == "ok" for r in records)
    # resuming inside a chain continues from the stored final state of its predecessor
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        os.remove(os.path.join(folder, "case-00001.json"))
    MPI.COMM_WORLD.Barrier()
    run_sweep(path, progress=False)
    again = json.load(open(os.path.join(folder, "case-00001.json")))
    assert again["continued"] and np.allclose(again["stats"]["impacts"], records[1]["stats"]["impacts"])
    with h5py.File(result["output"]) as f:
        assert [json.loads(v) for v in f["cases/parameters/sweep_direction"][:]] == ["up", "up", "down", "down"]


def test_changing_an_earlier_step_of_a_stepped_sine_reruns_every_step_after_it(shared_tmp_path):
    # Red team: a case's identity held its own scene only, so after the first frequency changed the
    # later steps were kept, although they had started from the old first step's final state.
    body = ('continuation = "excitation.frequency_hz"\ndirections = ["up"]\n[axes]\n'
            '"excitation.frequency_hz" = [{first}, 1.1]\n"integrator.t_end" = [0.3]\n')
    path = write_sweep(shared_tmp_path, body.format(first=0.9))
    folder = run_sweep(path, progress=False)["output"] + ".cases"
    old = json.load(open(os.path.join(folder, "case-00001.json")))
    path = write_sweep(shared_tmp_path, body.format(first=0.8))
    run_sweep(path, progress=False)
    new = json.load(open(os.path.join(folder, "case-00001.json")))
    fresh_folder = shared_tmp_path / "fresh"
    if MPI.COMM_WORLD.rank == 0:
        fresh_folder.mkdir()
    MPI.COMM_WORLD.Barrier()
    fresh_path = write_sweep(fresh_folder, body.format(first=0.8))
    fresh = json.load(open(os.path.join(run_sweep(fresh_path, progress=False)["output"] + ".cases",
                                        "case-00001.json")))
    assert new["identity"] != old["identity"] and new["continued"]
    assert not np.allclose(new["final_state"][0], old["final_state"][0]), "the step after the change was kept"
    np.testing.assert_allclose(new["final_state"][0], fresh["final_state"][0], rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("axis,values", [("basis.modes", "[4, 6]"), ("constraint.x", "[0.25, 0.3]"),
                                         ("structure.elements", "[40, 50]")])
def test_a_continuation_that_changes_the_reduced_coordinates_is_refused_before_any_work(shared_tmp_path, axis,
                                                                                       values):
    # Red team: continuation = "basis.modes" crashed (12 states into 16); across gyroscopic forms or
    # axial speeds the final state of one basis started a case of another and reported nonsense.
    path = write_sweep(shared_tmp_path, f'continuation = "{axis}"\n[axes]\n"{axis}" = {values}\n')
    with pytest.raises(InputError, match=f"continuation '{axis}' changes the reduced model's coordinates"):
        load_sweep(path)


def test_a_continuation_along_a_law_or_damping_value_is_accepted(shared_tmp_path):
    for axis, values in (("constraint.clearance", "[2e-3, 2.5e-3]"), ("damping.zeta", "[0.01, 0.02]")):
        path = write_sweep(shared_tmp_path, f'continuation = "{axis}"\n[axes]\n"{axis}" = {values}\n')
        assert load_sweep(path)["chains"] == [[0, 1], [2, 3]]


def _copy_scene(folder, name="base.toml", replace=None):
    path = folder / name
    if MPI.COMM_WORLD.rank == 0:
        text = open(PAPER).read()
        for old, new in (replace or {}).items():
            text = text.replace(old, new)
        path.write_text(text)
    MPI.COMM_WORLD.Barrier()
    return str(path)


SMALL = '''
[axes]
"excitation.frequency_hz" = [0.9, 1.1]
"integrator.t_end" = [0.3]
'''


def test_a_rerun_after_the_base_scene_changed_reruns_every_case_instead_of_reporting_old_results(shared_tmp_path):
    base = _copy_scene(shared_tmp_path)
    path = shared_tmp_path / "stale.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(f'scene = "{base}"\noutput = "stale.h5"\n' + SMALL)
    MPI.COMM_WORLD.Barrier()
    first = run_sweep(str(path), progress=False)
    with h5py.File(first["output"]) as f:
        before = f["cases/stats/displacement_peak"][:, 0].copy()
    _copy_scene(shared_tmp_path, replace={"amplitude = 5e-3": "amplitude = 5e-5"})   # 100x weaker
    second = run_sweep(str(path), progress=False)
    with h5py.File(second["output"]) as f:
        after = f["cases/stats/displacement_peak"][:, 0]
    assert np.all(after < 0.05 * before), (before, after)


def test_a_scene_edited_while_the_sweep_runs_changes_none_of_its_cases(shared_tmp_path, monkeypatch):
    # Red team: each case read the base scene again when it ran; edited meanwhile (clearance 2.5 ->
    # 4 mm), the summary mixed both clearances under one sweep, with exit 0, and the records kept the
    # identity of the scene as it was: restored, the scene reused results of the other clearance.
    from dbf_hpc import sweep as sweep_module

    def sweep_of(name):
        scene = _copy_scene(shared_tmp_path, f"{name}.toml")
        path = shared_tmp_path / f"{name}-sweep.toml"
        if MPI.COMM_WORLD.rank == 0:
            path.write_text(f'scene = "{scene}"\noutput = "{name}.h5"\n' + SMALL)
        MPI.COMM_WORLD.Barrier()
        return scene, str(path)

    _, untouched = sweep_of("untouched")
    with h5py.File(run_sweep(untouched, progress=False)["output"]) as f:
        expected = f["cases/stats/displacement_peak"][:, 0].copy()
    scene, edited = sweep_of("edited")
    prepare = sweep_module._prepare_models

    def edit_after_the_models_are_built(*args, **kwargs):
        models = prepare(*args, **kwargs)
        _copy_scene(shared_tmp_path, "edited.toml", replace={"clearance = 2.5e-3": "clearance = 4e-3"})
        return models

    monkeypatch.setattr(sweep_module, "_prepare_models", edit_after_the_models_are_built)
    with h5py.File(run_sweep(edited, progress=False)["output"]) as f:
        got = f["cases/stats/displacement_peak"][:, 0].copy()
    assert np.array_equal(got, expected), "every case ran the scene as it was when the sweep started"
    monkeypatch.undo()
    with h5py.File(run_sweep(edited, progress=False)["output"]) as f:   # the edit now holds: all rerun
        widened = f["cases/stats/displacement_peak"][:, 0]
    assert np.all(widened > 1.2 * expected), (expected, widened)


@pytest.mark.launcher
def test_a_case_stopped_on_two_ranks_is_not_continued_in_the_basis_one_rank_rebuilt(tmp_path):
    # Red team: a case's checkpoint held the case's identity only (no rank count, no meaning of q):
    # stopped on 2 ranks, the cache cleared, a 1-rank rerun resumed q in the basis it rebuilt, and the
    # case's statistics were those of neither layout. Its checkpoint is now refused, as a run's is.
    import shutil
    import signal
    import subprocess
    import sys
    import time

    body = ('scene = "{scene}"\noutput = "{out}"\n[axes]\n"integrator.t_end" = [150.0]\n"output.sample_dt" = [4e-3]\n'
            '"output.snapshots" = [0]\n"output.checkpoint_dt" = [5.0]\n"basis.cache" = ["off"]\n')
    env = {**os.environ, "OMPI_MCA_orte_execute_quiet": "1", "OMPI_MCA_rmaps_base_oversubscribe": "1",
           "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}

    def sweep(name, ranks, wait=True):
        path = tmp_path / f"{name}.toml"
        path.write_text(body.format(scene=PAPER, out=f"{name}.h5"))
        cmd = ["mpirun", "-n", str(ranks), sys.executable, "-m", "dbf_hpc.cli", "sweep", str(path), "-q"]
        if not wait:
            return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr
        with h5py.File(tmp_path / f"{name}.h5") as f:
            return {name: f[f"cases/stats/{name}"][()] for name in STATISTICS}

    uninterrupted = sweep("reference", 1)
    checkpoint = tmp_path / "stopped.h5.cases" / "case-00000.h5.checkpoint"
    job = sweep("stopped", 2, wait=False)
    deadline = time.monotonic() + 120
    while not checkpoint.exists():
        assert job.poll() is None and time.monotonic() < deadline, "the case ended before its first checkpoint"
        time.sleep(0.02)
    job.send_signal(signal.SIGTERM)   # mpirun passes it on: the case checkpoints and stops
    job.communicate(timeout=120)   # (mpirun, stopping, may drop the ranks' last line)
    assert job.returncode != 0 and checkpoint.exists(), "the case was stopped halfway"
    shutil.rmtree(tmp_path / "stopped.h5.cases" / "basis-cache")   # the basis is rebuilt on 1 rank
    finished = sweep("stopped", 1)
    for name in STATISTICS:
        assert np.array_equal(finished[name], uninterrupted[name], equal_nan=True), name


def _rank_pids(launcher) -> dict:
    """{rank: pid} of the processes mpirun `launcher` started (their OMPI_COMM_WORLD_RANK)."""
    import subprocess

    pids = {}
    for pid in subprocess.run(["pgrep", "-P", str(launcher.pid)], capture_output=True, text=True).stdout.split():
        with open(f"/proc/{pid}/environ", "rb") as f:
            env = dict(item.split(b"=", 1) for item in f.read().split(b"\0") if b"=" in item)
        if b"OMPI_COMM_WORLD_RANK" in env:
            pids[int(env[b"OMPI_COMM_WORLD_RANK"])] = int(pid)
    return pids


@pytest.mark.launcher
def test_a_termination_signal_to_rank_1_alone_stops_the_case_rank_0_is_running(tmp_path):
    # Red team: SIGTERM to rank 1 alone of a 2-rank sweep stopped rank 1 only; rank 0 ran every case it had
    # left (hours, on a real study) before the sweep said it was stopped. Here rank 1's one short case is
    # done and it waits at the end: its signal stops rank 0's long case at a step, checkpointed (no record:
    # it is not finished), one line, exit 1; the rerun resumes it and finishes both.
    import signal
    import subprocess
    import sys
    import time

    path = tmp_path / "stop.toml"
    path.write_text(f'scene = "{PAPER}"\noutput = "stop.h5"\n[[case]]\n"integrator.t_end" = 40.0\n'
                    '"output.checkpoint_dt" = 1.0\n[[case]]\n"integrator.t_end" = 0.5\n')
    env = {**os.environ, "OMPI_MCA_orte_execute_quiet": "1", "OMPI_MCA_rmaps_base_oversubscribe": "1",
           "PYTHONPATH": ROOT + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = ["mpirun", "-n", "2", sys.executable, "-m", "dbf_hpc.cli", "sweep", str(path), "-q"]
    job = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    folder = tmp_path / "stop.h5.cases"
    deadline = time.monotonic() + 120
    while not (folder / "case-00001.json").exists():   # rank 1's case (cases are dealt round-robin)
        assert job.poll() is None and time.monotonic() < deadline, "rank 1's case did not finish"
        time.sleep(0.02)
    os.kill(_rank_pids(job)[1], signal.SIGTERM)
    _, err = job.communicate(timeout=120)
    lines = [line for line in err.splitlines() if line.startswith("dbf-hpc")]
    assert job.returncode == 1 and lines == [
        "dbf-hpc: error: sweep stopped by a termination signal with 1 of 2 cases done; rerun the same command to "
        "continue (finished cases are kept, a running one resumes from its checkpoint)"], err
    assert not (folder / "case-00000.json").exists(), "rank 0's case was stopped, not run to its end"
    with h5py.File(folder / "case-00000.h5.checkpoint") as f:   # the simulated time it stopped at
        assert 0 < f["t"][()] < 40.0
    assert not (tmp_path / "stop.h5.lock").exists()
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    with h5py.File(tmp_path / "stop.h5") as f:
        assert [s.decode() for s in f["cases/status"][:]] == ["ok", "ok"]


def test_a_case_whose_model_cannot_be_built_is_recorded_and_the_others_go_on(shared_tmp_path):
    path = write_sweep(shared_tmp_path, SMALL + '[[case]]\n"basis.modes" = 500\n"integrator.t_end" = 0.3\n')
    result = run_sweep(path, progress=False)
    assert result["cases"] == 3 and result["failed"] == 1
    with h5py.File(result["output"]) as f:
        status = [s.decode() for s in f["cases/status"][:]]
        assert status == ["ok", "ok", "failed"]
        assert "[basis] modes = 500: the structure has" in f["cases/error"][2].decode()   # named by its key


def test_a_second_sweep_on_the_same_summary_is_refused(shared_tmp_path):
    from dbf_hpc.output import OutputLock

    path = write_sweep(shared_tmp_path, SMALL)
    lock = OutputLock(str(shared_tmp_path / "summary.h5"))
    if MPI.COMM_WORLD.rank == 0:
        lock.acquire()
    MPI.COMM_WORLD.Barrier()
    try:
        with pytest.raises(InputError, match="is being written by another job"):
            run_sweep(path, progress=False)
    finally:
        if MPI.COMM_WORLD.rank == 0:
            lock.release()


def test_sigterm_stops_the_sweep_and_a_rerun_finishes_every_case_without_failures(shared_tmp_path):
    import signal
    import threading
    import time

    from dbf_hpc.errors import Interrupted

    # 8 cases, 4 a rank: the signal comes after a rank's first case, and a case that has left its
    # integration (writing, estimating) finishes before the sweep stops, so more than one must be left
    path = write_sweep(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.8, 0.85, 0.9, 0.95, 1.0, 1.05, '
                                        '1.1, 1.15]\n"integrator.t_end" = [1.0]\n')
    folder = shared_tmp_path / "summary.h5.cases"

    def terminate():
        while not list(folder.glob("case-*.json")):
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=terminate, daemon=True).start()   # every rank: a batch system signals all
    with pytest.raises(Interrupted, match="rerun the same command to continue"):
        run_sweep(path, progress=False)
    done = MPI.COMM_WORLD.bcast(sorted(p.name for p in folder.glob("case-*.json")), root=0)
    assert 1 <= len(done) < 8
    for name in done:
        with open(folder / name) as f:
            assert json.load(f)["status"] == "ok", "an interrupted case is not recorded as failed"
    result = run_sweep(path, progress=False)
    assert result["cases"] == 8 and result["failed"] == 0


def test_a_stepped_sine_keeps_the_structure_where_it_was_when_the_frequency_steps(shared_tmp_path):
    # Continuation restarted the base motion at phase 0 while keeping q, so the structure jumped by
    # -r Omega(t_end) (2.2 mm into a 2.5 mm stop). The excitation now continues its phase: the total
    # displacement is continuous, and the velocity jump r (Omega'_new - Omega'_old) of the support
    # is taken up by q as far as the basis represents r.
    path = write_sweep(shared_tmp_path, 'keep_outputs = true\ncontinuation = "excitation.frequency_hz"\n'
                                        'directions = ["up"]\n[axes]\n"excitation.frequency_hz" = [0.9, 1.3]\n'
                                        '"integrator.t_end" = [0.37]\n"excitation.amplitude" = [1e-3]\n')
    result = run_sweep(path, progress=False)
    assert result["failed"] == 0
    folder = result["output"] + ".cases"
    with h5py.File(os.path.join(folder, "case-00000.h5")) as a, h5py.File(os.path.join(folder, "case-00001.h5")) as b:
        z0, z1 = a["constraints/displacement"][-1, 0], b["constraints/displacement"][0, 0]
        v0, v1 = a["constraints/velocity"][-1, 0], b["constraints/velocity"][0, 0]
        w0, w1 = a["probes/displacement"][-1, 0], b["probes/displacement"][0, 0]
    assert abs(z0) > 1e-5, "the state carried over is not rest"
    assert abs(z1 - z0) < 1e-12 and abs(w1 - w0) < 1e-12, "the total displacement does not jump"
    # r_c = 0.75 at x = 0.25 (Eq. 26); uncorrected, v would jump by r_c times the support's jump
    support_jump = 0.75 * 1e-3 * 2 * np.pi * abs(1.3 - 0.9) * abs(np.cos(2 * np.pi * 0.9 * 0.37))
    assert abs(v1 - v0) < 0.2 * support_jump, (v1 - v0, support_jump)   # measured 0.11 of it (7 vectors)


def _gyroscopic_matrices_scene(folder, form):
    """A band running at 30 m/s (test_gyroscopic's BAND) as a matrices scene with its G, shaken at its
    left support (r: the rigid rotation about the right end) against a one-sided guide at x = 0.3. The
    matrices model leaves out G's share of the support's velocity (schema: gyroscopic); what the test
    checks, the continuity of the total state, holds either way."""
    import scipy.io
    import scipy.sparse

    from dbf_hpc import Beam, FullOrderModel

    band = dict(length=1.0, E=2e11, I=2.5e-12, A=3e-5, rho=7800.0, tension=2000.0)
    fom = FullOrderModel.build(Beam(elements=40, axial_speed=30.0, **band))
    try:
        mats = {}
        for name, mat in (("K", fom.operators.K), ("M", fom.operators.M), ("G", fom.operators.G)):
            indptr, indices, values = mat.getValuesCSR()
            lo, hi = mat.getOwnershipRange()
            local = scipy.sparse.csr_matrix((values, indices, indptr), shape=(hi - lo, mat.getSize()[1]))
            mats[name] = scipy.sparse.vstack(MPI.COMM_WORLD.allgather(local)).tocsr()
        mesh = fom.operators.mesh
        free = mesh.free_dofs
    finally:
        fom.destroy()
    x = mesh.x[free // 2]
    r = np.where(free % 2 == 0, 1.0 - x, 1.0)     # w = 1 - x, slope w' = -1 (rz is -w')
    guide = int(np.flatnonzero((free % 2 == 0) & np.isclose(x, 0.3))[0])
    probe = int(np.flatnonzero((free % 2 == 0) & np.isclose(x, 0.5))[0])
    if MPI.COMM_WORLD.rank == 0:
        for name, mat in mats.items():
            scipy.io.mmwrite(str(folder / f"{name}.mtx"), mat, precision=17, symmetry="general")
        np.savetxt(folder / "r.txt", r)
        (folder / "band.toml").write_text(f"""[structure]
kind = "matrices"
stiffness = "K.mtx"
mass = "M.mtx"
gyroscopic = "G.mtx"
influence = "r.txt"
[excitation]
kind = "base"
amplitude = 2e-4
frequency_hz = 40.0
[[constraint]]
dof = {guide}
law = "deadband"
clearance_minus = 1.0
clearance_plus = 3e-4
k_minus = 0.0
k_plus = 2e5
[damping]
rayleigh_alpha = 5.0
[basis]
modes = 6
gyroscopic_form = "{form}"
estimate = false
cache = "off"
[integrator]
t_end = 0.0193
[output]
probes = [{probe}]
""")
    MPI.COMM_WORLD.Barrier()
    return str(folder / "band.toml"), r[guide]


@pytest.mark.parametrize("form", ["state_space", "second_order"])
def test_a_stepped_sine_on_a_gyroscopic_structure_keeps_it_where_it_was_in_either_form(shared_tmp_path, form):
    # The state-space form kept eta as it was when the frequency stepped: the support's velocity jump
    # went into the relative velocity whole (its r_q was zeros). Now eta takes -[r dv; r dw] projected
    # in A = diag(M, K), as the initial state is.
    scene, r_c = _gyroscopic_matrices_scene(shared_tmp_path, form)
    path = shared_tmp_path / "sweep.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(f'scene = "{scene}"\noutput = "summary.h5"\nkeep_outputs = true\n'
                        'continuation = "excitation.frequency_hz"\ndirections = ["up"]\n'
                        '[axes]\n"excitation.frequency_hz" = [40.0, 46.0]\n')
    MPI.COMM_WORLD.Barrier()
    result = run_sweep(str(path), progress=False)
    assert result["failed"] == 0
    folder = result["output"] + ".cases"
    with h5py.File(os.path.join(folder, "case-00000.h5")) as a, h5py.File(os.path.join(folder, "case-00001.h5")) as b:
        assert a.attrs["reduced_form"] == form
        z0, z1 = a["constraints/displacement"][-1, 0], b["constraints/displacement"][0, 0]
        v0, v1 = a["constraints/velocity"][-1, 0], b["constraints/velocity"][0, 0]
        w0, w1 = a["probes/displacement"][-1, 0], b["probes/displacement"][0, 0]
    assert abs(z0) > 1e-6, "the state carried over is not rest"
    scale = max(abs(z0), abs(w0))
    # state space: 4.5e-5 of it, as the velocity's jump projected onto Psi moves its displacement part
    assert abs(z1 - z0) < 1e-3 * scale and abs(w1 - w0) < 1e-3 * scale, "the total displacement does not jump"
    support_jump = abs(r_c) * 2e-4 * 2 * np.pi * abs(46.0 - 40.0) * abs(np.cos(2 * np.pi * 40.0 * 0.0193))
    assert abs(v1 - v0) < 0.2 * support_jump, (v1 - v0, support_jump)   # measured 0.041 and 0.038 of it


def test_a_case_a_run_would_warn_of_is_warned_and_its_summary_row_says_so(shared_tmp_path, capfd):
    # Red team: a clearance of 2.5 given for 2.5 mm: the stop is never reached, and `dbf-hpc run` warns of the
    # clearance's unit; the sweep's summary showed 0 impacts under "ok" without a word, as it did for a basis
    # below the forcing (the shipped two-plane sweep had 60 Hz turbulence on modes below 40 Hz). A clearance
    # beyond the beam's length is refused before any run now: 1 (for 1 mm) on the 1 m beam is let through.
    path = write_sweep(shared_tmp_path, '[axes]\n"constraint.clearance" = [2.5e-3, 1.0]\n"integrator.t_end" = [0.3]\n'
                                        '[[case]]\n"integrator.t_end" = 0.3\n"excitation.frequency_hz" = 200.0\n'
                                        '"excitation.amplitude" = 1e-6\n"constraint.clearance" = 2.5e-3\n')
    result = run_sweep(path, progress=False)
    err = MPI.COMM_WORLD.gather(capfd.readouterr().err, root=0)
    if MPI.COMM_WORLD.rank == 0:
        err = "".join(err)
        assert re.search(r"warning: case 2: constraint 1 at x = 0.25 m never reached its stop .*clearance 1 m", err), err
        assert re.search(r"warning: case 3: the excitation \(200 Hz\) lies above the highest reference mode", err), err
        assert "case 1:" not in err, err
        with h5py.File(result["output"]) as f:
            warned = [w.decode() for w in f["cases/warnings"][:]]
            assert warned[0] == "" and "never reached its stop" in warned[1] and "above the highest" in warned[2]
        lines = describe(result["output"])
        case2 = next(k for k, line in enumerate(lines) if line.startswith("  case 2 "))
        assert "never reached its stop" in lines[case2 + 1] and lines[case2 + 1].startswith("    warning: ")


def test_every_dataset_of_a_summary_carries_its_unit(shared_tmp_path):
    path = write_sweep(shared_tmp_path, SMALL)
    result = run_sweep(path, progress=False)
    if MPI.COMM_WORLD.rank == 0:
        missing = []
        with h5py.File(result["output"]) as f:
            f.visititems(lambda name, obj: missing.append(name)
                         if isinstance(obj, h5py.Dataset) and "unit" not in obj.attrs else None)
            assert f["cases/parameters/excitation.frequency_hz"].attrs["unit"] == "Hz"
        assert not missing, missing


def test_a_two_plane_tube_sweep_over_clearance_and_turbulence_level_records_work_rate_per_support(shared_tmp_path):
    """The shipped 2-D sweep, shortened: every case ok, the work rate, its interval and the wear volume
    per support in the summary, wear = K_w T work_rate, every case sliding."""
    from dbf_hpc.report import describe

    shipped = os.path.join(ROOT, "jobs", "sweep_steam_generator_2d.toml")
    path = shared_tmp_path / "sweep2d.toml"
    if MPI.COMM_WORLD.rank == 0:
        text = open(shipped).read().replace('scene = "steam_generator_tube_2d.toml"',
                                            f'scene = "{os.path.join(ROOT, "jobs", "steam_generator_tube_2d.toml")}"')
        # 0.05 s from rest: stronger turbulence and tighter holes than the shipped study, to meet them
        text = text.replace('"integrator.t_end" = [0.25]', '"integrator.t_end" = [0.05]')
        text = text.replace('"excitation.psd" = [0.01, 0.04]', '"excitation.psd" = [1.0, 4.0]')
        path.write_text(text.replace('"constraint.clearance" = [1e-4, 2e-4]', '"constraint.clearance" = [2e-5, 8e-5]'))
    MPI.COMM_WORLD.Barrier()
    result = run_sweep(str(path), progress=False, overrides=[f"basis.cache={json.dumps(str(shared_tmp_path))}",
                                                             "basis.estimate=false", "structure.elements=100"])
    assert result["cases"] == 4 and result["failed"] == 0
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(result["output"]) as f:
            rate, ci = f["cases/stats/work_rate"][:], f["cases/stats/work_rate_ci95"][:]
            wear = f["cases/stats/wear_volume"][:]
            assert rate.shape == (4, 12) and f["cases/stats/work_rate"].attrs["unit"] == "W"
            assert np.all(np.isfinite(ci)) and np.all(rate >= 0)
            assert np.allclose(wear, 2e-14 * 0.05 * rate, rtol=1e-9, atol=0)
            assert np.all(rate.sum(axis=1) > 0)        # every case slides somewhere
            np.testing.assert_array_equal(f["cases/parameters/constraint.clearance"][:], [2e-5, 2e-5, 8e-5, 8e-5])
        lines = describe(result["output"])
        assert any("max work rate" in line and "wear volume" in line for line in lines)
        from dbf_hpc.plots import _read_sweep, plot_sweep

        with h5py.File(result["output"]) as f:
            assert np.array_equal(_read_sweep(f)["stats"]["work_rate"], rate, equal_nan=True)
        written = plot_sweep(result["output"], str(shared_tmp_path))
        assert len(written) == 2 and all(os.path.getsize(p) > 10000 for p in written)
    assert_all(True)


def test_a_case_whose_partial_output_cannot_continue_starts_again_instead_of_failing_on_every_rerun(shared_tmp_path):
    # A sweep user cannot "rerun without --resume": a case with a valid checkpoint and a damaged
    # .partial failed again on every rerun.
    import signal
    import threading
    import time

    from dbf_hpc.errors import Interrupted

    size = MPI.COMM_WORLD.size   # one case a rank, each stopped after its first checkpoint
    frequencies = ", ".join(f"{1.0 + 0.05 * i}" for i in range(size))
    path = write_sweep(shared_tmp_path, f'[axes]\n"excitation.frequency_hz" = [{frequencies}]\n'
                                        '"integrator.t_end" = [2.0]\n"output.checkpoint_dt" = [0.05]\n')
    folder = shared_tmp_path / "summary.h5.cases"

    def terminate():
        while len(list(folder.glob("case-*.h5.checkpoint"))) < size:
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=terminate, daemon=True).start()   # every rank: a batch system signals all
    with pytest.raises(Interrupted):
        run_sweep(path, progress=False)
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        partials = sorted(folder.glob("case-*.h5.partial"))
        assert len(partials) == size
        for partial in partials:
            with h5py.File(partial, "r+") as f:   # a sample the checkpoint did not save
                f["constraints/displacement"][3, 0] += 1e-3
    MPI.COMM_WORLD.Barrier()
    result = run_sweep(path, progress=False)
    assert result["failed"] == 0
    with h5py.File(result["output"]) as f:
        assert all(s.decode() == "ok" for s in f["cases/status"][:])
        assert np.all(np.abs(f["cases/stats/displacement_peak"][:, 0] / 2.5e-3 - 1) < 0.05)


def test_cases_that_differ_in_the_load_direction_get_their_own_load(shared_tmp_path):
    # Red team: excitation.direction was not part of the model key, so both cases ran the first
    # case's load (55 impacts each); a force along z slides parallel to flats across y: no impact.
    scene = shared_tmp_path / "tube2.toml"
    if MPI.COMM_WORLD.rank == 0:
        scene.write_text('[structure]\nkind = "beam"\nlength = 1.0\nelements = 30\nE = 2e11\nI = 1e-9\nA = 1e-4\n'
                         'rho = 8000.0\nplanes = 2\n[excitation]\nkind = "force"\nx = 0.5\namplitude = 50.0\n'
                         'frequency_hz = 20.0\ndirection = [1.0, 0.0]\n[[constraint]]\nx = 0.3\nlaw = "flat_bar"\n'
                         'clearance = 1e-4\nk = 1e6\n[basis]\nmodes = 4\nestimate = false\n'
                         f'cache = "{shared_tmp_path / "cache"}"\n[integrator]\nt_end = 0.2\n')
    path = shared_tmp_path / "directions.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(f'scene = "{scene}"\noutput = "directions.h5"\n[[case]]\n"excitation.direction" = [1.0, 0.0]\n'
                        '[[case]]\n"excitation.direction" = [0.0, 1.0]\n')
    MPI.COMM_WORLD.Barrier()
    result = run_sweep(str(path), progress=False)
    assert result["failed"] == 0
    with h5py.File(result["output"]) as f:
        impacts = f["cases/stats/impacts"][:, 0]
    assert impacts[0] > 10 and impacts[1] == 0, impacts


def test_a_step_is_not_continued_from_a_state_computed_in_another_basis(shared_tmp_path):
    # Red team: a rebuilt basis (cache cleared, another rank layout) can turn a repeated frequency's
    # modes; a step continuing from its predecessor's stored q then starts in another physical state.
    # Here the predecessor's record says it was computed in another basis: its chain runs again.
    path, files = _swept(shared_tmp_path, 'continuation = "excitation.frequency_hz"\ndirections = ["up"]\n[axes]\n'
                                          '"excitation.frequency_hz" = [0.9, 1.1]\n"integrator.t_end" = [0.05]\n', 2)
    fresh = [json.load(open(name)) for name in files]
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        _write_record(files[0], dict(fresh[0], coordinates="0" * 64))
        os.remove(files[1])          # killed before step 2 ran
    MPI.COMM_WORLD.Barrier()
    run_sweep(path, progress=False)
    again = [json.load(open(name)) for name in files]
    assert_all(again[0]["coordinates"] == fresh[0]["coordinates"], "step 1 ran again in the basis of now")
    assert_all(again[1]["continued"] and again[1]["stats"] == fresh[1]["stats"])


def test_every_rank_runs_the_sweep_rank_0_read_also_when_another_rank_cannot_read_it(shared_tmp_path, monkeypatch):
    # Each rank read the sweep file and its scenes itself: an edit while the job started, or a node that
    # cannot read the path, gave the ranks different cases or one rank's error while the others went on
    import dbf_hpc.sweep as sweep_module

    path = write_sweep(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n"integrator.t_end" = [0.05]\n')
    if MPI.COMM_WORLD.rank:
        monkeypatch.setattr(sweep_module, "load_sweep", lambda *args: (_ for _ in ()).throw(
            InputError(f"cannot read sweep {path!r}")))
    result = run_sweep(path, progress=False)
    assert result["cases"] == 2 and result["failed"] == 0


def test_a_listed_case_that_leaves_another_parameter_unset_is_drawn_in_the_sweep_figure(shared_tmp_path, monkeypatch):
    # Red team: its NaN in the other parameter's column matched no line (NaN != NaN): the case was
    # left out of the figure without a word
    import matplotlib.axes

    from dbf_hpc.plots import plot_sweep

    path = write_sweep(shared_tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n"damping.zeta" = [0.01, 0.02]\n'
                                        '"integrator.t_end" = [0.05]\n'
                                        '[[case]]\n"excitation.frequency_hz" = 1.3\n"integrator.t_end" = 0.05\n')
    result = run_sweep(path, progress=False)
    if MPI.COMM_WORLD.rank == 0:
        drawn, plot = [], matplotlib.axes.Axes.plot
        monkeypatch.setattr(matplotlib.axes.Axes, "plot", lambda ax, *a, **k: (drawn.append((a, k)), plot(ax, *a, **k))[1])
        plot_sweep(result["output"], str(shared_tmp_path))
        lines = [(np.asarray(a[0]), k["label"]) for a, k in drawn if k.get("label", "").startswith("constraint 1")]
        assert any(1.3 in x and "zeta not set" in label for x, label in lines), [(list(x), l) for x, l in lines]
    assert_all(True)


def test_a_reused_case_shows_the_value_the_sweep_sets_now_however_the_sweep_file_spells_it(shared_tmp_path):
    # red team: the axis renamed from constraint.k to constraint.1.k (one constraint: the same scenes, so
    # both records were reused) wrote NaN, "the base scene's value" of 1e6 N/m, for cases at 1e5 and 2e5 N/m
    base = _copy_scene(shared_tmp_path)
    path = shared_tmp_path / "renamed.toml"
    for axis in ("constraint.k", "constraint.1.k"):
        if MPI.COMM_WORLD.rank == 0:
            path.write_text(f'scene = "{base}"\noutput = "renamed.h5"\n[axes]\n"{axis}" = [1e5, 2e5]\n'
                            f'"integrator.t_end" = [0.05]\n')
        MPI.COMM_WORLD.Barrier()
        before = counters["eigen_solves"]
        result = run_sweep(str(path), progress=False)
    assert counters["eigen_solves"] == before, "the renamed axis sets the same scenes: no case is run again"
    with h5py.File(result["output"]) as f:
        np.testing.assert_array_equal(f["cases/parameters/constraint.1.k"][:], [1e5, 2e5])
        assert "constraint.k" not in f["cases/parameters"]


def test_keep_outputs_turned_on_after_a_sweep_writes_every_case_output_it_promises(shared_tmp_path):
    # red team: the rerun reused every record and wrote no case's HDF5 output, in silence
    base = _copy_scene(shared_tmp_path)
    path = shared_tmp_path / "kept.toml"
    for keep in ("false", "true"):
        if MPI.COMM_WORLD.rank == 0:
            path.write_text(f'scene = "{base}"\noutput = "kept.h5"\nkeep_outputs = {keep}\n' + SMALL)
        MPI.COMM_WORLD.Barrier()
        result = run_sweep(str(path), progress=False)
    folder = result["output"] + ".cases"
    outputs = [os.path.join(folder, f"case-{i:05d}.h5") for i in range(2)]
    assert_all(all(os.path.isfile(p) for p in outputs), "keep_outputs = true keeps each case's output")
    with h5py.File(outputs[1]) as f:
        assert f.attrs["complete"] and abs(f["time"][-1] - 0.3) < 1e-12   # the case's own run, to its t_end
    # a kept output removed since is written again; the other case's is not
    stamp = os.path.getmtime(outputs[1])
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        os.remove(outputs[0])
    MPI.COMM_WORLD.Barrier()
    run_sweep(str(path), progress=False)
    assert_all(os.path.isfile(outputs[0]) and os.path.getmtime(outputs[1]) == stamp)


def test_a_sweeps_info_line_says_its_impacts_are_those_of_all_constraints_together(shared_tmp_path):
    # New-user pass: "max |w| 0.00015 m, 659 impacts" read as the impacts of the constraint with the
    # largest |w|; it is the sum over the constraints (here the paper's four stops).
    path = shared_tmp_path / "sweep4.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(f'scene = "{os.path.join(ROOT, "jobs", "paper_beam_4.toml")}"\noutput = "summary4.h5"\n'
                        '[axes]\n"integrator.t_end" = [2.0]\n"basis.cache" = ["off"]\n')
    MPI.COMM_WORLD.Barrier()
    result = run_sweep(str(path), progress=False)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(result["output"]) as f:
            per_stop = f["cases/stats/impacts"][0]
        assert per_stop.shape == (4,) and np.count_nonzero(per_stop) > 1, per_stop
        line = next(line for line in describe(result["output"]) if line.startswith("  case 1 "))
        assert f", {per_stop.sum():.0f} impacts at the 4 constraint(s) together, " in line, line


def test_a_sweep_figure_draws_each_supports_work_rate_with_its_95_percent_interval():
    # A wear study reads the work rate with its batch-means interval (info prints both); the sweep
    # figure drew the rate alone (day-one user). Per support, and on the worst support of many.
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.container import ErrorbarContainer

    from dbf_hpc.plots import _sweep_lines

    rate = np.array([[1e-3, 2e-3], [3e-3, 1e-3]])
    ci = np.array([[1e-4, 2e-4], [3e-4, 4e-4]])
    x = np.array([1e-4, 2e-4])
    for supports in (2, 6):   # a line per support, or the mean and the worst of many
        data = {"ok": np.ones(2, bool), "stats": {"work_rate": np.tile(rate, (1, supports // 2)),
                                                   "work_rate_ci95": np.tile(ci, (1, supports // 2))},
                "probe_peak": np.zeros((2, 0))}
        fig, ax = plt.subplots()
        _sweep_lines(ax, "work_rate", 1e3, (), [()] * 2, x, [], data, {}, iter(plt.cm.tab20(np.linspace(0, 1, 20))))
        bars = [c for c in ax.containers if isinstance(c, ErrorbarContainer)]
        plt.close(fig)
        assert len(bars) == (2 if supports == 2 else 1), bars
        # the worst support's interval is that support's own: case 1 worst at support 2 (2e-3 +- 2e-4), case 2
        # at support 1 (3e-3 +- 3e-4), in mW
        segments = bars[-1].lines[2][0].get_segments()
        heights = [seg[1][1] - seg[0][1] for seg in segments]
        expected = [2 * 2e-4 * 1e3, 2 * 4e-4 * 1e3] if supports == 2 else [2 * 2e-4 * 1e3, 2 * 3e-4 * 1e3]
        np.testing.assert_allclose(heights, expected, rtol=1e-12)


def test_a_case_whose_output_is_not_kept_writes_none_and_its_statistics_are_the_kept_ones(shared_tmp_path,
                                                                                          monkeypatch):
    # Without keep_outputs a case's HDF5 output (some 80 datasets with their units) was written, then
    # removed: half a short case's wall time. Now only its samples for the checkpoints are streamed;
    # the impact statistics, probe peaks and final states are those of the kept run, bit for bit.
    from dbf_hpc.output import OutputWriter

    finished = []
    original = OutputWriter.finish
    monkeypatch.setattr(OutputWriter, "finish", lambda self, *a, **k: (finished.append(self.path),
                                                                       original(self, *a, **k)))
    base = _copy_scene(shared_tmp_path)
    path = shared_tmp_path / "keep.toml"
    summaries, counts = {}, {}
    for keep in ("false", "true"):
        if MPI.COMM_WORLD.rank == 0:
            path.write_text(f'scene = "{base}"\noutput = "keep_{keep}.h5"\nkeep_outputs = {keep}\n' + SMALL)
        MPI.COMM_WORLD.Barrier()
        finished.clear()
        result = run_sweep(str(path), progress=False)
        counts[keep] = MPI.COMM_WORLD.allreduce(len(finished))
        with h5py.File(result["output"]) as f:
            summaries[keep] = {name: f[f"cases/stats/{name}"][()] for name in STATISTICS}
            summaries[keep]["probe_peak"] = f["cases/probe_peak"][()]
        folder = result["output"] + ".cases"
        records = [json.load(open(os.path.join(folder, f"case-{i:05d}.json"))) for i in range(2)]
        summaries[keep]["final_state"] = np.array([r["final_state"] for r in records])
    assert counts == {"false": 0, "true": 2}, counts
    assert not any(name.endswith((".h5", ".partial", ".checkpoint"))
                   for name in os.listdir(shared_tmp_path / "keep_false.h5.cases"))
    assert summaries["false"]["impacts"].sum() > 0
    for name, value in summaries["true"].items():
        np.testing.assert_array_equal(summaries["false"][name], value, err_msg=name)


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="one rank: on several the signalled rank ends the job (test_cli)")
def test_a_termination_signal_while_the_sweep_prepares_its_models_stops_it_and_records_no_case(tmp_path, monkeypatch,
                                                                                               capsys):
    # Red team: the signal's Interrupted, raised by the command's handler while a model was built, was
    # taken for that model's failure: every case of it was recorded "failed" with the signal's line, and
    # the sweep went on to its other models and wrote a summary. A batch system's time limit stops it.
    import signal

    from dbf_hpc import cli, sweep

    class Signalled(sweep.Reductor):
        def __init__(self, *args, **kwargs):
            os.kill(os.getpid(), signal.SIGTERM)
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(sweep, "Reductor", Signalled)
    path = write_sweep(tmp_path, '[axes]\n"excitation.frequency_hz" = [0.9, 1.1]\n"integrator.t_end" = [0.2]\n')
    assert cli.main(["sweep", path, "-q"]) == 1
    err = capsys.readouterr().err
    assert err.splitlines() == [f"dbf-hpc: error: {cli.TERMINATED_SWEEP}"], err
    assert not list(tmp_path.glob("summary.h5.cases/case-*")) and not list(tmp_path.glob("summary.h5*.lock"))
    assert not (tmp_path / "summary.h5").exists()


def test_a_cells_file_changes_no_case_identity(shared_tmp_path):
    # [structure] cells only draw a case's field: a sweep's finished records stay reused when they
    # are added or changed (a kept output drawn without them is rerun: finished_output, test_run)
    from dbf_hpc.scene import load_scene
    from dbf_hpc.sweep import _coordinates_key, _identities
    from test_xdmf import solid

    cells, points = load_scene(solid(shared_tmp_path)), load_scene(solid(shared_tmp_path, cells=False))
    assert _identities({"chains": []}, [cells]) == _identities({"chains": []}, [points])
    assert _coordinates_key(cells) == _coordinates_key(points)
    assert _identities({"chains": []}, [cells]) != _identities({"chains": []}, [cells.with_values("basis", modes=3)])


def test_a_sweep_warns_once_naming_the_cases_whose_atol_lets_w_err_by_over_a_percent_of_a_clearance(
        shared_tmp_path, capfd):
    # `dbf-hpc run` warns of a loose atol (run.loose_atol); a sweep of the same cases said nothing. One line
    # names the cases (1 and 2; case 3's atol is tight enough), printed by rank 0 alone
    from conftest import small_mass_chain

    scene = small_mass_chain(shared_tmp_path)
    path = write_sweep(shared_tmp_path, '[axes]\n"integrator.atol" = [1e-9, 1e-10, 1e-14]\n', scene, "atol.toml", "atol.h5")
    capfd.readouterr()
    assert run_sweep(path, progress=False)["failed"] == 0
    err = capfd.readouterr().err
    lines = [line for line in err.splitlines() if "[integrator] atol = " in line]
    if MPI.COMM_WORLD.rank == 0:
        assert_all(len(lines) == 1 and lines[0].startswith("dbf-hpc: warning: sweep: cases 1, 2: [integrator] "
                                                           "atol = 1e-09") and "(case 1, the worst)" in lines[0], err)
    else:
        assert_all(not lines, err)


def test_each_case_keeps_the_warnings_the_sweep_said_once_for_its_cases_and_they_are_not_said_again(
        shared_tmp_path, capfd):
    # Warnings parity: a loose atol (run.loose_atol) and a sample interval that aliases the forcing are said once
    # by the sweep, naming the cases, before they run; cases/warnings, where `dbf-hpc info` and a reader of the
    # summary look, held no trace of them. Each case's row now holds them in the order its run would print them,
    # and the rank that runs a case does not print them a second time. The chain of small masses forced at
    # 10 Hz: atol 1e-9 is loose for its 1 um stop (1e-14 is not), and samples 0.06 s apart are fewer than 2 a
    # period.
    from conftest import small_mass_chain

    scene = small_mass_chain(shared_tmp_path)
    path = write_sweep(shared_tmp_path, '[axes]\n"integrator.atol" = [1e-9, 1e-14]\n"output.sample_dt" = [1e-4, 0.06]\n'
                       '"integrator.t_end" = [0.2]\n', scene, "said.toml", "said.h5")
    capfd.readouterr()
    result = run_sweep(path, progress=False)
    assert result["failed"] == 0
    err = "".join(MPI.COMM_WORLD.allgather(capfd.readouterr().err))
    assert_all(err.count("[integrator] atol = 1e-09 (modal units") == 1, err)
    assert_all(err.count("fewer than 2: the sampled series") == 1, err)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(result["output"]) as f:
            atol = f["cases/parameters/integrator.atol"][:]
            sample_dt = f["cases/parameters/output.sample_dt"][:]
            warned = [w.decode().split("\n") if w else [] for w in f["cases/warnings"][:]]
        for a, dt, lines in zip(atol, sample_dt, warned):
            expected = ([f"[output] sample_dt = {dt:g} s takes"] if dt > 1e-3 else []) + \
                ([f"[integrator] atol = {a:g} (modal units"] if a > 1e-12 else [])
            assert [line[:len(e)] for line, e in zip(lines, expected)] == expected and len(lines) == len(expected), \
                (a, dt, lines)
        assert sum(len(lines) for lines in warned) == 4


def test_a_case_keeps_the_very_warnings_a_run_of_its_scene_stores_in_its_output(shared_tmp_path, capfd):
    # Warnings parity: the same result, the same lines. The paper's beam at a fixed step of 5e-5 s, whose
    # impacts last one step: `dbf-hpc run` warns that the step does not resolve them, advising a shorter dt
    # or adaptive steps; the sweep's row of the same case left the advice of adaptive steps out. A one-case
    # sweep of that scene keeps exactly the lines the run's output keeps.
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    sets = {"integrator.t_end": "0.12", "integrator.adaptive": "false", "integrator.dt": "5e-5",
            "basis.estimate": "false", "output.snapshots": "0", "basis.cache": '"off"'}
    ran = run(load_scene(PAPER, [f"{k}={v}" for k, v in sets.items()]), str(shared_tmp_path / "one.h5"),
              progress=False)
    path = write_sweep(shared_tmp_path, "[axes]\n" + "".join(f'"{k}" = [{v}]\n' for k, v in sets.items()))
    result = run_sweep(path, progress=False)
    capfd.readouterr()
    assert result["failed"] == 0 and len(ran["warnings"]) == 1, ran["warnings"]
    assert "fixed steps on average" in ran["warnings"][0] and ran["warnings"][0].endswith(
        "or set [integrator] adaptive = true"), ran["warnings"]
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(result["output"]) as f:
            assert f["cases/warnings"][0].decode().split("\n") == ran["warnings"]


def test_a_basis_a_run_warns_of_is_warned_once_for_the_cases_that_share_it_and_kept_in_each_row(shared_tmp_path,
                                                                                                   capfd):
    # Warnings parity: `dbf-hpc run` warns of its basis (here the lowest elastic frequency, 0.000254 Hz, of a
    # chain whose stiffness and mass files are swapped, and the flexibility its 4 modes capture); a sweep of such
    # cases said nothing of it. The sweep now says each once, naming the cases of that model, and each case's
    # row keeps the lines the run of the same scene stores in its output (the run's order: the matrix files'
    # warnings, the basis', the result's), none printed a second time per case.
    import scipy.io
    import scipy.sparse

    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    n = 10
    K = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr() * 1e5
    scene, path = shared_tmp_path / "swapped.toml", shared_tmp_path / "swapped-sweep.toml"
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(str(shared_tmp_path / "K.mtx"), K, precision=17)
        scipy.io.mmwrite(str(shared_tmp_path / "M.mtx"), scipy.sparse.identity(n, format="csr"))
        scene.write_text('[structure]\nkind = "matrices"\nstiffness = "M.mtx"\nmass = "K.mtx"\n'
                         '[excitation]\nkind = "force"\ndof = 2\namplitude = 1.0\nfrequency_hz = 1e-5\n'
                         '[[constraint]]\ndof = 5\nclearance = 1e-3\nk = 1e5\n[basis]\nmodes = 4\ncache = "off"\n'
                         'estimate = false\n[integrator]\nt_end = 0.01\n')
        path.write_text(f'scene = "{scene}"\noutput = "swapped.h5"\n[axes]\n"excitation.amplitude" = [1.0, 2.0]\n')
    MPI.COMM_WORLD.Barrier()
    ran = run(load_scene(str(scene)), str(shared_tmp_path / "swapped-run.h5"), progress=False)
    capfd.readouterr()
    result = run_sweep(str(path), progress=False)
    err = "".join(MPI.COMM_WORLD.allgather(capfd.readouterr().err))
    units = [line for line in err.splitlines() if "lowest elastic frequency" in line]
    assert_all(len(units) == 1 and units[0].startswith("dbf-hpc: warning: sweep: cases 1, 2: the lowest elastic "
                                                       "frequency is 0.000254 Hz"), err)
    assert any("lowest elastic frequency" in w for w in ran["warnings"]), ran["warnings"]
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(result["output"]) as f:
            rows = [w.decode().split("\n") for w in f["cases/warnings"][:]]
        # case 1 is the run's scene; case 2, of twice the force, differs in its result's line alone
        assert rows[0] == ran["warnings"] and rows[1][:-1] == ran["warnings"][:-1], (rows, ran["warnings"])
        assert "never reached its stop" in rows[1][-1] and len(ran["warnings"]) == 4, ran["warnings"]


def test_a_rerun_of_a_finished_sweep_says_again_what_its_cases_warned_each_line_once(shared_tmp_path, capfd):
    # Warnings parity: `dbf-hpc run --resume` of a finished output prints its run's warnings again; a rerun of
    # a finished sweep (a requeued job) computed nothing and said nothing of what its cases had warned. Now
    # each line of the kept cases' rows is said once, naming its cases. Case 1's atol (1e-9) is loose for the
    # chain's 1 um stop, case 2's (1e-14) is not.
    from conftest import small_mass_chain

    scene = small_mass_chain(shared_tmp_path)
    path = write_sweep(shared_tmp_path, '[axes]\n"integrator.atol" = [1e-9, 1e-14]\n', scene, "again.toml", "again.h5")
    first = run_sweep(path, progress=False)
    capfd.readouterr()
    again = run_sweep(path)
    out, err = capfd.readouterr()
    assert first["failed"] == again["failed"] == 0
    assert_all(MPI.COMM_WORLD.rank != 0 or "2 already done, 0 to run" in out, out)
    lines = [line for line in err.splitlines() if "[integrator] atol = " in line]
    assert_all(lines == [] if MPI.COMM_WORLD.rank else len(lines) == 1 and lines[0].startswith(
        "dbf-hpc: warning: case 1 (done before): [integrator] atol = 1e-09 (modal units"), err)


def test_a_scene_given_to_sweep_is_named_a_scene_with_the_command_that_runs_it():
    # New-user pass: `dbf-hpc sweep jobs/paper_beam.toml` said "unknown key 'structure' (sweep files have ...)".
    paper = os.path.join(ROOT, "jobs", "paper_beam.toml")
    with pytest.raises(InputError, match=rf"^{re.escape(paper)}: is a scene, not a sweep file \(scene = the base "
                                         rf"scene, and \[axes\] or \[\[case\]\]\): run it with dbf-hpc run "):
        load_sweep(paper)


def test_a_sweep_path_that_does_not_exist_names_the_directory_it_was_looked_for_in(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match=rf"^cannot read sweep 'jobs/sweep.toml': No such file or directory "
                                         rf"\(relative to the current directory {re.escape(str(tmp_path))}\)$"):
        load_sweep("jobs/sweep.toml")


@pytest.mark.parametrize("kind", ["unused_keys", "micro_beam", "state_space_form"])
def test_a_case_says_and_keeps_the_very_warnings_a_run_of_its_scene_gives_of_unused_keys_forms_and_micro_motion(
        shared_tmp_path, capfd, kind):
    # Warnings parity: `dbf-hpc run` warns of [basis] keys it does not read (estimate windows with estimate =
    # false, DBF keys with enrichment = "static", the state-space form on a structure without G) and of an atol
    # above a micro-beam's whole motion (run.motion_reach, no clearance to compare with); a sweep of the same
    # scene said none of them but the last, kept in its row and never printed. Now the sweep says each once
    # naming its case (the form's line as the model is built), and the row is the run's list.
    from conftest import MICRO_BEAM
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    if kind == "state_space_form":
        scene, sets = PAPER, {"integrator.t_end": "0.01", "basis.modes": "4", "basis.estimate": "false",
                              "basis.gyroscopic_form": '"state_space"', "output.snapshots": "0",
                              "basis.cache": '"off"'}
        expected = ('[basis] gyroscopic_form = "state_space" is for gyroscopic structures',)
    elif kind == "unused_keys":
        scene, sets = PAPER, {"integrator.t_end": "0.01", "basis.modes": "4", "basis.estimate": "false",
                              "basis.estimate_window": "0.005", "basis.enrichment": '"static"',
                              "basis.dbf_stiffness": "1e5", "output.snapshots": "0", "basis.cache": '"off"'}
        expected = ("[basis] estimate_window is not used: [basis] estimate = false",
                    '[basis] dbf_stiffness is not used by enrichment = "static"')
    else:
        scene = shared_tmp_path / "micro_sweep.toml"
        if MPI.COMM_WORLD.rank == 0:
            scene.write_text(MICRO_BEAM + '\n[basis]\nmodes = 4\ncache = "off"\n\n[output]\nprobes = [5e-5]\n')
        MPI.COMM_WORLD.Barrier()
        scene, sets = str(scene), {"integrator.t_end": "2e-5", "output.sample_dt": "1e-7"}
        expected = ("[integrator] atol = 1e-09 (modal units, m kg^(1/2)) lets w err by up to",)
    ran = run(load_scene(scene, [f"{k}={v}" for k, v in sets.items()]), str(shared_tmp_path / f"{kind}.h5"),
              progress=False)
    capfd.readouterr()
    path = write_sweep(shared_tmp_path, "[axes]\n" + "".join(f'"{k}" = [{v}]\n' for k, v in sets.items()), scene,
                       f"{kind}.toml", f"{kind}-sweep.h5")
    result = run_sweep(path, progress=False)
    err = "".join(MPI.COMM_WORLD.allgather(capfd.readouterr().err))
    assert result["failed"] == 0 and len(ran["warnings"]) == len(expected), ran["warnings"]
    for line in expected:
        assert any(w.startswith(line) for w in ran["warnings"]), (line, ran["warnings"])
        named = "" if kind == "state_space_form" else r"(sweep|\S+): case 1: "   # (said as the model is built)
        assert_all(err.count(line) == 1 and re.search(r"warning: " + named + re.escape(line), err), err)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(result["output"]) as f:
            assert f["cases/warnings"][0].decode().split("\n") == ran["warnings"]


def test_a_case_whose_samples_cap_its_step_below_its_floor_fails_before_its_basis_and_the_others_run(
        shared_tmp_path):
    # What `dbf-hpc run` refuses before the basis (run.cap_refusal_before_basis: t_end = 1e-9 s on the paper's
    # beam), a case fails with before it too, with the run's line: a model whose every case is so refused is
    # not built (no eigensolve), and a case that runs (t_end = 1e-7 s) is not held up by another's refusal.
    cache = shared_tmp_path / "cap_cache"
    body = (f'[axes]\n"integrator.t_end" = [{{t}}]\n"basis.modes" = [6]\n"basis.estimate" = [false]\n'
            f'"output.snapshots" = [0]\n"basis.cache" = ["{cache}"]\n')
    solves = counters["eigen_solves"]
    result = run_sweep(write_sweep(shared_tmp_path, body.format(t="1e-9"), name="cap.toml", output="cap.h5"),
                       progress=False)
    assert result["failed"] == 1 and counters["eigen_solves"] == solves and not os.path.exists(cache)
    with h5py.File(result["output"]) as f:
        errors = [e.decode() if isinstance(e, bytes) else e for e in f["cases/error"][:]]
    assert errors[0].startswith("[integrator] t_end = 1e-09 s: its output samples, 1e-13 s apart, cap an adaptive "
                                "step at 1e-12 s, not above the smallest step it may take (1e-12 s)"), errors
    both = run_sweep(write_sweep(shared_tmp_path, body.format(t="1e-9, 1e-7"), name="cap2.toml", output="cap2.h5"),
                     progress=False)
    assert both["failed"] == 1 and both["cases"] == 2, both


# Rank 0 of a 2-rank run_sweep (the Python API) meets an exception no write foresaw as it writes the
# summary (here a ValueError from _units, after the summary's .partial was made); every rank says what it
# raised, then rank 0 lists the folder
_UNEXPECTED_AS_RANK_0_SUMMARIZES = """
import os, sys
from mpi4py import MPI
from dbf_hpc import sweep

folder, paper, rank = sys.argv[1], sys.argv[2], MPI.COMM_WORLD.rank
def refuse(*args, **kwargs):
    raise ValueError("rank 0's summary refused")
if rank == 0:
    sweep._units = refuse
path = os.path.join(folder, "sweep.toml")
if rank == 0:
    with open(path, "w") as f:
        f.write(f'scene = "{paper}"\\noutput = "summary.h5"\\n[axes]\\n"excitation.frequency_hz" = [0.9, 1.1]\\n')
MPI.COMM_WORLD.Barrier()
def act():
    sweep.run_sweep(path, progress=False, overrides=["integrator.t_end=0.05", "structure.elements=20", "basis.cache=off",
                                                     "basis.estimate=false", "output.snapshots=0"])


every_rank_says(act, folder)
"""


@pytest.mark.launcher
def test_an_unexpected_error_while_rank_0_writes_the_sweep_summary_is_raised_on_every_rank(tmp_path):
    # Red team: the summary's write passed on a write error (OSError, RuntimeError) alone; any other
    # exception on rank 0 left it alone with it, its summary.h5.partial behind, and the other ranks
    # waiting in the broadcast after it for ever (the Python API does not abort as `python -m mpi4py`
    # does). Now every rank raises it (rank 0 its own, rank 1 a copy naming rank 0), and only the case
    # records are kept (a rerun writes the summary from them).
    out = two_ranks_of(_UNEXPECTED_AS_RANK_0_SUMMARIZES, tmp_path, PAPER)
    assert out.returncode == 0, f"exit {out.returncode} (124: a rank waited for ever)\n{out.stdout}{out.stderr}"
    assert out.stdout.splitlines() == ["rank 0: ValueError: rank 0's summary refused (origin None)",
                                       "rank 1: ValueError: rank 0's summary refused (origin 0)",
                                       "files ['summary.h5.cases', 'sweep.toml']"], out.stdout + out.stderr
