"""Reduced nonlinear dynamics (reduced.py, integrate.py, run.py, output.py) against exact answers:
the closed-form linear response of the pinned beam, the paper's impacting beam, energy conservation."""
import dataclasses
import json
import os

import h5py
import numpy as np
import pytest
from mpi4py import MPI

from conftest import MICRO_BEAM, assert_all, rank0_files, two_ranks_of
from dbf_hpc.errors import InputError
from dbf_hpc.laws import ConstraintLaws
from dbf_hpc.run import run
from dbf_hpc.scene import load_scene
from exact import pinned_beam_base_modal_amplitudes, pinned_beam_base_response

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAPER = os.path.join(ROOT, "jobs", "paper_beam.toml")
EI, RHOA = 117e9 * 8.78e-16, 11800 * 2.9e-7


def paper_run(tmp, *sets, name="out.h5", scene=PAPER):
    s = load_scene(scene, ["basis.cache=off", *sets])
    path = str(tmp / name)
    summary = run(s, path, progress=False)
    return s, h5py.File(path, "r") if MPI.COMM_WORLD.rank == 0 else None, summary


def without_constraints(tmp):
    text = open(PAPER).read()
    text = text[:text.index("[[constraint]]")] + text[text.index("[basis]"):]
    path = tmp / "no_constraint.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(text)
    MPI.COMM_WORLD.Barrier()
    return str(path)

def two_plane_tube_with_three_holes(tmp) -> str:
    """The paper's beam bending in two planes, held by round holes (clearance 2.5 mm, 1e6 N/m) at
    x = 0.25, 0.6 and 0.8 m: a scene file in tmp, written by rank 0. Collective."""
    text = open(PAPER).read().replace('right = "pinned"', 'right = "pinned"\nplanes = 2')
    stops = "".join(f'[[constraint]]\nx = {x}\nlaw = "circular"\nclearance = 2.5e-3\nk = 1e6\n\n'
                    for x in (0.25, 0.6, 0.8))
    text = text[:text.index("[[constraint]]")] + stops + text[text.index("[basis]"):]
    path = tmp / "two_planes.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(text)
    MPI.COMM_WORLD.Barrier()
    return str(path)



def test_modal_model_without_constraints_is_the_closed_form_truncated_to_n_modes(shared_tmp_path):
    scene = without_constraints(shared_tmp_path)
    _, f, _ = paper_run(shared_tmp_path, "basis.modes=6", "integrator.rtol=1e-8", "integrator.atol=1e-12",
                        "output.sample_dt=1e-3", scene=scene)
    if f is not None:
        t, w = f["time"][:], f["probes/displacement"][:, 0]
        exact = pinned_beam_base_response(EI, RHOA, 1.0, np.array([0.5]), t, 5e-3, 1.0, 6)[:, 0]
        # rtol 1e-8 over 10 s: measured 2.7e-7 of the peak
        assert np.abs(w - exact).max() < 2e-6 * np.abs(exact).max()
        assert f["constraints/displacement"].shape == (t.size, 0)


def test_unreached_constraint_gives_the_linear_response_within_the_truncation_error(shared_tmp_path):
    errors = []
    for N in (6, 10):
        _, f, _ = paper_run(shared_tmp_path, f"basis.modes={N}", "constraint.clearance=1.0",
                            "integrator.rtol=1e-8", "integrator.atol=1e-12", "output.sample_dt=1e-3",
                            name=f"lin{N}.h5")
        if f is not None:
            t, z = f["time"][:], f["constraints/displacement"][:, 0]
            assert not f["constraints/force"][:].any(), "the constraint is never reached"
            exact = pinned_beam_base_response(EI, RHOA, 1.0, np.array([0.25]), t, 5e-3, 1.0, 200)[:, 0]
            errors.append(np.abs(z - exact).max() / np.abs(exact).max())
    if errors:
        assert errors[0] < 1e-3, errors        # truncation error bound at the paper's N = 6
        assert errors[1] < errors[0], errors   # and it shrinks as N grows


def test_paper_beam_stays_at_the_clearance_and_its_mode_4_ignores_the_impacts(shared_tmp_path):
    # Paper Sec. 3.3: max |w(l, t)| ~ d_x over 10 s. l = 0.25 is a node of mode 4, so the impacts
    # cannot drive it: its coordinate is exactly the linear response to the base motion alone.
    s, f, summary = paper_run(shared_tmp_path)
    if f is not None:
        t, z = f["time"][:], f["constraints/displacement"][:, 0]
        assert abs(np.abs(z).max() / 2.5e-3 - 1) < 0.03
        free = pinned_beam_base_response(EI, RHOA, 1.0, np.array([0.25]), t, 5e-3, 1.0, 50)[:, 0]
        assert np.abs(free).max() > 5 * 2.5e-3, "without the stop the beam would swing far past it"
        assert abs(f["reduced/B"][0, 3]) < 1e-8 * np.abs(f["reduced/B"][:]).max()
        q4 = f["reduced/q"][:, 3]
        linear = pinned_beam_base_modal_amplitudes(EI, RHOA, 1.0, t, 5e-3, 1.0, 4)[:, 3]
        linear *= np.sign(q4 @ linear)
        assert np.abs(q4 - linear).max() < 1e-3 * np.abs(linear).max()   # measured 3.9e-4 at rtol 1e-6
        stats = json.loads(f.attrs["solver_stats"])
        assert stats["steps"] > 0 and f.attrs["complete"]
    assert summary["stats"]["steps"] > 0


def test_free_vibration_with_elastic_contact_conserves_energy_over_many_impacts(shared_tmp_path):
    s, f, _ = paper_run(shared_tmp_path, "excitation.kind=none", "initial.mode=2", "initial.amplitude=0.003",
                        "constraint.k_minus=100.0", "constraint.k_plus=100.0", "integrator.t_end=2.0",
                        "integrator.rtol=1e-8", "integrator.atol=1e-12")
    if f is not None:
        q, p, K, z = f["reduced/q"][:], f["reduced/qdot"][:], f["reduced/K"][:], f["constraints/displacement"][:]
        laws = ConstraintLaws([c.law for c in s.constraints])
        energy = (0.5 * np.sum(p * p, 1) + 0.5 * np.einsum("ti,ij,tj->t", q, K, q)
                  + np.array([laws.potential(row).sum() for row in z]))
        contact = f["constraints/force"][:, 0] != 0
        impacts = np.count_nonzero(np.diff(contact.astype(int)) == 1)
        assert impacts > 20
        assert np.abs(energy / energy[0] - 1).max() < 5e-4   # measured 8e-5 over 10 s at rtol 1e-8


def test_output_has_the_documented_layout(shared_tmp_path):
    s, f, _ = paper_run(shared_tmp_path, "integrator.t_end=0.5", "output.sample_dt=0.01", "output.snapshots=5")
    if f is not None:
        nt = 51
        expected = {"time": (nt,), "constraints/position": (1,), "constraints/displacement": (nt, 1),
                    "constraints/velocity": (nt, 1), "constraints/force": (nt, 1), "probes/position": (1,),
                    "probes/displacement": (nt, 1), "basis/omega": (6,), "basis/enrichment_omega": (1,),
                    "basis/dbf_k": (1,), "reduced/q": (nt, 7), "reduced/K": (7, 7), "reduced/B": (1, 7),
                    "snapshots/time": (5,), "snapshots/x": (101,), "snapshots/w": (5, 101)}
        for name, shape in expected.items():
            assert f[name].shape == shape, name
        np.testing.assert_allclose(f["time"][:], np.linspace(0, 0.5, nt), atol=1e-12)
        assert f.attrs["complete"] and "Table 1" in f.attrs["scene"]
        for key in ("petsc_version", "slepc_version", "dbf_hpc_version", "solver_stats", "wall_times"):
            assert key in f.attrs
        # the snapshots are the total displacement: the moving support follows Omega(t)
        t5 = f["snapshots/time"][:]
        np.testing.assert_allclose(f["snapshots/w"][:, 0], 5e-3 * np.sin(2 * np.pi * t5), atol=1e-12)
        assert np.all(f["snapshots/w"][:, -1] == 0)


def test_failed_run_leaves_no_output_and_never_clobbers(shared_tmp_path):
    target = shared_tmp_path / "keep.h5"
    if MPI.COMM_WORLD.rank == 0:
        target.write_bytes(b"previous results")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError):
        paper_run(shared_tmp_path, "integrator.scheme=ars443", name="keep.h5")
    assert_all(target.read_bytes() == b"previous results")
    assert rank0_files(shared_tmp_path) == ["keep.h5"], "no .partial, no lock"



def test_a_returned_run_has_released_its_output_lock_on_every_rank(shared_tmp_path):
    # Each rank looks itself, right after run() returns: a parameter-study script on rank 1 that
    # checks for OUT.h5.lock, or starts the next case, must not find the lock rank 0 is still removing.
    paper_run(shared_tmp_path, "integrator.t_end=0.01", name="done.h5")
    seen = sorted(os.listdir(shared_tmp_path))
    assert_all(seen == ["done.h5", "done.xdmf"], seen)


def test_a_basis_option_petsc_refuses_is_one_line_from_run_and_leaves_no_file(shared_tmp_path):
    # Red team: run() from Python let a refused -modes_ option out as a bare petsc4py.PETSc.Error with
    # PETSc's multi-line traceback (only the command line made it one line). Every rank raises the
    # SolverError naming the option, and nothing is written.
    from conftest import petsc_options
    from dbf_hpc.errors import SolverError

    with petsc_options(modes_eps_type="bogus"), pytest.raises(SolverError) as refused:
        paper_run(shared_tmp_path, "integrator.t_end=0.01", name="refused.h5")
    line = str(refused.value)
    assert_all("\n" not in line and "EPSSetType" in line and "(given: -modes_eps_type bogus)" in line, line)
    assert not any(name.startswith("refused") for name in rank0_files(shared_tmp_path)), "no output, no lock"


@pytest.mark.parametrize("suffix", [".partial", ".checkpoint"])
def test_a_file_named_like_the_runs_partial_output_or_checkpoint_is_never_replaced(shared_tmp_path, suffix):
    # Red team: `echo precious > x.h5.partial` was overwritten by the run, a y.h5.checkpoint deleted at its end.
    target = shared_tmp_path / f"x{suffix}.h5"
    other = shared_tmp_path / f"x{suffix}.h5{suffix}"
    if MPI.COMM_WORLD.rank == 0:
        other.write_bytes(b"precious")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=f"{suffix}' exists and is not a dbf-hpc output"):
        paper_run(shared_tmp_path, "integrator.t_end=0.01", name=target.name)
    assert_all(other.read_bytes() == b"precious" and not target.exists())
    if MPI.COMM_WORLD.rank == 0:   # a damaged HDF5 file under that name (a full disk) is the run's own
        other.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\0" * 100)
    MPI.COMM_WORLD.Barrier()
    _, f, _ = paper_run(shared_tmp_path, "integrator.t_end=0.01", name=target.name)
    if f is not None:
        f.close()
    assert_all(target.exists() and not other.exists())


def test_a_paraview_file_the_full_disk_refused_leaves_the_finished_output_and_nothing_to_resume(shared_tmp_path,
                                                                                              monkeypatch):
    # Red team (a 3 MB tmpfs filled just before OUT.xdmf): the error said only "cannot write OUT.xdmf",
    # and the checkpoint stayed beside the finished OUT.h5, so the --resume the user tried was refused
    # ("OUT.h5.partial cannot be resumed").
    import errno

    from dbf_hpc import xdmf
    from dbf_hpc.errors import SolverError, replacing

    def full_disk(path, *args, **kwargs):
        with replacing(path) as tmp, open(tmp, "w"):
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(xdmf, "write", full_disk)
    out = shared_tmp_path / "out.h5"
    scene = load_scene(PAPER, ["basis.cache=off", "integrator.t_end=0.2", "output.snapshots=5",
                               "output.checkpoint_dt=0.05"])
    with pytest.raises(SolverError, match=f"wrote {out}, but not its ParaView file .*out.xdmf: No space left on "
                                          f"device; free some space and rerun"):
        run(scene, str(out), progress=False)
    MPI.COMM_WORLD.Barrier()   # rank 0 removes the output's lock after the error has reached every rank
    left = sorted(os.listdir(shared_tmp_path))
    assert_all(left == ["out.h5"], f"the output, complete; no checkpoint or temporary: {left}")
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(out) as f:
            assert f.attrs["complete"] and f["snapshots/w"].shape[0] == 5


def test_a_fixed_step_longer_than_the_sample_interval_runs(shared_tmp_path):
    # 0.01 s sampled every 1 us with a fixed 0.1 ms step: 100 steps, samples from the dense output.
    _, f, summary = paper_run(shared_tmp_path, "integrator.adaptive=false", "integrator.t_end=0.01",
                              "integrator.dt=1e-4", name="long_step.h5")
    assert summary["stats"]["steps"] == 100
    if f is not None:
        assert f["time"].size == 10001


def test_a_probe_never_changes_the_model_even_a_micrometre_from_a_stop(shared_tmp_path):
    # Red team: a probe 1 um from the stop used to build a 1 um element and change w at the stop by
    # 93 %. A request for output must not change what is computed.
    _, f, _ = paper_run(shared_tmp_path, "integrator.t_end=0.3", "output.probes=[0.5]", name="one.h5")
    _, g, _ = paper_run(shared_tmp_path, "integrator.t_end=0.3", "output.probes=[0.5, 0.250001]", name="two.h5")
    if f is not None:
        np.testing.assert_array_equal(f["constraints/displacement"][:], g["constraints/displacement"][:])
        # the same probe, to round-off (a 2-row matrix-vector product sums in another order)
        np.testing.assert_allclose(f["probes/displacement"][:, 0], g["probes/displacement"][:, 0], rtol=0,
                                   atol=1e-14 * np.abs(f["probes/displacement"][:]).max())
        near = g["probes/displacement"][:, 1]
        assert np.abs(near - g["constraints/displacement"][:, 0]).max() < 1e-3 * 2.5e-3, "w is continuous"


def test_a_matrix_model_with_a_node_map_writes_the_beams_snapshots_as_vectors_at_its_nodes(shared_tmp_path):
    # Bring-your-own model: the paper's beam given as K, M files with node coordinates and a DOF map
    # (w along y, theta about z) gives, at every node, the displacement vector the beam gives; both
    # are written for ParaView (XDMF beside the output). A stop never reached keeps the comparison
    # free of the impacts' amplification of round-off.
    import scipy.io

    from dbf_hpc import Beam, FullOrderModel
    from test_matrices import to_scipy

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    with FullOrderModel.build(beam) as fom:
        K, M, mesh = to_scipy(fom.operators.K), to_scipy(fom.operators.M), fom.operators.mesh
        rows = {"c": mesh.w_row(0.25), "f": mesh.w_row(0.5)}
    common = """
[excitation]
kind = "force"
amplitude = 0.05
frequency_hz = 3.0
{force}
[[constraint]]
{where}
law = "deadband"
clearance = 1.0
k = 1e6
[integrator]
t_end = 0.2
[output]
snapshots = 5
[basis]
cache = "off"
"""
    beam_text = """[structure]
kind = "beam"
length = 1.0
elements = 20
E = 117e9
I = 8.78e-16
A = 2.9e-7
rho = 11800.0
""" + common.format(force="x = 0.5", where="x = 0.25")
    matrices_text = """[structure]
kind = "matrices"
stiffness = "K.mtx"
mass = "M.mtx"
nodes = "nodes.txt"
dofs = "dofs.txt"
""" + common.format(force=f"dof = {rows['f']}", where=f"dof = {rows['c']}")
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(str(shared_tmp_path / "K.mtx"), K, precision=17)
        scipy.io.mmwrite(str(shared_tmp_path / "M.mtx"), M, precision=17)
        np.savetxt(shared_tmp_path / "nodes.txt", np.column_stack([mesh.x, 0 * mesh.x]))
        with open(shared_tmp_path / "dofs.txt", "w") as f:
            for dof in mesh.free_dofs:
                f.write(f"{dof // 2} {'y' if dof % 2 == 0 else 'rz'}\n")
        (shared_tmp_path / "b.toml").write_text(beam_text)
        (shared_tmp_path / "m.toml").write_text(matrices_text)
    MPI.COMM_WORLD.Barrier()
    for name in ("b", "m"):
        run(load_scene(str(shared_tmp_path / f"{name}.toml")), str(shared_tmp_path / f"{name}.h5"), progress=False)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(shared_tmp_path / "b.h5") as b, h5py.File(shared_tmp_path / "m.h5") as m:
            assert m.attrs["field_kind"] == "nodes" and b.attrs["field_kind"] == "beam"
            np.testing.assert_allclose(m["snapshots/points"][:, 0], b["snapshots/points"][:, 0], rtol=0, atol=1e-15)
            for i in range(5):
                vb, vm = b[f"snapshots/displacement/{i:06d}"][:], m[f"snapshots/displacement/{i:06d}"][:]
                assert np.abs(vm - vb).max() <= 1e-9 * max(np.abs(vb).max(), 1e-12), i
        for name in ("b", "m"):
            text = open(shared_tmp_path / f"{name}.xdmf").read()
            assert text.count('<Grid Name="displacement ') == 5 and f"{name}.h5:/snapshots/points" in text


def test_a_damping_ratio_per_basis_vector_runs_with_its_estimate_explained_and_tolerance_refuses_it(shared_tmp_path):
    # Red team: 7 ratios for 6 modes + 1 DBF ended the run with "7 ratios for 13 basis vectors" (the
    # estimate's richer basis); the ratios only fit the user's basis.
    zeta = "damping.zeta=[0.01, 0.05, 0.02, 0.02, 0.02, 0.02, 0.3]"
    _, f, summary = paper_run(shared_tmp_path, zeta, "integrator.t_end=0.05")
    assert np.isnan(summary["estimated_error"])
    if f is not None:
        assert "one ratio per basis vector" in f.attrs["estimated_error_note"]
        np.testing.assert_allclose(np.diag(f["reduced/D"][:])[:2] / (2 * f["basis/omega"][:2]), [0.01, 0.05])
        f.close()
    with pytest.raises(InputError, match="tolerance picks the number of modes"):
        paper_run(shared_tmp_path, zeta, "basis.tolerance=0.05", name="tol.h5")


def test_a_run_without_a_richer_model_says_why_it_has_no_estimate(shared_tmp_path, capsys):
    # Red team: the reason was stored (estimated_error_note) but the run's log said nothing of the
    # estimate (here: damping ratios for the user's basis only, which the richer basis cannot take).
    s = load_scene(PAPER, ["basis.cache=off", "damping.zeta=[0.01, 0.05, 0.02, 0.02, 0.02, 0.02, 0.3]",
                           "integrator.t_end=0.02"])
    summary = run(s, str(shared_tmp_path / "coarse.h5"), progress=True)
    assert np.isnan(summary["estimated_error"])
    if MPI.COMM_WORLD.rank == 0:
        assert "estimated error: not available (" in capsys.readouterr().out


def test_samples_fewer_than_two_per_forcing_period_warn_that_the_series_aliases(shared_tmp_path, capfd):
    # Nyquist: a 99 Hz force sampled every 0.01 s shows as a 1 Hz oscillation, and probes/peak (over
    # the samples) misses the response's peak; at 4 samples a period the series is not aliased.
    for sample_dt, warned in ((1e-2, True), (2.5e-3, False)):
        paper_run(shared_tmp_path, "excitation.frequency_hz=99", "integrator.t_end=0.05",
                  f"output.sample_dt={sample_dt}", "basis.estimate=false", name=f"alias{sample_dt}.h5")
        err = capfd.readouterr().err
        if MPI.COMM_WORLD.rank == 0:
            assert ("fewer than 2: the sampled series (time, probes, constraints) alias the response" in err) == warned, \
                (sample_dt, err)


def test_a_free_free_beam_in_si_units_draws_no_unit_warning_from_its_rigid_body_modes(shared_tmp_path, capfd):
    # A free-free beam has two rigid-body modes at 0 Hz (computed as round-off, 1e-5 Hz here); its
    # lowest elastic frequency is the first cos-cosh root's (beta L = 4.730), 0.617 Hz for the paper's
    # beam: the units are right and "check the structure's units" was a false alarm. The same beam with
    # E in GPa given as Pa still draws it (0.617 Hz sqrt(1e-9) = 1.95e-5 Hz).
    text = open(PAPER).read().replace('left = "pinned"', 'left = "free"').replace('right = "pinned"', 'right = "free"')
    text = text[:text.index("[excitation]")] + ('[excitation]\nkind = "force"\nx = 0.5\namplitude = 1e-4\n'
                                                 'frequency_hz = 1.0\n\n') + text[text.index("[[constraint]]"):]
    path = shared_tmp_path / "free_free.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(text)
    MPI.COMM_WORLD.Barrier()
    for E, warned in ((117e9, False), (117.0, True)):
        s = load_scene(str(path), ["basis.cache=off", "integrator.t_end=0.01", "basis.estimate=false",
                                   f"structure.E={E}"])
        run(s, str(shared_tmp_path / f"free_free{E:g}.h5"), progress=True)
        captured = capfd.readouterr()
        if MPI.COMM_WORLD.rank == 0:
            assert "basis: 6 modes" in captured.out, captured.out
            # the line says so too: 0 Hz, not their round-off
            assert ("basis: 6 modes (2 rigid-body at 0 Hz, 0.617 ... " if not warned else
                    "basis: 6 modes (2 rigid-body at 0 Hz, 1.951e-05 ... ") in captured.out, captured.out
            assert ("the lowest elastic frequency is" in captured.err) == warned, (E, captured.err)
            assert not warned or "the lowest elastic frequency is 1.95e-05 Hz" in captured.err, captured.err


def test_a_two_plane_beams_flexibility_line_names_the_constraint_at_the_position_it_prints(shared_tmp_path, capfd):
    # Red team: on a beam of two planes each constraint has two DBF columns (y, z), and the run said
    # "min ... at constraint 3 (x = 1 m (y))" for the second of three constraints: the column's number.
    # The number printed and the position printed must be the same constraint's.
    import re
    path = two_plane_tube_with_three_holes(shared_tmp_path)
    s = load_scene(str(path), ["basis.cache=off", "basis.enrichment=\"none\"", "basis.modes=4",
                               "integrator.t_end=0.01", "basis.estimate=false"])
    run(s, str(shared_tmp_path / "two_planes.h5"), progress=True)
    out = capfd.readouterr()
    if MPI.COMM_WORLD.rank == 0:
        named = re.findall(r"at constraint (\d+) \(x = ([0-9.]+) m \([yz]\)\)", out.out + out.err)
        assert named, out
        for number, x in named:
            assert (0.25, 0.6, 0.8)[int(number) - 1] == float(x), (number, x, out.out)


def test_the_default_checkpoints_of_a_short_run_are_skipped_and_change_no_sample(shared_tmp_path, monkeypatch):
    # A checkpoint is some 30 HDF5 datasets and an fsync (10-20 ms): a short run spent more on its nine
    # default checkpoints (every t_end / 10) than on its integration. The default ones are written only
    # scene.CHECKPOINT_WALL s of wall time after the start or the last (here never, or always); a
    # checkpoint_dt given is kept; and a checkpoint changes nothing a run computes, bit for bit.
    import dbf_hpc.scene
    from dbf_hpc.checkpoint import Checkpoint

    writes = []
    original = Checkpoint.write
    monkeypatch.setattr(Checkpoint, "write", lambda self, state: (writes.append(state["t"]), original(self, state)))
    names = ("time", "reduced/q", "reduced/qdot", "constraints/force", "probes/displacement")
    runs = {}
    for wall, sets in ((float("inf"), ()), (0.0, ()), (float("inf"), ("output.checkpoint_dt=0.005",))):
        monkeypatch.setattr(dbf_hpc.scene, "CHECKPOINT_WALL", wall)
        writes.clear()
        name = f"ck_{wall}_{len(sets)}.h5"
        _, f, _ = paper_run(shared_tmp_path, "integrator.t_end=0.05", "basis.estimate=false", *sets, name=name)
        runs[name] = ({n: f[n][()] for n in names} if f is not None else None), len(writes)
    counts = [count for _, count in runs.values()]
    if MPI.COMM_WORLD.rank == 0:   # rank 0 integrates and checkpoints a reduced run
        assert counts[0] == 0 and counts[1] >= 5 and counts[2] == counts[1], counts
        first = next(iter(runs.values()))[0]
        for data, _ in runs.values():
            assert all(np.array_equal(data[n], first[n]) for n in names)
    else:
        assert counts == [0, 0, 0]


def test_a_cells_file_changes_no_run_identity_but_a_finished_output_drawn_without_it_is_computed_again(
        shared_tmp_path):
    # [structure] cells only draw the field: a checkpoint stays resumable when they are added (the
    # identity holds neither the key nor the file's bytes). But `--resume` on an output finished
    # without them (a Polyvertex in ParaView) must not call it complete for a scene that draws cells:
    # the output records its cells (field_cells_sha256), and one that differs is computed again (the
    # finished check is also called directly, with the scenes swapped).
    from petsc4py import PETSc

    from dbf_hpc.run import finished_output, request_identity, run_identity
    from test_xdmf import solid

    out = shared_tmp_path / "bar.h5"
    cells, points = load_scene(solid(shared_tmp_path)), load_scene(solid(shared_tmp_path, cells=False))
    comm = PETSc.COMM_WORLD
    assert cells.cells_file() == str(shared_tmp_path / "cells.txt") and points.cells_file() is None
    assert run_identity(cells, None, comm, "rom") == run_identity(points, None, comm, "rom")
    typed = load_scene(cells.path, ['structure.cell_type="Quadrilateral_8"'])
    assert run_identity(typed, None, comm, "rom") == run_identity(points, None, comm, "rom")
    assert request_identity(cells, comm, "rom") == request_identity(points, comm, "rom")
    without = set(cells.file_digests(comm))
    assert str(shared_tmp_path / "cells.txt") not in without and str(shared_tmp_path / "K.bin") in without
    assert ("cells file", str(shared_tmp_path / "cells.txt")) in cells.inputs()   # never written over
    assert "cells" in cells["structure"] and all("cells" not in keys for keys in cells.result_sections().values())

    def stored(path):
        """The request part of the output's stored run identity (what `--resume` compares)."""
        with h5py.File(path) as f:
            return {"request": json.loads(f.attrs["run_identity"])["request"]}

    run(points, str(out), progress=False)
    if MPI.COMM_WORLD.rank == 0:
        ident = stored(out)
        assert finished_output(str(out), ident, points) is not None
        assert finished_output(str(out), ident, cells) is None        # drawn as points: not this scene's output
    run(cells, str(out), progress=False, resume=True)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(out) as f:
            assert f.attrs["field_cells"] == "Hexahedron" and f["snapshots/cells"].shape == (16, 8)
        assert 'TopologyType="Hexahedron"' in open(shared_tmp_path / "bar.xdmf").read()
        ident = stored(out)
        assert finished_output(str(out), ident, cells) is not None
        assert finished_output(str(out), ident, points) is None
        typed = [load_scene(cells.path, [f'structure.cell_type="{name}"'])
                 for name in ("Hexahedron", "Quadrilateral_8")]
        assert finished_output(str(out), ident, typed[0]) is not None     # the type the node count gave
        assert finished_output(str(out), ident, typed[1]) is None         # the same file drawn as another type
        (shared_tmp_path / "cells.txt").write_text(open(shared_tmp_path / "cells.txt").read() + "0 1 6 5 15 16 21 20\n")
        assert finished_output(str(out), ident, cells) is None        # other cells since
        os.remove(shared_tmp_path / "cells.txt")
        assert finished_output(str(out), ident, cells) is None        # (the run says what is missing)


def test_an_absolute_tolerance_loose_against_small_masses_and_clearances_draws_a_warning_whose_atol_is_enough(
        shared_tmp_path):
    # Red team (new user): a structure of small masses and displacements in SI units (here a spring chain
    # of 1e-9 kg masses, 1e-4 N/m springs, a stop 1 um away) ran at the default atol = 1e-9 in modal units
    # (m kg^(1/2)), looser than its q ~ 1e-11, with no word: steps at their upper limit, w far from the
    # same model in kg (same frequencies, displacements and estimate window). The warning names an atol
    # that brings the run to the kg run; the same chain in kg is not warned.
    import scipy.io
    import scipy.sparse

    from dbf_hpc import (BasisSettings, Constraint, FullOrderModel, IntegratorSettings, MatrixFiles, PointForce,
                         Reductor, law, simulate_reduced)
    from dbf_hpc.run import loose_atol

    n = 10
    K = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr() * 1e5
    M = scipy.sparse.diags(np.linspace(1.0, 2.0, n)).tocsr()
    results, messages = {}, {}
    for scale in (1.0, 1e-9):
        paths = [str(shared_tmp_path / f"{name}{scale:g}.mtx") for name in ("K", "M")]
        if MPI.COMM_WORLD.rank == 0:
            scipy.io.mmwrite(paths[0], K * scale, precision=17)
            scipy.io.mmwrite(paths[1], M * scale, precision=17)
        MPI.COMM_WORLD.Barrier()
        stop = Constraint(law("deadband", clearance=1e-6, k=1e6 * scale), dof=5)
        with FullOrderModel.build(MatrixFiles(*paths), [stop], PointForce(amplitude=0.5 * scale, frequency_hz=10.0,
                                                                          dof=2)) as fom:
            with Reductor(fom, BasisSettings(modes=4)) as reductor:      # (no cache directory: none)
                model = reductor.reduce()
        messages[scale] = loose_atol(model, 1e-9, [stop])
        settings = IntegratorSettings(t_end=0.05, sample_dt=1e-4)
        results[scale] = simulate_reduced(model, settings).displacement[:, 0]
        if messages[scale]:
            atol = float(messages[scale].rsplit("atol = ", 1)[1].split()[0])
            results["advised"] = simulate_reduced(model, dataclasses.replace(settings, atol=atol)).displacement[:, 0]
    assert messages[1.0] is None
    assert messages[1e-9] is not None and messages[1e-9].startswith("[integrator] atol = 1e-09 (modal units, m kg^(1/2)) "
                                                                    "lets w at constraint 1 err by up to")
    truth = results[1.0]
    assert np.abs(truth).max() > 1e-6                                   # it hits the stop
    error = lambda w: np.abs(w - truth).max() / np.abs(truth).max()     # noqa: E731
    assert error(results[1e-9]) > 0.02 and error(results["advised"]) < 1e-3, (error(results[1e-9]),
                                                                              error(results["advised"]))


def test_stiffness_and_mass_files_swapped_draw_the_unit_warning_naming_the_swap(shared_tmp_path, capfd):
    # Red team (new user): a frame's K and M given as each other ran with "the lowest elastic frequency
    # is 1.8e-06 Hz: check the structure's units (...; matrices in N/m and kg)", which names no swap
    # (the failure path's hint, basis._units_hint, does). The files in their places draw no warning.
    import scipy.io
    import scipy.sparse

    n = 10
    K = scipy.sparse.diags([-np.ones(n - 1), 2 * np.ones(n), -np.ones(n - 1)], [-1, 0, 1]).tocsr() * 1e5
    if MPI.COMM_WORLD.rank == 0:
        scipy.io.mmwrite(str(shared_tmp_path / "K.mtx"), K, precision=17)
        scipy.io.mmwrite(str(shared_tmp_path / "M.mtx"), scipy.sparse.identity(n, format="csr"))
        for name, (stiffness, mass) in (("right.toml", ("K", "M")), ("swapped.toml", ("M", "K"))):
            (shared_tmp_path / name).write_text(
                f'[structure]\nkind = "matrices"\nstiffness = "{stiffness}.mtx"\nmass = "{mass}.mtx"\n'
                f'[excitation]\nkind = "force"\ndof = 2\namplitude = 1.0\nfrequency_hz = 1e-5\n'
                f'[[constraint]]\ndof = 5\nclearance = 1e-3\nk = 1e5\n[basis]\nmodes = 4\ncache = "off"\n'
                f'estimate = false\n[integrator]\nt_end = 0.01\n')
    MPI.COMM_WORLD.Barrier()
    for name, warned in (("right.toml", False), ("swapped.toml", True)):
        capfd.readouterr()
        run(load_scene(str(shared_tmp_path / name)), str(shared_tmp_path / f"{name}.h5"), progress=False)
        err = capfd.readouterr().err
        if MPI.COMM_WORLD.rank == 0:
            assert ("lowest elastic frequency" in err and "the stiffness and mass files not swapped" in err) == warned, err


@pytest.mark.parametrize("method", ["rom", "full"])
def test_hunt_crossley_damping_beyond_its_restitution_range_warns_once_and_only_there(shared_tmp_path, capfd, method):
    # The paper's beam strikes its stop at 0.024 m/s: alpha = 1000 s/m is alpha v = 24, where Hunt &
    # Crossley's e = 1 - (2/3) alpha v is long past 0 and the full-order peak force doubled from dt = 2e-6 s
    # to 5e-7 s with no word (red team); alpha = 10 s/m (alpha v = 0.24) is inside the law's range.
    for alpha, warned in ((1000.0, True), (10.0, False)):
        s = load_scene(PAPER, ["integrator.t_end=0.12", "integrator.dt=1e-5", "basis.estimate=false",
                               "output.snapshots=0", "constraint.damping=\"hunt_crossley\"", f"constraint.alpha={alpha}"])
        first = run(s, str(shared_tmp_path / f"hc-{method}-{alpha:g}.h5"), progress=False, method=method)
        err = capfd.readouterr().err
        count = err.count("Hunt-Crossley damping reached alpha |v|")
        if MPI.COMM_WORLD.rank == 0:
            assert count == (1 if warned else 0), err
            if warned:
                assert "constraint 1 at x = 0.25 m" in err and "above 1.5" in err and "at most 6" in err, err
                assert ("depend on dt" in err) == (method == "full"), err
        else:
            assert count == 0, err   # one line from the job, not one per rank
    # a requeued --resume of a finished output computes nothing, and its summary, read back from the file's
    # solver_stats, holds the alpha |v| the run returned
    summary = run(s, str(shared_tmp_path / f"hc-{method}-10.h5"), progress=False, method=method, resume=True)
    assert summary["stats"]["time_integration"] == first["stats"]["time_integration"]
    assert summary["alpha_speed"] == first["alpha_speed"] and 0 < first["alpha_speed"][0] < 1.5


def test_run_from_python_warns_once_where_atol_lets_w_err_by_over_a_percent_of_a_clearance(shared_tmp_path, capfd):
    # the Python API's run.run says what `dbf-hpc run` says (one line, rank 0), and a tight atol draws none
    from conftest import small_mass_chain

    for atol, expected in ((None, 1), (1e-14, 0)):
        scene = load_scene(small_mass_chain(shared_tmp_path, atol))
        capfd.readouterr()
        run(scene, str(shared_tmp_path / f"chain-{atol}.h5"), progress=False)
        err = capfd.readouterr().err
        count = err.count("dbf-hpc: warning: [integrator] atol = ")
        assert_all(count == (expected if MPI.COMM_WORLD.rank == 0 else 0), (atol, err))


def test_more_snapshots_than_output_samples_take_every_sample_and_warn_naming_the_key(shared_tmp_path, capfd):
    # Red team: the paper scene's snapshots = 50 on a run shortened to 0.01 s at sample_dt = 2.5e-3 s
    # (5 samples) wrote 5 snapshots without a word. Each snapshot is one output sample.
    s, f, _ = paper_run(shared_tmp_path, "integrator.t_end=0.01", "output.sample_dt=2.5e-3", "basis.modes=4",
                        "basis.estimate=false", name="capped.h5")
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert ("dbf-hpc: warning: [output] snapshots = 50 is more than the 5 output samples (t_end = 0.01 s at "
                "sample_dt = 0.0025 s), the only times a snapshot is taken at: all 5 are snapshots; for more, reduce "
                "sample_dt") in err, err
        assert np.allclose(f["snapshots/time"][:], [0.0, 2.5e-3, 5e-3, 7.5e-3, 1e-2], rtol=0, atol=1e-15)
        f.close()
    paper_run(shared_tmp_path, "integrator.t_end=0.01", "output.sample_dt=2e-4", "basis.modes=4",
              "basis.estimate=false", name="uncapped.h5")    # 51 samples: 50 snapshots, no word
    err = capfd.readouterr().err
    assert "snapshots" not in err, err


def test_an_atol_above_a_micro_beams_whole_motion_is_warned_and_the_advised_one_gives_the_exact_vibration(
        shared_tmp_path, capfd):
    # Red team: a 100 um steel micro-beam without constraints, started at 0.1 um in its first mode, ran at the
    # default atol = 1e-9 (modal units; its q are ~1e-13) with no word (the loose-atol check compared atol with
    # clearances only) and came 3.6 % off its exact free vibration w = w0 cos(omega t). The warning compares
    # atol with the motion's scale; the atol it names brings the run to the exact vibration, with no warning.
    omega = (np.pi / 1e-4) ** 2 * np.sqrt(2e11 * 8.333e-22 / (7800.0 * 1e-10))
    period = 2 * np.pi / omega
    path = shared_tmp_path / "micro_rom.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(MICRO_BEAM + "\n[basis]\nmodes = 4\n\n[output]\nprobes = [5e-5]\n")
    MPI.COMM_WORLD.Barrier()
    sets = [f"integrator.t_end={5 * period}", f"output.sample_dt={period / 50}"]
    errors, advised = {}, None
    for atol in (None, "advised"):
        extra = [] if advised is None else [f"integrator.atol={advised}"]
        _, f, _ = paper_run(shared_tmp_path, *sets, *extra, name=f"micro_{atol}.h5", scene=str(path))
        err = MPI.COMM_WORLD.bcast(capfd.readouterr().err, root=0)    # the warning is rank 0's
        if atol is None:
            assert "lets w err by up to" in err and "x the motion's scale 1e-07 m (the initial displacement)" in err, err
            advised = float(err.rsplit("atol = ", 1)[1].split()[0])
        else:
            assert "atol" not in err, err
        if f is not None:
            t, w = f["time"][:], f["probes/displacement"][:, 0]
            assert abs(abs(w[0]) - 1e-7) < 1e-13            # the peak of mode 1, at midspan
            errors[atol] = np.abs(w - w[0] * np.cos(omega * t)).max() / 1e-7
            f.close()
    if MPI.COMM_WORLD.rank == 0:
        assert errors[None] > 1e-2 and errors["advised"] < 1e-3, errors    # measured 3.6e-2 and 3.7e-4


def test_estimate_windows_given_to_a_run_that_makes_no_estimate_are_warned_as_unused(shared_tmp_path, capfd):
    # Red team: [basis] estimate_window = 0.05 with estimate = false (or on a scene without constraints) ran
    # without a word, the window read nowhere.
    from dbf_hpc.run import unused_estimate_keys_warning

    off = load_scene(PAPER, ["basis.estimate=false", "basis.estimate_window=0.05"])
    assert unused_estimate_keys_warning(off) == ("[basis] estimate_window is not used: [basis] estimate = false, so "
                                                 "the run makes no error estimate; remove it")
    both = load_scene(without_constraints(shared_tmp_path), ["basis.estimate_window=0.05",
                                                             "basis.estimate_statistics_window=1.0"])
    assert unused_estimate_keys_warning(both).startswith("[basis] estimate_window and estimate_statistics_window are "
                                                         "not used: the scene has no constraints")
    for used in (["basis.estimate_window=0.05"], ["basis.estimate=false"],
                 ["basis.estimate=false", "basis.estimate_window=0.05", "basis.tolerance=0.05"]):
        assert unused_estimate_keys_warning(load_scene(PAPER, used)) is None, used
    paper_run(shared_tmp_path, "integrator.t_end=0.01", "basis.modes=4", "basis.estimate=false",
              "basis.estimate_window=0.005", name="unestimated.h5")
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert "dbf-hpc: warning: [basis] estimate_window is not used: [basis] estimate = false" in err, err


def test_dbf_keys_given_to_a_comparator_enrichment_are_warned_as_unused(shared_tmp_path, capfd):
    # Red team: dbf_stiffness = 1e5 with enrichment = "static" (or "none") ran without a word, the key read
    # nowhere. The paper scene's own dbf_stiffness = "auto" (the default) under --set basis.enrichment=static
    # is no such key: no warning.
    from dbf_hpc.run import unused_dbf_keys_warning

    assert unused_dbf_keys_warning(load_scene(PAPER, ['basis.enrichment="static"', "basis.dbf_stiffness=1e5"])) == (
        '[basis] dbf_stiffness is not used by enrichment = "static" (it tunes the DBFs of enrichment = "dbf"); remove '
        'it or set enrichment = "dbf"')
    assert unused_dbf_keys_warning(load_scene(PAPER, ['basis.enrichment="none"', 'basis.dbf_solver="factor"',
                                                      "basis.groups=1"])).startswith(
        '[basis] dbf_solver, groups are not used by enrichment = "none" (they tune')
    for used in (['basis.enrichment="static"'], ["basis.dbf_stiffness=1e5"]):
        assert unused_dbf_keys_warning(load_scene(PAPER, used)) is None, used
    paper_run(shared_tmp_path, "integrator.t_end=0.01", "basis.modes=4", "basis.estimate=false",
              'basis.enrichment="none"', 'basis.dbf_derivative="central"', name="comparator.h5")
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert 'dbf-hpc: warning: [basis] dbf_derivative is not used by enrichment = "none"' in err, err


@pytest.mark.parametrize("method", ["rom", "full"])
def test_a_finished_output_stores_its_warnings_and_a_resume_of_it_or_info_shows_each_once(shared_tmp_path, capfd,
                                                                                         method):
    # Warnings parity: a requeued `--resume` of a finished output computed nothing and printed none of the
    # warnings its run had printed (a loose atol, a stop never reached), and the output kept no trace of
    # them. The output's `warnings` attribute now holds them; a resume prints each once (those this
    # invocation prints before looking at the output, here --method full's ignored rtol, are not doubled),
    # and `dbf-hpc info` lists them. A clearance of 1 m is never reached; atol 1e-4 is loose for it.
    from dbf_hpc.report import describe

    sets = ["constraint.clearance=1", "integrator.t_end=0.01", "basis.estimate=false", "output.snapshots=0",
            "basis.cache=off", "integrator.atol=1e-4" if method == "rom" else "integrator.rtol=1e-8"]
    expected = ("[integrator] atol = 0.0001 (modal units" if method == "rom" else
                "[integrator] rtol = 1e-08 is the reduced model's", "constraint 1 at x = 0.25 m never reached its stop")
    path = str(shared_tmp_path / f"warned-{method}.h5")
    capfd.readouterr()
    first = run(load_scene(PAPER, sets), path, progress=False, method=method)
    printed = capfd.readouterr().err
    again = run(load_scene(PAPER, sets), path, progress=False, method=method, resume=True)
    reprinted = capfd.readouterr().err
    assert again["stats"] == first["stats"]   # nothing computed again
    assert again["warnings"] == first["warnings"] and len(first["warnings"]) == 2, first["warnings"]
    assert [w[:len(e)] for w, e in zip(first["warnings"], expected)] == list(expected), first["warnings"]
    for err in (printed, reprinted):
        lines = [line for line in err.splitlines() if line.startswith("dbf-hpc: warning: ")]
        assert_all(lines == ([f"dbf-hpc: warning: {w}" for w in first["warnings"]] if MPI.COMM_WORLD.rank == 0
                             else []), err)
    if MPI.COMM_WORLD.rank == 0:
        with h5py.File(path, "r") as f:
            assert f.attrs["warnings"].split("\n") == first["warnings"]
        info = [line for line in describe(path) if "warning" in line]
        assert info == [f"  warning: {w}" for w in first["warnings"]], info


def test_a_run_whose_samples_cap_its_step_below_its_floor_is_refused_before_any_basis_and_one_above_runs(
        shared_tmp_path):
    # t_end = 1e-9 s on the paper's beam: samples 1e-13 s apart cap a step at 1e-12 s, the floor dt x 1e-8 of
    # every run whose highest reference mode is below 1 / (20 dt) = 500 Hz. The refusal came from the
    # integrator, after the modes and the DBFs (minutes on a big scene). Now it comes before them, with the
    # same line: no eigensolve, no cache entry, no output. The modes' frequency is counted by the inertia
    # (mode 42 is 480 Hz); 43 modes (503 Hz) lower the floor below the cap, and the run must still run.
    from dbf_hpc.modes import counters
    from dbf_hpc.reductor import Reductor
    from dbf_hpc.simulate import simulate_reduced

    cache = shared_tmp_path / "cap_cache"
    for modes in (6, 42):
        scene = load_scene(PAPER, [f"basis.cache={cache}", "integrator.t_end=1e-9", f"basis.modes={modes}"])
        solves = counters["eigen_solves"]
        with pytest.raises(InputError) as refused:
            run(scene, str(shared_tmp_path / "capped.h5"), progress=False)
        assert counters["eigen_solves"] == solves, modes
        assert str(refused.value).startswith("[integrator] t_end = 1e-09 s: its output samples, 1e-13 s apart, cap "
                                             "an adaptive step at 1e-12 s, not above the smallest step it may take "
                                             "(1e-12 s)"), str(refused.value)
        MPI.COMM_WORLD.Barrier()
        assert not os.path.exists(cache) and not [n for n in os.listdir(shared_tmp_path) if n.startswith("capped")]
    # the integrator's own line, once the basis is known, is the same
    with scene.full_order_model() as fom, Reductor(fom, scene.basis_settings()) as reductor:
        model = reductor.reduce()
    with pytest.raises(InputError) as integrator:
        simulate_reduced(model, scene.integrator_settings())
    assert str(integrator.value) == str(refused.value)
    accepted = load_scene(PAPER, ["basis.cache=off", "integrator.t_end=1e-9", "basis.modes=43", "basis.estimate=false"])
    summary = run(accepted, str(shared_tmp_path / "accepted.h5"), progress=False)
    assert summary["stats"]["steps"] >= 1000   # 10 samples a step at most



def test_a_max_frequency_cutoff_inside_a_chain_of_close_frequencies_is_left_to_the_integrator_not_refused_before_the_basis(
        shared_tmp_path):
    # [basis] max_frequency_hz bounds the highest reference mode F only where nothing lies just above the cutoff:
    # the basis keeps a repeated eigenvalue at it whole, and "whole" chains eigenvalues each within REPEATED_TOL of
    # the next. Red team: 250 modes of a diagonal (K, M), lambda 0.98e-6 apart (1.2e-4 from first to last in
    # frequency), cut at 1.0000001 Hz: the basis held all 250 (measured: F = 1.000122 Hz), above the frequency up
    # to which the samples refuse the step cap, so the integrator accepts the run; cap_refusal_before_basis refused
    # it by the cutoff alone. The truth here is the closed form: the diagonal's eigenvalues and modes.whole_count.
    import math

    from dbf_hpc.modes import whole_count
    from dbf_hpc.run import cap_refusal_before_basis
    from dbf_hpc.timestepping import cap_refusal, cap_refused_below_hz

    lam = np.concatenate([(2 * np.pi) ** 2 * (1 + 0.98e-6) ** np.arange(250),
                          (2 * np.pi * 10) ** 2 * (1 + 0.01 * np.arange(1, 11))])   # a gap, then 10 more
    if MPI.COMM_WORLD.rank == 0:
        for name, diagonal in (("K", lam), ("M", np.ones(lam.size))):
            (shared_tmp_path / f"{name}.mtx").write_text(
                f"%%MatrixMarket matrix coordinate real symmetric\n{lam.size} {lam.size} {lam.size}\n" +
                "".join(f"{i + 1} {i + 1} {v!r}\n" for i, v in enumerate(diagonal)))
        (shared_tmp_path / "chain.toml").write_text(
            '[structure]\nkind = "matrices"\nstiffness = "K.mtx"\nmass = "M.mtx"\n\n'
            '[excitation]\nkind = "force"\ndof = 250\namplitude = 1.0\nfrequency_hz = 0.5\n\n'
            '[basis]\nmax_frequency_hz = 1.0000001\ncache = "off"\n\n[integrator]\nt_end = 1.0\n\n'
            '[[constraint]]\ndof = 250\nlaw = "deadband"\nclearance = 1e-3\nk = 1e3\n')
    MPI.COMM_WORLD.Barrier()
    dt = 1 / (20 * 1.00011)   # the floor is dt x 1e-8 up to 1.00011 Hz; the cap a hair below it
    sets = [f"integrator.dt={dt!r}", f"integrator.t_end={dt * 1e-8 * (1 - 1e-6) * 1000!r}"]
    scene = load_scene(str(shared_tmp_path / "chain.toml"), sets)
    settings = scene.integrator_settings()
    lam_max = (2 * math.pi * 1.0000001) ** 2
    kept = whole_count(lam, int(np.count_nonzero(lam <= lam_max)))
    F = math.sqrt(lam[kept - 1]) / (2 * math.pi)
    assert kept == 250 and F > cap_refused_below_hz(settings) and cap_refusal(settings, F) is None   # accepted
    with scene.full_order_model() as fom:
        assert cap_refusal_before_basis(scene, fom, settings) is None
    # a cutoff with a gap above it is still refused before the basis (the paper's beam, modes 40 to 42 at 436,
    # 458 and 481 Hz: those up to 470 Hz, below the 500 Hz up to which its samples are refused)
    if MPI.COMM_WORLD.rank == 0:
        (shared_tmp_path / "paper.toml").write_text(open(PAPER).read().replace("\nmodes = 6 ", "\n# modes = 6 "))
    MPI.COMM_WORLD.Barrier()
    paper = load_scene(str(shared_tmp_path / "paper.toml"), ["integrator.t_end=1e-9", "basis.max_frequency_hz=470"])
    with paper.full_order_model() as fom:
        refusal = cap_refusal_before_basis(paper, fom, paper.integrator_settings())
    assert refusal is not None and refusal.startswith("[integrator] t_end = 1e-09 s: its output samples"), refusal


# Rank 0 of a 2-rank run() (the Python API) meets an exception no write foresaw, a ValueError from h5py's
# create_dataset (as it opens the output) or from os.replace (as it moves a checkpoint or the finished
# output into place); every rank says what it raised, then rank 0 lists the folder
_UNEXPECTED_AS_RANK_0_WRITES = """
import os, sys
import h5py
from mpi4py import MPI
import dbf_hpc

folder, method, where, paper, rank = *sys.argv[1:5], MPI.COMM_WORLD.rank
sets = sys.argv[5:]
def refuse(*args, **kwargs):
    raise ValueError(f"rank 0's {where} refused")
if rank == 0 and where == "create_dataset":
    h5py.Group.create_dataset = refuse
if rank == 0 and where == "os.replace":
    os.replace = refuse
scene = dbf_hpc.load_scene(paper, ["integrator.t_end=0.05", "structure.elements=20", "basis.cache=off",
                                   "basis.estimate=false", "output.snapshots=0", *sets])
def act():
    dbf_hpc.run(scene, os.path.join(folder, "out.h5"), progress=False, method=method)


every_rank_says(act, folder)
"""


@pytest.mark.launcher
@pytest.mark.parametrize("method, where, sets", [
    ("rom", "create_dataset", []), ("full", "create_dataset", []), ("full", "os.replace", []),
    ("full", "os.replace", ["output.checkpoint_dt=0.01"])], ids=["rom", "full-open", "full-finish", "full-checkpoint"])
def test_an_unexpected_error_while_rank_0_writes_a_runs_output_is_raised_on_every_rank(tmp_path, method, where, sets):
    # Red team: rank 0 writes a run's output while the others wait (run._run_reduced: in _wait_telling;
    # _run_full: in the broadcast after it opens or finishes the output; the full-order loop: at rank 0's
    # next word, fom_integrator._Run._word, after a checkpoint); only a DbfError or a write error reached
    # them, and any other exception (a bug, an h5py ValueError) left rank 0 alone with it and the other
    # ranks waiting for ever (the Python API does not abort as `python -m mpi4py` does). Now every rank
    # raises it (rank 0 its own, rank 1 a copy naming rank 0), the lock is released, no checkpoint's
    # temporary file is left, and the job ends (with the exception kept in a frame of its own traceback,
    # rank 0 freed the integration's PETSc objects alone at exit, and PETSc's clean-up there hung).
    out = two_ranks_of(_UNEXPECTED_AS_RANK_0_WRITES, tmp_path, method, where, PAPER, *sets)
    assert out.returncode == 0, f"exit {out.returncode} (124: a rank waited for ever)\n{out.stdout}{out.stderr}"
    lines = out.stdout.splitlines()
    assert lines[:2] == [f"rank 0: ValueError: rank 0's {where} refused (origin None)",
                         f"rank 1: ValueError: rank 0's {where} refused (origin 0)"], out.stdout + out.stderr
    # no output, lock or temporary file; the .partial stays, as a killed run's does (a rerun writes over it)
    assert lines[2:] == ["files ['out.h5.partial']"], out.stdout
