"""What a run records, whichever model computed it: samples, the peak force between samples, and
the impact statistics over the solver's steps; and what a run returns to a Python caller.

Both integrators hand their samples (total displacement and velocity at the constraints, probe
displacement, reduced coordinates if any) and their steps to a SampleRecorder, which writes rows
to a writer (output.py: an HDF5 file, or memory). Nothing here is collective: the recorder lives
on the rank that writes.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import layout
from .constraints import ConstraintSet
from .rom import ReducedModel
from .stats import ImpactAccumulator


class SampleRecorder:
    """Each sample becomes a row of the output; the impact statistics accumulate over the solver's
    steps, and the peak force over the steps since the previous sample goes with each sample
    (impacts are often shorter than a sample)."""

    def __init__(self, writer, constraints: ConstraintSet):
        self.writer, self.constraints = writer, constraints
        n = constraints.count * constraints.dimension
        # supports of two directions: statistics per support from radial quantities (stats.py)
        self.planar = constraints.dimension == 2
        self.impacts = ImpactAccumulator(constraints.count, work=True) if self.planar else ImpactAccumulator(n)
        self.peak = np.zeros(n)  # signed largest |N| at the steps since the previous sample
        self._tiled = {}         # block length -> the laws repeated for a block (steps)
        # Hunt-Crossley: the largest alpha |v| (alpha |v_n| on a support of two directions) at a step in contact,
        # per constraint (0 without Hunt-Crossley damping): the run warns above run.HUNT_CROSSLEY_MAX
        self.alpha = np.array([getattr(law, "alpha", 0.0) for law in constraints.laws.laws], dtype=float)
        self.hunt_crossley = bool(np.any(self.alpha > 0))
        self.alpha_speed = np.zeros(constraints.count)

    def _track_peak(self, force) -> None:
        larger = np.abs(force) > np.abs(self.peak)
        self.peak[larger] = force[larger]

    def sample(self, t, z, v, probe, q=(), p=()) -> None:
        force = self.constraints.force(z, v)
        self._track_peak(force)
        self.writer.append(**{layout.TIME: t, layout.CONSTRAINT_DISPLACEMENT: z, layout.CONSTRAINT_VELOCITY: v,
                              layout.CONSTRAINT_FORCE: force, layout.CONSTRAINT_FORCE_PEAK: self.peak.copy(),
                              layout.PROBE_DISPLACEMENT: probe, layout.REDUCED_Q: q, layout.REDUCED_QDOT: p})
        self.peak[:] = 0.0

    def step(self, t, z, v) -> None:
        force = self.constraints.force(z, v)
        if self.planar:
            r, vn, f, fn, vt, contact = (a[0] for a in self.constraints.laws.radial(z[None], v[None], force[None]))
            self.impacts.add(t, r, vn, f, contact, power=fn * np.abs(vn), work=fn * vt)
            self._track_alpha_speed(vn, contact)
        else:
            self.impacts.add(t, z, v, force)
            self._track_alpha_speed(v, force != 0)
        self._track_peak(force)

    def _track_alpha_speed(self, v, contact) -> None:
        """alpha_speed = max(alpha_speed, alpha |v|) over the points in contact (v, contact: (n,) or (k, n))."""
        if not self.hunt_crossley:
            return
        speed = np.where(contact, self.alpha * np.abs(v), 0.0).reshape(-1, self.alpha.size)
        larger = speed.max(axis=0, initial=0.0)
        bad = np.isnan(speed).any(axis=0) | np.isnan(self.alpha_speed)   # a NaN is kept, as in the C callbacks
        self.alpha_speed[:] = np.where(bad, np.nan, np.fmax(self.alpha_speed, larger))   # in place: C holds it

    def steps(self, t, z, v) -> None:
        """`step` for a block of k steps: t (k,), z and v (k, N_L d), in step order. One vectorized
        law evaluation and accumulation per block (the full-order integrator's form)."""
        t = np.asarray(t, dtype=float)
        if t.size == 0:
            return
        n = self.peak.size
        z = np.asarray(z, dtype=float).reshape(t.size, n)
        v = np.asarray(v, dtype=float).reshape(t.size, n)
        force = self._add_steps(t, z, v)
        if n:
            i = np.abs(force).argmax(axis=0)
            self._track_peak(force[i, np.arange(n)])

    def _add_steps(self, t, z, v) -> np.ndarray:
        """The laws' forces at steps t (k,) with z, v (k, N_L[, d]) into the impact statistics (radial
        values for supports of two directions); returns the forces."""
        n = self.peak.size
        force = self._block_laws(t.size).force(z.ravel(), v.ravel()).reshape(t.size, n)
        if self.planar:
            with np.errstate(over="ignore", invalid="ignore"):   # add_block says an overflow (stats._check_overflow)
                r, vn, f, fn, vt, contact = self.constraints.laws.radial(z, v, force)
                power, work = fn * np.abs(vn), fn * vt
            self.impacts.add_block(t, r, vn, f, power=power, work=work)
            self._track_alpha_speed(vn, contact)
        else:
            self.impacts.add_block(t, z, v, force)
            self._track_alpha_speed(v, force != 0)
        return force

    def _block_laws(self, k: int):
        """The laws repeated for k points (flat, point-major), one set per block length."""
        from .laws import ConstraintLaws, PlanarLaws

        if k not in self._tiled:
            kind = PlanarLaws if self.planar else ConstraintLaws
            self._tiled[k] = kind(list(self.constraints.laws.laws) * k)
        return self._tiled[k]

    def state(self) -> dict:
        """The recorder's part of a checkpoint (arrays)."""
        return {"peak": self.peak.copy(), "alpha_speed": self.alpha_speed.copy(),
                **{f"impacts/{k}": v for k, v in self.impacts.state().items()}}

    def restore(self, state: dict) -> None:
        self.peak = np.array(state["peak"], dtype=float)
        if "alpha_speed" in state:   # (a checkpoint written before it was recorded: from 0)
            self.alpha_speed[:] = np.asarray(state["alpha_speed"], dtype=float)
        self.impacts = ImpactAccumulator.from_state({k[len("impacts/"):]: v for k, v in state.items()
                                                     if k.startswith("impacts/")})


class FullRecorder(SampleRecorder):
    """A full-order run's samples and steps, handed over in blocks (fom_integrator.integrate_full's
    on_block): u and u' relative to the support at the observation's rows (the constraints', then
    those the probes combine), made total by the observation (fom.Observation)."""

    def __init__(self, writer, constraints: ConstraintSet, observation):
        super().__init__(writer, constraints)
        self.observation = observation

    def block(self, steps, samples) -> None:
        """steps = (t (k,), z (k, N_L), v (k, N_L)) after each step; samples = (t (J,), x (J, m),
        xd (J, m), cut (J,)), sample j after the first cut[j] steps: the same rows, peaks and
        statistics as step-by-step `step` and `sample` calls in that order."""
        n = self.peak.size
        t, z, v = steps
        if t.size:
            z, v = self.observation.constraint_totals(t, z, v)
            force = self._add_steps(t, z, v)
        ts, x, xd, cut = samples
        if not ts.size:
            if t.size:
                self.peak = _segment_peaks(np.vstack((self.peak, force)), np.array([0]))[0]
            return
        z_s, v_s, probe = self.observation.block_totals(ts, x, xd)
        sample_force = self._block_laws(ts.size).force(z_s.ravel(), v_s.ravel()).reshape(ts.size, n)
        # The sequence a step-by-step record sees: the peak carried in, then for each sample the steps
        # before it and the sample itself (whose row carries the peak since the previous sample).
        events = np.vstack((self.peak, np.insert(force, cut, sample_force, axis=0) if t.size else sample_force))
        ends = 1 + np.asarray(cut) + np.arange(ts.size)
        peaks = _segment_peaks(events[:ends[-1] + 1], np.concatenate(([0], ends[:-1] + 1)))
        tail = events[ends[-1] + 1:]
        self.peak = _segment_peaks(np.vstack((np.zeros(n), tail)), np.array([0]))[0] if tail.size else np.zeros(n)
        empty = np.zeros((ts.size, 0))
        self.writer.append_rows(**{layout.TIME: ts, layout.CONSTRAINT_DISPLACEMENT: z_s,
                                   layout.CONSTRAINT_VELOCITY: v_s, layout.CONSTRAINT_FORCE: sample_force,
                                   layout.CONSTRAINT_FORCE_PEAK: peaks, layout.PROBE_DISPLACEMENT: probe,
                                   layout.REDUCED_Q: empty, layout.REDUCED_QDOT: empty})


def _segment_peaks(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """(len(starts), n): in each run of rows values[starts[i]:starts[i + 1]] (the last to the end),
    per column the first value of largest magnitude, signed: what successive `_track_peak` calls
    keep (a later value replaces the peak only when strictly larger)."""
    magnitude = np.abs(values)
    largest = np.maximum.reduceat(magnitude, starts, axis=0)
    segment = np.repeat(np.arange(starts.size), np.diff(np.append(starts, values.shape[0])))
    rows = np.arange(values.shape[0])[:, None]
    first = np.minimum.reduceat(np.where(magnitude == largest[segment], rows, values.shape[0]), starts, axis=0)
    return values[first, np.arange(values.shape[1])]


class ReducedRecorder(SampleRecorder):
    """A reduced run's samples from q: the values at the constraints and probes, the coordinates at
    the snapshot samples (for the field, rom.ReducedField), and the final state."""

    def __init__(self, writer, model: ReducedModel, snapshot_samples=()):
        super().__init__(writer, model.constraints)
        self.model = model
        self.snapshot_samples = set(int(i) for i in snapshot_samples)
        self._snapshot_sorted = np.array(sorted(self.snapshot_samples), dtype=np.int64)
        self.snapshot_q = {}
        self.index = 0
        self.final = (model.q0.copy(), model.p0.copy())

    def record(self, t, q, p) -> None:
        m = self.model
        if self.index in self.snapshot_samples:
            self.snapshot_q[self.index] = q.copy()
        self.index += 1
        z, v = m.constraint_state(t, q, p)
        self.sample(t, z, v, m.probes(t, q), q, p)
        self.final = (q, p)

    def on_step(self, t, q, p) -> None:
        self.step(t, *self.model.constraint_state(t, q, p))

    def record_rows(self, rows: np.ndarray) -> None:
        """A block of samples the C callbacks computed (rom_integrator.py), one row each:
        [t, q (r), q' (r), z, v, force, peak (N_L d each), probe (P)], the same values `record` gives
        (the peak already includes the steps before each sample, and is reset after it)."""
        r, n, m = self.model.size, self.peak.size, rows.shape[0]
        edges = [0, 1, 1 + r, 1 + 2 * r, 1 + 2 * r + n, 1 + 2 * r + 2 * n, 1 + 2 * r + 3 * n, 1 + 2 * r + 4 * n,
                 rows.shape[1]]
        t, q, p, z, v, force, peak, probe = (rows[:, a:b] for a, b in zip(edges[:-1], edges[1:]))
        due = self._snapshot_sorted
        lo, hi = np.searchsorted(due, [self.index, self.index + m])
        for i in due[lo:hi].tolist():
            self.snapshot_q[i] = q[i - self.index].copy()
        self.index += m
        self.writer.append_rows(**{layout.TIME: t[:, 0], layout.CONSTRAINT_DISPLACEMENT: z,
                                   layout.CONSTRAINT_VELOCITY: v, layout.CONSTRAINT_FORCE: force,
                                   layout.CONSTRAINT_FORCE_PEAK: peak, layout.PROBE_DISPLACEMENT: probe,
                                   layout.REDUCED_Q: q, layout.REDUCED_QDOT: p})
        self.final = (q[-1].copy(), p[-1].copy())

    def snapshots(self, times: np.ndarray):
        """(snapshot times, w at the field points) from the coordinates kept at the snapshot samples."""
        indices = sorted(self.snapshot_q)
        field = self.model.field
        if field is None or not indices:
            return np.zeros(0), np.zeros((0, 0 if field is None else field.positions.size))
        t = times[indices]
        w = np.array([field.at(self.snapshot_q[i], self.model.support.value(ti)) for i, ti in zip(indices, t)])
        return t, w

    def state(self) -> dict:
        out = super().state()
        out.update(final_q=self.final[0], final_p=self.final[1], index=np.array(self.index),
                   snapshot_index=np.array(sorted(self.snapshot_q), dtype=np.int64),
                   snapshot_q=np.array([self.snapshot_q[i] for i in sorted(self.snapshot_q)]).reshape(
                       -1, self.model.size))
        return out

    def restore(self, state: dict) -> None:
        super().restore(state)
        self.final = (np.array(state["final_q"]), np.array(state["final_p"]))
        self.index = int(state["index"])
        self.snapshot_q = {int(i): np.array(q) for i, q in zip(state["snapshot_index"], state["snapshot_q"])}


@dataclass
class Result:
    """A run's results as numpy arrays (the Python API; a file-backed run has the same in HDF5).
    Constraint arrays are nt x N_L; q and qdot are nt x r (width 0 for a full-order run)."""

    time: np.ndarray
    displacement: np.ndarray          # total w at the constraints, m
    velocity: np.ndarray              # m/s
    force: np.ndarray                 # N on the structure at the samples
    force_peak: np.ndarray            # N, the largest |N| at the steps since the previous sample
    probes: np.ndarray                # total w at the probes, m
    q: np.ndarray
    qdot: np.ndarray
    statistics: dict                  # impact statistics per constraint (stats.STATISTICS)
    solver: dict = field(default_factory=dict)   # steps, rejections, Newton failures, wall time
    snapshot_time: np.ndarray = field(default_factory=lambda: np.zeros(0))
    snapshot_w: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))   # S x F, at the field points
    # per constraint, the largest alpha |v| of Hunt-Crossley damping at a step in contact (|v.n| on a support of
    # two directions; 0 without it): above run.HUNT_CROSSLEY_MAX (1.5) the law is outside its range
    alpha_speed: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def from_recorder(cls, recorder: SampleRecorder, solver: dict) -> "Result":
        data = {name: recorder.writer.series_data(name) for name in layout.SERIES}
        return cls(time=data[layout.TIME], displacement=data[layout.CONSTRAINT_DISPLACEMENT],
                   velocity=data[layout.CONSTRAINT_VELOCITY], force=data[layout.CONSTRAINT_FORCE],
                   force_peak=data[layout.CONSTRAINT_FORCE_PEAK], probes=data[layout.PROBE_DISPLACEMENT],
                   q=data[layout.REDUCED_Q], qdot=data[layout.REDUCED_QDOT],
                   statistics=recorder.impacts.result(), solver=dict(solver), alpha_speed=recorder.alpha_speed.copy())
