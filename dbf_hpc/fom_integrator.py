"""Time integration of the full-order model (fom.py) with PETSc TS on the distributed state: the
reference the reduced model is measured against.

TSALPHA2 is the generalized-alpha method (Chung & Hulbert 1993): second order, unconditionally
stable, with a tunable dissipation of the highest mesh modes (-full_ts_alpha_radius, default 0.9),
at the fixed step [integrator] dt: adaptive steps (-full_ts_adapt_type basic) resolve the mesh
modes that every impact sets ringing and collapse to ~1e-8 s. The step and the mesh are checked by
halving them (scripts/study_accuracy.py). Its Jacobian

    dF/du + shift_V dF/du' + shift_A dF/du'' = K + shift_V C + shift_A M - G (N_z + shift_V N_v) G^T

differs from the linear operators only on the diagonal at the constraint rows; MUMPS factors it on
the model's communicator. Options prefix `full_`; the [integrator] values are set first, so
command-line options win.

PETSc's generalized-alpha has no dense output. The samples are cubic Hermite interpolants of
(u, u') between the two steps around each sample time (third order, above the scheme's second),
so output never shortens a step. Everything here is collective on the model's communicator.
"""
from __future__ import annotations

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .errors import WRITE_ERRORS, write_failure
from .fom import FullOrderModel
from .laws import ConstraintLaws
from .petsctools import destroy, direct_solver
from .timestepping import IntegratorSettings, StepMonitor, check_outcome, configure, solve

PREFIX = "full_"
WHAT = "full-order integration"
SAME = PETSc.Mat.Structure.SAME_NONZERO_PATTERN


class FullProblem:
    """The TS callbacks of a full-order model (petsc4py demo style: the object owns its PETSc
    objects). Each rank evaluates the laws of the constraints whose rows it owns: a law needs only
    its own DOF, so contact costs no communication."""

    def __init__(self, fom: FullOrderModel):
        self.fom = fom
        ops = fom.operators
        self.C = fom.damping_matrix()
        lo, hi = ops.K.getOwnershipRange()
        self.lo = lo
        rows = fom.constraints.flat_rows
        mine = np.flatnonzero((rows >= lo) & (rows < hi))
        self.local_rows = rows[mine] - lo
        self.global_rows = rows[mine].astype(PETSc.IntType)
        self.laws = ConstraintLaws([fom.constraints.laws.laws[j] for j in mine]) if mine.size else None
        self.r_c = fom.influence_at(rows)[mine]
        self.J, self.on_pattern = self._pattern()
        self.jacobian_key = None
        self.jacobians = 0

    def _pattern(self):
        """The Jacobian's pattern is the union of K's, M's and C's; K, M, C are copied onto it once
        so that every update is a same-pattern axpy. A gyroscopic G would break the symmetry: the
        Jacobian is flagged symmetric only without one."""
        ops = self.fom.operators
        pattern = PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN
        J = ops.K.duplicate(copy=True)
        J.axpy(1.0, ops.M, pattern)
        if self.C is not None:
            J.axpy(1.0, self.C, pattern)
        J.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        J.setOption(PETSc.Mat.Option.SYMMETRIC, ops.G is None)
        copies = []
        for A in (ops.K, ops.M, self.C):
            B = None
            if A is not None:
                B = J.duplicate(copy=False)
                B.axpy(1.0, A, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
            copies.append(B)
        return J, copies

    def constraint_state(self, t, u, v):
        """Total displacement and velocity at this rank's constraints."""
        support = self.fom.support
        z = u.getArray(readonly=True)[self.local_rows] + self.r_c * support.value(t)
        w = v.getArray(readonly=True)[self.local_rows] + self.r_c * support.rate(t)
        return z, w

    def i2function(self, ts, t, u, v, a, F):
        K, M, C = self.on_pattern
        M.mult(a, F)
        K.multAdd(u, F, F)
        if C is not None:
            C.multAdd(v, F, F)
        self.fom.add_loads(t, F, scale=-1.0)
        if self.laws is not None:
            F.getArray()[self.local_rows] -= self.laws.force(*self.constraint_state(t, u, v))

    def i2jacobian(self, ts, t, u, v, a, shift_v, shift_a, J, P):
        if self.laws is not None:
            _, dz, dv = self.laws.force_and_jacobian(*self.constraint_state(t, u, v))
            diagonal = -(dz + shift_v * dv)
        else:
            diagonal = np.zeros(0)
        # Rebuild (and so refactor) only when something changed on some rank: assembly is collective.
        key = (shift_v, shift_a, diagonal.tobytes())
        changed = self.fom.comm.tompi4py().allreduce(key != self.jacobian_key, op=MPI.LOR)
        if not changed:
            return True
        self.jacobian_key = key
        self.jacobians += 1
        K, M, C = self.on_pattern
        K.copy(P, SAME)
        P.axpy(shift_a, M, SAME)
        if C is not None:
            P.axpy(shift_v, C, SAME)
        for row, value in zip(self.global_rows, diagonal):
            P.setValue(row, row, value, addv=PETSc.InsertMode.ADD_VALUES)
        P.assemble()
        if J != P:
            J.assemble()
        return True

    def destroy(self) -> None:
        destroy(self.J, *self.on_pattern)


def _hermite(s: float, h: float):
    """Cubic Hermite weights (u0, h v0, u1, h v1) for the value and, divided by h, the rate at s."""
    s2, s3 = s * s, s * s * s
    value = (2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2)
    rate = ((6 * s2 - 6 * s) / h, 3 * s2 - 4 * s + 1, (-6 * s2 + 6 * s) / h, 3 * s2 - 2 * s)
    return value, rate


class Observer:
    """TS monitor: gathers (u, u') at the observed rows after every step, interpolates them to the
    sample times for `record(t, values, rates)`, hands each step's values to `on_step(t, values,
    rates)` (both on rank 0), and gathers the whole field at the snapshot samples for
    `snapshot(i, u)` (rank 0; None elsewhere). Collective: every rank takes the same path; an
    OSError on rank 0 (a full disk) stops every rank at the same step."""

    def __init__(self, problem: FullProblem, rows, steps: StepMonitor, record, on_step, snapshot_samples, snapshot):
        self.problem, self.rows, self.steps = problem, np.asarray(rows, dtype=np.int64), steps
        self.record, self.on_step, self.snapshot = record, on_step, snapshot
        self.snapshot_samples = set(int(i) for i in snapshot_samples)
        self.prev = None            # (t, values, rates) at the previous step
        self.prev_u = self.prev_v = None
        self.world = problem.fom.comm.tompi4py()
        self.scatter = self.full = None

    def _gather(self, u, v):
        lo, hi = u.getOwnershipRange()
        mine = (self.rows >= lo) & (self.rows < hi)
        out = np.zeros((2, self.rows.size))
        out[0, mine] = u.getArray(readonly=True)[self.rows[mine] - lo]
        out[1, mine] = v.getArray(readonly=True)[self.rows[mine] - lo]
        out = self.world.allreduce(out)
        return out[0], out[1]

    def _field(self, u) -> np.ndarray | None:
        if self.scatter is None:
            self.scatter, self.full = PETSc.Scatter.toZero(u)
        self.scatter.scatter(u, self.full, addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        return self.full.getArray(readonly=True).copy() if self.world.rank == 0 else None

    def _interpolated_field(self, weights, h, u, v):
        (a0, b0, a1, b1) = weights
        field = self.prev_u.copy()
        field.scale(a0)
        field.axpy(b0 * h, self.prev_v)
        field.axpy(a1, u)
        field.axpy(b1 * h, v)
        values = self._field(field)
        field.destroy()
        return values

    def _sample(self, index, sample, exact, t, u, v, values, rates):
        if exact or self.prev is None:
            x, xd = values, rates
            field = self._field(u) if index in self.snapshot_samples else None
        else:
            t0, x0, xd0 = self.prev
            h = t - t0
            weights, (c0, d0, c1, d1) = _hermite((sample - t0) / h, h)
            a0, b0, a1, b1 = weights
            x = a0 * x0 + b0 * h * xd0 + a1 * values + b1 * h * rates
            xd = c0 * x0 + d0 * xd0 + c1 * values + d1 * rates
            field = self._interpolated_field(weights, h, u, v) if index in self.snapshot_samples else None
        if index in self.snapshot_samples:
            self.snapshot(index, field)
        if self.world.rank == 0:
            self._on_rank0(self.record, sample, x, xd)

    def __call__(self, ts, step, t, u):
        steps = self.steps
        if steps.failure:
            return
        _, v = ts.getSolution2()
        if not steps.check_finite(ts, step, t, u.norm() + v.norm(), "reduce [integrator] dt or rtol, or raise "
                                  "-full_ts_alpha_radius below 1 to damp the mesh modes"):
            return
        values, rates = self._gather(u, v)
        for index, sample, exact in steps.samples_due(t):
            self._sample(index, sample, exact, t, u, v, values, rates)
        if self.world.rank == 0 and self.on_step is not None:
            self._on_rank0(self.on_step, t, values, rates)
        # Rank 0 writes the output: a failure there (a full disk) must stop every rank at this step.
        failure = self.world.bcast(steps.failure, root=0)
        if failure:
            steps.stop(ts, t, failure)
            return
        self.prev = (t, values, rates)
        if self.snapshot_samples:
            if self.prev_u is None:
                self.prev_u, self.prev_v = u.duplicate(), v.duplicate()
            u.copy(self.prev_u)
            v.copy(self.prev_v)
        steps.report(step, t)

    def _on_rank0(self, callback, *args) -> None:
        if self.steps.failure:
            return
        try:
            callback(*args)
        except WRITE_ERRORS as exc:
            self.steps.failure = f"cannot write the output: {write_failure(exc)}"

    def destroy(self) -> None:
        destroy(self.prev_u, self.prev_v, self.scatter, self.full)


def integrate_full(fom: FullOrderModel, settings: IntegratorSettings, rows, record, on_step=None,
                   snapshot_samples=(), snapshot=None, say=None) -> dict:
    """Integrate from (u(0), u'(0) = 0) at t = 0 to t_end with TSALPHA2, observing (u, u') at `rows`
    (record(t, values, rates) at the samples, on_step(t, values, rates) after each step, on rank
    0) and the field at `snapshot_samples` (snapshot(i, u on rank 0)). Returns solver statistics
    (the same keys as the reduced integrator's). Collective."""
    problem = FullProblem(fom)
    u = fom.initial_displacement()
    v, F = u.duplicate(), u.duplicate()
    v.zeroEntries()
    ts = PETSc.TS().create(comm=fom.comm)
    steps = StepMonitor(settings.sample_times, say=say)
    observer = Observer(problem, rows, steps, record, on_step, snapshot_samples, snapshot)
    try:
        ts.setProblemType(PETSc.TS.ProblemType.NONLINEAR)
        ts.setType(PETSc.TS.Type.ALPHA2)
        ts.setI2Function(problem.i2function, F)
        ts.setI2Jacobian(problem.i2jacobian, problem.J, problem.J)
        direct_solver(ts.getSNES().getKSP(), "lu")
        ts.setMonitor(observer)
        # Fixed steps by default: the generalized-alpha error estimate counts the velocities of the
        # mesh modes that every impact sets ringing, and its adaptive steps collapse to ~1e-8 s after
        # the first impact (measured on the paper's beam). -full_ts_adapt_type basic turns it on.
        defaults = {"ts_adapt_type": "none", "snes_linesearch_type": "basic", "ts_alpha_radius": "0.9"}
        adaptive = PETSc.Options(PREFIX).getString("ts_adapt_type", defaults["ts_adapt_type"]) != "none"
        configure(ts, settings, PREFIX, defaults, adaptive)
        ts.setSolution2(u, v)
        wall = solve(ts, u, steps, WHAT, "reduce [integrator] dt or rtol")
        stats = {"steps": ts.getStepNumber(), "rejected_steps": ts.getStepRejections(),
                 "snes_failures": ts.getSNESFailures(), "newton_iterations": ts.getSNESIterations(),
                 "factorizations": problem.jacobians, "time_integration": wall, "scheme": "alpha2",
                 "final_time": ts.getTime(), "adaptive": adaptive, "contact": "implicit", "dt": settings.dt,
                 "dofs": fom.size}
        reason = ts.getConvergedReason()
    finally:
        observer.destroy()
        problem.destroy()
        destroy(ts, u, v, F)
    check_outcome(steps, reason, stats, settings.t_end, WHAT, "reduce [integrator] dt or rtol")
    return stats
