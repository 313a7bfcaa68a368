"""The reduced integrator (rom_integrator.py) on reduced models built by hand: exact solutions of
small linear systems, a non-identity reduced mass, implicit and explicit contact, failures that
say what to change."""
import re

import numpy as np
import pytest

from dbf_hpc.constraints import ConstraintSet
from dbf_hpc.errors import SolverError
from dbf_hpc.excitation import Harmonic
from dbf_hpc.laws import ConstraintLaws, law
from dbf_hpc.rom import ReducedModel
from dbf_hpc.rom_integrator import integrate_reduced
from dbf_hpc.timestepping import IntegratorSettings

# Hand-built models every rank holds whole, integrated on PETSc.COMM_SELF: the 2-rank pass repeated
# each test on both ranks (about 10 s of it measured under load); the collective side of the reduced
# runs is tested there by test_run, test_rom_fast and test_api.
pytestmark = pytest.mark.serial


def oscillator(mass=1.0, stiffness=4.0, damping=0.0, spring=0.0, b=1.0, q0=1e-3):
    """One coordinate: mass q'' + damping q' + stiffness q = -spring b (b q), a linear-spring
    constraint acting on z = b q."""
    laws = ConstraintLaws([law("linear", k=spring)] if spring else [law("deadband", clearance=1.0, k=1.0)])
    constraints = ConstraintSet(rows=[[0]], laws=laws, labels=("c",), positions=np.zeros(1))
    return ReducedModel(M=np.array([[mass]]), C=np.array([[damping]]), K=np.array([[stiffness]]),
                        B=np.array([[b]]), r_c=np.zeros(1), base_load=np.zeros(1), force_shape=np.zeros(1),
                        constraints=constraints, support=Harmonic(), force=Harmonic(), q0=np.array([q0]),
                        p0=np.zeros(1), probe_B=np.zeros((0, 1)), probe_r=np.zeros(0),
                        basis_info={"omega": np.zeros(1), "enrichment_omega": np.zeros(0), "dbf_k": np.zeros(0),
                                    "enrichment": "none"})


def run(model, **settings):
    samples = []
    stats = integrate_reduced(model, IntegratorSettings(**settings), lambda t, q, p: samples.append((t, q[0], p[0])))
    return np.array(samples), stats


@pytest.mark.parametrize("mass", [1.0, 2.5])
def test_free_vibration_runs_at_the_frequency_of_stiffness_plus_spring_over_the_reduced_mass(mass):
    # q'' M + (K + k b^2) q = 0 from q(0) = q0: q0 cos(omega t), omega^2 = (K + k b^2) / M. The
    # integrator must use M_r itself, not assume V^T M V = I.
    model = oscillator(mass=mass, stiffness=4.0, spring=5.0, b=0.5)
    s, _ = run(model, t_end=2.0, scheme="4", adaptive=False, dt=1e-4, sample_dt=1e-2)
    omega = np.sqrt((4.0 + 5.0 * 0.25) / mass)
    np.testing.assert_allclose(s[:, 1], 1e-3 * np.cos(omega * s[:, 0]), atol=1e-9)


def test_damping_decays_at_the_exact_rate():
    # q'' + c q' + w^2 q = 0, under-damped: q0 e^(-c t / 2) (cos wd t + (c / 2 wd) sin wd t).
    model = oscillator(stiffness=100.0, damping=1.0)
    s, _ = run(model, t_end=3.0, rtol=1e-9, atol=1e-14, sample_dt=1e-2)
    wd = np.sqrt(100.0 - 0.25)
    t = s[:, 0]
    exact = 1e-3 * np.exp(-0.5 * t) * (np.cos(wd * t) + 0.5 / wd * np.sin(wd * t))
    assert np.abs(s[:, 1] - exact).max() < 1e-7 * 1e-3 * 100


def test_explicit_contact_converges_to_the_implicit_answer():
    model = oscillator(stiffness=4.0, spring=20.0)
    implicit, _ = run(model, t_end=1.0, scheme="4", adaptive=False, dt=1e-4, sample_dt=1e-2)
    explicit, _ = run(model, t_end=1.0, scheme="4", adaptive=False, dt=1e-4, sample_dt=1e-2, contact="explicit")
    assert np.abs(implicit[:, 1] - explicit[:, 1]).max() < 1e-8


def test_a_step_too_long_for_explicit_contact_is_an_error_saying_to_make_it_implicit():
    model = oscillator(stiffness=1.0, spring=1e8)
    with pytest.raises(SolverError, match='set contact = "implicit"'):
        run(model, t_end=1.0, adaptive=False, dt=1e-2, sample_dt=1e-2, contact="explicit")


def test_a_stop_requested_after_a_step_ends_the_run_with_that_message():
    model = oscillator()
    with pytest.raises(SolverError, match="asked to stop"):
        integrate_reduced(model, IntegratorSettings(t_end=1.0, sample_dt=1e-2), lambda t, q, p: None,
                          on_step=lambda ts, t, q, p: "asked to stop" if t > 0.1 else None)


@pytest.mark.parametrize("callbacks", ["python", "c"])
def test_repeated_integrations_leave_no_solver_behind_in_petscs_garbage(callbacks, capfd):
    # Ownership: the integrator held a reference to its TS's KSP past the TS's destruction; petsc4py
    # 3.18 then parks the KSP in PETSc's garbage until a collective cleanup: one per reduced run of a
    # parameter study (both callback paths).
    from petsc4py import PETSc

    from conftest import petsc_garbage

    model = oscillator(spring=5.0)
    PETSc.garbage_cleanup()
    for _ in range(3):
        integrate_reduced(model, IntegratorSettings(t_end=0.1, dt=1e-2, sample_dt=1e-2, adaptive=False,
                                                    callbacks=callbacks), lambda t, q, p: None)
    assert petsc_garbage(capfd) == 0, "the reduced run's KSP was left in PETSc's garbage"


def test_an_exception_from_a_record_callback_frees_the_time_stepper(capfd):
    # Ownership on the error path: the callback's exception carried, in its traceback, the TS petsc4py
    # handed the monitor; it outlived the integrator's destroy, and petsc4py 3.18 parks the TS (with its
    # SNES, KSP and matrices) in PETSc's garbage until a collective cleanup.
    from petsc4py import PETSc

    from conftest import petsc_garbage

    def record(t, q, p):
        raise KeyError("a study script's own bug")

    PETSc.garbage_cleanup()
    for _ in range(2):
        with pytest.raises(KeyError):
            integrate_reduced(oscillator(spring=5.0), IntegratorSettings(t_end=0.1, dt=1e-2, sample_dt=1e-2,
                                                                         adaptive=False, callbacks="python"), record)
    assert petsc_garbage(capfd) == 0, "the failed run's TS was left in PETSc's garbage"


def stopped_oscillator():
    """The oscillator from 1 mm against a stop (1e7 N/m) 0.1 mm away: a contact lasting ~1 ms."""
    import dataclasses

    stop = ConstraintSet(rows=[[0]], laws=ConstraintLaws([law("deadband", clearance=1e-4, k=1e7)]),
                         labels=("x = 0.5 m",), positions=np.zeros(1))
    return dataclasses.replace(oscillator(stiffness=100.0), constraints=stop)


@pytest.mark.parametrize("callbacks", ["python", "c"])
def test_a_fixed_step_whose_newton_solve_fails_names_the_reason_the_step_the_constraint_and_dt_not_rtol(callbacks):
    # Red team: every such stop said "reduce [integrator] dt or rtol, or try another scheme": rtol does
    # nothing to a fixed step, and the line named neither the Newton failure nor the constraint.
    with pytest.raises(SolverError) as info:
        run(stopped_oscillator(), t_end=1.0, sample_dt=1e-2, adaptive=False, dt=0.05, callbacks=callbacks)
    line = str(info.value)
    assert "\n" not in line and "rtol" not in line and "another scheme" not in line, line
    assert "the Newton solve of a step of 0.05 s failed (DIVERGED_" in line, line
    # from 1 mm at 10 rad/s, 0.1 s after its last sample; the failed step reaches the stop 0.1 mm away
    assert re.search(r"no constraint in contact at its start, the nearest its stop: constraint 1 \(x = 0.5 m, "
                     r"deadband\), [0-9.e-]+ m away;", line), line
    assert line.endswith("lower [integrator] dt (now 0.05 s), or set [integrator] adaptive = true, whose steps shrink "
                         "where a Newton solve fails"), line


@pytest.mark.parametrize("callbacks", ["python", "c"])
def test_a_newton_solve_starved_by_the_users_own_option_names_that_option(callbacks):
    # -rom_snes_max_it 1 stops a run that the defaults finish (the same run without it does): the line
    # names the option and the Newton solve's reason, not dt or rtol.
    from conftest import petsc_options

    # a 1 ms step leaves the 1 ms contact in its first step: the Newton solve needs more than one iteration
    settings = dict(t_end=0.1, sample_dt=1e-2, adaptive=False, dt=1e-3, callbacks=callbacks)
    run(stopped_oscillator(), **settings)
    with petsc_options(rom_snes_max_it=1), pytest.raises(SolverError) as info:
        run(stopped_oscillator(), **settings)
    line = str(info.value)
    assert "(DIVERGED_MAX_IT after 1 iterations)" in line and "check the options given (-rom_snes_max_it) first" in line
    assert "in contact at its start: constraint 1 (x = 0.5 m, deadband)" in line, line   # the stop's first contact
    assert "rtol" not in line and "reduce [integrator] dt" not in line, line
    # it failed in its first step, which the line then pinned on the input; the option did it
    assert "stopped at t = 0 s" in line and "points to the input" not in line, line


@pytest.mark.parametrize("callbacks", ["python", "c"])
@pytest.mark.parametrize("load", ["force", "support"])
def test_a_harmonic_load_on_a_non_identity_reduced_mass_drives_the_exact_forced_response(callbacks, load):
    # M q'' + K q = g sin(W t) from rest: q = g / (K - M W^2) (sin W t - (W / w) sin w t), w^2 = K / M, with
    # g = s a for a force of amplitude a on the load shape s, and g = l a W^2 for a support moving as a sin(W t)
    # (its inertia load -l Omega''). Planted bug it catches: the load shape not taken through M_r^-1 (the
    # integrator's equations are M_r^-1 times the model's), which no test with a load had (their M_r = I).
    import dataclasses

    if callbacks == "c":
        from dbf_hpc import _romc

        if _romc.core is None:
            pytest.skip("the C callbacks are not built")
    mass, stiffness, a, f = 2.5, 40.0, 3e-3, 0.7
    W, w = 2 * np.pi * f, np.sqrt(stiffness / mass)
    if load == "force":
        model = dataclasses.replace(oscillator(mass=mass, stiffness=stiffness, q0=0.0), force_shape=np.array([0.8]),
                                    force=Harmonic(a, f))
        g = 0.8 * a
    else:
        model = dataclasses.replace(oscillator(mass=mass, stiffness=stiffness, q0=0.0), base_load=np.array([1.3]),
                                    support=Harmonic(a, f))
        g = 1.3 * a * W * W
    s, _ = run(model, t_end=1.0, rtol=1e-10, atol=1e-15, sample_dt=1e-2, callbacks=callbacks)
    t = s[:, 0]
    exact = g / (stiffness - mass * W * W) * (np.sin(W * t) - W / w * np.sin(w * t))
    assert np.abs(s[:, 1] - exact).max() < 1e-6 * np.abs(exact).max()
