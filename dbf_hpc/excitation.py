"""What drives the structure: support motion Omega(t) and forces F(t) with their spatial shapes.

The descriptions (BaseMotion, PointForce, RandomForce, Turbulence, NoExcitation) are plain values:
what a scene or a Python script asks for. The full-order model turns one into its time functions (Harmonic,
RandomProcess) and, for forces, a load at one DOF or a load vector. In relative coordinates
(paper Eqs. 26-27) support motion loads the structure with -M r Omega''(t) and the laws act on the
total displacement u + r Omega(t).

The descriptions and time functions are plain numpy: nothing here is collective (the full-order
model assembles the loads, fom.py).
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass, field
from typing import Optional

import numpy as np


@dataclass(frozen=True)
class Harmonic:
    """a sin(2 pi f t + phase) and its derivatives. With phase 0, Omega(0) = 0: a run starts with the
    support at rest. A stepped sine continues the phase of the previous step (sweep.py)."""

    amplitude: float = 0.0
    frequency_hz: float = 0.0
    phase: float = 0.0

    def __post_init__(self):
        """Finite numbers, the frequency at least 0 (the API's edge: ReducedModel.with_case takes one).
        Red team: Harmonic(nan, 1.0) as a case's force ran into "reduce [integrator] dt or rtol"."""
        from .errors import check_number

        object.__setattr__(self, "amplitude", check_number("Harmonic amplitude", self.amplitude))
        object.__setattr__(self, "frequency_hz", check_number("Harmonic frequency_hz (Hz)", self.frequency_hz, 0.0))
        object.__setattr__(self, "phase", check_number("Harmonic phase (rad)", self.phase))

    def value(self, t):
        return self.amplitude * np.sin(2 * np.pi * self.frequency_hz * t + self.phase)

    def rate(self, t):
        w = 2 * np.pi * self.frequency_hz
        return self.amplitude * w * np.cos(w * t + self.phase)

    def acceleration(self, t):
        w = 2 * np.pi * self.frequency_hz
        return -self.amplitude * w * w * np.sin(w * t + self.phase)


class RandomProcess:
    """Band-limited random history with a flat one-sided PSD S over [f_low, f_high] (spectral
    representation, Shinozuka): sum_k sqrt(2 S df) cos(2 pi f_k t + phi_k), f_k at the centres of
    `components` equal bins, phi_k uniform from `seed`. Its variance is exactly S (f_high - f_low);
    it is smooth, so adaptive integrators handle it, and the same seed gives the same history."""

    def __init__(self, psd: float, band, seed: int, components: int = 256):
        f_low, f_high = band
        self.band = (float(f_low), float(f_high))
        df = (f_high - f_low) / components
        self.frequency = f_low + (np.arange(components) + 0.5) * df
        self.amplitude = np.full(components, np.sqrt(2 * psd * df))
        self.phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, components)
        self.omega = 2 * np.pi * self.frequency

    def value(self, t):
        t = np.asarray(t, dtype=float)
        return np.cos(np.multiply.outer(t, self.omega) + self.phase) @ self.amplitude


@dataclass(frozen=True)
class NoExcitation:
    """Free vibration from the initial state."""

    kind = "none"


def unit_direction(where: str, direction) -> tuple:
    """(dy, dz) scaled to length 1, or one InputError naming `where`: two finite numbers, not both 0
    (the magnitude of a motion or force is its amplitude; a scene's direction is scaled the same way)."""
    from .errors import InputError, check_number

    if isinstance(direction, (str, bytes)) or not np.iterable(direction) or len(direction) != 2:
        raise InputError(f"{where} must be (dy, dz), two numbers not both 0, got {direction!r}")
    dy, dz = (check_number(where, value) for value in direction)
    norm = float(np.hypot(dy, dz))
    if norm == 0:
        raise InputError(f"{where} must be (dy, dz), two numbers not both 0, got {direction!r}")
    if abs(norm - 1.0) <= 1e-12:   # already unit (a scene's, scaled there): kept bit for bit
        return (dy, dz)
    return (dy / norm, dz / norm)


def _band(name: str, band) -> tuple:
    """(f_low, f_high) in Hz with 0 <= f_low < f_high, or an InputError."""
    from .errors import InputError, check_number

    if isinstance(band, (str, bytes)) or not np.iterable(band) or len(band) != 2:
        raise InputError(f"{name} band must be (f_low, f_high) in Hz, got {band!r}")
    f_low, f_high = (check_number(f"{name} band", f) for f in band)
    if not 0 <= f_low < f_high:
        raise InputError(f"{name} band must be (f_low, f_high) with 0 <= f_low < f_high (Hz), got {band!r}")
    return (f_low, f_high)


# The cosines of one history: each is evaluated at every right-hand side of the integrator, and 8 bytes of
# each of its four arrays are kept; 2^16 resolve a band to 1e-5 of its width, far finer than any run's
# frequency resolution 1 / t_end. More would only cost memory and time (red team: components = 1e9 asked
# for 30 GB and ended in a MemoryError).
MAX_COMPONENTS = 2 ** 16
MAX_COSINES = 2 ** 22     # over all the histories of a Turbulence (CorrelatedProcess): 128 MB of arrays


def _components(name: str, components) -> int:
    """components as an int from 1 to MAX_COMPONENTS, or an InputError."""
    from .errors import InputError, check_number

    components = check_number(f"{name} components", components, 1, integer=True)
    if components > MAX_COMPONENTS:
        raise InputError(f"{name} components must be at most {MAX_COMPONENTS} (cosines per history; more resolve "
                         f"nothing a run can see and cost memory and time), got {components}")
    return components


def _check_peak(name: str, psd: float, band: tuple, components: int) -> None:
    """The largest value a history can take, components sqrt(2 psd df) (RandomProcess: every cosine at
    its crest), a finite number, or an InputError naming psd. Red team: psd = 1e308 printed numpy's
    overflow warning, then a first-step failure that named neither psd nor the load."""
    from .errors import InputError

    with np.errstate(all="ignore"):
        peak = components * np.sqrt(2.0 * np.float64(psd) * ((band[1] - band[0]) / components))
    if not np.isfinite(peak):
        raise InputError(f"{name} psd = {psd:g} over the band {band[0]:g} to {band[1]:g} Hz: the load's peak "
                         f"overflows double precision (a value beyond 1.8e308): check its units ((N/m)^2/Hz)")


def _span(name: str, span) -> tuple:
    """() (the whole beam) or (x0, x1) in m with x0 < x1 (fom.py checks them against the beam)."""
    from .errors import InputError, check_number

    if isinstance(span, (str, bytes)) or not np.iterable(span) or len(span) not in (0, 2):
        raise InputError(f"{name} span must be (x0, x1) in m, or () for the whole beam, got {span!r}")
    span = tuple(check_number(f"{name} span", x) for x in span)
    if span and not span[0] < span[1]:
        raise InputError(f"{name} span must be (x0, x1) with x0 < x1 (m), got {span!r}")
    return span


def _harmonic_numbers(excitation, name: str) -> None:
    """The amplitude and frequency of a harmonic excitation as numbers, the frequency above 0 (a sine
    of 0 Hz is no load at all, whatever its amplitude: a scene refuses it too), its direction a unit
    vector (the Python API's edge)."""
    from .errors import check_number

    object.__setattr__(excitation, "amplitude", check_number(f"{name} amplitude", excitation.amplitude))
    object.__setattr__(excitation, "frequency_hz", check_number(f"{name} frequency_hz (Hz; a sine of 0 Hz is no "
                                                                f"load)", excitation.frequency_hz, 0.0, above=True))
    object.__setattr__(excitation, "direction", unit_direction(f"{name} direction", excitation.direction))


@dataclass(frozen=True)
class BaseMotion:
    """The transverse support at `end` ("left" or "right" of a beam; the influence vector of a
    matrix model) moves as amplitude sin(2 pi frequency_hz t) (m); on a beam of two planes along
    `direction` (dy, dz), scaled to a unit vector (only a beam of two planes takes another than
    (1, 0))."""

    amplitude: float
    frequency_hz: float
    end: str = "left"
    direction: tuple = (1.0, 0.0)
    kind = "base"

    def __post_init__(self):
        _harmonic_numbers(self, "BaseMotion")
        if self.end not in ("left", "right"):
            from .errors import InputError

            raise InputError(f'BaseMotion end must be "left" or "right", got {self.end!r}')

    def support(self) -> Harmonic:
        return Harmonic(self.amplitude, self.frequency_hz)


@dataclass(frozen=True)
class PointForce:
    """amplitude sin(2 pi frequency_hz t) (N) at x (m, a beam) or at DOF `dof` (a matrix model); on a
    beam of two planes along `direction` (dy, dz), scaled to a unit vector."""

    amplitude: float
    frequency_hz: float
    x: Optional[float] = None
    dof: Optional[int] = None
    direction: tuple = (1.0, 0.0)
    kind = "force"

    def __post_init__(self):
        from .errors import InputError, check_number

        _harmonic_numbers(self, "PointForce")
        if (self.x is None) == (self.dof is None):
            raise InputError("PointForce: give where it acts, one of x (m, on a beam) or dof (a matrix model)")
        if self.x is not None:   # red team: x = "a" was a TypeError, x = True a force at 1 m
            object.__setattr__(self, "x", check_number("PointForce x (m)", self.x))
        else:
            object.__setattr__(self, "dof", check_number("PointForce dof", self.dof, 0, integer=True))

    def history(self) -> Harmonic:
        return Harmonic(self.amplitude, self.frequency_hz)


@dataclass(frozen=True)
class RandomForce:
    """A distributed force per unit length on [span[0], span[1]] of a beam, fully correlated along
    the span: a flat one-sided PSD psd ((N/m)^2/Hz) over band = (f_low, f_high) Hz, from seed; on a
    beam of two planes along the unit vector `direction` (dy, dz)."""

    psd: float
    band: tuple
    seed: int = 1
    components: int = 256
    span: tuple = field(default=())
    direction: tuple = (1.0, 0.0)
    kind = "random"

    def __post_init__(self):
        """The numbers checked once (the Python API's edge); span () is the whole beam (fom.py)."""
        from .errors import check_number

        put = object.__setattr__
        put(self, "psd", check_number("RandomForce psd ((N/m)^2/Hz)", self.psd, 0.0, above=True))
        put(self, "band", _band("RandomForce", self.band))
        put(self, "seed", check_number("RandomForce seed", self.seed, 0, integer=True))
        put(self, "components", _components("RandomForce", self.components))
        put(self, "span", _span("RandomForce", self.span))
        put(self, "direction", unit_direction("RandomForce direction", self.direction))
        _check_peak("RandomForce", self.psd, self.band, self.components)

    def history(self) -> RandomProcess:
        return RandomProcess(self.psd, self.band, self.seed, self.components)


@dataclass(frozen=True)
class Turbulence:
    """Turbulence along a span of a beam with partial correlation: a random force per unit length
    p(x, t) with the one-sided PSD S(f) ((N/m)^2/Hz: the PSD of the force per unit length at a
    point, so that var p = int S df in (N/m)^2) over band = (f_low, f_high) Hz, and the spatial
    coherence exp(-|x_i - x_j| / correlation_length) (real, the same at every frequency;
    correlation_length in m, inf for a fully correlated load). spectrum "flat": S = psd; "knee":
    S = psd up to corner_hz and psd (f / corner_hz)^-slope above (the flat-then-power-law shape of
    the reduced-frequency bounding spectra of tube-bundle turbulence). Generated at the span's nodes
    (span = (x0, x1), default the whole beam) from seed; with two planes, independent fields in y
    and z (the one plane with planes = 1). A distributed load: p is linear between the nodes and
    enters through the consistent load vector of the Hermite elements (fom.py)."""

    psd: float
    band: tuple
    correlation_length: float
    seed: int = 1
    components: int = 128
    span: tuple = field(default=())
    spectrum: str = "flat"
    corner_hz: float = 0.0
    slope: float = 0.0
    kind = "turbulence"

    def __post_init__(self):
        from .errors import InputError, check_number

        put = object.__setattr__
        put(self, "band", _band("turbulence:", self.band))
        put(self, "span", _span("turbulence:", self.span))
        for name in ("psd", "correlation_length", "corner_hz", "slope"):   # correlation_length may be inf
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or value != value:
                raise InputError(f"turbulence: {name} must be a number, got {value!r}")
            if name != "correlation_length" and not np.isfinite(value):   # an infinite psd is a NaN load
                raise InputError(f"turbulence: {name} must be finite, got {value!r}")
        put(self, "seed", check_number("turbulence: seed", self.seed, 0, integer=True))
        put(self, "components", _components("turbulence:", self.components))
        problems = [(not (self.psd > 0), f"psd must be positive, got {self.psd!r}"),   # band, components: above
                    (not (self.correlation_length > 0), f"correlation_length must be positive (m), got "
                                                        f"{self.correlation_length!r}"),
                    (self.spectrum not in ("flat", "knee"), f"spectrum must be \"flat\" or \"knee\", got "
                                                            f"{self.spectrum!r}"),
                    (self.spectrum == "knee" and not (self.corner_hz > 0 and self.slope > 0),
                     "a knee spectrum needs corner_hz > 0 and slope > 0")]
        for bad, message in problems:
            if bad:
                raise InputError(f"turbulence: {message}")
        _check_peak("turbulence:", self.psd, self.band, self.components)   # a knee spectrum is at most psd

    def density(self, f) -> np.ndarray:
        """S(f), (N/m)^2/Hz."""
        f = np.asarray(f, dtype=float)
        if self.spectrum == "knee":
            fall = (np.maximum(f, 1e-300) / self.corner_hz) ** -self.slope
            return self.psd * np.where(f <= self.corner_hz, 1.0, fall)
        return np.full(f.shape, float(self.psd))

    def coherence(self, x) -> np.ndarray:
        """exp(-|x_i - x_j| / lambda) between the points x (m)."""
        x = np.asarray(x, dtype=float)
        return np.exp(-np.abs(x[:, None] - x[None, :]) / self.correlation_length)


# The coherence matrix is factored by its eigenvectors (Gamma = Q L Q^T), keeping the fewest that hold
# this share of its trace: few histories for long correlation lengths (one at lambda = inf).
VARIANCE_KEPT = 0.999


def coherence_factor(coherence: np.ndarray) -> np.ndarray:
    """H (n x m) with H H^T ~ Gamma (the coherence matrix): the leading eigenvectors scaled by the
    square roots of their eigenvalues, the fewest that hold VARIANCE_KEPT of the trace, each row then
    scaled so that diag(H H^T) = 1 exactly (every point keeps its PSD). Deterministic (LAPACK's
    symmetric eigensolver on the same small matrix on every rank). A Cholesky factor would do the
    same with n histories; this one also takes the singular Gamma of lambda = inf (one history)."""
    values, vectors = np.linalg.eigh(coherence)
    order = np.argsort(values)[::-1]
    values, vectors = np.clip(values[order], 0.0, None), vectors[:, order]
    share = np.cumsum(values) / values.sum()
    m = int(np.searchsorted(share, VARIANCE_KEPT) + 1)
    m = min(m, values.size)
    H = vectors[:, :m] * np.sqrt(values[:m])
    # fix each eigenvector's sign (eigh's is arbitrary): its first clearly nonzero entry positive (the
    # sum would not do: half the eigenvectors of evenly spaced nodes are antisymmetric)
    first = np.argmax(np.abs(H) > 1e-6 * np.abs(H).max(axis=0), axis=0)
    H *= np.where(H[first, np.arange(m)] < 0, -1.0, 1.0)
    return H / np.linalg.norm(H, axis=1)[:, None]


class CorrelatedProcess:
    """Independent unit histories X_m(t), m = 0..n-1, of the spectral density S(f) of a Turbulence
    (Shinozuka's spectral representation with Deodatis' double-indexed frequencies, so that a single
    long sample is ergodic in its cross-correlations as well):

        X_m(t) = sum_k sqrt(2 S(f_mk) df) cos(2 pi f_mk t + phi_mk),  f_mk = f_low + (k + (m + 1/2)/n) df

    df = (f_high - f_low) / components, phi_mk uniform on [0, 2 pi) from the seed. value(t) is the
    vector X(t) (n,), the histories a load matrix multiplies (fom.py, rom.py). Not collective: every
    rank makes the same numbers from the same seed."""

    def __init__(self, turbulence: Turbulence, count: int):
        from .errors import InputError

        f_low, f_high = turbulence.band
        K = turbulence.components
        if count * K > MAX_COSINES:
            raise InputError(f"turbulence: {count} histories (the span's nodes the coherence needs, per plane) of "
                             f"{K} components are {count * K} cosines at every step, more than {MAX_COSINES}: lower "
                             f"components, or shorten the span or coarsen its elements")
        df = (f_high - f_low) / K
        shift = (np.arange(count) + 0.5) / count
        self.count, self.band = count, (float(f_low), float(f_high))
        self.frequency = f_low + (np.arange(K)[None, :] + shift[:, None]) * df      # (n, K)
        self.amplitude = np.sqrt(2 * turbulence.density(self.frequency) * df)
        self.phase = np.random.default_rng(turbulence.seed).uniform(0, 2 * np.pi, (count, K))
        self.omega = 2 * np.pi * self.frequency
        self._w, self._a, self._ph = self.omega.ravel(), self.amplitude.ravel(), self.phase.ravel()

    def value(self, t: float) -> np.ndarray:
        """X(t), (n,)."""
        return (self._a * np.cos(self._w * float(t) + self._ph)).reshape(self.count, -1).sum(axis=1)

    def sample(self, times, chunk: int = 256) -> np.ndarray:
        """X at many times, (len(times), n), in chunks (memory)."""
        times = np.asarray(times, dtype=float)
        out = np.empty((times.size, self.count))
        for i in range(0, times.size, chunk):
            t = times[i:i + chunk]
            out[i:i + chunk] = np.einsum("tmk,mk->tm", np.cos(t[:, None, None] * self.omega + self.phase),
                                         self.amplitude)
        return out


def fastest_hz(*histories) -> float:
    """The highest frequency (Hz) time functions contain: a Harmonic's frequency, a random process's upper
    band edge; 0 for none (scene.fastest_forcing_hz from the histories: the Python API's models)."""
    return max([0.0, *(float(h.band[1]) if hasattr(h, "band") else float(getattr(h, "frequency_hz", 0.0))
                       for h in histories)])


def time_functions(excitation) -> tuple:
    """(support motion Omega(t), force history F(t)) of an excitation description; a zero Harmonic
    stands for what it does not have (the histories of Turbulence depend on the mesh: fom.py makes
    them)."""
    support = excitation.support() if excitation.kind == "base" else Harmonic()
    force = excitation.history() if excitation.kind in ("force", "random") else Harmonic()
    return support, force
