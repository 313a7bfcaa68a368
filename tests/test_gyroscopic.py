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
