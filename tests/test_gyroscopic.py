"""Gyroscopic continua (issue 19): axially moving beams and strings, pipes conveying fluid, against
closed forms and an independent Galerkin solution; their complex modes (gyroscopic.py), stability,
and the full-order reference with G. Serial and on 2 ranks (every number compared is the same on
every rank: the eigenvalues and the run's samples are collective results)."""
import numpy as np
import pytest
import scipy.io
import scipy.sparse
from mpi4py import MPI
from petsc4py import PETSc

from dbf_hpc.errors import InputError
from dbf_hpc.gyroscopic import gyroscopic_modes
from dbf_hpc.modes import reference_modes
from dbf_hpc.structure import Beam, assemble_beam

L, E, I, A, RHO = 1.0, 2e11, 1e-8, 1e-4, 7800.0
EI, RHOA = E * I, RHO * A


def complex_frequencies(beam, count):
    ops = assemble_beam(beam)
    try:
        modes = gyroscopic_modes(ops, count=count)
        values, unstable = modes.eigenvalues.copy(), modes.unstable
        modes.destroy()
    finally:
        ops.destroy()
    return values, unstable


def galerkin_sine(beam, terms=40):
    """Eigenvalues (Im > 0, ascending) of the pinned-pinned operator by `terms` sine modes, numpy only:
    M = rho A L/2 I, G_jk = 2 m_t U k pi int_0^1 sin(j pi s) cos(k pi s) ds, K = L/2 (EI k^4 pi^4 / L^4 +
    (T - m_t U^2) k^2 pi^2 / L^2) on the diagonal."""
    k = np.arange(1, terms + 1, dtype=float)
    j = k[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.where(j == k, 0.0, j * (1 - (-1.0) ** (j + k)) / (np.pi * (j**2 - k**2)))
    M = np.eye(terms) * beam.rhoA * beam.length / 2
    G = 2 * beam.m_t * beam.axial_speed * k[None, :] * np.pi * c
    K = np.diag(beam.length / 2 * (beam.EI * (k * np.pi / beam.length) ** 4
                                   + beam.axial_force * (k * np.pi / beam.length) ** 2))
    Minv = np.linalg.inv(M)
    state = np.block([[np.zeros((terms, terms)), np.eye(terms)], [-Minv @ K, -Minv @ G]])
    lam = np.linalg.eigvals(state)
    return np.sort(lam[lam.imag > 0].imag)


def test_travelling_string_frequencies_are_n_pi_c_over_l_times_one_minus_v2_over_c2():
    # omega_n = (n pi c / L)(1 - v^2 / c^2), c = sqrt(T / rho A), m_t = rho A; EI -> 0 (EI n^2 pi^2 / T ~ 1e-10).
    T, rhoA, v = 100.0, 1.0, 4.0
    c = np.sqrt(T / rhoA)
    string = Beam(length=L, E=1e3, I=1e-12, A=1e-3, rho=1000.0, elements=200, axial_speed=v, tension=T)
    values, unstable = complex_frequencies(string, 4)
    n = np.arange(1, 5)
    exact = n * np.pi * c / L * (1 - v**2 / c**2)
    assert not unstable and np.all(np.abs(values.real) < 1e-8 * np.abs(values))
    assert np.max(np.abs(values.imag / exact - 1)) < 1e-7


@pytest.mark.parametrize("u", [1.0, 2.0, 3.0])
def test_pinned_pinned_pipe_frequencies_agree_with_a_converged_sine_galerkin_solution(u):
    # u = U L sqrt(m_t / EI); half the mass is the transported fluid (beta = 0.5).
    m_t = 0.5 * RHOA
    pipe = Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=100, transported_mass=m_t,
                axial_speed=u / L * np.sqrt(EI / m_t))
    values, unstable = complex_frequencies(pipe, 3)
    reference = galerkin_sine(pipe, 120)[:3]
    assert not unstable
    # Measured: 60 sine terms agree with 120 to 2e-9 (converged); 100 Hermite elements with them to 7e-8.
    assert np.max(np.abs(galerkin_sine(pipe, 60)[:3] / reference - 1)) < 1e-8
    assert np.max(np.abs(values.imag / reference - 1)) < 3e-7


def test_pinned_pinned_pipe_diverges_at_u_equal_pi_where_the_first_frequency_falls_to_zero():
    m_t = 0.5 * RHOA
    omega_0 = np.pi**2 * np.sqrt(EI / (RHOA * L**4))

    def pipe(u):
        return Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=100, transported_mass=m_t,
                    axial_speed=u / L * np.sqrt(EI / m_t))

    # Within ~1e-4 of u = pi, K (factored for the shift about 0) is so near singular that the backward
    # error check refuses the pairs; at 1e-3 omega_1 ~ sqrt(2e-3) omega_0.
    below, unstable_below = complex_frequencies(pipe(np.pi * (1 - 1e-3)), 2)
    above, unstable_above = complex_frequencies(pipe(np.pi * (1 + 1e-3)), 2)
    assert not unstable_below and 0 < below[0].imag < 0.1 * omega_0
    assert unstable_above == [0] and above[0].imag == 0 and above[0].real > 0
    assert above[1].imag > 0.5 * omega_0   # the second mode is still an oscillation


def test_axially_moving_beam_critical_speed_is_rho_a_vc2_equal_t_plus_ei_pi2_over_l2():
    T = 500.0
    v_c = np.sqrt((T + EI * np.pi**2 / L**2) / RHOA)
    for factor, diverges in ((1 - 1e-3, False), (1 + 1e-3, True)):
        beam = Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=100, tension=T, axial_speed=factor * v_c)
        _, unstable = complex_frequencies(beam, 2)
        assert (unstable == [0]) == diverges, factor


def test_without_transport_the_matrices_are_unchanged_and_there_is_no_g(comm):
    plain = assemble_beam(Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=30))
    zero = assemble_beam(Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=30, axial_speed=0.0, tension=0.0,
                              transported_mass=2.0))
    try:
        assert zero.G is None
        for a, b in ((plain.K, zero.K), (plain.M, zero.M)):
            same = all(np.array_equal(x, y) for x, y in zip(a.getValuesCSR(), b.getValuesCSR()))
            assert MPI.COMM_WORLD.allreduce(same, op=MPI.LAND)
    finally:
        plain.destroy()
        zero.destroy()


def test_with_a_zero_g_the_complex_modes_are_the_real_reference_modes():
    ops = assemble_beam(Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=60, tension=300.0))
    try:
        ops.G = ops.K.duplicate(copy=False)    # the same pattern, all zeros
        ops.G.zeroEntries()
        modes = gyroscopic_modes(ops, count=4)
        real = reference_modes(ops, count=4)
        assert np.max(np.abs(modes.omega / real.omega - 1)) < 1e-9 and not modes.unstable
        modes.destroy()
        real.destroy()
    finally:
        ops.destroy()


def test_g_is_skew_symmetric_and_the_transport_softens_k(comm):
    beam = Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=20, axial_speed=50.0, tension=100.0)
    ops = assemble_beam(beam)
    still = assemble_beam(Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=20, tension=100.0 - RHOA * 50.0**2))
    try:
        Gt = ops.G.transpose(PETSc.Mat())
        Gt.axpy(1.0, ops.G)
        assert Gt.norm() == 0.0 and ops.G.norm() > 0
        Gt.destroy()
        D = ops.K.duplicate(copy=True)
        D.axpy(-1.0, still.K)
        assert D.norm() <= 1e-13 * ops.K.norm()   # K depends on T - m_t U^2 only
        D.destroy()
    finally:
        ops.destroy()
        still.destroy()


def test_a_matrix_model_takes_a_skew_gyroscopic_matrix_and_refuses_one_that_is_not(shared_tmp_path):
    from dbf_hpc.matrices import MatrixFiles, load_operators

    K = scipy.sparse.diags([2.0, 3.0, 4.0]).tocsr()
    M = scipy.sparse.identity(3, format="csr")
    G = scipy.sparse.csr_matrix(np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.5], [0.0, -0.5, 0.0]]))
    paths = {name: str(shared_tmp_path / f"{name}.mtx") for name in ("K", "M", "G", "bad")}
    if MPI.COMM_WORLD.rank == 0:
        for name, mat in (("K", K), ("M", M), ("G", G), ("bad", abs(G))):
            scipy.io.mmwrite(paths[name], mat, precision=17, symmetry="general")
    MPI.COMM_WORLD.Barrier()
    ops = load_operators(MatrixFiles(paths["K"], paths["M"], gyroscopic=paths["G"]))
    try:
        modes = gyroscopic_modes(ops, count=3)
        # Independent: the companion linearization in numpy.
        state = np.block([[np.zeros((3, 3)), np.eye(3)], [-K.toarray(), -G.toarray()]])
        lam = np.linalg.eigvals(state)
        assert np.allclose(modes.omega, np.sort(lam[lam.imag > 0].imag), rtol=1e-10)
        modes.destroy()
    finally:
        ops.destroy()
    with pytest.raises(InputError, match="not skew-symmetric"):
        load_operators(MatrixFiles(paths["K"], paths["M"], gyroscopic=paths["bad"]))


def moving_fom(speed, mode=1, elements=60, tension=100.0):
    from dbf_hpc.excitation import NoExcitation
    from dbf_hpc.fom import FullOrderModel, InitialState

    beam = Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=elements, axial_speed=speed, tension=tension)
    return FullOrderModel.build(beam, (), NoExcitation(), probes=(0.25,),
                                initial=InitialState(mode=mode, amplitude=1e-3))


def full_free_vibration(fom, omega, periods=3, per_period=2000):
    from dbf_hpc.simulate import simulate_full
    from dbf_hpc.timestepping import IntegratorSettings

    T = 2 * np.pi / omega
    return simulate_full(fom, IntegratorSettings(t_end=periods * T, dt=T / per_period, sample_dt=T / 200))


def test_full_order_model_without_transport_is_unchanged_cholesky_and_the_same_samples():
    results = []
    for keys in ({}, {"axial_speed": 0.0, "tension": 0.0}):
        from dbf_hpc.excitation import NoExcitation
        from dbf_hpc.fom import FullOrderModel, InitialState

        beam = Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=40, **keys)
        with FullOrderModel.build(beam, (), NoExcitation(), probes=(0.25,),
                                  initial=InitialState(mode=1, amplitude=1e-3)) as fom:
            assert fom.velocity_matrix() is None
            results.append(full_free_vibration(fom, 500.0, periods=1, per_period=200))
    assert np.array_equal(results[0].probes, results[1].probes)
    assert "cholesky" in results[0].solver["factorization"]


@pytest.mark.parametrize("mode", [1, 2])
def test_free_vibration_of_a_moving_beam_from_its_complex_mode_oscillates_at_the_gyroscopic_frequency(mode):
    # U = 60 m/s is 0.38 of the critical speed; the frequencies are 5 to 14 % below the beam at rest's.
    with moving_fom(60.0, mode) as fom:
        modes = gyroscopic_modes(fom.operators, count=mode)
        omega = modes.omega[mode - 1]
        modes.destroy()
        result = full_free_vibration(fom, omega)
    t, w = result.time, result.probes[:, 0]
    # A single mode: w at a point is one sinusoid, |x_p| cos(omega t + phi_p) (the start included).
    basis = np.column_stack([np.cos(omega * t), np.sin(omega * t)])
    fit = np.linalg.lstsq(basis, w, rcond=None)[0]
    assert np.abs(basis @ fit - w).max() < 1e-4 * np.abs(w).max()
    up = np.flatnonzero((w[:-1] < 0) & (w[1:] >= 0))
    crossings = t[up] - w[up] * (t[up + 1] - t[up]) / (w[up + 1] - w[up])
    measured = 2 * np.pi / np.mean(np.diff(crossings))
    # Generalized-alpha's period error (omega dt)^2 / 12 = 8e-7 at 2000 steps a period.
    assert abs(measured / omega - 1) < 1e-5
    assert "lu" in result.solver["factorization"] and "cholesky" not in result.solver["factorization"]


def moving_scene(tmp, speed):
    text = f"""
[structure]
kind = "beam"
length = 1.0
elements = 40
E = 2e11
I = 1e-8
A = 1e-4
rho = 7800.0
axial_speed = {speed}
tension = 100.0

[excitation]
kind = "none"

[initial]
amplitude = 1e-3

[basis]
modes = 4
cache = "off"

[integrator]
t_end = 0.002

[output]
probes = [0.5]
"""
    path = tmp / f"moving_{speed}.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(text)
    MPI.COMM_WORLD.Barrier()
    return str(path)


def test_run_refuses_above_the_critical_speed_naming_the_mode_and_the_speed(shared_tmp_path):
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    scene = load_scene(moving_scene(shared_tmp_path, 200.0))   # u = 3.96 > pi
    for method in ("full", "rom"):
        with pytest.raises(InputError, match=r"unstable at axial speed 200 m/s: mode 1 is unstable \(divergence"):
            run(scene, str(shared_tmp_path / "unstable.h5"), progress=False, method=method)
        assert not (shared_tmp_path / "unstable.h5").exists()


def test_the_reduced_gyroscopic_model_is_refused_in_one_line_and_full_runs(shared_tmp_path):
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    scene = load_scene(moving_scene(shared_tmp_path, 30.0))
    with pytest.raises(InputError, match="reduced model of a gyroscopic structure .* not built yet.*--method full"):
        run(scene, str(shared_tmp_path / "rom.h5"), progress=False, method="rom")
    summary = run(scene, str(shared_tmp_path / "full.h5"), progress=False, method="full")
    assert summary is not None


def test_an_axially_moving_beam_needs_w_fixed_at_both_ends():
    with pytest.raises(InputError, match="needs w fixed at both ends"):
        Beam(length=L, E=E, I=I, A=A, rho=RHO, left="clamped", right="free", axial_speed=1.0)


def test_the_reduced_basis_of_a_gyroscopic_structure_is_refused_in_one_line():
    from dbf_hpc.basis import build_basis

    ops = assemble_beam(Beam(length=L, E=E, I=I, A=A, rho=RHO, elements=20, axial_speed=10.0))
    try:
        with pytest.raises(InputError, match="reduced basis of a gyroscopic structure .* not built yet"):
            build_basis(ops, [3])
    finally:
        ops.destroy()


@pytest.mark.parametrize("keys, message", [
    ('kind = "matrices"\nstiffness = "K.mtx"\nmass = "M.mtx"\naxial_speed = 3.0', "apply to a beam"),
    ('kind = "beam"\nlength = 1.0\nE = 2e11\nI = 1e-8\nA = 1e-4\nrho = 7800.0\ngyroscopic = "G.mtx"',
     "is for kind"),
    ('kind = "beam"\nlength = 1.0\nE = 2e11\nI = 1e-8\nA = 1e-4\nrho = 7800.0\nright = "free"\naxial_speed = 1.0',
     "needs w fixed at both ends"),
], ids=["speed-on-matrices", "g-on-a-beam", "free-end"])
def test_scene_keys_of_axial_transport_are_checked_in_one_line(shared_tmp_path, keys, message):
    from dbf_hpc.scene import load_scene

    path = shared_tmp_path / "keys.toml"
    if MPI.COMM_WORLD.rank == 0:
        path.write_text(f"[structure]\n{keys}\n\n[excitation]\nkind = \"none\"\n")
    MPI.COMM_WORLD.Barrier()
    with pytest.raises(InputError, match=message):
        load_scene(str(path))
