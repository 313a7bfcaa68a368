"""Checks of the independent references in tests/exact.py themselves (no dbf_hpc involved)."""
import numpy as np
import pytest
from scipy.linalg import eigh, svdvals

import exact

# Closed forms and numpy/scipy only, no MPI: each rank of the 2-rank pass computed the same numbers
# (about 25 s of that pass measured under load, its 2000 x 2000 eigenproblems on both ranks at once).
pytestmark = pytest.mark.serial

# The paper's Table 1 beam (SI).
E, I, A, RHO, L = 117e9, 0.000878e-12, 0.29e-6, 11800.0, 1.0
EI, RHOA = E * I, RHO * A
C = np.sqrt(EI / RHOA)  # omega = C beta^2
AMP, FREQ = 5e-3, 1.0


def sine_omegas(n):
    return C * (np.asarray(n) * np.pi / L) ** 2


def spring(ell, k, count=6):
    return exact.spring_supported_pinned_beam_omegas(EI, RHOA, L, ell, k, count)


def rayleigh_ritz(ell, k, count, modes=2000):
    """Ritz values with `modes` sine modes: K = diag(omega_i^2) + k phi(ell) phi(ell)^T, M = I.

    Solved as the largest eigenvalues of K^{-1} (Sherman-Morrison), so the low eigenvalues keep full
    relative accuracy despite ||K|| ~ omega_2000^2.
    """
    n = np.arange(1, modes + 1)
    d = sine_omegas(n) ** 2
    v = np.sqrt(2 / (RHOA * L)) * np.sin(n * np.pi * ell / L)
    u = v / d
    flex = np.diag(1 / d) - k * np.outer(u, u) / (1 + k * v @ u)
    mu = eigh(flex, eigvals_only=True, subset_by_index=[modes - count, modes - 1])
    return np.sqrt(np.sort(1 / mu))


def interface_matrix(beta, ell, k):
    """The 4x4 system for (a, c cosh(beta ell), d, e cosh(beta s)) of w1 = a sin + c sinh (x),
    w2 = d sin + e sinh (L - x): rows w, w'/beta, w''/beta^2 continuity and the scaled shear jump
    [EI (w1''' - w2''') - k w(ell)] / (EI beta^3 + k)."""
    s = L - ell
    sl, cl, ss, cs = np.sin(beta * ell), np.cos(beta * ell), np.sin(beta * s), np.cos(beta * s)
    tl, ts = np.tanh(beta * ell), np.tanh(beta * s)
    q = EI * beta ** 3
    return np.array([
        [sl, tl, -ss, -ts],
        [cl, 1.0, cs, 1.0],
        [-sl, tl, ss, -ts],
        [(-q * cl - k * sl) / (q + k), (q - k * tl) / (q + k), -q * cs / (q + k), q / (q + k)],
    ])


def test_spring_frequencies_tend_to_sine_frequencies_as_k_to_zero():
    n = np.arange(1, 7)
    np.testing.assert_allclose(spring(0.25, 1e-12), sine_omegas(n), rtol=1e-9)  # shift ~5e-11
    # second-order perturbation: omega^2 = omega_n^2 + k v_n^2 (1 - k S_n), v = phi(ell),
    # S_n = sum_{m != n} v_m^2 / (omega_m^2 - omega_n^2)  (20000 modes)
    k, ell = 1e-6, 0.3
    m = np.arange(1, 20001)
    v2 = 2 / (RHOA * L) * np.sin(m * np.pi * ell / L) ** 2
    lam = sine_omegas(m) ** 2
    S = np.array([np.sum(np.delete(v2, j) / (np.delete(lam, j) - lam[j])) for j in n - 1])
    shift = spring(ell, k) ** 2 - lam[:6]
    np.testing.assert_allclose(shift, k * v2[:6] * (1 - k * S), rtol=1e-7)


@pytest.mark.parametrize("ell", [0.15, 0.25, 0.5, 0.7])
def test_spring_frequencies_tend_to_intermediate_pin_as_k_to_infinity(ell):
    pin = exact.pinned_beam_with_intermediate_pin_omegas(EI, RHOA, L, ell, 6)
    np.testing.assert_allclose(spring(ell, 1e12), pin, rtol=1e-9)
    np.testing.assert_allclose(spring(ell, 1e6), pin, rtol=1e-3)
    assert np.all(spring(ell, 1e6) <= pin)


def test_intermediate_pin_at_midspan_gives_half_beam_pinned_pinned_and_pinned_clamped_modes():
    # antisymmetric: pinned-pinned half spans, beta L/2 = j pi; symmetric: pinned-clamped, tan x = tanh x
    from scipy.optimize import brentq
    x = [brentq(lambda x: np.sin(x) - np.cos(x) * np.tanh(x), j * np.pi, (j + 0.5) * np.pi, xtol=1e-15)
         for j in range(1, 4)]
    half = np.sort(np.concatenate([np.arange(1, 4) * np.pi, x])) * 2 / L
    pin = exact.pinned_beam_with_intermediate_pin_omegas(EI, RHOA, L, 0.5, 6)
    np.testing.assert_allclose(pin, C * half ** 2, rtol=1e-13)


@pytest.mark.parametrize("ell", [0.15, 0.25, 0.25 + 1e-9, 0.3, 0.5])
@pytest.mark.parametrize("k", [1e-6, 1e-2, 0.1, 1.0, 1e2, 1e6, 1e12])
def test_spring_frequencies_are_roots_of_the_4x4_interface_determinant(ell, k):
    for omega in spring(ell, k, 8):
        beta = np.sqrt(omega / C)
        sv = svdvals(interface_matrix(beta, ell, k))
        assert sv[-1] < 1e-12 * sv[0]


@pytest.mark.parametrize("ell", [0.15, 0.25, 0.5])
@pytest.mark.parametrize("k", [1e-2, 0.1, 1.0, 1e2])
def test_spring_frequencies_match_rayleigh_ritz_with_2000_sine_modes_from_above(ell, k):
    ex, rr = spring(ell, k, 6), rayleigh_ritz(ell, k, 6)
    assert np.all(rr >= ex * (1 - 1e-13))
    np.testing.assert_allclose(rr, ex, rtol=1e-8)


def test_mode_4_frequency_at_quarter_span_is_independent_of_k_node_of_mode_4():
    w4 = sine_omegas(4)
    for k in np.logspace(-6, 12, 19):
        om = spring(0.25, k, 8)
        hits = np.abs(om / w4 - 1) < 1e-14
        assert hits.sum() == 1  # present once, never duplicated
        assert np.all(np.diff(om) > 0)


def test_even_mode_frequencies_at_midspan_are_independent_of_k_and_none_missed():
    for k in [1e-6, 0.1, 1e3, 1e12]:
        om = spring(0.5, k, 8)
        for n in (2, 4, 6):
            assert np.sum(np.abs(om / sine_omegas(n) - 1) < 1e-14) == 1
        np.testing.assert_allclose(om[:6], rayleigh_ritz(0.5, k, 6), rtol=1e-6)


def test_frequencies_are_continuous_in_ell_through_a_node_of_mode_4():
    for k in [1e-2, 1.0, 1e6]:
        for d in [1e-9, -1e-9, 1e-6]:
            np.testing.assert_allclose(spring(0.25 + d, k, 8), spring(0.25, k, 8), rtol=50 * abs(d))


def test_omega_1_increases_monotonically_with_k():
    om1 = np.array([spring(0.25, k, 1)[0] for k in np.logspace(-6, 12, 73)])
    assert np.all(np.diff(om1) >= 0)
    assert np.all(np.diff(om1[:50]) > 0)
    assert sine_omegas(1) < om1[0] and om1[-1] <= exact.pinned_beam_with_intermediate_pin_omegas(
        EI, RHOA, L, 0.25, 1)[0]


def test_spring_frequencies_are_well_defined_for_high_modes_without_overflow():
    om = spring(0.3, 1e3, 25)  # beta L up to ~80
    assert np.all(np.isfinite(om)) and np.all(np.diff(om) > 0)
    for omega in om:
        beta = np.sqrt(omega / C)
        sv = svdvals(interface_matrix(beta, 0.3, 1e3))
        assert sv[-1] < 1e-11 * sv[0]


# ---- support-driven response (paper Eqs. 26-33) ----

def eta(t, zeta=0.0, n_modes=6, freq=FREQ):
    return exact.pinned_beam_base_modal_amplitudes(EI, RHOA, L, t, AMP, freq, n_modes, zeta)


@pytest.mark.parametrize("zeta,freq", [(0.0, FREQ), (0.05, FREQ), (0.0, sine_omegas(2) / (2 * np.pi)),
                                       (0.3, 3.0)])
def test_base_modal_amplitudes_satisfy_their_ode(zeta, freq):
    n = np.arange(1, 7)
    om = sine_omegas(n)
    w = 2 * np.pi * freq
    gamma = np.sqrt(2 * RHOA * L) / (n * np.pi)
    t = np.linspace(0.0, 10.0, 23)[:, None]
    h = 0.02 / np.maximum(om, w)  # 4th-order central differences, per mode
    e = {j: np.stack([eta(ti + j * h, zeta, freq=freq)[np.arange(6), n - 1] for ti in t[:, 0]])
         for j in (-2, -1, 0, 1, 2)}  # e[j][i, m] = eta_m(t_i + j h_m)
    d1 = (-e[2] + 8 * e[1] - 8 * e[-1] + e[-2]) / (12 * h)
    d2 = (-e[2] + 16 * e[1] - 30 * e[0] + 16 * e[-1] - e[-2]) / (12 * h ** 2)
    omega_dd = -AMP * w ** 2 * np.sin(w * t)  # Omega''
    residual = d2 + 2 * zeta * om * d1 + om ** 2 * e[0] + gamma * omega_dd
    scale = gamma * AMP * w ** 2 * (1 + w * t)  # forcing (and resonant growth) scale
    assert np.max(np.abs(residual) / scale) < 1e-7


@pytest.mark.parametrize("zeta", [0.0, 0.05, 0.3])
def test_base_modal_amplitudes_start_from_rest(zeta):
    om = sine_omegas(np.arange(1, 7))
    h = 1e-6
    scale = np.sqrt(2 * RHOA * L) / np.pi * AMP * (2 * np.pi * FREQ) ** 2 / om  # F / omega
    assert np.max(np.abs(eta([0.0], zeta)) * om / scale) < 1e-14
    v0 = (eta([h], zeta) - eta([-h], zeta)) / (2 * h)
    assert np.max(np.abs(v0) / scale) < 1e-9


def test_undamped_solution_agrees_with_damped_formula_as_zeta_to_zero():
    t = np.linspace(0, 10, 101)
    np.testing.assert_allclose(eta(t, 1e-12), eta(t, 0.0), atol=1e-9 * np.abs(eta(t)).max())


@pytest.mark.parametrize("zeta", [0.0, 0.05])
def test_total_displacement_equals_support_motion_at_x_0_and_zero_at_x_L(zeta):
    t = np.linspace(0, 10, 201)
    w = exact.pinned_beam_base_response(EI, RHOA, L, [0.0, 0.25, L], t, AMP, FREQ, 20, zeta)
    assert w.shape == (201, 3)
    np.testing.assert_allclose(w[:, 0], AMP * np.sin(2 * np.pi * FREQ * t), rtol=0, atol=1e-15)
    np.testing.assert_allclose(w[:, 2], 0.0, atol=1e-15)
    assert np.max(np.abs(w[:, 1])) > AMP  # the beam responds beyond the rigid motion


def truncation_error_6_vs_200_modes(dt=5e-4):
    """max_t |w_6 - w_200| / max_t |w_200| at x = 0.25 over t in [0, 10] s (Table 1, 5 mm, 1 Hz)."""
    t = np.arange(0.0, 10.0 + dt / 2, dt)
    w6 = exact.pinned_beam_base_response(EI, RHOA, L, [0.25], t, AMP, FREQ, 6)[:, 0]
    w200 = exact.pinned_beam_base_response(EI, RHOA, L, [0.25], t, AMP, FREQ, 200)[:, 0]
    return np.max(np.abs(w6 - w200)) / np.max(np.abs(w200))


def test_six_mode_truncation_error_at_quarter_span_is_about_4e_5_of_peak():
    # measured 4.046e-5 (|w6 - w200| max 1.019 um, peak |w| 25.19 mm at t = 7.743 s)
    err = truncation_error_6_vs_200_modes()
    assert 3.9e-5 < err < 4.2e-5
    # and 200 modes are converged: the 200-vs-400 difference is far smaller
    t = np.linspace(0, 10, 2001)
    w200, w400 = (exact.pinned_beam_base_response(EI, RHOA, L, [0.25], t, AMP, FREQ, n)[:, 0] for n in (200, 400))
    assert np.max(np.abs(w400 - w200)) < 1e-4 * err * np.max(np.abs(w200))


def test_clamped_free_and_free_free_beta_l_roots():
    cf, ff = exact.clamped_free_beta_l(8), exact.free_free_beta_l(8)
    np.testing.assert_allclose(cf[:4], [1.875104069, 4.694091133, 7.854757438, 10.995540735], rtol=1e-9)
    np.testing.assert_allclose(ff[:4], [4.730040745, 7.853204624, 10.995607838, 14.137165491], rtol=1e-9)
    np.testing.assert_allclose(np.cos(cf) + 1 / np.cosh(cf), 0, atol=1e-14)
    np.testing.assert_allclose(np.cos(ff) - 1 / np.cosh(ff), 0, atol=1e-14)
    np.testing.assert_allclose(cf[5:], (np.arange(6, 9) - 0.5) * np.pi, rtol=1e-6)
    np.testing.assert_allclose(ff[5:], (np.arange(6, 9) + 0.5) * np.pi, rtol=1e-6)


def test_the_timoshenko_cantilever_tends_to_euler_bernoulli_when_slender_and_lies_below_it_when_stubby():
    # The frequency equation against its two limits: a slender bar (section 1 mm, L = 1 m) is
    # Euler-Bernoulli's beta L = 1.8751 to 1e-5; the 0.1 m steel bar loses 0.8 % to shear and rotary
    # inertia (81.155 Hz, as a 400-element Timoshenko finite-element beam gives), rigid shear
    # (kappa G -> infinity) keeping only rotary inertia's small share.
    E, G, rho = 200e9, 200e9 / 2.6, 7800.0

    def euler_bernoulli(a):
        return exact.clamped_free_beta_l(1)[0]**2 * np.sqrt(E * a**4 / 12 / (rho * a**2))

    slender = exact.clamped_free_timoshenko_first_omega(E, G, 5 / 6, rho, 1e-6, 1e-12 / 12, 1.0)
    assert slender == pytest.approx(euler_bernoulli(1e-3), rel=1e-5) and slender < euler_bernoulli(1e-3)
    stubby = exact.clamped_free_timoshenko_first_omega(E, G, 5 / 6, rho, 1e-2, 1e-4 / 12, 1.0)
    assert stubby / (2 * np.pi) == pytest.approx(81.1555, abs=1e-3)
    rotary_only = exact.clamped_free_timoshenko_first_omega(E, 1e6 * G, 5 / 6, rho, 1e-2, 1e-4 / 12, 1.0)
    assert stubby < rotary_only < euler_bernoulli(0.1) and euler_bernoulli(0.1) - rotary_only < 0.3 * (
        euler_bernoulli(0.1) - stubby)
