"""Impact statistics per constraint from the sampled time series of one run.

These are the quantities tube-vibration engineers read first (code_aster's POST_DYNA_MODA_T reports
the same family). Pure numpy; nothing here is collective.

Inputs, all sampled at the same times: t (nt,) strictly increasing, s; z (nt, N_L) total displacement
at each constraint, m; v (nt, N_L) velocity, m/s; force (nt, N_L) constraint force on the structure,
N (0 when not in contact); in_contact (nt, N_L) bool, by default ``force != 0``.

Sample weights. Sample i stands for the time between the midpoints to its neighbours:
    b_0 = t_0,  b_i = (t_{i-1} + t_i) / 2  (0 < i < nt),  b_nt = t_{nt-1},
    w_i = b_{i+1} - b_i = (t_{i+1} - t_{i-1}) / 2, with half intervals at the two ends,
so sum(w) = T = t[-1] - t[0], and a time-weighted mean <x> = sum(w_i x_i) / T is the trapezoid rule.
Uniform and non-uniform sampling are treated alike. Every time-weighted mean below uses these w_i.

Definitions (each returned value has shape (N_L,)):
- impacts: number of impacts, an impact being a maximal run of consecutive samples in contact. A run
  already in contact at t[0], or still in contact at t[-1], counts (it is truncated by the record).
- impact_rate = impacts / T.
- contact_fraction = sum of w_i over the samples in contact / T.
- impact duration of the run i0..i1 = sum_{i0<=i<=i1} w_i = b_{i1+1} - b_{i0}: from the midpoint
  before its first contact sample to the midpoint after its last one. Each end is within half a
  sample interval of the true crossing, so a duration is resolution-limited to about one sample
  interval; a one-sample impact lasts one sample interval. impact_duration_mean and
  impact_duration_max are the mean and max over the impacts of the constraint (0 if none).
- force_peak = max_i |force_i|.
- force_rms = sqrt(<force^2>) over the whole run.
- force_rms_contact = sqrt(sum_contact w_i force_i^2 / sum_contact w_i), over the contact samples
  only (0 if never in contact). With force 0 out of contact (the default in_contact),
  force_rms^2 = contact_fraction * force_rms_contact^2, so force_rms_contact >= force_rms.
- displacement_rms = sqrt(<z^2>): the RMS about zero (the rest position), NOT about the mean of z,
  so a static offset counts.
- displacement_peak = max_i |z_i|.
- impact_power_mean = <|force v|>, W: the mean normal impact power over the whole run. A planar model
  has no sliding, so this is NOT a wear work rate (Archard wear needs the tangential sliding power).

Supports of two directions (a tube in a round hole, laws.PlanarLaws): the statistics are per
support, from radial quantities: z is |u| (m), contact is |u| > c, force is |F| (N), the impact
power is <|F_n v_n|> (normal force times normal velocity), and one more statistic,
- work_rate = <|F_n| |v_t|>, W: the normal work rate of code_aster's POST_USURE (the time-average
  of the normal contact force times the sliding speed), the input of Archard's wear law. The
  accumulator computes it over the solver's steps, as every other statistic.

A record of one sample (nt = 1) has no duration: impact_rate and the durations are 0, impacts and
contact_fraction are 1 or 0 from that sample, and the "time-weighted means" are the sample's values.
N_L = 0 gives empty arrays. Bad shapes or times raise ValueError: those are programming errors.
"""
from __future__ import annotations

import numpy as np

STATISTICS = ("impacts", "impact_rate", "contact_fraction", "impact_duration_mean", "impact_duration_max",
              "force_peak", "force_rms", "force_rms_contact", "displacement_rms", "displacement_peak",
              "impact_power_mean")

UNITS = {
    "impacts": "1",
    "impact_rate": "1/s",
    "contact_fraction": "1",
    "impact_duration_mean": "s",
    "impact_duration_max": "s",
    "force_peak": "N",
    "force_rms": "N",
    "force_rms_contact": "N",
    "displacement_rms": "m",
    "displacement_peak": "m",
    "impact_power_mean": "W",
}

DESCRIPTIONS = {
    "impacts": "number of impacts (maximal runs of consecutive contact points, the integrator's steps; runs cut by "
               "the record count)",
    "impact_rate": "impacts per second: impacts / (t_end - t_start)",
    "contact_fraction": "fraction of the run time in contact (trapezoid weights of the integrator's steps)",
    "impact_duration_mean": "mean impact duration, resolved by the integrator's steps (0 if no impact)",
    "impact_duration_max": "longest impact duration, resolved by the integrator's steps (0 if no impact)",
    "force_peak": "peak constraint force magnitude max |F|",
    "force_rms": "RMS constraint force over the whole run (time-weighted)",
    "force_rms_contact": "RMS constraint force over the time in contact only (0 if never in contact)",
    "displacement_rms": "RMS displacement at the constraint about zero, not about its mean (time-weighted)",
    "displacement_peak": "peak displacement magnitude max |z| at the constraint",
    "impact_power_mean": "mean of |F v| over the run: normal impact power, NOT a wear work rate "
                         "(a planar model has no sliding)",
}

assert set(UNITS) == set(STATISTICS) == set(DESCRIPTIONS)

# Supports of two directions (laws.PlanarLaws) add the normal work rate and its confidence interval, and
# Archard's wear volume K_w int |F_n| |v_t| dt = K_w T work_rate with the interval K_w T work_rate_ci95.
STATISTICS_2D = STATISTICS + ("work_rate", "work_rate_ci95", "wear_volume", "wear_volume_ci95")
UNITS_2D = {**UNITS, "work_rate": "W", "work_rate_ci95": "W", "wear_volume": "m^3", "wear_volume_ci95": "m^3"}
DESCRIPTIONS_2D = {**DESCRIPTIONS,
                   "work_rate": "normal work rate <|F_n| |v_t|> (code_aster's definition, the input of Archard wear): "
                                "supports of two directions only",
                   "work_rate_ci95": "half-width of the 95 % confidence interval of the work rate, by batch means of "
                                     "the samples (10 batches, Student t); supports of two directions only",
                   "wear_volume": "Archard wear volume K_w int |F_n| |v_t| dt = K_w T work_rate over the run's T, for "
                                  "the constraint's wear_coefficient K_w (NaN without one); supports of two directions "
                                  "only",
                   "wear_volume_ci95": "half-width of the 95 % confidence interval of the wear volume: K_w T "
                                       "work_rate_ci95"}


def wear_volume(coefficients, duration: float, work_rate, work_rate_ci95) -> tuple:
    """(wear volume, half-width of its 95 % interval), m^3, per support: K_w T <|F_n| |v_t|> (Archard,
    with the work rate of code_aster's POST_USURE) and K_w T times the work rate's half-width; NaN
    where K_w is None."""
    k = np.array([np.nan if c is None else float(c) for c in coefficients], dtype=float)
    return k * duration * np.asarray(work_rate, dtype=float), k * duration * np.asarray(work_rate_ci95, dtype=float)

BATCHES = 10
_T_975 = 2.2621571627982053   # Student's t, 97.5 % quantile, BATCHES - 1 = 9 degrees of freedom


def batch_means_ci95(t, series) -> np.ndarray:
    """The half-width of the 95 % confidence interval of the time mean of `series` (nt, n) sampled at
    t (nt,): the samples cut into BATCHES runs of equal length, the trapezoid mean of each, and
    t_(0.975, BATCHES - 1) s / sqrt(BATCHES), s the batch means' standard deviation. Batch means
    treat the batches as independent: batches much longer than the correlation time of the series
    (the tube's lowest periods, a few of its impacts). Fewer than 2 BATCHES samples: NaN."""
    t = np.asarray(t, dtype=float)
    series = np.asarray(series, dtype=float).reshape(t.size, -1)
    if t.size < 2 * BATCHES:
        return np.full(series.shape[1], np.nan)
    means = []
    for part in np.array_split(np.arange(t.size), BATCHES):
        tp, sp = t[part], series[part]
        means.append(np.trapz(sp, tp, axis=0) / (tp[-1] - tp[0]))
    return _T_975 * np.std(means, axis=0, ddof=1) / np.sqrt(BATCHES)


def _check(t, z, v, force, in_contact):
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size == 0:
        raise ValueError(f"t must be a non-empty 1-D array, got shape {t.shape}")
    if t.size > 1 and not np.all(np.diff(t) > 0):
        raise ValueError("t must be strictly increasing")
    z = np.asarray(z, dtype=float)
    if z.ndim != 2 or z.shape[0] != t.size:
        raise ValueError(f"z must have shape (nt, N_L) = ({t.size}, N_L), got {z.shape}")
    v = np.asarray(v, dtype=float)
    force = np.asarray(force, dtype=float)
    for name, a in (("v", v), ("force", force)):
        if a.shape != z.shape:
            raise ValueError(f"{name} must have the shape of z {z.shape}, got {a.shape}")
    if in_contact is not None:
        in_contact = np.asarray(in_contact)
        if in_contact.shape != z.shape:
            raise ValueError(f"in_contact must have the shape of z {z.shape}, got {in_contact.shape}")
        in_contact = in_contact.astype(bool, copy=False)
    return t, z, v, force, in_contact


def _single_sample(z, v, force, contact) -> dict[str, np.ndarray]:
    c = contact[0].astype(float)
    f = np.abs(force[0])
    return {
        "impacts": contact[0].astype(np.int64),
        "impact_rate": np.zeros_like(c),
        "contact_fraction": c,
        "impact_duration_mean": np.zeros_like(c),
        "impact_duration_max": np.zeros_like(c),
        "force_peak": f,
        "force_rms": f.copy(),
        "force_rms_contact": np.where(contact[0], f, 0.0),
        "displacement_rms": np.abs(z[0]),
        "displacement_peak": np.abs(z[0]),
        "impact_power_mean": np.abs(force[0] * v[0]),
    }


# Rows per block of the single pass over the samples: about 2**18 values per block keeps the scratch
# arrays in cache and the memory bounded whatever nt is.
_BLOCK_VALUES = 2 ** 18


def _weighted_sums(w, z, v, force, given):
    """One pass over blocks of rows: the weighted sums and peaks, and the contact runs as
    (sums, first sample, constraint, first sample after) with the runs sorted by constraint, then
    time."""
    nt, nl = z.shape
    sums = {name: np.zeros(nl) for name in ("force_sq", "force_sq_contact", "power", "z_sq", "force_peak", "z_peak")}
    starts, ends = [], []          # (sample, constraint) of each run's first sample / first sample after
    previous = np.zeros((1, nl), dtype=bool)   # contact before t[0]: none
    rows = max(1, _BLOCK_VALUES // max(nl, 1))
    for a in range(0, nt, rows):
        b = min(a + rows, nt)
        fb, wb = force[a:b], w[a:b]
        cb = (fb != 0) if given is None else given[a:b]
        before = np.concatenate((previous, cb[:-1]))
        k, j = np.nonzero(cb > before)
        starts.append((k + a, j))
        k, j = np.nonzero(cb < before)
        ends.append((k + a, j))
        previous = cb[-1:]

        scratch = np.abs(fb)
        np.maximum(sums["force_peak"], scratch.max(axis=0), out=sums["force_peak"])
        np.multiply(scratch, scratch, out=scratch)
        sums["force_sq"] += wb @ scratch
        if given is not None:
            np.multiply(scratch, cb, out=scratch)
            sums["force_sq_contact"] += wb @ scratch
        np.multiply(fb, v[a:b], out=scratch)
        np.abs(scratch, out=scratch)
        sums["power"] += wb @ scratch
        np.abs(z[a:b], out=scratch)
        np.maximum(sums["z_peak"], scratch.max(axis=0), out=sums["z_peak"])
        np.multiply(scratch, scratch, out=scratch)
        sums["z_sq"] += wb @ scratch
    if given is None:  # force is exactly 0 out of contact
        sums["force_sq_contact"] = sums["force_sq"]
    j = np.flatnonzero(previous[0])  # runs still in contact at t[-1] end with the record
    ends.append((np.full(j.size, nt), j))

    # Pair each run's start with its end: both sorted by constraint, then by time.
    first, col = (np.concatenate(x) for x in zip(*starts))
    end, end_col = (np.concatenate(x) for x in zip(*ends))
    order = np.lexsort((first, col))
    return sums, first[order], col[order], end[np.lexsort((end, end_col))]


def impact_statistics(t, z, v, force, in_contact=None) -> dict[str, np.ndarray]:
    """The impact statistics of STATISTICS (definitions in the module docstring), each of shape (N_L,).

    t (nt,) strictly increasing; z, v, force, in_contact (nt, N_L); in_contact defaults to force != 0.
    impacts is an int64 array, the others float64.
    """
    t, z, v, force, given = _check(t, z, v, force, in_contact)
    nt, nl = z.shape
    if nt == 1:
        return _single_sample(z, v, force, (force != 0) if given is None else given)

    duration_total = t[-1] - t[0]
    bounds = np.empty(nt + 1)
    bounds[0], bounds[-1] = t[0], t[-1]
    bounds[1:-1] = 0.5 * (t[:-1] + t[1:])
    sums, first, col, end = _weighted_sums(np.diff(bounds), z, v, force, given)
    durations = bounds[end] - bounds[first]

    impacts = np.bincount(col, minlength=nl).astype(np.int64)
    contact_time = np.bincount(col, weights=durations, minlength=nl)
    hit = impacts > 0
    duration_mean = np.zeros(nl)
    duration_mean[hit] = contact_time[hit] / impacts[hit]
    duration_max = np.zeros(nl)
    if durations.size:
        offsets = np.concatenate(([0], np.cumsum(impacts)[:-1]))
        duration_max[hit] = np.maximum.reduceat(durations, offsets[hit])
    force_rms_contact = np.zeros(nl)
    touched = contact_time > 0
    force_rms_contact[touched] = np.sqrt(sums["force_sq_contact"][touched] / contact_time[touched])
    force_sq, z_sq, power, force_peak, z_peak = (sums[k] for k in ("force_sq", "z_sq", "power", "force_peak", "z_peak"))

    return {
        "impacts": impacts,
        "impact_rate": impacts / duration_total,
        "contact_fraction": contact_time / duration_total,
        "impact_duration_mean": duration_mean,
        "impact_duration_max": duration_max,
        "force_peak": force_peak,
        "force_rms": np.sqrt(force_sq / duration_total),
        "force_rms_contact": force_rms_contact,
        "displacement_rms": np.sqrt(z_sq / duration_total),
        "displacement_peak": z_peak,
        "impact_power_mean": power / duration_total,
    }


def _check_overflow(t, z, v, force, squares) -> None:
    """Refuse statistics whose squares (F^2, z^2, |F v|: squares (3, k, n) at the k times t) overflow
    where z, v and F are finite (|F| beyond ~1e154 N): the RMS values would be inf. A state that is not
    finite is left to the integrators' own check and line. Red team: a spring-mass chain shaken by
    1e300 m printed numpy's overflow warnings before the full-order run's one line. Not collective."""
    over = ~np.isfinite(squares).all(axis=0)
    if not over.any():
        return
    over &= np.isfinite(z) & np.isfinite(v) & np.isfinite(force)
    if over.any():
        from .errors import SolverError

        step, j = np.argwhere(over)[0]
        raise SolverError(f"the statistics of constraint {j + 1} overflow at t = {float(t[step]):.6g} s: its force "
                          f"({float(force[step, j]):.3g} N) or displacement ({float(z[step, j]):.3g} m) squared is beyond "
                          f"double precision; check the excitation, the initial state and the laws for values "
                          f"beyond double precision (units)")


class ImpactAccumulator:
    """The same statistics as `impact_statistics`, accumulated point by point (the solver's steps)
    without storing the history: memory stays flat, and impacts shorter than an output sample are
    resolved as finely as the steps resolve them. Each point carries the trapezoid weight of its
    half intervals, exactly as in `impact_statistics`, so both agree on the same points."""

    def __init__(self, n: int, work: bool = False):
        self.n = n
        self.with_work = work
        self.work = np.zeros(n)          # the trapezoid integral of the work-rate series (with work)
        self.work_prev = None
        self.t0 = self.t_prev = None
        zeros = lambda: np.zeros(n)  # noqa: E731
        self.impacts, self.contact_time, self.run, self.duration_max = zeros(), zeros(), zeros(), zeros()
        self.f2, self.z2, self.power = zeros(), zeros(), zeros()
        self.force_peak, self.displacement_peak = zeros(), zeros()
        self.prev = None  # (contact, F^2, z^2, |F v|) at the previous point

    def add(self, t: float, z, v, force, in_contact=None, power=None, work=None) -> None:
        """One point. `power` (default |force v|) and, for an accumulator with work, `work` (the
        work-rate series, W) are given directly by 2-D supports."""
        z, v, force = (np.asarray(a, dtype=float) for a in (z, v, force))
        contact = force != 0 if in_contact is None else np.asarray(in_contact, dtype=bool)
        with np.errstate(over="ignore", invalid="ignore"):   # said below, or by the state check, not numpy
            now = (contact.astype(float), force * force, z * z,
                   np.abs(force * v) if power is None else np.asarray(power, dtype=float))
        _check_overflow(np.array([t]), z[None], v[None], force[None], np.stack(now[1:])[:, None])
        if self.with_work:
            work = np.asarray(work, dtype=float)
            if self.work_prev is not None:
                self.work += 0.5 * (t - self.t_prev) * (self.work_prev + work)
            self.work_prev = work
        np.maximum(self.force_peak, np.abs(force), out=self.force_peak)
        np.maximum(self.displacement_peak, np.abs(z), out=self.displacement_peak)
        if self.prev is None:
            self.t0 = t
            self.impacts += contact
        else:
            half = 0.5 * (t - self.t_prev)
            c_prev = self.prev[0]
            self.contact_time += half * (c_prev + now[0])
            self.f2 += half * (self.prev[1] + now[1])
            self.z2 += half * (self.prev[2] + now[2])
            self.power += half * (self.prev[3] + now[3])
            self.run += half * c_prev                     # the previous point's right half
            ended = (c_prev > 0) & ~contact
            np.maximum(self.duration_max, np.where(ended, self.run, 0.0), out=self.duration_max)
            self.run[ended] = 0.0
            self.impacts += contact & (c_prev == 0)
            self.run += half * now[0]                     # this point's left half
        self.t_prev = t
        self.prev = now

    def add_block(self, t, z, v, force, power=None, work=None) -> None:
        """`add` for k points at once, t (k,) increasing, z, v, force (k, n): the same sums,
        vectorized (an integrator that takes 10^5 steps hands them over in blocks: a few dozen numpy
        calls per block instead of a dozen per point). Equal to k calls of `add` to round-off; the
        same blocks give the same bits."""
        t = np.asarray(t, dtype=float)
        k, n = t.size, self.n
        if k == 0:
            return
        z, v, force = (np.asarray(a, dtype=float).reshape(k, n) for a in (z, v, force))
        series = np.empty((4, k + 1, n))       # contact, F^2, z^2, |F v|; row 0: the previous point
        now = series[:, 1:]
        np.not_equal(force, 0.0, out=now[0])
        with np.errstate(over="ignore", invalid="ignore"):   # said below, or by the state check, not numpy
            np.multiply(force, force, out=now[1])
            np.multiply(z, z, out=now[2])
            if power is None:
                np.multiply(force, v, out=now[3])
                np.abs(now[3], out=now[3])
            else:
                now[3] = np.asarray(power, dtype=float).reshape(k, n)
        _check_overflow(t, z, v, force, now[1:])
        if self.with_work:
            work = np.asarray(work, dtype=float).reshape(k, n)
            wt = t if self.work_prev is None else np.concatenate(([self.t_prev], t))
            ws = work if self.work_prev is None else np.vstack((self.work_prev, work))
            if wt.size > 1:
                self.work += np.einsum("i,ij->j", 0.5 * np.diff(wt), ws[:-1] + ws[1:])
            self.work_prev = work[-1].copy()
        np.maximum(self.force_peak, np.abs(force).max(axis=0), out=self.force_peak)
        np.maximum(self.displacement_peak, np.abs(z).max(axis=0), out=self.displacement_peak)
        if self.prev is None:  # the first point of the run: no interval before it
            self.t0 = t[0]
            self.impacts += now[0, 0] > 0
            times = t
            series = series[:, 1:]
        else:
            series[:, 0] = self.prev
            times = np.concatenate(([self.t_prev], t))
        self.t_prev, self.prev = t[-1], tuple(series[:, -1].copy())
        if times.size < 2:
            return
        half = 0.5 * np.diff(times)
        pairs = series[:, :-1] + series[:, 1:]
        increments = pairs * half[None, :, None]                 # the trapezoid of each interval
        sums = increments.sum(axis=1)
        self.contact_time += sums[0]
        self.f2 += sums[1]
        self.z2 += sums[2]
        self.power += sums[3]
        c = series[0]
        self.impacts += np.count_nonzero((c[1:] > 0) & (c[:-1] == 0), axis=0)
        if not c.any() and not self.run.any():
            return
        # The running impact duration: each interval adds the previous point's right half and this
        # point's left half (together its contact_time increment); an interval that ends contact
        # closes the impact (its duration counts toward the maximum) and restarts the count at 0.
        total = self.run + np.cumsum(increments[0], axis=0)
        ended = (c[:-1] > 0) & (c[1:] == 0)
        cols = np.arange(n)
        if ended.any():
            index = np.where(ended, np.arange(ended.shape[0])[:, None], -1)
            last = np.maximum.accumulate(index, axis=0)                      # last end at or before
            before = np.vstack((np.full((1, n), -1), last[:-1]))             # last end strictly before
            base = np.where(before >= 0, total[np.maximum(before, 0), cols], 0.0)
            closed = np.where(ended, total - base, 0.0)
            np.maximum(self.duration_max, closed.max(axis=0), out=self.duration_max)
            self.run = total[-1] - np.where(last[-1] >= 0, total[np.maximum(last[-1], 0), cols], 0.0)
        else:
            self.run = total[-1]

    _ARRAYS = ("impacts", "contact_time", "run", "duration_max", "f2", "z2", "power", "force_peak",
               "displacement_peak")

    def state(self) -> dict:
        """Everything the accumulator holds, as numpy arrays (for a checkpoint)."""
        out = {name: getattr(self, name).copy() for name in self._ARRAYS}
        started = self.prev is not None
        out["times"] = np.array([self.t0, self.t_prev] if started else [np.nan, np.nan])
        out["prev"] = np.array(self.prev) if started else np.zeros((4, self.n))
        out["started"] = np.array(started)
        if self.with_work:
            out["work"] = self.work.copy()
            out["work_prev"] = self.work_prev.copy() if self.work_prev is not None else np.full(self.n, np.nan)
        return out

    @classmethod
    def from_state(cls, state: dict) -> "ImpactAccumulator":
        self = cls(np.asarray(state["impacts"]).size, work="work" in state)
        if self.with_work:
            self.work = np.array(state["work"], dtype=float)
            prev = np.array(state["work_prev"], dtype=float)
            self.work_prev = None if np.all(np.isnan(prev)) else prev
        for name in self._ARRAYS:
            setattr(self, name, np.array(state[name], dtype=float))
        if bool(state["started"]):
            self.t0, self.t_prev = (float(v) for v in state["times"])
            self.prev = tuple(np.array(row, dtype=float) for row in state["prev"])
        return self

    def result(self) -> dict:
        """The statistics so far (names as in STATISTICS, one value per constraint)."""
        span = (self.t_prev - self.t0) if self.prev is not None else 0.0
        duration_max = np.maximum(self.duration_max, self.run)
        safe = lambda a, b: np.divide(a, b, out=np.zeros(self.n), where=b > 0)  # noqa: E731
        extra = {}
        if self.with_work:
            extra["work_rate"] = self.work / span if span > 0 else np.zeros(self.n)
        return {
            "impacts": self.impacts.copy(),
            "impact_rate": self.impacts / span if span > 0 else np.zeros(self.n),
            "contact_fraction": self.contact_time / span if span > 0 else np.zeros(self.n),
            "impact_duration_mean": safe(self.contact_time, self.impacts),
            "impact_duration_max": duration_max,
            "force_peak": self.force_peak.copy(),
            "force_rms": np.sqrt(self.f2 / span) if span > 0 else np.zeros(self.n),
            "force_rms_contact": np.sqrt(safe(self.f2, self.contact_time)),
            "displacement_rms": np.sqrt(self.z2 / span) if span > 0 else np.zeros(self.n),
            "displacement_peak": self.displacement_peak.copy(),
            "impact_power_mean": self.power / span if span > 0 else np.zeros(self.n),
            **extra,
        }
