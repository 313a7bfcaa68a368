"""The full-order reference (fom_integrator.py, run --method full) against exact answers: the pinned-pinned
beam's natural frequencies, the closed-form response to support motion, and the reduced model on
the paper's beam up to and just after the first impact."""
import h5py
import numpy as np
import pytest
from mpi4py import MPI

from dbf_hpc.errors import InputError
from dbf_hpc.run import run
from dbf_hpc.scene import load_scene
from exact import pinned_beam_base_response
from conftest import MICRO_BEAM
from test_run import EI, PAPER, RHOA, two_plane_tube_with_three_holes, without_constraints


def full_run(tmp, *sets, name="full.h5", scene=PAPER, method="full"):
    s = load_scene(scene, ["basis.cache=off", *sets])
    path = str(tmp / name)
    summary = run(s, path, progress=False, method=method)
    return h5py.File(path, "r") if MPI.COMM_WORLD.rank == 0 else None, summary


@pytest.mark.parametrize("mode", [1, 2, 3])
def test_free_vibration_is_the_exact_pinned_pinned_mode(shared_tmp_path, mode):
    # omega_k = (k pi / L)^2 sqrt(EI / rho A); w(0.25, t) = A sin(k pi / 4) cos(omega_k t).
    omega = (mode * np.pi) ** 2 * np.sqrt(EI / RHOA)
    periods = 3
    scene = without_constraints(shared_tmp_path)
    f, _ = full_run(shared_tmp_path, "excitation.kind=none", "initial.amplitude=1e-3", f"initial.mode={mode}",
                    "output.probes=[0.25]", f"integrator.t_end={periods * 2 * np.pi / omega}",
                    f"integrator.dt={2 * np.pi / omega / 2000}", f"output.sample_dt={2 * np.pi / omega / 200}",
                    name=f"mode{mode}.h5", scene=scene)
    if f is not None:
        t, w = f["time"][:], f["probes/displacement"][:, 0]
        exact = 1e-3 * abs(np.sin(mode * np.pi / 4)) * np.cos(omega * t) * np.sign(w[0])  # a mode's sign is a convention
        # 2000 steps per period. Measured 1.0e-5 to 1.4e-5 of 1 mm after 3 periods with the consistent
        # start (A0 from the equation of motion); 5.8e-5 to 8.1e-5 with TSALPHA2's start (its A0
        # from two backward-Euler half steps, twice the backward-difference estimate in PETSc 3.18).
        assert np.abs(w - exact).max() < 2e-4 * 1e-3
        # The frequency itself, from the upward zero crossings of w.
        up = np.flatnonzero((w[:-1] < 0) & (w[1:] >= 0))
        crossings = t[up] - w[up] * (t[up + 1] - t[up]) / (w[up + 1] - w[up])
        measured = 2 * np.pi / np.mean(np.diff(crossings))
        # Generalized-alpha's period error (omega dt)^2 / 12 = 8e-7, as measured; the mesh's ~1e-9.
        assert abs(measured / omega - 1) < 1e-5
        assert f.attrs["method"] == "full" and "basis" not in f and f["reduced/q"].shape == (t.size, 0)


def test_support_motion_gives_the_closed_form_linear_response(shared_tmp_path):
    scene = without_constraints(shared_tmp_path)
    f, summary = full_run(shared_tmp_path, "integrator.t_end=2.0", "integrator.dt=2e-4", "output.sample_dt=1e-3",
                          "output.probes=[0.25, 0.5]", name="base.h5", scene=scene)
    if f is not None:
        t, w = f["time"][:], f["probes/displacement"][:]
        exact = pinned_beam_base_response(EI, RHOA, 1.0, np.array([0.25, 0.5]), t, 5e-3, 1.0, 200)
        # Measured 7e-7 of the peak.
        assert np.abs(w - exact).max() < 1e-5 * np.abs(exact).max()
        # From rest with no load at t = 0 the start needs no solve: one factorization for every step.
        assert summary["stats"]["factorizations"] == 1, "a fixed step on a linear model factors once"


def test_reduced_and_full_models_agree_on_the_paper_beam_until_just_after_the_first_impact(shared_tmp_path):
    sets = ["integrator.t_end=0.12", "output.sample_dt=1e-4", "integrator.rtol=1e-8", "integrator.atol=1e-12"]
    f_full, _ = full_run(shared_tmp_path, *sets, "integrator.dt=5e-6", name="truth.h5")
    f_rom, _ = full_run(shared_tmp_path, *sets, name="rom.h5", method="rom")
    if f_full is not None:
        t = f_full["time"][:]
        truth, rom = f_full["constraints/displacement"][:, 0], f_rom["constraints/displacement"][:, 0]
        touches = [t[np.flatnonzero(np.abs(z) > 2.5e-3)[0]] if np.any(np.abs(z) > 2.5e-3) else np.inf
                   for z in (truth, rom)]
        # Both reach the stop near 0.105 s (measured 0.1057 and 0.1052 s: w grazes the clearance, so
        # a displacement difference of 4e-5 moves the first touch by half a millisecond).
        assert all(0.104 < touch < 0.107 for touch in touches), touches
        first = min(touches)
        scale = np.abs(truth).max()
        before = t < first
        # Before the impact both are linear: the ROM's truncation to 6 modes + 1 DBF and the
        # truth's step. Measured 6.9e-5 of the peak.
        assert np.abs(rom - truth)[before].max() < 2e-4 * scale
        # Within 5 ms after it, the reduced model's impact differs from the full model's (measured
        # 4.5 %): 6 modes + 1 DBF cannot represent the mesh's local response at the contact.
        after = (t >= first) & (t < first + 5e-3)
        assert np.abs(rom - truth)[after].max() < 0.1 * scale
        # The full model writes the same layout: snapshots agree with the constraint series.
        i = np.searchsorted(t, f_full["snapshots/time"][:])
        node = np.argmin(np.abs(f_full["snapshots/x"][:] - 0.25))
        assert np.allclose(f_full["snapshots/w"][:, node], truth[i], atol=1e-12)
        for name in ("constraints/force_peak", "constraints/stats/impacts", "probes/displacement", "probes/peak"):
            assert f_full[name].shape[1:] == f_rom[name].shape[1:], name


def test_full_method_refuses_modal_damping_in_one_line_and_leaves_no_file(shared_tmp_path):
    s = load_scene(PAPER, ["basis.cache=off", "damping.zeta=0.02"])
    with pytest.raises(InputError, match="rayleigh_alpha"):
        run(s, str(shared_tmp_path / "x.h5"), progress=False, method="full")
    with pytest.raises(InputError, match="rayleigh_alpha"):
        run(s, str(shared_tmp_path / "x.h5"), progress=False, method="full", resume=True)
    if MPI.COMM_WORLD.rank == 0:
        assert not list(shared_tmp_path.glob("x.h5*")), "no file is left behind"


def test_an_initial_mode_the_mesh_does_not_have_is_refused_naming_initial_mode(shared_tmp_path):
    # it said "number of modes must be between 1 and 200", naming nothing the user wrote (red team)
    s = load_scene(PAPER, ["basis.cache=off", "excitation.kind=none", "initial.amplitude=1e-3", "initial.mode=500",
                           "integrator.t_end=0.01"])
    with pytest.raises(InputError, match=r"^\[initial\] mode = 500: .*between 1 and 200"):
        run(s, str(shared_tmp_path / "x.h5"), progress=False, method="full")


@pytest.mark.parametrize("alpha_share", [0.0, 1.0, 0.5], ids=["beta", "alpha", "alpha-and-beta"])
def test_rayleigh_damping_decays_the_full_model_at_the_exact_rate(shared_tmp_path, alpha_share):
    # C = alpha M + beta K: mode 1 decays as exp(-zeta omega t), zeta = alpha / (2 omega) + beta omega / 2,
    # here 0.01 from beta alone, from alpha alone, or half from each. The alpha M part was checked by no
    # test against an exact answer: a factor 2 on it in fom.damping_matrix passed every full-order test.
    omega = np.pi ** 2 * np.sqrt(EI / RHOA)
    alpha = alpha_share * 0.02 * omega
    beta = (1.0 - alpha_share) * 0.02 / omega
    scene = without_constraints(shared_tmp_path)
    f, _ = full_run(shared_tmp_path, "excitation.kind=none", "initial.amplitude=1e-3", "output.probes=[0.5]",
                    f"damping.rayleigh_alpha={alpha!r}", f"damping.rayleigh_beta={beta!r}",
                    f"integrator.t_end={2 * 2 * np.pi / omega}", f"integrator.dt={2 * np.pi / omega / 2000}",
                    name=f"damped_{alpha_share}.h5", scene=scene)
    if f is not None:
        t, w = f["time"][:], f["probes/displacement"][:, 0]
        zeta = 0.01
        wd = omega * np.sqrt(1 - zeta**2)
        exact = 1e-3 * np.exp(-zeta * omega * t) * (np.cos(wd * t) + zeta / np.sqrt(1 - zeta**2) * np.sin(wd * t))
        assert np.abs(w - exact).max() < 2e-4 * 1e-3  # measured 8.2e-6 of 1 mm (8.0e-5 with TSALPHA2's start)


def test_matrix_files_with_a_damping_matrix_give_the_beam_with_rayleigh_damping(shared_tmp_path):
    # The same structure two ways: the Table 1 beam with C = beta K (Rayleigh), and its K, M and
    # C = beta K written to Matrix Market files (by scipy, an independent writer) with the force
    # and the constraint named by DOF. The full-order runs must agree to round-off, contact included
    # (measured: identical, over 28 impacts).
    import scipy.io

    from test_matrices import to_scipy

    beta = 1e-4
    common = """[excitation]
kind = "force"
amplitude = 0.05
frequency_hz = 3.0
{force}
[damping]
{damping}
[[constraint]]
{where}
law = "deadband"
clearance = 2e-4
k = 1e6
[integrator]
t_end = 0.05
dt = 2e-5
[output]
probes = [{probe}]
sample_dt = 1e-4
"""
    beam = """[structure]
kind = "beam"
length = 1.0
elements = 30
E = 117e9
I = 8.78e-16
A = 2.9e-7
rho = 11800.0
""" + common.format(force="x = 0.5", damping=f"rayleigh_beta = {beta}", where="x = 0.25", probe="0.5")
    path = shared_tmp_path / "beam.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(beam)
    MPI.COMM_WORLD.Barrier()
    s = load_scene(str(path), ["basis.cache=off"])
    with s.full_order_model() as fom:
        K, M = to_scipy(fom.operators.K), to_scipy(fom.operators.M)
        force_row, constraint_row = fom.operators.mesh.w_row(0.5), int(fom.constraints.flat_rows[0])
    matrices = """[structure]
kind = "matrices"
stiffness = "K.mtx"
mass = "M.mtx"
damping = "C.mtx"
""" + common.format(force=f"dof = {force_row}", damping="", where=f"dof = {constraint_row}", probe=force_row)
    if MPI.COMM_WORLD.rank == 0:
        for name, A in (("K", K), ("M", M), ("C", beta * K)):
            scipy.io.mmwrite(str(shared_tmp_path / f"{name}.mtx"), A, precision=17)
        (shared_tmp_path / "matrices.toml").write_text(matrices)
    MPI.COMM_WORLD.Barrier()
    f_beam, _ = full_run(shared_tmp_path, name="beam_rayleigh.h5", scene=str(path))
    f_files, _ = full_run(shared_tmp_path, name="files_c.h5", scene=str(shared_tmp_path / "matrices.toml"))
    if f_beam is not None:
        z_beam, z_files = f_beam["constraints/displacement"][:, 0], f_files["constraints/displacement"][:, 0]
        assert np.abs(z_beam).max() > 2e-4, "the constraint is reached"
        assert np.abs(z_files - z_beam).max() < 1e-8 * np.abs(z_beam).max()
        w_beam, w_files = f_beam["probes/displacement"][:, 0], f_files["probes/displacement"][:, 0]
        assert np.abs(w_files - w_beam).max() < 1e-8 * np.abs(w_beam).max()


@pytest.mark.parametrize("law_keys", [
    {"law": "deadband", "clearance": 2.5e-3, "k": 1e6, "damping": "linear", "c": 5.0},
    {"law": "deadband", "clearance": 2.5e-3, "k": 1e6, "damping": "hunt_crossley", "alpha": 2.0},
    {"law": "hertz", "clearance": 2.5e-3, "k": 1e9},
    {"law": "table", "table": [[-3e-3, 500.0], [-2.5e-3, 0.0], [2.5e-3, 0.0], [2.6e-3, -20.0], [3e-3, -2000.0]],
     "damping": "linear", "c": 1.0},
], ids=["deadband-linear-damping", "deadband-hunt-crossley", "hertz", "table-linear-damping"])
def test_every_law_stops_the_full_model_at_its_clearance_kinks_and_force_jumps_included(shared_tmp_path, law_keys):
    # Linear contact damping switches c v on at the stop: the contact force jumps, and the condensed
    # Newton falls back to its Gauss-Seidel bisection there. The TSALPHA2 reference it replaces stopped at
    # the first impact of the first case (t = 0.107 s: its Newton failed on the jump).
    from dbf_hpc.constraints import Constraint
    from dbf_hpc.excitation import BaseMotion
    from dbf_hpc.fom import FullOrderModel
    from dbf_hpc.laws import law
    from dbf_hpc.simulate import simulate_full
    from dbf_hpc.structure import Beam
    from dbf_hpc.timestepping import IntegratorSettings

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=100)
    keys = dict(law_keys)
    stop = Constraint(law(keys.pop("law"), **keys), x=0.25)
    with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0)) as fom:
        result = simulate_full(fom, IntegratorSettings(t_end=0.125, dt=1e-5, sample_dt=1e-4))
    z = np.abs(result.displacement[:, 0])
    assert result.statistics["impacts"][0] >= 1 and result.solver["contact_steps"] > 10
    assert z.max() < 2.5e-3 * 1.001, "the stop holds the beam at its clearance"
    if law_keys.get("damping") == "linear":
        assert result.solver["contact_fallbacks"] >= 1, "the force jump is met"


def test_a_fixed_step_longer_than_a_twentieth_of_the_forcing_period_draws_a_warning(shared_tmp_path, capfd):
    # Generalized-alpha is unconditionally stable, so a step past the forcing's period fails nowhere:
    # dt = 0.3 s under a 10 Hz forcing took one step of 0.05 s and wrote a 727 N peak force and 0
    # impacts with no word. 20 steps a period is the scheme's phase error (omega dt)^2 / 12 < 1 %.
    for dt, warned in ((0.3, True), (5e-3, False), (1e-5, False)):
        s = load_scene(PAPER, ["basis.cache=off", "integrator.t_end=0.05", f"integrator.dt={dt}",
                               "excitation.frequency_hz=10", "output.sample_dt=1e-3"])
        run(s, str(shared_tmp_path / f"coarse{dt}.h5"), progress=True, method="full")
        err = capfd.readouterr().err
        if MPI.COMM_WORLD.rank == 0:
            assert ("fixed steps per period of the 10 Hz excitation" in err) == warned, (dt, err)


def test_a_step_too_coarse_for_the_forcing_warns_also_without_progress_output(shared_tmp_path, capfd):
    # -q silences the progress lines, not the warning that the response is wrong (red team: --method
    # full -q at 2.5 steps a period of a 4 kHz force wrote its aliased response with no word).
    s = load_scene(PAPER, ["basis.cache=off", "integrator.t_end=0.05", "integrator.dt=0.03",
                           "excitation.frequency_hz=10", "output.sample_dt=1e-3"])
    run(s, str(shared_tmp_path / "coarse_quiet.h5"), progress=False, method="full")
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert "fixed steps per period of the 10 Hz excitation" in err, err


def test_unresolved_impacts_warn_whatever_the_sample_interval(shared_tmp_path, capfd):
    # Impact durations are measured on the steps, not the samples: at k = 1e12 N/m and dt = 1e-5 s an
    # impact lasts one step, and samples 100 steps apart must not hide it (the docs said they would).
    s = load_scene(PAPER, ["basis.cache=off", "integrator.t_end=0.12", "integrator.dt=1e-5", "output.sample_dt=1e-3",
                           "constraint.k_minus=1e12", "constraint.k_plus=1e12"])
    run(s, str(shared_tmp_path / "sparse_samples.h5"), progress=True, method="full")
    err = capfd.readouterr().err
    if MPI.COMM_WORLD.rank == 0:
        assert "the impacts of constraint 1 at x = 0.25 m last 1 fixed steps" in err, err


def test_the_full_run_counts_two_condensed_dofs_per_round_hole_of_a_two_plane_beam(shared_tmp_path, capfd):
    # Red team: a round hole holds the tube in y and z, so three holes condense the contact on 6 DOFs;
    # the log said "contact condensed on 3 DOF(s)" (the constraints, not their DOFs).
    path = two_plane_tube_with_three_holes(shared_tmp_path)
    s = load_scene(str(path), ["basis.cache=off", "integrator.t_end=0.002", "integrator.dt=1e-4"])
    run(s, str(shared_tmp_path / "two_planes_full.h5"), progress=True, method="full")
    out = capfd.readouterr().out
    if MPI.COMM_WORLD.rank == 0:
        assert "contact condensed on 6 DOF(s)" in out, out


def test_the_full_order_estimate_of_its_step_error_is_within_2x_of_the_error_against_a_32x_shorter_step(
        shared_tmp_path):
    # Every result carries an error estimate: a full-order run's is the same model over the window
    # (twice the first contact) at a 4 times shorter step. Its own error, against a step 32 times
    # shorter, is measured at 1.26x (dt = 1e-4 s; 0.84 % true against 1.05 % estimated).
    f, summary = full_run(shared_tmp_path, "integrator.t_end=0.25", "integrator.dt=1e-4", name="est.h5")
    truth, _ = full_run(shared_tmp_path, "integrator.t_end=0.25", f"integrator.dt={1e-4 / 32}", "basis.estimate=false",
                        name="est_truth.h5")
    if f is not None:
        end = f.attrs["estimated_error_window"]
        t = f["time"][:]
        k = int(np.searchsorted(t, end * (1 + 1e-12), side="right"))
        first_contact = t[np.flatnonzero(f["constraints/force_peak"][:, 0])[0]]
        assert end == pytest.approx(2 * first_contact, abs=2 * (t[1] - t[0]))   # the impacts are in the window
        w, w_true = f["constraints/displacement"][:k], truth["constraints/displacement"][:k]
        true = np.abs(w - w_true).max() / np.abs(w_true).max()
        assert 0.5 < f.attrs["estimated_error"] / true < 2.0, (f.attrs["estimated_error"], true)
        assert "fixed step of 2.5e-05 s" in f.attrs["estimated_error_note"]
        assert summary["estimated_error"] == f.attrs["estimated_error"]
        assert "estimated_error" not in truth.attrs             # [basis] estimate = false: none


REDUCED_SETTINGS = {"integrator.rtol": "1e-9", "integrator.atol": "1e-10", "integrator.adaptive": "true",
                    "integrator.scheme": '"4"', "integrator.contact": '"explicit"', "integrator.callbacks": '"python"',
                    "basis.tolerance": "0.01", "basis.estimate_statistics_window": "0.01"}


def test_each_reduced_model_setting_a_full_order_run_ignores_draws_one_warning_naming_what_it_uses(shared_tmp_path,
                                                                                                   capfd):
    # Red team: --method full with rtol = 1e-9, scheme 4, contact = "explicit" and [basis] tolerance = 0.01 ran
    # at its fixed step, its accuracy that of dt, with no word. The keys that define the basis (modes, ...) are
    # left alone: every shipped scene sets them, and no one takes them for the full-order run's.
    base = ["integrator.t_end=0.02", "integrator.dt=1e-5", "basis.estimate=false", "output.snapshots=0"]
    cases = [("all", [f"{k}={v}" for k, v in REDUCED_SETTINGS.items()], set(REDUCED_SETTINGS)),
             ("none", [], set()), ("fixed", ["integrator.adaptive=false"], set())]
    for name, sets, expected in cases:
        run(load_scene(PAPER, [*base, *sets]), str(shared_tmp_path / f"ignored-{name}.h5"), progress=False,
            method="full")
        err = capfd.readouterr().err
        lines = [line for line in err.splitlines() if "is the reduced model's; --method full ignores it" in line]
        if MPI.COMM_WORLD.rank == 0:
            named = {f"{line.split('[')[1].split(']')[0]}.{line.split('] ')[1].split(' =')[0]}" for line in lines}
            assert named == expected and len(lines) == len(expected), err
            if expected:
                assert "[integrator] rtol = 1e-09 is the reduced model's; --method full ignores it: it takes fixed " \
                       "steps of [integrator] dt = 1e-05 s" in err, err
                assert '[integrator] scheme = "4"' in err and "generalized-alpha" in err, err
        else:
            assert not lines, err


def test_simulate_full_warns_of_each_reduced_model_setting_given_other_than_its_default(capfd):
    from dbf_hpc import Beam, Constraint, FullOrderModel, IntegratorSettings, law, simulate_full
    from dbf_hpc.excitation import BaseMotion

    beam = Beam(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0, elements=20)
    stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
    with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0)) as fom:
        for given, expected in (({}, 0), ({"rtol": 1e-8, "contact": "explicit"}, 2), ({"adaptive": False}, 0)):
            simulate_full(fom, IntegratorSettings(t_end=1e-3, dt=1e-4, sample_dt=1e-4, **given))
            err = capfd.readouterr().err
            count = err.count("is the reduced model's; simulate_full ignores it")
            assert count == (expected if MPI.COMM_WORLD.rank == 0 else 0), err
            if expected and MPI.COMM_WORLD.rank == 0:
                assert "IntegratorSettings rtol = 1e-08" in err and 'IntegratorSettings contact = "explicit"' in err


def test_a_contact_stiffer_than_the_step_resolves_warns_even_when_it_never_opens(shared_tmp_path, capfd):
    # Red team: hertz at k = 1e12 N/m and clearance 0 stays closed for the whole run (one impact of 0.12 s, so
    # the impacts-per-step warning is silent), and its mean impact power was 1.7e-5, 3.2e-4 and 2.0e-3 W at
    # dt = 1e-5, 2.5e-6 and 6.25e-7 s. The diagnostic's half-period, pi / (omega h) from D_jj |dN/dz|, is the
    # measured one where impacts do open: the paper's stop at dt = 2e-6 s (its ~15 us impacts, 7 steps).
    import json

    base = ["integrator.t_end=0.12", "basis.estimate=false", "output.snapshots=0"]
    cases = (("paper", ["integrator.dt=2e-6"], False),
             ("hertz", ["integrator.dt=1e-5", 'constraint.law="hertz"', "constraint.k=1e12", "constraint.clearance=0"],
              True))
    for name, sets, warned in cases:
        path = shared_tmp_path / f"stiff-{name}.h5"
        run(load_scene(PAPER, [*base, *sets]), str(path), progress=False, method="full")
        err = capfd.readouterr().err
        count = err.count("is too stiff for dt")
        if MPI.COMM_WORLD.rank == 0:
            assert count == (1 if warned else 0) and "fixed steps on average" not in err, err
            with h5py.File(path) as f:
                ratio = json.loads(f.attrs["solver_stats"])["contact_stiffness"][0]
                duration = f["constraints/stats/impact_duration_mean"][0]
            from dbf_hpc.fom_integrator import Alpha2
            P = Alpha2(0.9)
            half_period = np.pi / np.sqrt(ratio * P.am / (P.af * P.beta)) * (1e-5 if warned else 2e-6)
            if warned:
                assert "constraint 1 at x = 0.25 m" in err and "half-period of 0.17 fixed steps" in err, err
                assert duration > 1000 * half_period, "one contact the whole run: its duration says nothing"
            else:
                assert 0.8 < half_period / duration < 1.2, (half_period, duration)
        else:
            assert count == 0, err


def test_a_micro_beams_free_vibration_of_a_few_microseconds_is_sampled_at_the_sample_times(shared_tmp_path):
    # A 100 um steel micro-beam: f_1 = 2.3 MHz. Red team: every run shorter than 1 s took a sample at a step
    # up to 1 ns before it (the sample tolerance was 1e-9 s), 1.4 % of the amplitude here (omega x 1 ns), where
    # the integration is good to 1e-5.
    path = shared_tmp_path / "micro.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(MICRO_BEAM)
    MPI.COMM_WORLD.Barrier()
    omega = (np.pi / 1e-4) ** 2 * np.sqrt(2e11 * 8.333e-22 / (7800.0 * 1e-10))
    period = 2 * np.pi / omega
    f, _ = full_run(shared_tmp_path, f"integrator.t_end={3 * period}", f"integrator.dt={period / 2000}",
                    f"output.sample_dt={period / 200 * 1.013}", "output.probes=[5e-5]", name="micro.h5",
                    scene=str(path))
    if f is not None:
        t, w = f["time"][:], f["probes/displacement"][:, 0]
        exact = 1e-7 * np.cos(omega * t) * np.sign(w[0])
        assert t.size > 500 and np.abs(w - exact).max() < 2e-4 * 1e-7, np.abs(w - exact).max() / 1e-7
