"""The full-order integrator (fom_integrator.py) against independent implementations of the same
scheme: PETSc's TSALPHA2 before the first impact, a dense generalized-alpha with Newton on every DOF
through impacts, finite differences of the condensed contact Jacobian; and its bookkeeping: one
factorization per step size, the same answer on 1 and 2 ranks."""
import math
import re

import numpy as np
import pytest
from mpi4py import MPI
from petsc4py import PETSc

from conftest import assert_all, to_numpy
from dbf_hpc import (Beam, BaseMotion, Constraint, FullOrderModel, IntegratorSettings, law,
                     simulate_full)
from dbf_hpc.fom import Observation
from dbf_hpc.fom_integrator import Alpha2, ContactNewton, ContactStep, step_count
from dbf_hpc.laws import ConstraintLaws

PAPER_BEAM = dict(length=1.0, E=117e9, I=8.78e-16, A=2.9e-7, rho=11800.0)


def paper_fom(elements=100, constraints=None, comm=None, excitation=None, probes=(0.5,)):
    beam = Beam(elements=elements, **PAPER_BEAM)
    if constraints is None:
        constraints = [Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)]
    return FullOrderModel.build(beam, constraints, excitation or BaseMotion(amplitude=5e-3, frequency_hz=1.0),
                                probes=probes, comm=comm)


def tsalpha2_reference(fom, dt, t_end, sample_dt):
    """The previous reference: PETSc TS ALPHA2 (rho 0.9) on the linear part M u'' + K u = f(t), valid
    until the first impact; its w at the constraint and the probe, cubic Hermite at the samples."""
    ops = fom.operators
    K, M, load = ops.K, ops.M, ops.base_mass_load
    observation = Observation(fom)
    rows = observation.rows
    a, w = fom.support.amplitude, 2 * np.pi * fom.support.frequency_hz
    history = []

    def residual(ts, t, u, v, acc, F):
        M.mult(acc, F)
        K.multAdd(u, F, F)
        F.axpy(-a * w * w * math.sin(w * t), load)      # - f(t) = + M r Omega''(t)

    built = []   # the shift_a P holds: at a fixed step, K + shift_a M is formed (and factored) once

    def jacobian(ts, t, u, v, acc, shift_v, shift_a, J, P):
        if built != [shift_a]:   # PETSc factors again only a matrix that changed
            K.copy(P)
            P.axpy(shift_a, M)
            P.assemble()
            built[:] = [shift_a]
        return True

    def monitor(ts, step, t, u):
        _, v = ts.getSolution2()
        history.append((t, to_numpy(u)[rows], to_numpy(v)[rows]))

    J = K.duplicate(copy=True)
    J.axpy(1.0, M)
    ts = PETSc.TS().create(comm=fom.comm)
    F, u, v = K.createVecLeft(), K.createVecRight(), K.createVecRight()
    u.zeroEntries()
    v.zeroEntries()
    try:
        ts.setType(PETSc.TS.Type.ALPHA2)
        ts.setI2Function(residual, F)
        ts.setI2Jacobian(jacobian, J, J)
        ts.setTimeStep(dt)
        ts.setMaxTime(t_end)
        ts.setMaxSteps(10**9)
        ts.setExactFinalTime(PETSc.TS.ExactFinalTime.MATCHSTEP)
        ts.getSNES().setTolerances(rtol=1e-14, atol=1e-20, max_it=20)
        ts.getSNES().getKSP().setType("preonly")
        ts.getSNES().getKSP().getPC().setType("lu")
        ts.getSNES().getKSP().getPC().setFactorSolverType("petsc")   # serial only (MUMPS: 16x slower here)
        ts.setMonitor(monitor)
        ts.setAlphaRadius(0.9) if hasattr(ts, "setAlphaRadius") else PETSc.Options().setValue("ts_alpha_radius", 0.9)
        ts.setFromOptions()
        ts.setSolution2(u, v)
        ts.solve(u)
    finally:
        PETSc.Options().delValue("ts_alpha_radius")
        for obj in (ts, F, u, v, J):
            obj.destroy()
    t = np.array([h[0] for h in history])
    x = np.array([h[1] for h in history])
    xd = np.array([h[2] for h in history])
    times = np.arange(int(round(t_end / sample_dt)) + 1) * sample_dt
    out = []
    for s in times:
        i = min(max(np.searchsorted(t, s) - 1, 0), t.size - 2)
        h = t[i + 1] - t[i]
        q = (s - t[i]) / h
        out.append((2 * q**3 - 3 * q**2 + 1) * x[i] + (q**3 - 2 * q**2 + q) * h * xd[i]
                   + (-2 * q**3 + 3 * q**2) * x[i + 1] + (q**3 - q**2) * h * xd[i + 1])
    z, _, probes = observation.block_totals(times, np.array(out), np.array(out))
    return times, np.column_stack([z, probes])


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="TS with MUMPS takes minutes on 2 ranks; the 1-vs-2-ranks "
                                                   "test covers the parallel loop")
def test_condensed_generalized_alpha_is_petsc_tsalpha2_before_the_first_impact(comm):
    # The same scheme (rho 0.9) and the same step: before the first impact both are linear and may
    # differ only by round-off and by the start. PETSc's start takes A0 from two backward-Euler half
    # steps (twice the backward-difference estimate in 3.18), ours from the equation of motion; from
    # rest with f(0) = 0 both are nearly 0. Measured (100 elements, 10 us steps, 0.1 s): 8.2e-12 of the
    # peak at the constraint, 8.9e-12 at the probe.
    with paper_fom() as fom:
        settings = IntegratorSettings(t_end=0.1, dt=1e-5, sample_dt=1e-4)
        ours = simulate_full(fom, settings)
        times, theirs = tsalpha2_reference(fom, settings.dt, settings.t_end, settings.sample_dt)
    assert_all(np.array_equal(ours.time, times))
    w = np.column_stack([ours.displacement, ours.probes])
    assert_all(np.abs(w[:, 0]).max() < 2.5e-3, "no impact before 0.1 s")
    error = np.abs(w - theirs).max(axis=0) / np.abs(theirs).max(axis=0)
    assert_all(np.all(error < 1e-10), error)


def dense_generalized_alpha(fom, laws, t_end, dt, rho=0.9):
    """An independent implementation: generalized-alpha written for X1 with Newton on all DOFs (dense
    numpy), the laws at the mid-point, the consistent start. Returns (t, w at the constraints)."""
    from test_matrices import to_scipy

    K, M = to_scipy(fom.operators.K).toarray(), to_scipy(fom.operators.M).toarray()
    load = to_numpy(fom.operators.base_mass_load)
    rows = fom.constraints.flat_rows
    r_c = fom.influence_at(rows)
    s = fom.support
    f = lambda t: -s.acceleration(t) * load                    # noqa: E731
    P = Alpha2(rho)
    am, af, gamma, beta = P.am, P.af, P.gamma, P.beta
    n = K.shape[0]
    X, V = np.zeros(n), np.zeros(n)
    R0 = f(0.0) - K @ X
    R0[rows] += laws.force(X[rows] + r_c * s.value(0.0), V[rows] + r_c * s.rate(0.0))
    A = np.linalg.solve(M, R0)
    steps, _ = step_count(t_end, dt)
    h = dt
    out = [X[rows] + r_c * s.value(0.0)]
    for k in range(steps):
        ta = k * h + af * h
        X1 = X + h * V + h * h * (0.5 - beta) * A
        for it in range(50):
            A1 = (X1 - X - h * V) / (beta * h * h) - (1 - 2 * beta) / (2 * beta) * A
            V1 = V + h * ((1 - gamma) * A + gamma * A1)
            Xa, Va, Aa = X + af * (X1 - X), V + af * (V1 - V), A + am * (A1 - A)
            N, Nz, Nv = laws.force_and_jacobian(Xa[rows] + r_c * s.value(ta), Va[rows] + r_c * s.rate(ta))
            R = M @ Aa + K @ Xa - f(ta)
            R[rows] -= N
            J = am / (beta * h * h) * M + af * K
            J[rows, rows] -= af * (Nz + Nv * gamma / (beta * h))
            dX = np.linalg.solve(J, -R)
            X1 = X1 + dX
            if np.abs(dX).max() <= 1e-15 * np.abs(X1).max():
                break
        A1 = (X1 - X - h * V) / (beta * h * h) - (1 - 2 * beta) / (2 * beta) * A
        V = V + h * ((1 - gamma) * A + gamma * A1)
        X, A = X1, A1
        out.append(X[rows] + r_c * s.value((k + 1) * h))
    return np.arange(steps + 1) * h, np.array(out)


@pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="a dense serial reference")
def test_condensed_contact_is_newton_on_every_dof_through_impacts():
    # Two smooth laws that push hard (Hertz with Hunt-Crossley damping, a cubic spring with a dashpot):
    # the N_L-sized Newton with the Delassus operator must give what Newton on all 80 DOFs gives, step
    # for step, impacts included. Impacts amplify round-off (docs/design.md): measured 7.8e-11 of the
    # peak over the 15 impacts of the first 10 ms, growing to 1e-8 by 20 ms.
    laws = [law("hertz", clearance=2e-4, k=5e7, damping="hunt_crossley", alpha=0.3),
            law("cubic", k=20.0, k3=1e7, damping="linear", c=2e-3)]
    constraints = [Constraint(laws[0], x=0.25), Constraint(laws[1], x=0.6)]
    with paper_fom(elements=40, constraints=constraints, excitation=BaseMotion(amplitude=2e-2, frequency_hz=8.0),
                   probes=()) as fom:
        settings = IntegratorSettings(t_end=0.01, dt=2e-5, sample_dt=2e-5)
        ours = simulate_full(fom, settings)
        t, dense = dense_generalized_alpha(fom, ConstraintLaws(laws), settings.t_end, settings.dt)
    assert ours.statistics["impacts"][0] >= 10, "the Hertz stop is hit"
    assert ours.solver["contact_steps"] == 500, "the cubic spring always pushes"
    np.testing.assert_allclose(ours.time, t, rtol=0, atol=1e-12)
    error = np.abs(ours.displacement - dense).max() / np.abs(dense).max()
    assert error < 1e-9, error


def test_condensed_contact_jacobian_is_the_derivative_of_its_residual():
    # r(y) = y - y_free - D N(z_a(y), v_a(y)) / a_f with a smooth law and a dashpot: the exact
    # Jacobian J = I - D diag(N_z + s_V N_v) against central differences.
    rng = np.random.default_rng(11)
    n = 4
    B = rng.normal(size=(n, n))
    D = 1e-6 * (B @ B.T + n * np.eye(n))
    laws = ConstraintLaws([law("cubic", k=50.0, k3=1e8, damping="linear", c=0.3)] * 2
                          + [law("hertz", clearance=1e-4, k=1e9, damping="hunt_crossley", alpha=0.5)] * 2)
    P = Alpha2(0.9)
    sV, _ = P.shifts(1e-5)
    y_free = rng.normal(0, 1e-3, n)
    problem = ContactStep(laws, D, y_free, z_c=rng.normal(0, 1e-4, n), v_c=rng.normal(0, 1e-2, n),
                          x_pred=y_free + rng.normal(0, 1e-6, n), af=P.af, sV=sV)
    y = y_free + np.array([1e-5, -2e-5, 4e-4, -3e-4])   # the Hertz stops compressed
    _, _, J = problem.residual(y)
    fd = np.empty((n, n))
    for j in range(n):
        e = np.zeros(n)
        e[j] = 1e-9
        fd[:, j] = (problem.residual(y + e)[0] - problem.residual(y - e)[0]) / 2e-9
    assert np.abs(J - fd).max() < 1e-6 * np.abs(J).max(), np.abs(J - fd).max()


def test_contact_newton_solves_a_force_jump_as_the_set_valued_contact():
    # Linear contact damping switches c v on at the edge: with a fast approach the residual jumps
    # across 0 and has no root. The fallback returns the point of the jump with the force inside it
    # that satisfies y = y_free + D lambda.
    laws = ConstraintLaws([law("deadband", clearance=1e-3, k=1e3, damping="linear", c=500.0)])
    P = Alpha2(0.9)
    sV, _ = P.shifts(1e-5)
    D = np.array([[2e-7]])
    z_c = np.array([(1 - P.af) * 0.9e-3])
    edge = (1e-3 - z_c) / P.af             # y where the mid-point reaches the stop
    problem = ContactStep(laws, D, y_free=edge + 1e-4, z_c=z_c, v_c=np.array([5.0]), x_pred=edge, af=P.af, sV=sV)
    below, above = (problem.residual(edge + s)[0][0] for s in (-1e-12, 1e-12))
    assert below < 0 < above and above - below > 5e-4, "r jumps across 0 at the edge: no root"
    newton = ContactNewton()
    y, lam = newton.solve(problem, problem.y_free.copy(), 0.0)
    assert newton.fallbacks == 1 and newton.jumps >= 1
    assert abs(problem.state(y)[0][0] - 1e-3) < 1e-15, "the mid-point stops at the edge, inside the jump"
    assert lam[0] < 0 and abs(y[0] - problem.y_free[0] - D[0, 0] * lam[0]) < 1e-15
    assert -500.0 * 5.0 / P.af < lam[0], "lambda lies inside the jump, between 0 and the damping force"


def test_contact_newton_converges_where_the_residual_cannot_reach_its_tolerance_in_round_off():
    # Captured on the paper's beam at a 3.2e-4 s step: the stop's force k (z - d) / a_f makes D lambda
    # a thousand times the displacement scale of the tolerance, so |r| stays at its round-off (2e-16)
    # above tol (1.6e-16) while y is exact. Newton stops on its correction (no Gauss-Seidel fallback,
    # which made such steps cost 20 iterations and hundreds of law evaluations).
    laws = ConstraintLaws([law("deadband", clearance=2.5e-3, k=1e6)])
    D, y_free, af, sV, z_c, v_c, x_pred = (0.0005040768777111219, 0.00015855095169215903, 0.5263157894736842,
                                           6234.374999999998, 0.002418407200366047, 0.05701200703150072,
                                           0.00017241054780158004)
    problem = ContactStep(laws, np.array([[D]]), y_free=np.array([y_free]), z_c=np.array([z_c]),
                          v_c=np.array([v_c]), x_pred=np.array([x_pred]), af=af, sV=sV)
    newton = ContactNewton()
    y, lam = newton.solve(problem, problem.y_free.copy(), 0.0)
    assert newton.fallbacks == 0 and newton.iterations <= 3
    # the exact root on the contact branch z = z_c + a_f y > d: y = y_free - D k (z_c + a_f y - d) / a_f
    exact = (y_free - D * 1e6 * (z_c - 2.5e-3) / af) / (1 + D * 1e6)
    assert abs(y[0] - exact) <= 1e-12 * abs(exact)
    assert lam[0] < 0 and abs(y[0] - y_free - D * lam[0]) < 1e-15


def test_a_step_size_change_refactors_once_and_the_last_step_ends_at_t_end():
    with paper_fom(elements=20) as fom:
        whole = simulate_full(fom, IntegratorSettings(t_end=2e-3, dt=1e-4, sample_dt=1e-3))
        cut = simulate_full(fom, IntegratorSettings(t_end=2.05e-3, dt=1e-4, sample_dt=1e-3))
    assert_all(whole.solver["factorizations"] == 1 and whole.solver["steps"] == 20)
    # 20 steps of dt and a last one of dt / 2: two step sizes, two factorizations, no more.
    assert_all(cut.solver["factorizations"] == 2 and cut.solver["steps"] == 21)
    assert_all(abs(cut.time[-1] - 2.05e-3) < 1e-15 and cut.solver["final_time"] == 2.05e-3)


@pytest.mark.parallel
def test_one_and_two_ranks_agree_before_the_first_impact_with_constraints_on_the_rank_boundary():
    # 200 DOFs: rank 0 owns rows 0-99, rank 1 rows 100-199. One stop on each side of the boundary;
    # PETSc's Cholesky on every rank (the default for a beam) and MUMPS on both ranks.
    beam = Beam(elements=100, **PAPER_BEAM)
    x_last = 0.5  # node 50: w at row 99 (v at 0.5 m is row 2 * 50 - 1 for a pinned left end)
    with FullOrderModel.build(beam, [], BaseMotion(amplitude=5e-3, frequency_hz=1.0), probes=[x_last]) as fom:
        row = int(fom.operators.mesh.w_row(x_last))
        lo, hi = fom.operators.K.getOwnershipRange()
    boundary = MPI.COMM_WORLD.bcast(hi if MPI.COMM_WORLD.rank == 0 else None, root=0)
    assert_all(row in (boundary - 1, boundary), (row, boundary))
    stops = [Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=x) for x in (0.49, 0.5, 0.51)]
    settings = IntegratorSettings(t_end=0.05, dt=2e-5, sample_dt=1e-4)
    results = {}
    for ranks, options in (("2", {}), ("2 mumps", {"full_pc_factor_mat_solver_type": "mumps",
                                                   "full_pc_type": "cholesky"}), ("1", {})):
        comm = PETSc.COMM_SELF if ranks == "1" else PETSc.COMM_WORLD
        for k, v in options.items():
            PETSc.Options().setValue(k, v)
        try:
            with paper_fom(constraints=stops, comm=comm) as fom:
                if ranks != "1":
                    rows = fom.constraints.flat_rows
                    assert_all(rows.min() < boundary <= rows.max(), "the stops straddle the rank boundary")
                results[ranks] = simulate_full(fom, settings)
        finally:
            for k in options:
                PETSc.Options().delValue(k)
    assert_all("petsc cholesky on every rank" in results["2"].solver["factorization"])
    assert_all(results["2 mumps"].solver["factorization"] == "mumps cholesky")
    one = results["1"].displacement
    assert_all(np.abs(one).max() < 2.5e-3, "no impact before 0.05 s")
    for ranks in ("2", "2 mumps"):
        error = np.abs(results[ranks].displacement - one).max() / np.abs(one).max()
        assert_all(error < 1e-11, (ranks, error))


def test_a_gyroscopic_matrix_model_whose_g_couples_dofs_k_does_not_is_integrated_exactly(shared_tmp_path):
    # A 3-DOF rotor: K diagonal, G = 300 [[0, 1], [-1, 0]] couples DOFs 0 and 1 outside K's pattern, a
    # constraint on the uncoupled DOF 2 (never reached), a force on DOF 0. PETSc 3.18's own LU in its
    # default ordering factored K_eff wrongly (1.5e-4) and the one constraint row's residual check passed:
    # the reference was 0.4 % off at dt = 1e-4 s and 100 % at 2e-5 s. Independent truth: the linear
    # ODE M u'' + G u' + K u = e_0 sin(Omega t) by scipy's DOP853 at rtol 1e-11. To 0.2 s (3 periods of
    # the lowest mode, one of the force), not 0.5 s: 10^4 steps, where 2.5e4 took 12 s of the 2-rank
    # pass in CI (MUMPS on 3 DOFs, latency-bound); measured 7.5e-7 (1.1e-6 to 0.5 s), and G 0.1 % too
    # large in C + G gives 2.1e-3 (planted); the wrong ordering is refused by the exactness check.
    import h5py
    from scipy.integrate import solve_ivp

    from conftest import write_rotor
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    K = np.diag([1e4, 1.5e4, 2e4])
    G = np.array([[0.0, 300.0, 0.0], [-300.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    write_rotor(shared_tmp_path, K, G, {"rotor.toml": """[integrator]
t_end = 0.2
dt = 2e-5
[output]
probes = [0, 1]
"""})
    out = shared_tmp_path / "rotor.h5"
    run(load_scene(str(shared_tmp_path / "rotor.toml")), str(out), progress=False, method="full")
    MPI.COMM_WORLD.Barrier()
    with h5py.File(out, "r") as f:
        t, w = f["time"][:], f["probes/displacement"][:]
    omega = 2 * np.pi * 5.0

    def rate(t, y):
        return np.concatenate([y[3:], np.array([np.sin(omega * t), 0.0, 0.0]) - K @ y[:3] - G @ y[3:]])

    exact = solve_ivp(rate, (0.0, t[-1]), np.zeros(6), t_eval=t, rtol=1e-11, atol=1e-14, method="DOP853").y[:2].T
    # Measured: 7.5e-7 of the largest |w| (generalized-alpha's second order at dt = 2e-5 s).
    assert np.abs(w - exact).max() < 1e-5 * np.abs(exact).max()


def test_a_factorization_that_is_wrong_away_from_the_constraint_rows_is_an_error():
    from dbf_hpc.errors import SolverError
    from dbf_hpc.fom_integrator import _check_exact_dense

    A = PETSc.Mat().createAIJ((3, 3), nnz=1, comm=PETSc.COMM_SELF)
    for i, value in enumerate((2.0, 3.0, 4.0)):
        A.setValue(i, i, value)
    A.assemble()

    def exact(b, x):
        x.array[:] = b.array_r / np.array([2.0, 3.0, 4.0])

    def wrong(b, x):   # right on row 0 (a constraint row), 1e-4 off on row 2
        exact(b, x)
        x.array[2] *= 1 + 1e-4

    try:
        _check_exact_dense(A, exact, "test")
        with pytest.raises(SolverError, match="is not exact: relative residual .* on a load on every DOF"):
            _check_exact_dense(A, wrong, "test")
    finally:
        A.destroy()


def test_repeated_full_order_runs_leave_no_factor_behind_in_petscs_garbage(capfd):
    # Ownership: the step's K_eff and the start's M were solved through the factor's MatSolve, and the
    # reference to the factor outlived its KSP; petsc4py 3.18 then parks the factor in PETSc's garbage
    # until a collective cleanup: one factored K_eff (and one M) per run of a parameter study. A
    # displaced start (M A0 = -K X0) factors M too.
    from conftest import petsc_garbage
    from dbf_hpc import InitialState

    beam = Beam(elements=20, **PAPER_BEAM)
    stop = Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)
    PETSc.garbage_cleanup()
    for _ in range(2):
        with FullOrderModel.build(beam, [stop], BaseMotion(amplitude=5e-3, frequency_hz=1.0), probes=[0.5],
                                  initial=InitialState(amplitude=1e-3)) as fom:
            simulate_full(fom, IntegratorSettings(t_end=1e-4, dt=1e-5, sample_dt=1e-5))
    assert petsc_garbage(capfd) == 0, "a factored matrix of the run was left in PETSc's garbage"


def test_a_state_beyond_double_precision_ends_the_run_with_its_one_line_and_no_numpy_warning(shared_tmp_path):
    # Red team: a base amplitude of 1e300 m under --method full printed numpy's "RuntimeWarning: overflow
    # encountered in matmul" with its source lines before the one-line error; the state is checked itself.
    # On a matrix model: a beam refuses a support motion longer than itself when it is built. With a stop:
    # its force's square overflowed in the impact statistics before the state did (numpy's warning, red
    # team), now said in the run's one line (stats._check_overflow) or the state's, as here.
    import warnings

    from conftest import twin_chains
    from dbf_hpc.errors import InputError, SolverError
    from dbf_hpc.matrices import MatrixFiles

    twin_chains(shared_tmp_path, copies=1)[0].destroy()
    if MPI.COMM_WORLD.rank == 0:
        np.savetxt(shared_tmp_path / "r.txt", np.ones(10))   # the chain's support moves all its masses
    MPI.COMM_WORLD.Barrier()
    chain = MatrixFiles(str(shared_tmp_path / "K.mtx"), str(shared_tmp_path / "M.mtx"),
                        influence=str(shared_tmp_path / "r.txt"))
    stop = Constraint(law("deadband", clearance=1e-3, k=1e6), dof=3)
    with FullOrderModel.build(chain, [stop], BaseMotion(amplitude=1e300, frequency_hz=1.0)) as fom:
        with warnings.catch_warnings():
            warnings.simplefilter("error")   # a RuntimeWarning would be an exception, not the SolverError
            with pytest.raises(SolverError, match=r"^the state is not finite at t = \S+ s"):
                simulate_full(fom, IntegratorSettings(t_end=1e-4, dt=2e-6, sample_dt=1e-4))
    with pytest.raises(InputError, match=r"^FullOrderModel.build: BaseMotion: amplitude = 1e\+300 m, the support's "
                                         r"motion, is more than the beam's length"):
        paper_fom(excitation=BaseMotion(amplitude=1e300, frequency_hz=1.0))


@pytest.mark.parametrize("t_end, dt", [(1e-200, 1e-4), (1e-300, 1e-300), (1e-100, 1e-100), (1.0, 1e-31)])
def test_a_step_shorter_than_anything_a_structure_does_is_refused_before_any_work(t_end, dt):
    # Red team: t_end = 1e-200 s was an internal ZeroDivisionError (h^2 underflowed), 1e-100 s "the solve with
    # K_eff is not finite: check K, M and C" after a .partial was written
    from dbf_hpc.errors import InputError
    from dbf_hpc.fom_integrator import check_step

    settings = IntegratorSettings(t_end=t_end, dt=dt, sample_dt=t_end)
    with pytest.raises(InputError, match=r"^--method full: a step of .* s \(\[integrator\] dt = .* is below 1e-30 s"):
        check_step(settings)
    with paper_fom() as fom, pytest.raises(InputError, match="is below 1e-30 s"):
        simulate_full(fom, settings)


def test_the_shortest_step_allowed_moves_the_beam_with_its_support_exactly():
    # t_end = dt = 1e-30 s: one step, over which the left support moves 5e-3 sin(2 pi t) ~ pi 1e-32 m and the
    # beam, far too slow to bend, follows as a rigid body pinned at the right: w(x) = (1 - x) Omega(t)
    with paper_fom(probes=(0.5,)) as fom:
        result = simulate_full(fom, IntegratorSettings(t_end=1e-30, dt=1e-30, sample_dt=1e-30))
    omega = 5e-3 * math.sin(2 * math.pi * 1e-30)
    assert_all(abs(result.probes[-1, 0] - 0.5 * omega) < 1e-6 * abs(omega))


@pytest.mark.parametrize("coefficients", [dict(rayleigh_alpha=1e300), dict(rayleigh_beta=1e300)])
def test_a_damping_matrix_beyond_double_precision_is_blamed_on_the_rayleigh_coefficients(coefficients):
    # Red team: rayleigh_alpha or rayleigh_beta = 1e300 under --method full read "check K, M and C for entries
    # that are not finite": K and M are fine, C = alpha M + beta K times the step's shift 1 / dt is not
    from dbf_hpc.damping import Damping
    from dbf_hpc.errors import SolverError

    beam = Beam(elements=20, **PAPER_BEAM)
    constraints = [Constraint(law("deadband", clearance=2.5e-3, k=1e6), x=0.25)]
    with FullOrderModel.build(beam, constraints, BaseMotion(amplitude=5e-3, frequency_hz=1.0),
                              Damping(**coefficients)) as fom:
        with pytest.raises(SolverError, match=r"is not finite: .*\[damping\] rayleigh_alpha and rayleigh_beta$"):
            simulate_full(fom, IntegratorSettings(t_end=1e-3, dt=1e-5, sample_dt=1e-3))


def test_a_contact_problem_that_does_not_converge_names_the_constraint_its_law_and_the_step():
    # Red team: a two-direction support with Coulomb friction far too stiff for the step (mu = 5, v_reg =
    # 1e-6 m/s, k = 1e9 N/m) ended in "reduce [integrator] dt or soften the stops (a smaller k)": neither the
    # constraint, nor its friction, nor the step. The same tube and support with the usual friction runs.
    from dbf_hpc import InitialState
    from dbf_hpc.errors import SolverError

    tube = Beam(length=1.0, E=2e11, I=1e-9, A=1e-4, rho=7800.0, elements=8, planes=2)
    start = InitialState(mode=1, amplitude=1e-3, velocity=1.0)
    settings = IntegratorSettings(t_end=0.02, dt=1e-3, sample_dt=1e-3)
    usual = Constraint(law("circular", clearance=1e-4, k=1e6, mu=0.3), x=0.5)
    with FullOrderModel.build(tube, [usual], initial=start) as fom:
        assert simulate_full(fom, settings).time[-1] == pytest.approx(0.02)
    stiff = Constraint(law("circular", clearance=1e-4, k=1e9, mu=5.0, v_reg=1e-6), x=0.5)
    with FullOrderModel.build(tube, [stiff], initial=start) as fom:
        with pytest.raises(SolverError) as info:
            simulate_full(fom, settings)
    line = str(info.value)
    assert "\n" not in line and "soften the stops" not in line, line
    assert re.match(r"^the contact problem at t = [0-9.e-]+ s did not converge \(200 Gauss-Seidel sweeps after 20 Newton "
                    r"iterations\), constraint 1 \(x = 0.5 m, circular: k = 1e\+09, mu = 5, v_reg = 1e-06\) moving most "
                    r"in the last sweep \([0-9.e-]+ m\): lower \[integrator\] dt \(now 0.001 s\), or check that law's "
                    r"stiffness, damping and friction regularization", line), line


@pytest.mark.parametrize("s", [0.0, 0.13, 0.5, 0.77, 1.0])
def test_samples_between_two_steps_reproduce_any_cubic_and_its_rate_exactly(s):
    # The full-order loop samples between its steps with cubic Hermite weights on (u0, h v0, u1, h v1): exact for
    # every cubic u(t), value and rate. Planted bugs it catches: a wrong coefficient in the value's or the rate's
    # weights (each passed every test of this module: the samples of the other tests land on steps).
    from dbf_hpc.fom_integrator import _hermite

    h, t0 = 0.37, 1.1
    c = np.array([0.3, -1.7, 2.2, 0.9])
    u = lambda t: c[0] + c[1] * t + c[2] * t ** 2 + c[3] * t ** 3            # noqa: E731
    du = lambda t: c[1] + 2 * c[2] * t + 3 * c[3] * t ** 2                   # noqa: E731
    ends = np.array([u(t0), h * du(t0), u(t0 + h), h * du(t0 + h)])
    value, rate = _hermite(s, h)
    assert np.dot(value, ends) == pytest.approx(u(t0 + s * h), rel=1e-13, abs=1e-13)
    # the rate's weights apply to (u0, v0, u1, v1), as the loop's blend uses them
    assert np.dot(rate, [u(t0), du(t0), u(t0 + h), du(t0 + h)]) == pytest.approx(du(t0 + s * h), rel=1e-12)
