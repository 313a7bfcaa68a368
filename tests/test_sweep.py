"""Parameter studies (sweep.py): cases over the ranks, one basis per distinct structure, a summary
with the impact statistics, resume after a kill, failed cases recorded."""
import json
import os

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from conftest import assert_all
from dbf_hpc.errors import InputError
from dbf_hpc.modes import counters
from dbf_hpc.stats import STATISTICS
from dbf_hpc.sweep import load_sweep, run_sweep

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER = os.path.join(ROOT, "jobs", "paper_beam.toml")


def write_sweep(folder, body):
    path = folder / "sweep.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(f'scene = "{PAPER}"\noutput = "summary.h5"\n' + body)
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
    assert result["cases"] == 6 and result["failed"] == 1
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


def test_a_bad_case_stops_the_sweep_before_any_work(shared_tmp_path):
    path = write_sweep(shared_tmp_path, '[axes]\n"constraint.clearance" = [1e-3, -1]\n"basis.mode" = [3]\n')
    with pytest.raises(InputError, match="case 1 .*unknown key 'mode' in \\[basis\\]"):
        load_sweep(path)


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
