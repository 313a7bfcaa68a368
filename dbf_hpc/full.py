"""The full-order reference: the whole finite-element model with the same constraint laws,
excitation and damping as the reduced model, integrated by PETSc TS on the distributed state.

    M u'' + C u' + K u = -(M r) Omega''(t) + g_F F(t) + sum_j g_j N_j(z_j, v_j)
    z_j = u_j + r_j Omega(t),   v_j = u'_j + r_j Omega'(t)

u is the displacement relative to the support motion, as in the reduced model (DESIGN.md), so the
two solve the same equations and differ only by the basis. TSALPHA2 is the generalized-alpha
method (Chung & Hulbert 1993): second order, unconditionally stable, with a tunable dissipation of
the highest mesh modes (-full_ts_alpha_radius, default 0.9), at the fixed step [integrator] dt:
adaptive steps (-full_ts_adapt_type basic) resolve the mesh modes that every impact sets ringing
and collapse to ~1e-8 s. The step and the mesh are checked by halving them (scripts/study_accuracy.py).
Its Jacobian

    dF/du + shift_V dF/du' + shift_A dF/du'' = K + shift_V C + shift_A M - G (N_z + shift_V N_v) G^T

differs from the linear operators only on the diagonal at the constraint rows; MUMPS factors it on
COMM_WORLD. Options prefix `full_`; the scene's [integrator] values are set first, so
command-line options win.

PETSc's generalized-alpha has no dense output. The samples are cubic Hermite interpolants of
(u, u') between the two steps around each sample time (third order, above the scheme's second),
so output never shortens a step.

Everything here is collective on ops.comm. Modal damping (zeta) has no sparse full-order
counterpart: the full model takes Rayleigh damping or a damping matrix.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

from .damping import Damping
from .errors import InputError, SolverError
from .integrate import sample_times
from .laws import ConstraintLaws
from .modes import reference_modes
from .operators import Operators, direct_solver, options_defaults, values_at
from .reduced import Harmonic

PREFIX = "full_"
SAME = PETSc.Mat.Structure.SAME_NONZERO_PATTERN


@dataclass(frozen=True)
class FullSettings:
    t_end: float
    dt: float                  # the step (the first step with -full_ts_adapt_type basic)
    rtol: float = 1e-6         # rtol, atol: used only with -full_ts_adapt_type basic
    atol: float = 1e-9
    sample_dt: float = 1e-3

    @property
    def sample_times(self) -> np.ndarray:
        return sample_times(self.t_end, self.sample_dt)


def damping_matrix(ops: Operators, damping: Damping) -> PETSc.Mat | None:
    """C of the full model: the given matrix, or alpha M + beta K. Collective."""
    if ops.C is not None:
        return ops.C
    if damping.kind == "modal":
        raise InputError("--method full: modal damping ([damping] zeta) has no sparse full-order counterpart; "
                         "give Rayleigh coefficients ([damping] rayleigh_alpha, rayleigh_beta) or a damping matrix")
    if damping.kind == "none":
        return None
    C = ops.M.duplicate(copy=True)
    C.scale(damping.rayleigh_alpha)
    C.axpy(damping.rayleigh_beta, ops.K, PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN)
    return C


class FullProblem:
    """The TS callbacks of the full model (petsc4py demo style: the object owns its PETSc objects).

    Each rank evaluates the laws of the constraints whose rows it owns: a law needs only its own
    DOF, so contact costs no communication."""

    def __init__(self, ops: Operators, rows, laws: ConstraintLaws, damping: Damping, support: Harmonic,
                 force, force_row: int | None = None, force_load: PETSc.Vec | None = None):
        self.ops, self.support, self.force = ops, support, force
        self.C = damping_matrix(ops, damping)
        self.own_C = self.C is not None and self.C is not ops.C
        lo, hi = ops.K.getOwnershipRange()
        self.lo = lo
        rows = np.asarray(rows, dtype=np.int64)
        mine = np.flatnonzero((rows >= lo) & (rows < hi))
        self.local_rows = rows[mine] - lo
        self.global_rows = rows[mine].astype(PETSc.IntType)
        self.laws = ConstraintLaws([laws.laws[j] for j in mine]) if mine.size else None
        moving = ops.influence is not None and support.amplitude != 0.0
        self.r_c = values_at(ops.influence, rows)[mine] if moving else np.zeros(mine.size)
        self.base_mass_load = ops.base_mass_load if moving else None
        self.force_row = force_row if force_row is not None and lo <= force_row < hi else None
        self.force_load = force_load
        # The Jacobian's pattern is the union of K's, M's and C's; K, M, C are copied onto it once
        # so that every update is a same-pattern axpy.
        pattern = PETSc.Mat.Structure.DIFFERENT_NONZERO_PATTERN
        self.J = ops.K.duplicate(copy=True)
        self.J.axpy(1.0, ops.M, pattern)
        if self.C is not None:
            self.J.axpy(1.0, self.C, pattern)
        self.J.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, True)
        self.J.setOption(PETSc.Mat.Option.SYMMETRIC, True)
        self.on_pattern = []
        for A in (ops.K, ops.M, self.C):
            if A is None:
                self.on_pattern.append(None)
                continue
            B = self.J.duplicate(copy=False)
            B.axpy(1.0, A, PETSc.Mat.Structure.SUBSET_NONZERO_PATTERN)
            self.on_pattern.append(B)
        self.jacobian_key = None
        self.jacobians = 0

    def constraint_state(self, t, u, v):
        """Total displacement and velocity at this rank's constraints."""
        z = u.getArray(readonly=True)[self.local_rows] + self.r_c * self.support.value(t)
        w = v.getArray(readonly=True)[self.local_rows] + self.r_c * self.support.rate(t)
        return z, w

    def i2function(self, ts, t, u, v, a, F):
        K, M, _ = self.on_pattern
        M.mult(a, F)
        K.multAdd(u, F, F)
        if self.C is not None:
            self.C.multAdd(v, F, F)
        if self.base_mass_load is not None:
            F.axpy(self.support.acceleration(t), self.base_mass_load)
        if self.force_load is not None:
            F.axpy(-float(self.force.value(t)), self.force_load)
        out = F.getArray()
        if self.force_row is not None:
            out[self.force_row - self.lo] -= float(self.force.value(t))
        if self.laws is not None:
            out[self.local_rows] -= self.laws.force(*self.constraint_state(t, u, v))

    def i2jacobian(self, ts, t, u, v, a, shift_v, shift_a, J, P):
        if self.laws is not None:
            _, dz, dv = self.laws.force_and_jacobian(*self.constraint_state(t, u, v))
            diagonal = -(dz + shift_v * dv)
        else:
            diagonal = np.zeros(0)
        # Rebuild (and so refactor) only when something changed on some rank: assembly is collective.
        key = (shift_v, shift_a, diagonal.tobytes())
        changed = self.ops.comm.tompi4py().allreduce(key != self.jacobian_key, op=MPI.LOR)
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
        for obj in (self.J, *self.on_pattern):
            if obj is not None:
                obj.destroy()
        if self.own_C:
            self.C.destroy()


def initial_displacement(ops: Operators, mode: int, amplitude: float) -> PETSc.Vec:
    """u(0): `amplitude` m peak (over the displacement DOFs) in reference mode `mode`, or zero."""
    u = ops.K.createVecRight()
    u.zeroEntries()
    if not amplitude:
        return u
    modes = reference_modes(ops, count=mode)
    modes.vectors.copyVec(mode - 1, u)
    modes.destroy()
    values = u.getArray(readonly=True)
    if ops.mesh is not None:
        lo, hi = u.getOwnershipRange()
        w_rows = ops.mesh.row[:, 0]
        values = values[w_rows[(w_rows >= lo) & (w_rows < hi)] - lo]
    peak = ops.comm.tompi4py().allreduce(float(np.abs(values).max(initial=0.0)), op=MPI.MAX)
    u.scale(amplitude / peak)
    return u


def _hermite(s: float, h: float):
    """Cubic Hermite weights (u0, h v0, u1, h v1) for the value and, divided by h, the rate at s."""
    s2, s3 = s * s, s * s * s
    value = (2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2)
    rate = ((6 * s2 - 6 * s) / h, 3 * s2 - 4 * s + 1, (-6 * s2 + 6 * s) / h, 3 * s2 - 2 * s)
    return value, rate


class Observer:
    """TS monitor: gathers (u, u') at the observed rows after every step, interpolates them to the
    sample times for `record(t, values, rates)`, hands each step's values to `on_step(t, values,
    rates)`, and gathers the whole field at the snapshot samples for `snapshot(i, u)` (rank 0).
    Collective: every rank takes the same path."""

    def __init__(self, problem: FullProblem, rows, times, record, on_step, snapshot_samples, snapshot,
                 progress: bool):
        self.problem, self.rows, self.times = problem, np.asarray(rows, dtype=np.int64), times
        self.record, self.on_step, self.snapshot = record, on_step, snapshot
        self.snapshot_samples = set(int(i) for i in snapshot_samples)
        self.next = 0
        self.prev = None            # (t, values, rates) at the previous step
        self.prev_u = self.prev_v = None
        self.failure = None
        self.progress, self.start = progress, time.perf_counter()
        self.last_report = self.start
        comm = problem.ops.comm
        self.world = comm.tompi4py()
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

    def monitor(self, ts, step, t, u):
        if self.failure:
            return
        _, v = ts.getSolution2()
        norm = u.norm() + v.norm()
        if not math.isfinite(norm):
            self.failure = (f"the state is not finite at t = {t:.6g} s (step {step}); reduce [integrator] dt "
                            f"or rtol, or raise -full_ts_alpha_radius below 1 to damp the mesh modes")
            ts.setMaxTime(t)
            return
        values, rates = self._gather(u, v)
        tol = 1e-9 * max(self.times[-1], 1.0)
        while self.next < self.times.size and self.times[self.next] <= t + tol:
            ts_ = self.times[self.next]
            if abs(ts_ - t) <= tol or self.prev is None:
                x, xd = values, rates
                field = u if self.next in self.snapshot_samples else None
            else:
                t0, x0, xd0 = self.prev
                h = t - t0
                (a0, b0, a1, b1), (c0, d0, c1, d1) = _hermite((ts_ - t0) / h, h)
                x = a0 * x0 + b0 * h * xd0 + a1 * values + b1 * h * rates
                xd = c0 * x0 + d0 * xd0 + c1 * values + d1 * rates
                field = None
                if self.next in self.snapshot_samples:
                    field = self.prev_u.copy()
                    field.scale(a0)
                    field.axpy(b0 * h, self.prev_v)
                    field.axpy(a1, u)
                    field.axpy(b1 * h, v)
            if field is not None:
                self.snapshot(self.next, self._field(field))
                if field is not u:
                    field.destroy()
            if self.world.rank == 0:
                self._on_rank0(self.record, ts_, x, xd)
            self.next += 1
        if self.world.rank == 0 and self.on_step is not None:
            self._on_rank0(self.on_step, t, values, rates)
        # Rank 0 writes the output: a failure there (a full disk) must stop every rank at this step.
        failure = self.world.bcast(self.failure, root=0)
        if failure:
            self.failure = failure
            ts.setMaxTime(t)
            return
        self.prev = (t, values, rates)
        if self.snapshot_samples:
            if self.prev_u is None:
                self.prev_u, self.prev_v = u.duplicate(), v.duplicate()
            u.copy(self.prev_u)
            v.copy(self.prev_v)
        now = time.perf_counter()
        if self.progress and now - self.last_report > 5.0 and t > 0:
            self.last_report = now
            t_end = self.times[-1]
            PETSc.Sys.Print(f"  t = {t:.4g} s of {t_end:g} s ({100 * t / t_end:.0f} %), "
                            f"{step / (now - self.start):.0f} steps/s, "
                            f"ETA {(now - self.start) * (t_end - t) / t:.0f} s", comm=self.problem.ops.comm)

    def _on_rank0(self, callback, *args) -> None:
        if self.failure:
            return
        try:
            callback(*args)
        except OSError as exc:
            self.failure = f"cannot write the output: {exc.strerror or exc}"

    def destroy(self) -> None:
        for obj in (self.prev_u, self.prev_v, self.scatter, self.full):
            if obj is not None:
                obj.destroy()


def integrate_full(problem: FullProblem, settings: FullSettings, u0: PETSc.Vec, observer: Observer) -> dict:
    """Integrate from (u0, u' = 0) at t = 0 to t_end with TSALPHA2. Returns solver statistics (the
    same keys as the reduced integrator's). Collective."""
    ops = problem.ops
    comm = ops.comm
    u = u0.duplicate()
    u0.copy(u)
    v = u.duplicate()
    v.zeroEntries()
    F = u.duplicate()
    ts = PETSc.TS().create(comm=comm)
    ts.setProblemType(PETSc.TS.ProblemType.NONLINEAR)
    ts.setType(PETSc.TS.Type.ALPHA2)
    ts.setI2Function(problem.i2function, F)
    ts.setI2Jacobian(problem.i2jacobian, problem.J, problem.J)
    ts.setTime(0.0)
    ts.setTimeStep(settings.dt)
    ts.setMaxTime(settings.t_end)
    ts.setMaxSteps(10**9)
    ts.setExactFinalTime(PETSc.TS.ExactFinalTime.MATCHSTEP)
    ts.setTolerances(rtol=settings.rtol, atol=settings.atol)
    ts.setErrorIfStepFails(False)
    ts.setMaxStepRejections(50)
    # Fixed steps by default: the generalized-alpha error estimate counts the velocities of the
    # mesh modes that every impact sets ringing, and its adaptive steps collapse to ~1e-8 s after
    # the first impact (measured on the paper's beam). -full_ts_adapt_type basic turns it on.
    defaults = {"ts_adapt_type": "none", "snes_linesearch_type": "basic", "ts_alpha_radius": "0.9"}
    adaptive = PETSc.Options(PREFIX).getString("ts_adapt_type", defaults["ts_adapt_type"]) != "none"
    # Adaptive: a failed Newton solve shrinks the step. Fixed: the first failure ends the run.
    ts.setMaxSNESFailures(-1 if adaptive else 1)
    if adaptive:  # a fixed step needs no limits (and dt may exceed 10 samples)
        ts.setStepLimits(settings.dt * 1e-8, max(settings.dt, settings.sample_dt * 10))
    snes = ts.getSNES()
    snes.setTolerances(rtol=1e-10, atol=1e-14, max_it=20)
    direct_solver(snes.getKSP(), "lu")
    ts.setMonitor(observer.monitor)
    with options_defaults(PREFIX, defaults):
        ts.setOptionsPrefix(PREFIX)
        ts.setFromOptions()
    ts.setSolution2(u, v)

    start = time.perf_counter()
    try:
        ts.solve(u)
    except PETSc.Error as e:
        if observer.failure is None:
            raise SolverError(f"the full-order integration failed at t = {ts.getTime():.6g} s: PETSc error "
                              f"{e.ierr}; reduce [integrator] dt or rtol") from None
    wall = time.perf_counter() - start
    stats = {"steps": ts.getStepNumber(), "rejected_steps": ts.getStepRejections(),
             "snes_failures": ts.getSNESFailures(), "newton_iterations": ts.getSNESIterations(),
             "factorizations": problem.jacobians, "time_integration": wall, "scheme": "alpha2",
             "final_time": ts.getTime(), "adaptive": adaptive, "contact": "implicit", "dt": settings.dt}
    reason = ts.getConvergedReason()
    for obj in (ts, u, v, F):
        obj.destroy()
    if observer.failure:
        raise SolverError(observer.failure)
    if reason < 0 or observer.next < observer.times.size:
        raise SolverError(f"the full-order integration stopped at t = {stats['final_time']:.6g} s of "
                          f"{settings.t_end:g} s (TS reason {reason}, {stats['snes_failures']} Newton failures, "
                          f"{stats['rejected_steps']} rejected steps): reduce [integrator] dt or rtol")
    return stats
