"""Accuracy control: an error indicator with every basis and an error estimate with every reduced run
(docs/accuracy.md, "Error estimate and tolerance mode").

A-priori, per constraint j (no time integration): the captured static flexibility

    f_basis / f_exact,   f_exact = g_j^T K^-1 g_j,   f_basis = g_j^T V (V^T K V)^-1 V^T g_j = B_j K_r^-1 B_j^T

g_j the unit vector at the constraint DOF. By Rayleigh-Ritz f_basis <= f_exact; the ratio is 1 when
the basis contains the static mode K^-1 g_j (enrichment = "static"), and it rises with the number of
modes. A low value says the basis cannot reproduce how the structure deflects under the contact
force (paper Sec. 2.2: that is what the enrichment column is for). Undefined (NaN) when K is
singular (rigid-body modes).

A-posteriori (nested comparison): the same scene on a richer basis (max(2N, N + N_L) reference modes,
rich_modes, and the same enrichment columns; span(V) is inside the richer span) at a 10 times tighter rtol and implicit
contact, over a window that holds the first impacts; estimated_error = max over constraints and
samples of |w - w_rich| over the largest |w_rich| at any constraint, over that window. Where that is
SECOND_CHECK or more, also against a second richer basis of 1.5 times its modes (richer_models), and the larger
difference: on a coarse run the 2N reference can share much of the run's error. The error is
normalized by the largest motion at any constraint, not by each constraint's own: on the
steam-generator tube a support plate that barely moves (max |w| half its clearance) had a relative
error of 173 % by its own peak, which says nothing about the response; the same normalization is the
accuracy study's error in w (scripts/study_accuracy.py), so estimate and truth are compared alike.
One scale per kind of DOF, though: where a node map names constraints on rotations (rx, ry, rz) and
translations, each kind is relative to its own largest |w| and the estimate is the worse (m and rad
are no one scale; a cantilever's tip rotation of 7e-4 rad read a stop's 2.3 % error 20 um from the
clamp as 1.37 %; per kind the estimate said 2.05 %: docs/accuracy.md, "Why one scale per kind of DOF").

The indicator is collective on the model's communicator (solves with K); the estimate integrates
reduced models, which are replicated, on the calling rank alone.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .errors import InputError, Interrupted, SolverError

# Below this captured flexibility at some constraint a run prints a warning. Measured on the paper's
# beam (1 and 9 stops; docs/accuracy.md): modes alone capture 0.979 to 0.996 at N = 4 (errors of 25 to
# 118 % in w), 0.9998 at N = 10, every DBF or static basis 1 - 2e-7 or closer; the tube's 16 modes alone 0.9947.
# The indicator is necessary, not sufficient: the a-posteriori estimate is the measure of error.
FLEXIBILITY_WARN = 0.99
# The richer basis of the estimate: this many times the reference modes, and at least N_L modes more than the run
# (rich_modes), rtol this many times tighter (100 times tighter gave the same ratios to the true error on the paper's
# beam at twice the cost).
RICH_MODES = 2
RICH_RTOL = 10.0
# The second richer model (second_modes: SECOND_MODES times the first's modes), integrated when the first one's
# difference is at least SECOND_CHECK, and the estimate the larger of the two differences. On a coarse run the first
# reference can share much of the run's error: measured against the full-order model (docs/accuracy.md, "Why a second
# richer model"), paper_beam_4.toml with Rayleigh damping at 6 and 12 modes read 0.47x and 0.74x, undamped at 6 modes
# 0.74x, paper_beam_9.toml at 4 (over [0, 0.105] s), 6 and 20 modes 0.55x, 0.77x and 0.61x; with the second 0.79x to
# 1.10x. Every one of those first differences was above 2.5 %. Below SECOND_CHECK the run has enough modes for the
# second to be costly (the paper's beam at N = 40, first difference 1.3 %: 120 modes took 13 s against 0.5 s for 80),
# and the first read 0.8x or more there.
SECOND_MODES = 1.5
SECOND_CHECK = 0.02
RICH_STEP = 4       # a fixed step's richer run (and the full-order estimate's) is this many times shorter
# Without any contact in the run, the estimate's window is this fraction of t_end.
LINEAR_WINDOW = 0.1


def exact_flexibility(ops, rows) -> np.ndarray:
    """f_exact_j = g_j^T K^-1 g_j (m/N) of every constraint row: one Cholesky factorization of K and
    its solves, a block of unit loads at a time (enrichment.static_modes, options prefix static_). NaN for all when K is
    singular (rigid-body modes, or a solve that fails: the indicator never stops a basis that can be
    built). Solved once per operators and rows (ops.flexibility: the tolerance mode builds a basis per
    candidate, and K factored for each). Collective on ops.comm."""
    rows = np.asarray(rows, dtype=np.int64)
    if ops.rigid_modes or not rows.size:
        return np.full(rows.size, np.nan)
    key = rows.tobytes()
    if key not in ops.flexibility:
        ops.flexibility[key] = _solve_flexibility(ops, rows)
    return ops.flexibility[key].copy()


def _solve_flexibility(ops, rows: np.ndarray) -> np.ndarray:
    """exact_flexibility's factorization and solves. Collective on ops.comm."""
    from .enrichment import static_modes

    try:
        psi = static_modes(ops, rows)
    except Interrupted:   # a termination signal is not a failed solve
        raise
    except SolverError:   # decided on every rank alike (a collective residual norm)
        return np.full(rows.size, np.nan)
    try:
        lo, hi = psi.getOwnershipRange()
        local = psi.getDenseArray()
        out = np.zeros(rows.size)
        for j, row in enumerate(rows):
            if lo <= row < hi:
                out[j] = local[row - lo, j]
    finally:
        psi.destroy()
    return ops.comm.tompi4py().allreduce(out)


def basis_flexibility(K_r: np.ndarray, B: np.ndarray) -> np.ndarray:
    """f_basis_j = B_j K_r^-1 B_j^T (m/N): the reduced model's own static flexibility at each
    constraint (K_r = V^T K V and B = G^T V of Eq. 21). NaN when K_r is singular. Not collective."""
    if not B.shape[0]:
        return np.zeros(0)
    K_sym = 0.5 * (K_r + K_r.T)
    try:
        X = np.linalg.solve(K_sym, B.T)
    except np.linalg.LinAlgError:
        return np.full(B.shape[0], np.nan)
    f = np.einsum("ij,ji->i", B, X)
    return np.where(np.isfinite(f) & (np.linalg.cond(K_sym) < 1e14), f, np.nan)


def captured(f_basis: np.ndarray, f_exact: np.ndarray) -> np.ndarray:
    """f_basis / f_exact (1), NaN where undefined."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(f_exact > 0, f_basis / np.where(f_exact > 0, f_exact, 1.0), np.nan)


def flexibility_warning(values: np.ndarray, labels, dimension: int = 1) -> str | None:
    """One line naming the constraint whose captured flexibility is lowest, if below FLEXIBILITY_WARN.
    values and labels have one entry per component (the DBF columns): `dimension` of them per
    constraint (2 on a beam of two planes), so component j belongs to constraint j // dimension + 1."""
    values = np.asarray(values, dtype=float)
    if not values.size or not np.any(np.isfinite(values)):
        return None
    j = int(np.nanargmin(values))
    if values[j] >= FLEXIBILITY_WARN:
        return None
    low = np.unique(np.flatnonzero(values < FLEXIBILITY_WARN) // dimension).size
    return (f"the basis captures {values[j]:.1%} of the static flexibility at constraint {j // dimension + 1} "
            f"({labels[j]})"
            f"{f' ({low} constraints below {FLEXIBILITY_WARN:.0%})' if low > 1 else ''}: expect errors of several "
            f"percent; add modes, or use enrichment = \"static\" or a basis tolerance (docs/accuracy.md)")


@dataclass(frozen=True)
class EstimateSettings:
    """[basis] estimate (on by default), estimate_window (s; None: automatic, estimate_window below),
    tolerance (the tolerance mode: the basis size is picked to meet it; None: off) and
    estimate_statistics_window (s; None: STATISTICS_FRACTION t_end, for long runs only)."""

    enabled: bool = True
    window: float | None = None
    tolerance: float | None = None
    statistics_window: float | None = None

    def __post_init__(self):
        if self.window is not None and not self.window > 0:
            raise InputError(f"[basis] estimate_window must be positive (s), got {self.window!r}")
        if self.tolerance is not None and not 0 < self.tolerance < 1:
            raise InputError(f"[basis] tolerance must be between 0 and 1 (a relative error), got {self.tolerance!r}")
        if self.statistics_window is not None and not self.statistics_window > 0:
            raise InputError(f"[basis] estimate_statistics_window must be positive (s), got "
                             f"{self.statistics_window!r}")


@dataclass(frozen=True)
class Estimate:
    """estimated_error (1, NaN if none), the window [0, window] s it holds over, the wall time of the
    richer run (s) and a note on how it was made."""

    value: float
    window: float
    seconds: float = 0.0
    note: str = ""
    reference: np.ndarray | None = None   # the richer run's w over the window (nt x N_L), for reuse
    reference_time: np.ndarray | None = None   # its sample times (s)
    kinds: list | None = None   # constraint_kinds of w's columns (None: one scale for all)

    def attrs(self) -> dict:
        """The output's root attributes."""
        return {"estimated_error": float(self.value), "estimated_error_window": float(self.window),
                "estimated_error_note": self.note}

    def line(self) -> str:
        if not math.isfinite(self.value):
            return f"estimated error: not available ({self.note})"
        kind = " of its kind" if self.kinds else ""
        return (f"estimated error: {self.value:.3g} ({percent(self.value)} of the largest |w|{kind} at the constraints) "
                f"over "
                f"[0, {self.window:g}] s ({self.note}; {self.seconds:.2f} s)")


def percent(value: float) -> str:
    """A relative error as a percentage of three significant digits ("0.0027%", not "0.00%")."""
    return f"{100 * value:.3g}%"


def blind_to_contact(estimate: Estimate, t_contact: float | None) -> Estimate:
    """The estimate with its note saying so when its window ends before the run's first contact (a
    given estimate_window, or the tolerance mode's): it then measures the motion before any impact,
    not the impacts, and a small value says nothing about them. Not collective."""
    if t_contact is None or not t_contact > estimate.window or not math.isfinite(estimate.value):
        return estimate
    return dataclasses.replace(estimate, note=f"{estimate.note}; the window ends before the run's first contact at "
                                              f"{t_contact:g} s: it does not see the impacts")


def first_contact(times: np.ndarray, force_peak: np.ndarray, before: np.ndarray | None = None) -> float | None:
    """The run's first impact: the first sample time whose interval holds a nonzero force at a
    constraint whose force was zero over the interval before, or None. A constraint in force from the
    first interval on (a linear spring, an interference fit, a zero gap) is no impact until it lets go
    and touches again (red team: a linear spring's force put the window at t_end / 10, before the
    stop's impacts, and its estimate said 0.02 % against 2.2 %). `before`: the row of force_peak
    preceding `times[0]`, when reading a run in blocks (None: times[0] is the run's start, t = 0).
    Not collective."""
    n = force_peak.shape[0]
    engaged = np.abs(force_peak.reshape(n, force_peak.shape[1] if force_peak.ndim > 1 else 1, -1)).max(axis=2) > 0
    if before is None:   # the start: samples 0 and 1 (t = 0 and the first interval) are no onset
        start = 2
        onset = engaged[start:] & ~engaged[start - 1:-1]
    else:
        start = 0
        prior = np.abs(np.asarray(before).reshape(engaged.shape[1], -1)).max(axis=1) > 0
        onset = engaged & ~np.vstack([prior[None, :], engaged[:-1]])
    hit = np.flatnonzero(onset.any(axis=1))
    return float(times[start + hit[0]]) if hit.size else None


def estimate_window(times: np.ndarray, t_contact: float | None, t_end: float, window: float | None = None) -> float:
    """The sample time that ends the estimate's window: the given window, else twice the time of the
    first contact (so the window holds the first impacts and what follows them for as long again),
    else LINEAR_WINDOW t_end without contact (or with contact from the start: in the first sample
    interval, as an interference fit has it; twice that was a window of two samples, new-user
    pass); never beyond t_end and never before the second sample. Not collective."""
    if window is None:
        from_start = t_contact is not None and times.size > 1 and t_contact <= times[1]
        window = 2 * t_contact if t_contact and not from_start else LINEAR_WINDOW * t_end
    k = int(np.searchsorted(times, min(window, t_end) * (1 - 1e-12)))
    return float(times[min(max(k, 1), times.size - 1)])


def rich_settings(settings, window: float):
    """The richer run's integrator settings: to `window`, rtol and atol RICH_RTOL times tighter,
    implicit contact; a fixed step RICH_STEP times shorter, or an adaptive step's upper limit RICH_STEP
    times lower. Without the lower limit a run whose tolerances let every step grow to the limit (10
    samples) had a richer run on the same steps, blind to their error (red team, the pipe at atol 1e-3:
    estimated 2.7 %, 8.6 % against the full-order model at a 100 times shorter step; at 1e300: 0.02 %)."""
    from .timestepping import ATOL_FLOOR, RTOL_FLOOR

    return dataclasses.replace(settings, t_end=window, rtol=max(settings.rtol / RICH_RTOL, RTOL_FLOOR),
                               atol=max(settings.atol / RICH_RTOL, ATOL_FLOOR), contact="implicit",
                               dt=settings.dt if settings.adaptive else settings.dt / RICH_STEP,
                               max_step_scale=settings.max_step_scale / RICH_STEP)


def rich_step_refusal(rich_model, settings, window: float) -> str | None:
    """Why the richer run (rich_settings) cannot be made where its adaptive step's cap, RICH_STEP times
    lower than the run's, is not above its floor (timestepping.cap_refusal with the richer model's highest
    mode), else None. Red team: t_end = 2e-9 s on the paper's beam ran, and its estimate's richer run was
    then refused as "[integrator] t_end = 2e-10 s: ..." (its window, not t_end), the whole run lost to a
    .partial; the estimate is not available instead, saying why, as where the richer model fails. Not
    collective."""
    from .rom_integrator import highest_mode_hz
    from .timestepping import cap_refusal, step_cap, step_floor

    rich, hz = rich_settings(settings, window), highest_mode_hz(rich_model)
    if not rich.adaptive or cap_refusal(rich, hz) is None:
        return None
    return (f"the richer run's adaptive step, capped {RICH_STEP} times lower than the run's at {step_cap(rich):g} s, "
            f"would not be above its floor ({step_floor(rich, hz):g} s): give a longer [output] sample_dt or t_end for an "
            f"estimate")


def rich_note(rich_model, settings, end: float) -> str:
    """What the richer run was: its basis vectors, and its rtol, or its fixed step for a run of fixed
    steps (whose rtol steers nothing). Not collective."""
    rich = rich_settings(settings, end)
    how = f"rtol {rich.rtol:g}" if rich.adaptive else f"a fixed step of {rich.dt:g} s"
    return f"against {rich_model.size} basis vectors at {how}"


def constraint_kinds(ops, constraints) -> list | None:
    """The kind of DOF of each flat component of the constraints' w (constraint-major, as w's columns):
    1 for a rotation (a node map's rx, ry or rz: rad), 0 for a translation (m); None when every one is
    a translation or no node map tells (relative_difference then scales them all alike). Not collective."""
    rotations = getattr(ops, "rotations", None)
    if rotations is None or not constraints.count:
        return None
    kinds = np.isin(constraints.flat_rows, rotations).astype(int)
    return kinds.tolist() if kinds.any() else None


KINDS_NOTE = "; translations (m) and rotations (rad) each over their own largest |w|, the worse"


def relative_difference(w: np.ndarray, w_rich: np.ndarray, kinds=None) -> float:
    """max over constraints and samples of |w - w_rich|, over max |w_rich| at any constraint and
    sample (both nt x N_L; module docstring: why one scale for all constraints). With `kinds`
    (constraint_kinds: 0 translation, 1 rotation per column), each kind over its own largest |w_rich|
    and the worse of the two: m and rad are not one scale. Not collective."""
    n = min(w.shape[0], w_rich.shape[0])
    w, w_rich = w[:n].reshape(n, -1), w_rich[:n].reshape(n, -1)
    if not w.size:
        return 0.0
    kinds = np.zeros(w.shape[1], dtype=int) if kinds is None else np.asarray(kinds, dtype=int)
    worst = 0.0
    for kind in np.unique(kinds):
        cols = kinds == kind
        scale = float(np.abs(w_rich[:, cols]).max())
        worst = max(worst, float(np.abs(w[:, cols] - w_rich[:, cols]).max() / (scale if scale > 0 else 1.0)))
    return worst


def relative_difference_each(w: np.ndarray, w_ref: np.ndarray) -> float:
    """The former, per-constraint measure, for comparison only (the accuracy study's err_w_each):
    max over constraints of max_t |w - w_ref| / max_t |w_ref|. Not collective."""
    n = min(w.shape[0], w_ref.shape[0])
    w, w_ref = w[:n].reshape(n, -1), w_ref[:n].reshape(n, -1)
    scale = np.abs(w_ref).max(axis=0)
    return float(np.max(np.abs(w - w_ref).max(axis=0) / np.where(scale > 0, scale, 1.0)))


def nested_estimate(rich_model, settings, times: np.ndarray, w: np.ndarray, end: float, second=None) -> Estimate:
    """The a-posteriori estimate of a run whose samples at `times` are w (nt x N_L, at least to
    `end`, estimate_window): the richer model (richer_basis) integrated to `end` with rich_settings,
    compared sample by sample. With a `second` richer model (richer_models) and a difference of at
    least SECOND_CHECK, the second is integrated too and the estimate is the larger difference (its
    reference, kept for reuse, is the first's). Not collective (a reduced model runs on one rank)."""
    first = _nested(rich_model, settings, times, w, end)
    if second is None or not first.value >= SECOND_CHECK:
        return first
    other = _nested(second, settings, times, w, end)
    seconds = first.seconds + other.seconds
    if not math.isfinite(other.value):
        return dataclasses.replace(first, seconds=seconds, note=f"{first.note}; the second richer model "
                                                                f"({second.size} basis vectors) gave none: {other.note}")
    larger = max(first.value, other.value)
    note = (f"the larger difference, against {rich_model.size} basis vectors ({percent(first.value)}) and "
            f"{second.size} ({percent(other.value)}), at {rich_note(second, settings, end).split(' at ', 1)[1]}"
            f"{KINDS_NOTE if first.kinds else ''}")
    return dataclasses.replace(first, value=larger, seconds=seconds, note=note)


def _nested(rich_model, settings, times: np.ndarray, w: np.ndarray, end: float) -> Estimate:
    """nested_estimate against one richer model. Not collective."""
    import time

    from .simulate import integrate_samples

    start = time.perf_counter()
    refusal = rich_step_refusal(rich_model, settings, end)
    if refusal:
        return Estimate(np.nan, end, 0.0, refusal)
    try:
        result = integrate_samples(rich_model, rich_settings(settings, end))
    except Interrupted:
        raise
    except SolverError as e:
        return Estimate(np.nan, end, time.perf_counter() - start, f"the richer model failed: {e}")
    k = result.time.size
    if k > times.size or not np.allclose(result.time, times[:k], rtol=0, atol=1e-9 * max(end, 1e-300)):
        return Estimate(np.nan, end, time.perf_counter() - start, "the richer run is not sampled alike")
    kinds = rich_model.basis_info.get("constraint_kinds")
    value = relative_difference(w[:k], result.displacement, kinds)
    note = rich_note(rich_model, settings, end) + (KINDS_NOTE if kinds else "")
    return Estimate(value, end, time.perf_counter() - start, note, result.displacement, result.time, kinds)


def reused_estimate(calibration: Estimate, times: np.ndarray, w: np.ndarray) -> Estimate:
    """A run's estimate against the richer run its calibration made (the tolerance mode): the
    difference over the same window, without integrating the richer model again. Not collective."""
    k = calibration.reference.shape[0]
    if times.size < k:
        return Estimate(np.nan, calibration.window, 0.0, "the run is shorter than its calibration window")
    if calibration.reference_time is not None and not np.allclose(
            times[:k], calibration.reference_time, rtol=0, atol=1e-9 * max(calibration.window, 1e-300)):
        return Estimate(np.nan, calibration.window, 0.0, "the run is not sampled as its calibration was")
    value = relative_difference(w[:k], calibration.reference, calibration.kinds)
    return Estimate(value, calibration.window, 0.0, f"{calibration.note}, from the calibration")


# Long runs: the statistics' errors (docs/accuracy.md, "Statistics of long runs"). A run is long when
# t_end exceeds STATISTICS_WINDOWS times the pointwise estimate's window: past the first impacts and
# as long again, w itself drifts off any reference (chaotic horizon) and the estimate in w says
# nothing about the rest of the run, while the statistics still converge.
STATISTICS_WINDOWS = 5
# The statistics window: [0, STATISTICS_FRACTION t_end] unless [basis] estimate_statistics_window
# gives it, and at most STATISTICS_MAX_SAMPLES samples. Per simulated second the richer run cost 1.3
# times the reduced run on the paper's beam (6 modes, 13 richer vectors) and 2.7 times on the 2-D
# tube (40 Hz basis): with this fraction the estimate costs 0.3 to 0.7 times the run (docs/accuracy.md).
# The richer run's samples are held in memory
# (simulate_reduced): the cap bounds that (a 10^5-sample run grew by 37 MB without it) and the cost.
STATISTICS_FRACTION = 0.25
STATISTICS_MAX_SAMPLES = 5000
# The statistics estimated: those a time mean over a long run converges for (peaks and durations
# are extremes, not means: no batch-means interval), and the work rate of 2-D laws.
ESTIMATED_STATISTICS = ("impact_rate", "contact_fraction", "force_rms", "displacement_rms")
ESTIMATED_STATISTICS_2D = ESTIMATED_STATISTICS + ("work_rate",)


def is_long(t_end: float, window: float) -> bool:
    """Whether a run to t_end gets the statistics' estimate besides the pointwise one over
    [0, window]. Not collective."""
    return math.isfinite(window) and window > 0 and t_end > STATISTICS_WINDOWS * window


def statistics_window(t_end: float, sample_dt: float, given: float | None = None) -> float:
    """The end of the statistics window: the given one, else STATISTICS_FRACTION t_end but at least
    the 2 BATCHES samples its batch-means intervals need (red team: a 0.05 s run sampled every 1 ms had
    a 13-sample window and printed every statistic's error as "+- nan"); never beyond t_end nor
    STATISTICS_MAX_SAMPLES samples of sample_dt. Not collective."""
    from .stats import BATCHES

    window = given if given is not None else max(STATISTICS_FRACTION * t_end, 2 * BATCHES * sample_dt)
    return min(window, t_end, STATISTICS_MAX_SAMPLES * sample_dt)


def _statistics(t, z, v, force, laws) -> dict:
    """The ESTIMATED_STATISTICS (with work_rate for 2-D laws, `laws` a PlanarLaws) from samples, as
    stats.impact_statistics defines them (radial values on supports of two directions)."""
    from .stats import impact_statistics

    k = t.size
    if laws is None:
        s = impact_statistics(t, z.reshape(k, -1), v.reshape(k, -1), force.reshape(k, -1))
        return {name: np.asarray(s[name], dtype=float) for name in ESTIMATED_STATISTICS}
    r, vn, f, fn, vt, contact = laws.radial(z.reshape(k, -1), v.reshape(k, -1), force.reshape(k, -1))
    s = impact_statistics(t, r, vn, f, contact)
    out = {name: np.asarray(s[name], dtype=float) for name in ESTIMATED_STATISTICS}
    out["work_rate"] = np.trapz(fn * vt, t, axis=0) / (t[-1] - t[0]) if k > 1 else fn[0] * vt[0]
    return out


def batch_ci95(read, nt: int, laws=None) -> dict:
    """The half-width of the 95 % confidence interval of each estimated statistic of nt samples, by
    batch means: stats.BATCHES batches of equal sample count, each batch's statistic, Student t over
    their spread (stats.batch_means_ci95's construction, applied to each statistic instead of a time
    mean). read(lo, hi) gives the samples' (t, z, v, force) from lo to hi: one batch in memory at a
    time. NaN with fewer than 2 BATCHES samples. Not collective."""
    from .stats import _T_975, BATCHES

    if nt < 2 * BATCHES:
        t, z, v, force = read(0, nt)
        return {name: np.full(value.shape, np.nan) for name, value in _statistics(t, z, v, force, laws).items()}
    bounds = [part[0] for part in np.array_split(np.arange(nt), BATCHES)] + [nt]
    batches = [_statistics(*read(lo, hi), laws) for lo, hi in zip(bounds[:-1], bounds[1:])]
    return {name: _T_975 * np.std([b[name] for b in batches], axis=0, ddof=1) / math.sqrt(BATCHES)
            for name in batches[0]}


def window_statistics(t, z, v, force, laws=None) -> tuple:
    """(values, ci95) of the estimated statistics over the samples t, each (N_L,): the values over
    all of them and their batch-means half-widths (batch_ci95). Not collective."""
    t = np.asarray(t, dtype=float)
    return _statistics(t, z, v, force, laws), batch_ci95(lambda lo, hi: (t[lo:hi], z[lo:hi], v[lo:hi], force[lo:hi]),
                                                         t.size, laws)


@dataclass
class StatisticsEstimate:
    """The statistics' errors of a long run, per statistic (each (N_L,)): `sampling` the 95 %
    half-width of the run's own statistic over [0, t_end] (batch means); over [0, window], the
    reduced run's and the richer run's values and half-widths; `error` = |rich - reduced| + the three
    half-widths (a bound: the model difference, its uncertainty and the run's sampling error). NaN
    arrays (and a note) when the richer run failed."""

    window: float
    sampling: dict
    reduced: dict
    reduced_ci95: dict
    rich: dict
    rich_ci95: dict
    seconds: float = 0.0
    note: str = ""

    @property
    def difference(self) -> dict:
        return {name: self.rich[name] - self.reduced[name] for name in self.sampling}

    @property
    def error(self) -> dict:
        return {name: np.abs(self.rich[name] - self.reduced[name]) + self.sampling[name] + self.reduced_ci95[name]
                + self.rich_ci95[name] for name in self.sampling}

    def datasets(self, group: str) -> dict:
        """name -> array under `group` (layout.STATISTICS_ERROR)."""
        out = {}
        for name in self.sampling:
            out.update({f"{group}/{name}": self.error[name], f"{group}/{name}_sampling_ci95": self.sampling[name],
                        f"{group}/{name}_model": self.difference[name],
                        f"{group}/{name}_window_reduced": self.reduced[name],
                        f"{group}/{name}_window_reduced_ci95": self.reduced_ci95[name],
                        f"{group}/{name}_window_rich": self.rich[name],
                        f"{group}/{name}_window_rich_ci95": self.rich_ci95[name]})
        return out

    def attrs(self) -> dict:
        return {"estimated_statistics_window": float(self.window), "estimated_statistics_note": self.note}

    def summary(self) -> dict:
        return {"window": self.window, "note": self.note,
                **{name: {"error": self.error[name].tolist(), "sampling_ci95": self.sampling[name].tolist(),
                          "model": self.difference[name].tolist(), "reduced_ci95": self.reduced_ci95[name].tolist(),
                          "rich_ci95": self.rich_ci95[name].tolist()} for name in self.sampling}}

    def lines(self, values: dict | None = None) -> list:
        """One line a constraint: each statistic's estimated error (with the run's value, if given)."""
        head = (f"statistics' estimated errors (run's 95 % CI + |richer - reduced| over [0, {self.window:g}] s + "
                f"both CIs; {self.note}; {self.seconds:.2f} s):")
        return [head] + statistics_lines(self.error, values)


_SHORT = {"impact_rate": ("impact rate", "/s"), "contact_fraction": ("contact fraction", ""),
          "force_rms": ("force RMS", " N"), "displacement_rms": ("displacement RMS", " m"),
          "work_rate": ("work rate", " W")}


def statistics_lines(error: dict, values: dict | None = None) -> list:
    """`  constraint j: impact rate 4.1 +- 0.3/s, ...` from per-statistic arrays (N_L,)."""
    names = [name for name in _SHORT if name in error]
    count = len(error[names[0]]) if names else 0
    lines = []
    for j in range(count):
        parts = []
        for name in names:
            label, unit = _SHORT[name]
            value = f"{values[name][j]:.4g} " if values is not None and name in values else ""
            parts.append(f"{label} {value}+- {error[name][j]:.2g}{unit}")
        lines.append(f"  constraint {j + 1}: " + ", ".join(parts))
    return lines


def statistics_estimate(rich_model, settings, read, times, end: float, laws=None) -> StatisticsEstimate:
    """The statistics' errors of a long run sampled at `times`, read(lo, hi) its samples' (t, z, v,
    force) (batch_ci95): the run's own batch-means intervals, and the richer model (nested_estimate's)
    integrated over [0, end] with rich_settings, its statistics against the run's over the same
    samples. Not collective."""
    import time

    from .simulate import integrate_samples

    start = time.perf_counter()
    sampling = batch_ci95(read, times.size, laws)
    k = int(np.searchsorted(times, end * (1 + 1e-12), side="right"))
    reduced, reduced_ci = window_statistics(*read(0, k), laws)
    nan = {name: np.full(value.shape, np.nan) for name, value in reduced.items()}
    refusal = rich_step_refusal(rich_model, settings, float(times[k - 1]))
    if refusal:
        return StatisticsEstimate(end, sampling, reduced, reduced_ci, nan, nan, time.perf_counter() - start, refusal)
    try:
        result = integrate_samples(rich_model, rich_settings(settings, float(times[k - 1])))
    except Interrupted:
        raise
    except SolverError as e:
        return StatisticsEstimate(end, sampling, reduced, reduced_ci, nan, nan, time.perf_counter() - start,
                                  f"the richer model failed: {e}")
    if result.time.size != k or not np.allclose(result.time, times[:k], rtol=0, atol=1e-9 * max(end, 1e-300)):
        return StatisticsEstimate(end, sampling, reduced, reduced_ci, nan, nan, time.perf_counter() - start,
                                  "the richer run is not sampled alike")
    rich, rich_ci = window_statistics(result.time, result.displacement, result.velocity, result.force, laws)
    note = rich_note(rich_model, settings, end)
    return StatisticsEstimate(float(times[k - 1]), sampling, reduced, reduced_ci, rich, rich_ci,
                              time.perf_counter() - start, note)


# The tolerance mode: the largest basis it tries, and the margin it keeps. The accuracy study
# (scripts/study_accuracy.py --grid control, docs/accuracy.md) measured the estimate at 0.58 to 1.39
# times the true error over 64 cases (1, 4, 9 stops and the tube), below 0.80 in one case only:
# accepting estimates below 0.75 times the tolerance keeps the true error below it where the
# estimate is at least 0.75 times the truth. (The rules before, margin 0.5, doubling and rtol =
# tolerance x 1e-4 with the scene's atol, cost more than twice the cheapest grid setting meeting
# the same tolerance in 6 of the 11 runs that met it.)
MAX_MODES = 256
TOLERANCE_MARGIN = 0.75
# rtol = TOLERANCE_RTOL x tolerance (1e-4 for 1 %). The estimate's richer run is 10 times tighter,
# so it sees the time-stepping error too: the study's estimates at rtol 1e-4 were as close to the
# truth as at 1e-6, and at N = 40 a run at rtol 1e-4 cost 0.44 to 0.67 times one at 1e-6, its
# estimate 0.2 to 0.4 times.
TOLERANCE_RTOL = 1e-2
# The next candidate's modes: from the estimates' power law e ~ N^-p, the N that reaches the
# margin, at least GROWTH_MIN and at most GROWTH_MAX times the last (doubling when the estimates
# do not fall).
GROWTH_MIN, GROWTH_MAX = 1.25, 2.0
# Given up early when the last TREND_POINTS estimates fall and the power law through them (and the
# one through all) needs more than TREND_BEYOND times the largest basis: a tolerance of 1e-9 on the
# paper's beam (200 DOFs) went on to 48 and 96 modes (27 s and about 2 min a candidate) when 24
# modes' law already put it near 4e8. Only candidates of TREND_MIN_MODES or more count: from 1 mode
# the estimates rose and fell (0.198, 0.455, 0.194) and their law refused 0.02, which 21 modes meet.
TREND_POINTS, TREND_BEYOND, TREND_MIN_MODES = 3, 10.0, 4


def hopeless(tried: list, target: float, limit: int) -> tuple[float, float] | None:
    """(N, p) of the power law when the tolerance is out of reach by the rule above, else None. Not
    collective."""
    asymptotic = [(m, e) for m, e in tried if m >= TREND_MIN_MODES and math.isfinite(e) and e > 0]
    last = asymptotic[-TREND_POINTS:]
    if len(last) < TREND_POINTS or not all(b[1] < a[1] for a, b in zip(last, last[1:])):
        return None
    laws = [modes_needed(last, target), modes_needed(asymptotic, target)]
    if any(law is None or law[0] <= TREND_BEYOND * limit for law in laws):
        return None
    return laws[1]


def rich_modes(modes: int, components: int) -> int:
    """The reference modes of the estimate's richer basis for a run of `modes` modes and `components`
    constraint components (N_L, the DBF columns of a second-order basis): max(RICH_MODES N, N + N_L).
    With many stops the run's N_L enrichment columns already hold the static response to every contact
    force, and twice the modes added too few to see what the run misses: a clamped beam with 30 stops
    and 6 modes was estimated at 0.45 % against a true 1.01 % (0.45x; 3 modes 0.27x), three spans with 12
    stops at 2.50 % against 3.13 %. With N + N_L modes the same read 1.00x, 1.01x and 1.01x (docs/accuracy.md). Where N_L <= N
    the basis is twice the modes, as before. Not collective."""
    return max(RICH_MODES * modes, modes + components)


def richer_model(fom, basis, cache_dir: str | None = None):
    """The reduced model of the estimate's richer basis (rich_modes: max(2N, N + N_L) modes, the same
    enrichment columns, each named by its constraint component), or the reason it cannot be made (a
    string). Where the structure has too few DOFs for N + N_L modes and the columns, twice the modes
    (RICH_MODES) as before. With cache_dir, its reference modes come from the basis cache
    (cache.obtain_modes), or for complex modes the whole richer basis (cache.obtain_richer). Collective."""
    from .basis import richer_basis
    from .cache import obtain_modes, obtain_richer
    from .errors import DbfError
    from .petsctools import destroy
    from .reductor import Reductor

    if zeta_per_vector(fom):
        return ("no richer model: [damping] zeta gives one ratio per basis vector, none for the richer basis's "
                "extra modes (one zeta for all, or Rayleigh damping, has an estimate)")
    # a gyroscopic basis has two columns (Re, Im) per complex mode: twice the complex modes
    modes = basis.stats.get("complex_modes", basis.mode_count)
    labels = fom.constraints.component_labels
    cached = cache_dir and fom.operators.G is None and getattr(basis, "form", "") != "state_space"
    for count in dict.fromkeys((rich_modes(modes, len(labels)), RICH_MODES * modes)):
        more = None
        try:
            if fom.operators.G is not None:   # complex modes: the whole richer basis cached (either form)
                rich = obtain_richer(fom.operators, basis, count, fom.fingerprint, cache_dir)
            elif cached:
                more = obtain_modes(fom.operators, count, fom.fingerprint, cache_dir)
                rich = richer_basis(fom.operators, basis, count, labels, reference=more)
            else:
                rich = richer_basis(fom.operators, basis, count, labels)
            break
        except Interrupted:   # a termination signal is not a basis the DOFs cannot hold
            raise
        except DbfError as e:  # the same on every rank: too few DOFs, or a column the richer modes hold
            failure = e
        finally:
            destroy(more)
    else:
        return f"no richer basis: {failure}"
    with Reductor(fom, rich.settings, basis=rich) as reductor:
        return reductor.reduce()


def second_modes(modes: int, components: int) -> int:
    """The reference modes of the estimate's second richer basis: SECOND_MODES times the first's (rich_modes),
    rounded up (the modes solved for it keep a repeated frequency at the cut whole: richer_models). Not
    collective."""
    return int(math.ceil(SECOND_MODES * rich_modes(modes, components) - 1e-9))


def richer_models(fom, basis, cache_dir: str | None = None):
    """(richer_model's model or its reason, the second richer model or None): the second has
    second_modes reference modes (1.5 times the first's) and the same enrichment columns, where the
    structure holds them; both from one eigensolve, kept in the basis cache with cache_dir
    (cache.obtain_modes: a run whose basis is cached solves no eigenproblem for its estimate either,
    and gets the same models bit for bit). None for a gyroscopic or
    state-space basis (complex modes: their richer model alone, as before), and where the second's
    projection keeps defects above reductor.PROJECTION_TOL that the reductor could not turn away
    (reductor._turn_in_span), whose unstructured stage solves are slow (the paper's beam at N = 40
    before such bases were turned: 7.9 s for 121 vectors against 0.33 s for 81 with the structure).
    Collective."""
    from .basis import richer_basis
    from .cache import obtain_modes
    from .errors import DbfError
    from .reductor import PROJECTION_TOL, Reductor

    labels = fom.constraints.component_labels
    modes = basis.mode_count
    count = second_modes(modes, len(labels))
    if (zeta_per_vector(fom) or fom.operators.G is not None or getattr(basis, "form", "") == "state_space"
            or count + basis.enrichment_count > fom.size):
        return richer_model(fom, basis, cache_dir), None
    # A count ending inside a repeated frequency (1.5 (N + N_L) can be odd on a beam of two planes: 2 modes
    # and 2 round holes give 9, whose last y-z pair was cut, red team: 55.2 % on 1 rank, 69.3 % on 2) comes
    # back whole (obtain_modes, reference_modes' whole="extend": 10), and richer_basis takes it whole
    try:
        more = obtain_modes(fom.operators, count, fom.fingerprint, cache_dir)
    except Interrupted:
        raise
    except DbfError:   # the same on every rank
        return richer_model(fom, basis, cache_dir), None
    if more.count + basis.enrichment_count > fom.size:   # the whole repeated frequency does not fit
        more.destroy()
        return richer_model(fom, basis, cache_dir), None
    try:
        built = []
        for size in (rich_modes(modes, len(labels)), count):
            try:
                rich = richer_basis(fom.operators, basis, size, labels, reference=more)
            except Interrupted:
                raise
            except DbfError:   # a column the richer modes hold: the first as richer_model makes it, no second
                break
            with Reductor(fom, rich.settings, basis=rich) as reductor:
                built.append(reductor.reduce())
    finally:
        more.destroy()
    if not built:
        return richer_model(fom, basis, cache_dir), None
    second = built[1] if len(built) > 1 else None
    if second is not None and not second.basis_info.get("turned_in_span") and max(
            second.basis_info.get("mass_orthonormality_defect", 0.0),
            second.basis_info.get("mode_coupling_defect", 0.0)) > PROJECTION_TOL:
        second = None   # its stage solves would be dense (reductor._clean_projection): 121 vectors 7.9 s, 81 0.33 s
    return built[0], second


def zeta_per_vector(fom) -> bool:
    """Whether the modal damping gives a ratio per basis vector (a list), which fits one basis size only."""
    damping = fom.damping
    return damping is not None and damping.kind == "modal" and np.atleast_1d(damping.zeta).size > 1


def tolerance_rtol(tolerance: float) -> float:
    """The integrator rtol of the tolerance mode: TOLERANCE_RTOL x tolerance (the tolerance mode
    picks the rtol as it picks the modes; the scene's rtol only sets atol's proportion to it,
    pick_basis). Not collective."""
    from .timestepping import RTOL_FLOOR

    return max(TOLERANCE_RTOL * tolerance, RTOL_FLOOR)


def modes_needed(tried: list, target: float) -> tuple[float, float] | None:
    """(N, p): the modes at which the power law e = C N^-p, fitted (least squares in log-log) through
    every finite estimate of the (modes, estimate) pairs, reaches `target`; None without a falling
    law (fewer than two finite estimates, or p <= 0). Not collective."""
    points = np.array([(m, e) for m, e in tried if math.isfinite(e) and e > 0], dtype=float).reshape(-1, 2)
    if len(points) < 2 or np.ptp(points[:, 0]) == 0:
        return None
    slope, intercept = np.polyfit(np.log(points[:, 0]), np.log(points[:, 1]), 1)
    if slope >= 0:
        return None
    return math.exp(min((math.log(target) - intercept) / slope, 700.0)), -slope


def next_modes(tried: list, target: float) -> int:
    """The next candidate's number of modes after the (modes, estimate) pairs tried so far: the power
    law e = C N^-p fitted (least squares in log-log) through every finite estimate, solved for
    `target`, the growth over the last candidate kept within [GROWTH_MIN, GROWTH_MAX]; GROWTH_MAX
    times the last when the estimates do not fall (p <= 0) or fewer than two are finite. A fit
    through all, not the last two: on 9 stops the estimates rose from 32 to 40 modes (0.82 % to
    1.2 %) before falling again. Not collective."""
    n = tried[-1][0]
    law = modes_needed(tried, target)
    grow = GROWTH_MAX if law is None else min(max(law[0] / n, GROWTH_MIN), GROWTH_MAX)
    return max(int(math.ceil(n * grow - 1e-9)), n + 1)


@dataclass
class Pick:
    """What the tolerance mode picked: modes, rtol, the estimate over the calibration window (with the
    richer run's w, which the run's own estimate reuses), each candidate's (modes, estimate) and atol."""

    modes: int
    rtol: float
    estimate: Estimate
    tried: list
    atol: float = 0.0


def _measure(fom, basis_settings, cache_dir, settings, window: float | None, comm):
    """One candidate of the tolerance mode: its basis, its richer model, both integrated over the
    window (rank 0). Without a window, the candidate is first integrated over LINEAR_WINDOW t_end,
    then t_end if it met no contact, and the window is estimate_window's (on to twice the first
    contact when that is beyond the first probe: cut at the probe, the window held the first impact
    and little after it). Every end is a sample time of the run to t_end, so that the run can reuse
    the richer run's samples. Returns the estimate (the same on every rank). Collective."""
    from petsc4py import PETSc

    from .errors import DbfError, from_rank0, petsc_failure
    from .reductor import Reductor
    from .errors import wait_for_rank0
    from .simulate import integrate_samples

    with Reductor(fom, basis_settings, cache_dir, warn_basis=False) as reductor:
        model = reductor.reduce()
        rich = richer_model(fom, reductor.basis(), cache_dir)
    world = comm.tompi4py()
    result = failure = None
    unexpected = []
    if world.rank == 0:
        try:
            if isinstance(rich, str):
                raise SolverError(rich)
            grid = settings.sample_times   # every probe ends on the run's own samples: the run reuses its w
            for probe in ((window,) if window else (LINEAR_WINDOW * settings.t_end, settings.t_end)):
                probe = estimate_window(grid, None, settings.t_end, probe)
                run = integrate_samples(model, dataclasses.replace(settings, t_end=probe))
                contact = first_contact(run.time, run.force_peak)
                if window or contact is not None:
                    break
            want = estimate_window(grid, contact, settings.t_end, window)
            if want > run.time[-1] * (1 + 1e-12):   # twice the first contact is beyond the probe: go on to it
                run = integrate_samples(model, dataclasses.replace(settings, t_end=want))
            end = estimate_window(run.time, contact, settings.t_end, window)
            refusal = rich_step_refusal(rich, settings, end)
            if refusal:   # the tolerance mode needs the estimate (not a NaN among the candidates' values)
                raise InputError(refusal)
            result = nested_estimate(rich, settings, run.time, run.displacement, end)
        # every failure of rank 0's integration is every rank's (red team: a PETSc error, a bad -rom_
        # option, escaped on rank 0 alone; its Ibarrier at the command's end met the others' in
        # wait_for_rank0, and the job hung, rank 0 in allgather, the others in this bcast)
        except DbfError as e:
            failure = (isinstance(e, InputError), str(e))
        except PETSc.Error as e:
            failure = (False, f"the reduced integration: {petsc_failure(e)}; check the -rom_ options")
        except BaseException as e:   # anything else (a bug) too: every rank raises it (errors.from_rank0)
            unexpected.append(e)
    wait_for_rank0(world)
    result, failure = from_rank0(world, (result, failure), unexpected)
    if failure:
        raise (InputError if failure[0] else SolverError)(
            f"[basis] tolerance: the candidate with {basis_settings.modes} modes failed: {failure[1]}")
    return result


def pick_basis(fom, basis_settings, cache_dir, settings, estimate: EstimateSettings, comm, say=None) -> Pick:
    """The tolerance mode: modes from basis_settings.modes, growing (next_modes: at most doubling; at
    most MAX_MODES, and twice them below the structure's DOFs) until the nested estimate over the
    calibration window is at most TOLERANCE_MARGIN times the tolerance, at the rtol tolerance_rtol
    picks. The calibration window is estimate.window, or the first candidate's (_measure), then the
    same for every candidate. No full-order run. An InputError naming what it reached when the
    tolerance cannot be met: at the largest basis, or as soon as the estimates' trend puts it beyond
    reach (hopeless). Collective."""
    from .basis import modes_per_frequency
    from .modes import RepeatedCut
    from .timestepping import ATOL_FLOOR

    tol = estimate.tolerance
    if not fom.constraints.count:
        raise InputError("[basis] tolerance bounds the error in w at the constraints; this scene has none")
    # atol in the scene's proportion to rtol: on the paper's beam (40 modes + DBF, rtol 1e-4) the
    # scene's atol 1e-9 took 1992 steps against 329 at 1e-7, following the high modes' tiny q. Not below
    # ATOL_FLOOR (an error norm that overflows near rest).
    rtol = tolerance_rtol(tol)
    settings = dataclasses.replace(settings, rtol=rtol, atol=max(settings.atol * rtol / settings.rtol, ATOL_FLOOR))
    modes, tried, window = max(int(basis_settings.modes or 4), 1), [], estimate.window
    limit = min(MAX_MODES, (fom.size - fom.constraints.count) // RICH_MODES)
    pairs = modes_per_frequency(fom.operators)   # whole y-z pairs on a beam of two planes (basis.check_pairs)
    limit -= limit % pairs
    if modes > limit:
        raise InputError(f"[basis] tolerance: the first candidate, [basis] modes = {modes}, is beyond the largest "
                         f"basis the tolerance mode tries, {limit} modes (at most {MAX_MODES}, and the richer basis "
                         f"of at least twice them and the {fom.constraints.count} constraint(s) within the {fom.size} DOFs): "
                         f"give fewer [basis] modes, or a finer mesh")
    while modes <= limit:
        candidate = dataclasses.replace(basis_settings, modes=modes, max_frequency_hz=None)
        try:
            measured = _measure(fom, candidate, cache_dir, settings, window, comm)
        except RepeatedCut as cut:   # every rank's (rank 0's cut): the candidate keeps the repeated frequency whole
            if cut.whole <= limit:
                modes = cut.whole
            elif cut.first > (tried[-1][0] if tried else 0):
                modes = cut.first
            else:
                raise InputError(f"[basis] tolerance: the candidate of {modes} modes ends inside a repeated frequency "
                                 f"that ends beyond the largest basis tried, {limit} modes: {cut}") from None
            continue
        window = measured.window     # every candidate over the first one's window
        tried.append((modes, measured.value))
        if say is not None:
            say(f"tolerance {tol:g}: {modes} modes at rtol {settings.rtol:g}: {measured.line()}")
        if measured.value <= TOLERANCE_MARGIN * tol:
            return Pick(modes, settings.rtol, measured, tried, settings.atol)
        law = hopeless(tried, TOLERANCE_MARGIN * tol, limit)
        if law is not None:
            reached = ", ".join(f"{m} modes {e:.3g}" for m, e in tried)
            raise InputError(f"[basis] tolerance = {tol:g} cannot be met within {limit} modes: reached {reached}, "
                             f"falling like N^-{law[1]:.2g}, which reaches {TOLERANCE_MARGIN * tol:.3g} near "
                             f"{law[0]:.2g} modes; loosen the tolerance, use a richer enrichment or a finer "
                             f"question (a shorter estimate_window)")
        modes = next_modes(tried, TOLERANCE_MARGIN * tol)
        modes += -modes % pairs
        if modes > limit and tried[-1][0] < limit:
            modes = limit         # the largest basis is tried before giving up
    reached = ", ".join(f"{m} modes {e:.3g}" for m, e in tried)
    raise InputError(f"[basis] tolerance = {tol:g} cannot be met within {limit} modes (estimates must reach "
                     f"{TOLERANCE_MARGIN * tol:.3g}): reached {reached}; loosen the tolerance, use a richer "
                     f"enrichment or a finer question (a shorter estimate_window)")
