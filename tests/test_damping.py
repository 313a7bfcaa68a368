"""Damping descriptions: modal ratios give 2 zeta omega, Rayleigh projects to alpha I + beta K_r."""
import numpy as np
import pytest

from dbf_hpc.damping import Damping
from dbf_hpc.errors import InputError


def test_modal_ratio_gives_two_zeta_omega_on_every_basis_vector():
    omega = np.array([1.7, 6.8, 15.4])
    np.testing.assert_allclose(Damping(zeta=0.02).modal_coefficients(omega), 2 * 0.02 * omega)
    np.testing.assert_allclose(Damping(zeta=(0.01, 0.02, 0.03)).modal_coefficients(omega),
                               2 * np.array([0.01, 0.02, 0.03]) * omega)


def test_modal_damping_of_a_dbf_uses_its_hat_omega():
    # Reduced stiffness with a coupled DBF block: diag gives omega_i^2 (hat-omega^2 for the DBF, Eq. 41).
    Kr = np.array([[4.0, 0.0, 0.0], [0.0, 9.0, 1.0], [0.0, 1.0, 100.0]])
    np.testing.assert_allclose(np.diag(Damping(zeta=0.05).reduced_matrix(Kr)), 2 * 0.05 * np.array([2, 3, 10]))


def test_rayleigh_damping_projects_exactly_onto_an_m_orthonormal_basis():
    Kr = np.array([[4.0, 0.5], [0.5, 9.0]])
    d = Damping(rayleigh_alpha=0.3, rayleigh_beta=1e-3)
    np.testing.assert_allclose(d.reduced_matrix(Kr), 0.3 * np.eye(2) + 1e-3 * Kr)
    # each mode's ratio: zeta = alpha / (2 omega) + beta omega / 2
    omega = np.array([2.0, 30.0])
    np.testing.assert_allclose(d.modal_coefficients(omega) / (2 * omega), 0.3 / (2 * omega) + 1e-3 * omega / 2)


def test_no_damping_is_zero():
    assert Damping().kind == "none"
    assert not Damping().reduced_matrix(np.diag([1.0, 4.0])).any()


@pytest.mark.parametrize("kwargs,word", [(dict(zeta=-0.1), "zeta"), (dict(rayleigh_beta=-1.0), "rayleigh_beta"),
                                         (dict(zeta=0.01, rayleigh_alpha=0.1), "not both")])
def test_bad_damping_is_a_clear_error(kwargs, word):
    with pytest.raises(InputError, match=word):
        Damping(**kwargs)


def test_per_vector_ratios_must_match_the_basis_size():
    with pytest.raises(InputError, match="2 ratios for 3 basis vectors"):
        Damping(zeta=(0.01, 0.02)).modal_coefficients(np.ones(3))


def test_one_repeated_frequency_takes_one_ratio_as_its_modes_are_any_mix_of_its_directions():
    # Red team: on a tube of two planes, zeta = [0.05, 0, ...] damped the z mix of mode 1 and not the y.
    omega = np.array([10.0, 10.0 * (1 + 1e-12), 40.0])
    with pytest.raises(InputError, match="basis vectors 1 and 2 share the frequency .* give them one ratio"):
        Damping(zeta=(0.05, 0.0, 0.0)).modal_coefficients(omega)
    np.testing.assert_allclose(Damping(zeta=(0.05, 0.05, 0.0)).modal_coefficients(omega),
                               [1.0, 1.0 * (1 + 1e-12), 0.0])
    # enrichment columns are no mix of a repeated mode: two DBFs of symmetric stops share hat-omega
    np.testing.assert_allclose(Damping(zeta=(0.05, 0.05, 0.0, 0.1)).modal_coefficients(
        np.array([10.0, 10.0, 40.0, 40.0]), modes=2), [1.0, 1.0, 0.0, 8.0])


@pytest.mark.parametrize("kwargs", [dict(zeta="a"), dict(zeta=None), dict(zeta=True), dict(zeta=[[0.1]]),
                                    dict(zeta=()), dict(zeta=(0.01, "b")), dict(zeta=float("inf")),
                                    dict(rayleigh_alpha="x"), dict(rayleigh_alpha=None), dict(rayleigh_beta=True),
                                    dict(rayleigh_beta=float("nan"))])
def test_a_damping_that_is_not_a_non_negative_number_is_one_input_error_not_a_numpy_traceback(kwargs):
    # a ratio or coefficient is a physical number (1, 1/s, s); a string, a bool or a nested list has no meaning
    with pytest.raises(InputError, match="damping (zeta|rayleigh_alpha|rayleigh_beta) must be"):
        Damping(**kwargs)


def test_integer_and_numpy_ratios_are_numbers():
    omega = np.array([2.0, 5.0])
    np.testing.assert_allclose(Damping(zeta=(1, np.float64(0.5))).modal_coefficients(omega), 2 * np.array([1, 0.5]) * omega)
    np.testing.assert_allclose(Damping(rayleigh_alpha=np.float32(0.5)).modal_coefficients(omega), 0.5)


def test_a_modal_ratio_far_above_critical_is_refused_at_the_edge_not_as_an_integrator_failure():
    # Red team: zeta = 1e300 overflowed 2 zeta omega and ended as "integration stopped: reduce dt"
    for zeta in (1e300, (0.01, 1e3)):
        with pytest.raises(InputError, match="give ratios of at most 100"):
            Damping(zeta=zeta)
    assert Damping(zeta=100.0).kind == "modal"     # strongly overdamped modes stay possible


def test_rayleigh_coefficients_that_damp_a_reference_mode_far_above_critical_are_refused():
    omega = np.array([0.0, 10.0, 1000.0])      # a rigid-body mode takes no ratio
    Damping(rayleigh_alpha=1000.0, rayleigh_beta=0.1).check_rayleigh(omega)   # ratios 50 and 50: kept
    for kwargs in (dict(rayleigh_alpha=1e300), dict(rayleigh_beta=1e300), dict(rayleigh_alpha=2001.0)):
        with pytest.raises(InputError, match="damping ratio of .* at most 100"):
            Damping(**kwargs).check_rayleigh(omega)


@pytest.mark.parametrize("gap, one", [(0.4e-6, True), (0.6e-6, False)])
def test_damping_takes_a_frequency_as_repeated_exactly_where_the_reference_modes_do(gap, one):
    # relative gap in omega: 0.4e-6 is 0.8e-6 in lambda (one repeated frequency for modes.whole_count, one
    # ratio), 0.6e-6 is 1.2e-6 (two frequencies, two ratios); the check was 1e-6 in omega and refused both
    from dbf_hpc.modes import whole_count

    omega = np.array([10.0, 10.0 * (1 + gap), 40.0])
    assert whole_count(omega ** 2, 1) == (2 if one else 1)
    damping = Damping(zeta=(0.05, 0.0, 0.0))
    if one:
        with pytest.raises(InputError, match="basis vectors 1 and 2 share the frequency"):
            damping.modal_coefficients(omega)
    else:
        np.testing.assert_allclose(damping.modal_coefficients(omega), [1.0, 0.0, 0.0])


def test_rayleigh_damping_projects_exactly_onto_a_basis_that_is_not_m_orthonormal():
    # V^T (alpha M + beta K) V = alpha V^T M V + beta V^T K V for any V (a gyroscopic basis of the real and
    # imaginary parts of complex modes is not M-orthonormal). Planted bug it catches: reduced_matrix taking
    # I for the reduced mass even when it is given.
    rng = np.random.default_rng(5)
    n, r = 12, 4
    A = rng.standard_normal((n, n))
    M = A @ A.T + n * np.eye(n)
    B = rng.standard_normal((n, n))
    K = 1e3 * (B @ B.T + np.eye(n))
    V = rng.standard_normal((n, r))
    alpha, beta = 0.7, 2e-4
    C = alpha * M + beta * K
    np.testing.assert_allclose(Damping(rayleigh_alpha=alpha, rayleigh_beta=beta).reduced_matrix(V.T @ K @ V, V.T @ M @ V),
                               V.T @ C @ V, rtol=1e-12, atol=1e-12 * np.abs(V.T @ C @ V).max())
