"""Independent exact references for the pinned-pinned beam of Brake & Segalman (2011).

Nothing here imports dbf_hpc: these are closed forms and transcendental equations, solved with
numpy/scipy only, so the code under test can be checked against them.  SI units throughout.

Beam: rho A w_tt + EI w_xxxx = 0 on 0 < x < L, pinned at both ends (w = w_xx = 0), optionally with a
linear spring k at x = ell (paper Eq. 34), i.e. at ell (paper Eq. 36, with the spring force -k w):

    w, w', w'' continuous,    EI (w'''(ell-) - w'''(ell+)) = k w(ell).

Frequency equation (derivation in `spring_supported_pinned_beam_omegas`), with beta = (rho A omega^2 /
EI)^(1/4), s = L - ell:

    1 + k G(beta) = 0,    G(beta) = [T(beta) - H(beta)] / (2 EI beta^3),
    T = sin(beta ell) sin(beta s) / sin(beta L),    H = sinh(beta ell) sinh(beta s) / sinh(beta L),

where G is the beam's exact dynamic point receptance at ell (G(0) = ell^2 s^2 / (3 EI L), the static
point compliance), and the k -> infinity limit (intermediate pin) is T = H.
"""
import numpy as np
from scipy.optimize import brentq

_EPS = np.finfo(float).eps
_NODE_TOL = 1e-12  # n ell / L this close to an integer: ell is a node of sine mode n


def _T_minus_H(n, delta, ell, L):
    """T - H of the module docstring at beta = n pi / L + delta, overflow-free for any beta > 0.

    sin(beta L) = (-1)^n sin(delta L), so the distance to the pole beta_n keeps full relative accuracy
    (tiny frequency shifts for tiny k are resolved).  H = (1 - e^{-2 beta ell})(1 - e^{-2 beta s}) /
    (2 (1 - e^{-2 beta L})) exactly (ell + s = L) is bounded by 1/2: no cosh/sinh of large arguments.
    T has removable 0/0 points where ell is a node of a sine mode; at an exact 0/0 its limit 0 is used.
    """
    s = L - ell
    beta = n * np.pi / L + delta
    H = 0.5 * np.expm1(-2 * beta * ell) * np.expm1(-2 * beta * s) / -np.expm1(-2 * beta * L)
    den = (-1) ** n * np.sin(delta * L)
    num = np.sin(beta * ell) * np.sin(beta * s)
    T = num / den if den != 0.0 else 0.0
    return T - H


def _is_node(n, ell, L):
    r = n * ell / L
    return abs(r - round(r)) < _NODE_TOL


def _frequencies(EI, rhoA, L, ell, inv_k, count):
    """Lowest `count` omegas for spring 1/inv_k at ell (inv_k = 0: a pin at ell).

    Sine mode n (beta_n = n pi / L) is a pole of G unless ell is a node of it.  G is a sum of
    phi_n(ell)^2 / (omega_n^2 - omega^2), increasing in omega between poles, and G(0) > 0, so 1 + k G = 0
    has exactly one root between consecutive poles and none below the first (interlacing).  The sine modes
    with a node at ell are exact modes for every k.  So each mode index n gives one frequency:
    beta_n itself if ell is a node of mode n, else the root in (beta_n, beta_next pole).  Frequencies from
    indices > N are >= beta_{N+1}, which bounds the search.
    """
    if not 0.0 < ell < L:
        raise ValueError("need 0 < ell < L")
    if count < 1:
        return np.zeros(0)

    def root(n):
        b_n = n * np.pi / L
        if _is_node(n, ell, L):
            return b_n
        m = n + 1
        while _is_node(m, ell, L):
            m += 1

        def h(delta):  # same sign as 1 + k G at beta = b_n + delta; well scaled for k -> 0 and infinity
            q = 2.0 * EI * (b_n + delta) ** 3 * inv_k
            return (q + _T_minus_H(n, delta, ell, L)) / (1.0 + q)

        lo, hi = 1e-280 * b_n, (m - n) * np.pi / L * (1 - 8 * _EPS)
        if h(lo) >= 0.0:  # root indistinguishable from the lower pole
            return b_n
        if h(hi) <= 0.0:  # root within 8 eps of the upper pole (ell nearly a node of mode m)
            return b_n + hi
        return b_n + brentq(h, lo, hi, xtol=1e-300, rtol=4 * _EPS, maxiter=2000)

    betas, N = [], count
    while True:
        betas += [root(n) for n in range(len(betas) + 1, N + 1)]
        found = np.sort(betas)[:count]
        if found[-1] < (N + 1) * np.pi / L:  # no index > N can give a lower frequency
            return np.sqrt(EI / rhoA) * found ** 2
        N *= 2


def spring_supported_pinned_beam_omegas(EI, rhoA, L, ell, k, count=1):
    """Lowest `count` natural frequencies (rad/s) of a pinned-pinned beam with a spring k (N/m) at ell.

    Derivation.  With beta^4 = rho A omega^2 / EI and s = L - ell, the pinned ends are built in:
        w1 = a sin(beta x) + c sinh(beta x)                 (0 <= x <= ell)
        w2 = d sin(beta (L-x)) + e sinh(beta (L-x))         (ell <= x <= L).
    Let A = a sin(beta ell), C = c sinh(beta ell).  Continuity of w and w'' gives A = d sin(beta s),
    C = e sinh(beta s) (so w(ell) = A + C); continuity of w' gives A P + C Q = 0 with
        P = cot(beta ell) + cot(beta s) = sin(beta L) / (sin(beta ell) sin(beta s)),
        Q = coth(beta ell) + coth(beta s) = sinh(beta L) / (sinh(beta ell) sinh(beta s));
    the shear jump EI (w1''' - w2''') = k w(ell) reads EI beta^3 (-A P + C Q) = k (A + C).  Eliminating A:
        2 EI beta^3 = k (1/Q - 1/P),   i.e.   1 + k (T - H) / (2 EI beta^3) = 0,   T = 1/P, H = 1/Q,
    the 4x4 determinant divided by its nonzero factors.  The case C = 0 forces w(ell) = 0 and gives only the
    sine modes with a node at ell (beta = n pi / L with n ell / L an integer), which are modes for every k;
    they are added explicitly.  (T - H)/(2 EI beta^3) is the exact point receptance of the unsupported beam,
    sum_n phi_n(ell)^2 / (omega_n^2 - omega^2): roots interlace with its poles (see `_frequencies`), which
    gives a complete, spurious-free bracketing.  Roots are found with brentq to ~1e-15 relative in beta.
    """
    if k < 0:
        raise ValueError("need k >= 0")
    if k == 0:
        n = np.arange(1, count + 1)
        return np.sqrt(EI / rhoA) * (n * np.pi / L) ** 2
    return _frequencies(EI, rhoA, L, ell, 1.0 / k, count)


def pinned_beam_with_intermediate_pin_omegas(EI, rhoA, L, ell, count):
    """Lowest `count` natural frequencies of a pinned-pinned beam with an extra pin (w = 0) at ell.

    The k -> infinity limit of `spring_supported_pinned_beam_omegas`: with w(ell) = A + C = 0 and slope
    continuity A P + C Q = 0 (notation there), A != 0 needs P = Q, i.e.
        sin(beta ell) sin(beta s) sinh(beta L) = sinh(beta ell) sinh(beta s) sin(beta L),
    plus the sine modes with a node at ell (C = 0); same bracketing as the spring case.
    """
    return _frequencies(EI, rhoA, L, ell, 0.0, count)


def pinned_beam_base_modal_amplitudes(EI, rhoA, L, t, amplitude, frequency_hz, n_modes, zeta=0.0):
    """eta_n(t), shape (len(t), n_modes): relative-coordinate modal amplitudes under support motion.

    Paper Eqs. 26-33: w = u + Omega(t)(1 - x/L), u = sum eta_n phi_n, phi_n = sqrt(2/(rho A L)) sin(n pi x/L),
        eta_n'' + 2 zeta omega_n eta_n' + omega_n^2 eta_n = -Gamma_n Omega''(t) = F_n sin(w t),
    with Omega = a sin(w t), w = 2 pi f, Gamma_n = rho A int phi_n (1 - x/L) dx = sqrt(2 rho A L)/(n pi),
    F_n = Gamma_n a w^2, and eta_n(0) = eta_n'(0) = 0.  Exact solution for 0 <= zeta < 1:
        steady state  X sin(w t) + Y cos(w t),  D = (omega^2 - w^2)^2 + (2 zeta omega w)^2,
                      X = F (omega^2 - w^2) / D,  Y = -2 F zeta omega w / D,
        transient     e^{-zeta omega t} (C1 cos(omega_d t) + C2 sin(omega_d t)),  omega_d = omega sqrt(1-zeta^2),
                      C1 = -Y,  C2 = (zeta omega C1 - w X) / omega_d.
    For zeta = 0 the same solution F (sin(w t) - (w/omega) sin(omega t)) / (omega^2 - w^2) is written as
        F/(omega + w) [sin(omega t)/omega - t cos((omega + w) t / 2) sinc((omega - w) t / (2 pi))],
    which is free of cancellation near resonance and gives F (sin - omega t cos)(omega t) / (2 omega^2) at it.
    """
    if not 0.0 <= zeta < 1.0:
        raise ValueError("need 0 <= zeta < 1")
    t = np.atleast_1d(np.asarray(t, float))[:, None]
    n = np.arange(1, n_modes + 1)
    om = np.sqrt(EI / rhoA) * (n * np.pi / L) ** 2
    w = 2 * np.pi * frequency_hz
    F = np.sqrt(2 * rhoA * L) / (n * np.pi) * amplitude * w ** 2
    if zeta == 0.0:
        return F / (om + w) * (np.sin(om * t) / om
                               - t * np.cos(0.5 * (om + w) * t) * np.sinc((om - w) * t / (2 * np.pi)))
    D = (om ** 2 - w ** 2) ** 2 + (2 * zeta * om * w) ** 2
    X = F * (om ** 2 - w ** 2) / D
    Y = -2 * F * zeta * om * w / D
    wd = om * np.sqrt(1 - zeta ** 2)
    C1 = -Y
    C2 = (zeta * om * C1 - w * X) / wd
    return (X * np.sin(w * t) + Y * np.cos(w * t)
            + np.exp(-zeta * om * t) * (C1 * np.cos(wd * t) + C2 * np.sin(wd * t)))


def pinned_beam_base_response(EI, rhoA, L, x, t, amplitude, frequency_hz, n_modes, zeta=0.0):
    """Total displacement w(x, t), shape (len(t), len(x)), of the pinned beam driven at its left support.

    Omega(t) = amplitude sin(2 pi f t) at x = 0, w(L, t) = 0, starting from rest in relative coordinates;
    w = Omega(t)(1 - x/L) + sum_{n <= n_modes} eta_n(t) phi_n(x), eta_n from
    `pinned_beam_base_modal_amplitudes` (paper Eqs. 26-33).
    """
    x = np.atleast_1d(np.asarray(x, float))
    t = np.atleast_1d(np.asarray(t, float))
    eta = pinned_beam_base_modal_amplitudes(EI, rhoA, L, t, amplitude, frequency_hz, n_modes, zeta)
    n = np.arange(1, n_modes + 1)
    phi = np.sqrt(2 / (rhoA * L)) * np.sin(np.outer(n, x) * np.pi / L)  # (n_modes, len(x))
    Omega = amplitude * np.sin(2 * np.pi * frequency_hz * t)
    return np.outer(Omega, 1 - x / L) + eta @ phi


def _beta_l_roots(f, count, first):
    return np.array([brentq(f, (first + j) * np.pi, (first + j + 1) * np.pi, xtol=1e-15, rtol=4 * _EPS)
                     for j in range(count)])


def clamped_free_beta_l(count):
    """First `count` positive roots of cos x cosh x = -1 (cantilever beta L: 1.8751, 4.6941, ...).

    Solved as cos x + 1/cosh x = 0, one root in each ((j-1) pi, j pi), j = 1, 2, ...
    """
    return _beta_l_roots(lambda x: np.cos(x) + 1 / np.cosh(x), count, 0)


def free_free_beta_l(count):
    """First `count` roots x > 0 of cos x cosh x = 1 (free-free beta L: 4.7300, 7.8532, ...).

    Solved as cos x - 1/cosh x = 0, one root in each (j pi, (j+1) pi), j = 1, 2, ...; none in (0, pi].
    """
    return _beta_l_roots(lambda x: np.cos(x) - 1 / np.cosh(x), count, 1)


def clamped_free_timoshenko_first_omega(E, G, kappa, rho, A, I, L):
    """First bending omega (rad/s) of a uniform clamped-free Timoshenko beam (shear deformation and
    rotary inertia), the root of its frequency equation (Huang 1961; Han, Benaroya & Wei 1999, Eq. 52):

        2 + [b^2 (r^2 - s^2)^2 + 2] cosh(b a) cos(b c) - b (r^2 + s^2) / sqrt(1 - b^2 r^2 s^2) sinh(b a) sin(b c) = 0,

    b^2 = rho A L^4 omega^2 / (E I), r^2 = I / (A L^2), s^2 = E I / (kappa G A L^2),
    (a, c) = sqrt((-/+ (r^2 + s^2) + sqrt((r^2 - s^2)^2 + 4 / b^2)) / 2), valid below the second
    spectrum (b r s < 1). It lies below the Euler-Bernoulli value 1.8751^2 sqrt(E I / (rho A L^4)),
    which it approaches as the beam becomes slender (r, s -> 0); on the 1 m x 0.1 m steel bar 81.16 Hz
    against Euler-Bernoulli's 81.80 Hz (a 400-element Timoshenko finite-element beam agrees to 1e-6).
    """
    r2, s2 = I / (A * L**2), E * I / (kappa * G * A * L**2)

    def f(omega):
        b = np.sqrt(rho * A * L**4 * omega**2 / (E * I))
        root = np.sqrt((r2 - s2)**2 + 4 / b**2)
        a, c = np.sqrt((root - (r2 + s2)) / 2), np.sqrt((root + (r2 + s2)) / 2)
        return (2 + (b**2 * (r2 - s2)**2 + 2) * np.cosh(b * a) * np.cos(b * c)
                - b * (r2 + s2) / np.sqrt(1 - b**2 * r2 * s2) * np.sinh(b * a) * np.sin(b * c))

    euler_bernoulli = clamped_free_beta_l(1)[0]**2 * np.sqrt(E * I / (rho * A * L**4))
    return brentq(f, 0.5 * euler_bernoulli, euler_bernoulli, xtol=1e-12, rtol=4 * _EPS)
