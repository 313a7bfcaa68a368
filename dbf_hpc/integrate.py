"""Time integration of the reduced model with PETSc TS ARKIMEX on y = [q, p], p = q' (DESIGN step 7).

    F(t, y, y') = [ q' - p ;  p' + D_r p + K_r q - B^T N(z, v) ]      implicit (stiff) part
    G(t, y)     = [ 0      ;  f_r(t) ]                                 explicit part (forcing)

With `contact = "explicit"` the contact force moves from F to G: the paper's IMEX split, where the
constraint is treated explicitly. The Jacobian of F is exact (the laws' derivatives):

    dF/dy + shift dF/dy' = [ shift I        -I                          ]
                           [ K_r - B^T N_z B   shift I + D_r - B^T N_v B ]

Options prefix `rom_` (-rom_ts_arkimex_type, -rom_ts_adapt_type, -rom_snes_test_jacobian, ...); the
scene's [integrator] values are set first, so command-line options win. A single case runs on one
rank (COMM_SELF). Samples are taken at fixed times by the TS's dense output (interpolated), or, for
the types without one, by making steps land on the sample times.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from petsc4py import PETSc

from .errors import InputError, SolverError
from .operators import options_defaults
from .reduced import ReducedModel

ARKIMEX_TYPES = ("1bee", "a2", "l2", "ars122", "2c", "2d", "2e", "prssp2", "3", "bpr3", "ars443", "4", "5")
NO_DENSE_OUTPUT = ("prssp2", "bpr3", "ars443")  # also without an embedded error estimate
PREFIX = "rom_"


@dataclass(frozen=True)
class IntegratorSettings:
    t_end: float
    dt: float
    scheme: str = "3"
    adaptive: bool = True
    rtol: float = 1e-6
    atol: float = 1e-9
    contact: str = "implicit"
    sample_dt: float = 1e-3

    def __post_init__(self):
        if self.scheme.lower() not in ARKIMEX_TYPES:
            raise InputError(f"[integrator] scheme {self.scheme!r} is not an ARKIMEX type; "
                             f"choose one of {', '.join(ARKIMEX_TYPES)}")
        if self.adaptive and self.scheme.lower() in NO_DENSE_OUTPUT:
            raise InputError(f"[integrator] scheme {self.scheme} has no embedded error estimate: "
                             f"set adaptive = false (fixed step dt) or choose an adaptive scheme")

    @property
    def sample_times(self) -> np.ndarray:
        return sample_times(self.t_end, self.sample_dt)


def sample_times(t_end: float, sample_dt: float) -> np.ndarray:
    """0, sample_dt, 2 sample_dt, ... and t_end itself."""
    count = int(math.floor(t_end / sample_dt * (1 + 1e-12))) + 1
    times = np.arange(count) * sample_dt
    return times if math.isclose(times[-1], t_end) else np.append(times, t_end)


class ReducedProblem:
    """The TS callbacks for one reduced model (petsc4py demo style: the object owns the state)."""

    def __init__(self, model: ReducedModel, implicit_contact: bool):
        self.model = model
        self.implicit_contact = implicit_contact and model.B.shape[0] > 0
        self.r = model.size

    def split(self, y):
        a = y.getArray(readonly=True)
        return a[: self.r], a[self.r:]

    def contact(self, t, q, p):
        z, v = self.model.constraint_state(t, q, p)
        return self.model.B.T @ self.model.laws.force(z, v)

    def ifunction(self, ts, t, y, ydot, f):
        m, r = self.model, self.r
        q, p = self.split(y)
        qd, pd = ydot.getArray(readonly=True)[:r], ydot.getArray(readonly=True)[r:]
        out = f.getArray()
        out[:r] = qd - p
        out[r:] = pd + m.D @ p + m.K @ q
        if self.implicit_contact:
            out[r:] -= self.contact(t, q, p)

    def ijacobian(self, ts, t, y, ydot, shift, J, P):
        m, r = self.model, self.r
        q, p = self.split(y)
        a = P.getDenseArray()
        a[:r, :r] = shift * np.eye(r)
        a[:r, r:] = -np.eye(r)
        a[r:, :r] = m.K
        a[r:, r:] = shift * np.eye(r) + m.D
        if self.implicit_contact:
            z, v = m.constraint_state(t, q, p)
            _, dz, dv = m.laws.force_and_jacobian(z, v)
            a[r:, :r] -= m.B.T @ (dz[:, None] * m.B)
            a[r:, r:] -= m.B.T @ (dv[:, None] * m.B)
        P.assemble()
        if J != P:
            J.assemble()
        return True

    def rhsfunction(self, ts, t, y, g):
        out = g.getArray()
        out[: self.r] = 0.0
        out[self.r:] = self.model.external_force(t)
        if not self.implicit_contact and self.model.B.shape[0]:
            q, p = self.split(y)
            out[self.r:] += self.contact(t, q, p)


class Sampler:
    """TS monitor: hands the state at each sample time to `record(t, q, p)` and then every step's
    end state to `on_step(ts, t, q, p)`, which may return a message to stop the run (an interrupt);
    reports progress."""

    def __init__(self, problem: ReducedProblem, times: np.ndarray, record, dense: bool, progress: bool,
                 on_step=None, first_sample: int = 0, resumed: bool = False):
        self.problem, self.times, self.record, self.dense = problem, times, record, dense
        self.on_step = on_step
        self.next = first_sample
        self.skip_step = resumed  # a resumed run's first call is the checkpointed step: seen already
        self.progress = progress
        self.failure = None
        self.start = self.last_report = time.perf_counter()
        self.first_step = self.first_time = None
        self.work = None

    def monitor(self, ts, step, t, y):
        if self.failure:
            return
        a = y.getArray(readonly=True)
        if not np.all(np.isfinite(a)):
            self.failure = (f"the state is not finite at t = {t:.6g} s (step {step}); reduce [integrator] dt "
                            f"or rtol, or set contact = \"implicit\"")
            ts.setMaxTime(t)
            return
        tol = 1e-9 * max(self.times[-1], 1.0)
        while self.next < self.times.size and self.times[self.next] <= t + tol:
            ts_ = self.times[self.next]
            if abs(ts_ - t) <= tol:
                state = a
            elif self.dense:
                if self.work is None:
                    self.work = y.duplicate()
                ts.interpolate(ts_, self.work)
                state = self.work.getArray(readonly=True)
            else:  # steps land on sample times (setTimeSpan): should not happen
                state = a
            r = self.problem.r
            self.record(ts_, state[:r].copy(), state[r:].copy())
            self.next += 1
        if self.on_step is not None and not self.skip_step:
            stop = self.on_step(ts, t, a[: self.problem.r], a[self.problem.r:])
            if stop:
                self.failure = stop
                ts.setMaxTime(t)
        self.skip_step = False
        now = time.perf_counter()
        if self.first_step is None:  # a resumed run starts at its checkpoint, not at 0
            self.first_step, self.first_time = step, t
        if self.progress and now - self.last_report > 5.0 and t > self.first_time:
            self.last_report = now
            t_end = self.times[-1]
            rate = (step - self.first_step) / (now - self.start)
            eta = (now - self.start) * (t_end - t) / (t - self.first_time)
            print(f"  t = {t:.4g} s of {t_end:g} s ({100 * t / t_end:.0f} %), {rate:.0f} steps/s, "
                  f"ETA {eta:.0f} s", flush=True)


def integrate(model: ReducedModel, settings: IntegratorSettings, record, progress: bool = False,
              on_step=None, resume: dict | None = None) -> dict:
    """Integrate from t = 0 (at rest in relative coordinates unless model.q0/p0) to t_end, calling
    record(t, q, p) at every sample time and on_step(ts, t, q, p) after every step. `resume` (from a
    checkpoint taken at the end of a step: t, dt, steps, next_sample, q, p and the failure counts
    so far) continues exactly where that step ended: same steps, same answer. Returns solver
    statistics. Runs on COMM_SELF."""
    r = model.size
    problem = ReducedProblem(model, settings.contact == "implicit")
    scheme = settings.scheme.lower()
    comm = PETSc.COMM_SELF
    y = PETSc.Vec().createSeq(2 * r, comm=comm)
    if resume:
        y.getArray()[:r], y.getArray()[r:] = resume["q"], resume["p"]
    else:
        y.getArray()[:r] = model.q0
        y.getArray()[r:] = 0.0 if model.p0 is None else model.p0
    F, G = y.duplicate(), y.duplicate()
    J = PETSc.Mat().createDense((2 * r, 2 * r), comm=comm)
    J.setUp()

    ts = PETSc.TS().create(comm=comm)
    ts.setProblemType(PETSc.TS.ProblemType.NONLINEAR)
    ts.setType(PETSc.TS.Type.ARKIMEX)
    ts.setARKIMEXType(scheme)
    ts.setIFunction(problem.ifunction, F)
    ts.setIJacobian(problem.ijacobian, J, J)
    ts.setRHSFunction(problem.rhsfunction, G)
    ts.setTime(resume["t"] if resume else 0.0)
    ts.setTimeStep(resume["dt"] if resume else settings.dt)
    if resume:
        ts.setStepNumber(resume["steps"])
    ts.setMaxTime(settings.t_end)
    ts.setMaxSteps(10**9)
    ts.setExactFinalTime(PETSc.TS.ExactFinalTime.MATCHSTEP)
    ts.setTolerances(rtol=settings.rtol, atol=settings.atol)
    ts.setErrorIfStepFails(False)
    # Adaptive: a failed Newton solve shrinks the step (down to the floor set below, where the run
    # stops with an error); failures are counted and reported. Fixed step: retrying the same step
    # would loop for ever, so the first failure ends the run with an error.
    ts.setMaxSNESFailures(-1 if settings.adaptive else 1)
    ts.setMaxStepRejections(50)  # consecutive, within one step: bounds the retries of a hopeless step
    # petsc4py 3.18 exposes neither TSAdapt nor SNESLineSearch: those defaults go through the
    # options database (operators.options_defaults: only where the user has not set them).
    # Full Newton steps: a backtracking line search stalls on the kinks of piecewise laws
    # (measured on the paper's beam: 90 Newton failures in 3 s with bt, 16 with basic).
    defaults = {"ts_adapt_type": "basic" if settings.adaptive else "none", "snes_linesearch_type": "basic"}
    if settings.adaptive:  # a fixed step needs no limits (and dt may exceed 10 samples)
        ts.setStepLimits(settings.dt * 1e-8, max(settings.dt, settings.sample_dt * 10))
    snes = ts.getSNES()
    snes.setTolerances(rtol=1e-10, atol=1e-14, max_it=20)
    ksp = snes.getKSP()
    ksp.setType(PETSc.KSP.Type.PREONLY)
    ksp.getPC().setType(PETSc.PC.Type.LU)
    dense = scheme not in NO_DENSE_OUTPUT
    times = settings.sample_times
    first = resume["next_sample"] if resume else 0
    if not dense:  # the span starts at the initial time
        ts.setTimeSpan(np.concatenate([[resume["t"]], times[first:]]) if resume else times)
    sampler = Sampler(problem, times, record, dense, progress, on_step, first, resumed=bool(resume))
    ts.setMonitor(sampler.monitor)
    with options_defaults(PREFIX, defaults):
        ts.setOptionsPrefix(PREFIX)
        ts.setFromOptions()

    start = time.perf_counter()
    try:
        ts.solve(y)
    except PETSc.Error as e:
        if sampler.failure is None:
            raise SolverError(f"the time integration failed at t = {ts.getTime():.6g} s: PETSc error {e.ierr}; "
                              f"reduce [integrator] dt or rtol") from None
    wall = time.perf_counter() - start
    before = resume or {}
    stats = {"steps": ts.getStepNumber(), "rejected_steps": ts.getStepRejections() + before.get("rejected", 0),
             "snes_failures": ts.getSNESFailures() + before.get("snes_failures", 0),
             "time_integration": wall + before.get("wall", 0.0),
             "scheme": ts.getARKIMEXType(), "final_time": ts.getTime(),
             "adaptive": settings.adaptive, "contact": settings.contact}
    reason = ts.getConvergedReason()
    for obj in (ts, y, F, G, J):
        obj.destroy()
    if sampler.work is not None:
        sampler.work.destroy()
    if sampler.failure:
        raise SolverError(sampler.failure)
    if reason < 0 or sampler.next < times.size:
        advice = ("set contact = \"implicit\" or reduce [integrator] dt" if settings.contact == "explicit"
                  else "reduce [integrator] dt or rtol, or try another scheme")
        raise SolverError(f"the time integration stopped at t = {stats['final_time']:.6g} s of {settings.t_end:g} s "
                          f"(TS reason {reason}, {stats['snes_failures']} Newton failures, "
                          f"{stats['rejected_steps']} rejected steps): {advice}")
    return stats
