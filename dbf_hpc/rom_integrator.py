"""Time integration of the reduced model with PETSc TS ARKIMEX on y = [q, p], p = q' (docs/design.md).

    F(t, y, y') = [ q' - p ;  p' + M_r^-1 (D p + K_r q - B^T N(z, v)) ]   implicit (stiff) part
    G(t, y)     = [ 0      ;  M_r^-1 f_r(t) ]                              explicit part (forcing)

D = C_r + G_r. ARKIMEX's explicit stages take F to be y' plus a function of y (an identity mass),
so M_r (I to round-off for an M-orthonormal basis) is factored out once, here. With
`contact = "explicit"` the contact force moves from F to G: the paper's IMEX split, where the
constraint is treated explicitly. The Jacobian of F is exact (the laws' derivatives):

    dF/dy + shift dF/dy' = [ shift I                      -I                               ]
                           [ M_r^-1 (K_r - B^T N_z B)    shift I + M_r^-1 (D - B^T N_v B)  ]

Options prefix `rom_` (-rom_ts_arkimex_type, -rom_ts_adapt_type, -rom_snes_test_jacobian, ...); the
[integrator] values are set first, so command-line options win, except over what [integrator] alone
sets (timestepping.SETTINGS_OPTIONS: refused, as the error estimate's richer run derives from it).
A case runs on one rank (COMM_SELF). Samples are taken at fixed times by the TS's dense output
(interpolated), or, for the types without one, by making steps land on the sample times.

Two implementations of the same callbacks ([integrator] callbacks, docs/design.md "The reduced
integrator's fast path"): ReducedProblem and _Monitor below, in Python, are the readable reference;
the C core (dbf_hpc/_romc: rom_core.c, core.pyx), built as an optional extension, is the fast path.
It keeps ARKIMEX and every option, and changes how the stage equations are solved: the Jacobian is a
MatShell, and its exact inverse is structured (A(shift) = shift^2 M_r + shift D + K_r factored once per
shift, Woodbury on the constraints in contact), applied by a Newton iteration in C (SNESSHELL) unless
a -rom_snes_*, -rom_ksp_* or -rom_pc_* option asks for PETSc's own (then NEWTONLS, KSPPREONLY and the
exact solve as a PCSHELL, so that -rom_snes_test_jacobian and monitors work). Its monitor takes the
samples and the per-step statistics in C and calls Python only to write blocks of samples and when
the per-step hook is due.
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from .errors import InputError, SolverError, warn
from .petsctools import destroy
from .rom import ReducedModel, applied
from .timestepping import (ADAPT_DEFAULTS, LAW_SCALES, NO_DENSE_OUTPUT, IntegratorSettings, StepMonitor,
                           check_outcome, checked_by_the_integrator, configure, solve)

PREFIX = "rom_"
WHAT = "time integration"
_warned = []


def c_core(callbacks: str, dimension: int = 1):
    """The C core for [integrator] callbacks = `callbacks`, or None for the Python callbacks. "c"
    without the extension is an InputError (one line saying how to build it); "auto" falls back to
    Python with a one-line warning (once per process). The C callbacks handle every law of laws.py:
    those of one direction (d = 1, with law = "friction"), and those of two (d = 2: circular, flat_bar,
    with friction and contact damping); one load shape times one history, or a load matrix times its
    histories (turbulence). With constraints of `dimension` > 2 directions "auto" takes the Python
    callbacks without a warning, and "c" is an InputError. The decision depends on the model alone:
    the same on every rank."""
    if callbacks == "python":
        return None
    if not _covered(dimension):
        if callbacks == "c":
            raise InputError(f"callbacks = \"c\": the C callbacks handle constraints of one or two directions, "
                             f"not {dimension}; use callbacks = \"auto\" or \"python\"")
        return None
    from . import _romc
    if _romc.core is not None:
        return _romc.core
    if callbacks == "c":
        raise InputError(_romc.why)
    say_fallback(callbacks, dimension, PETSc.COMM_WORLD)
    return None


def fallback_warning(callbacks: str, dimension: int = 1) -> str | None:
    """The line for callbacks = "auto" taking the Python callbacks where the C extension is not built or
    is switched off (DBF_HPC_NO_C), or None: decided by the setting, the laws' `dimension` and the
    installation, so the same on every rank. Not collective."""
    from . import _romc
    if callbacks != "auto" or not _covered(dimension) or _romc.core is not None:
        return None
    return f"{_romc.why}; using the Python callbacks (slower)"


def say_fallback(callbacks: str, dimension: int, comm) -> None:
    """fallback_warning once a process, from rank 0 of `comm` (errors.warn; not recorded in a run's
    output: it is of the installation, not the result, and a stored list must not depend on what the
    process ran before). Every rank decides it alike: the front ends call it on every rank before any
    case runs (run.run, sweep.run_sweep), c_core on the rank that integrates (simulate_reduced, called on
    every rank of a script, says it once). Red team: a sweep on 2 ranks, each rank integrating its own
    cases, printed it once per rank. Not collective."""
    message = fallback_warning(callbacks, dimension)
    if message and not _warned:
        _warned.append(True)
        warn(message, comm, record=False)


def effective_callbacks(callbacks: str, dimension: int = 1) -> str:
    """"c" or "python": what [integrator] callbacks = `callbacks` runs on this installation for laws
    of `dimension` (as c_core decides; part of a checkpoint's identity: the two agree to the
    integrator's tolerance, not bit for bit)."""
    from . import _romc
    return "c" if callbacks != "python" and _covered(dimension) and _romc.core is not None \
        else "python"


def _covered(dimension: int) -> bool:
    """Whether the C callbacks implement the model: laws of one or two directions (with friction, with
    a load matrix or not: every law and load is covered)."""
    return dimension in (1, 2)


def _user_solver_options() -> bool:
    """Whether the user set any -rom_snes_*, -rom_ksp_* or -rom_pc_* option (then PETSc's own Newton)."""
    return any(name.startswith((PREFIX + "snes_", PREFIX + "ksp_", PREFIX + "pc_"))
               for name in PETSc.Options().getAll())


def _user_viewers() -> bool:
    return any(name.startswith(PREFIX) and "view" in name for name in PETSc.Options().getAll())


class ReducedProblem:
    """The TS callbacks for one reduced model (petsc4py demo style: the object owns the state).
    The model's matrices are taken with M_r^-1 applied once (module docstring)."""

    def __init__(self, model: ReducedModel, implicit_contact: bool):
        self.model = model
        self.implicit_contact = implicit_contact and model.B.shape[0] > 0
        self.r = r = model.size
        identity = np.array_equal(model.M, np.eye(r))
        solve = (lambda A: A) if identity else (lambda A: np.linalg.solve(model.M, A))
        self.K, self.D, self.Bt = solve(model.K), solve(model.damping), solve(model.B.T)
        self.force_shape, self.base_load = solve(model.force_shape), solve(model.base_load)
        self.eye = np.eye(r)

    def coordinates(self, t, state, copy: bool = True):
        """(q, q') of a state vector's array (copies, or views with copy=False)."""
        q, p = state[: self.r], state[self.r:]
        return (q.copy(), p.copy()) if copy else (q, p)

    def commit(self, t, q, p) -> None:
        """The laws' state after an accepted step."""
        self.model.constraints.commit(*self.model.constraint_state(t, q, p))

    def split(self, y):
        a = y.getArray(readonly=True)
        return a[: self.r], a[self.r:]

    def contact(self, t, q, p):
        z, v = self.model.constraint_state(t, q, p)
        return self.Bt @ self.model.constraints.force(z, v)

    def forcing(self, t) -> np.ndarray:
        m = self.model
        return applied(self.force_shape, m.force.value(t)) - self.base_load * m.support.acceleration(t)

    @checked_by_the_integrator
    def ifunction(self, ts, t, y, ydot, f):
        r = self.r
        q, p = self.split(y)
        qd, pd = ydot.getArray(readonly=True)[:r], ydot.getArray(readonly=True)[r:]
        out = f.getArray()
        out[:r] = qd - p
        out[r:] = pd + self.D @ p + self.K @ q
        if self.implicit_contact:
            out[r:] -= self.contact(t, q, p)

    @checked_by_the_integrator
    def ijacobian(self, ts, t, y, ydot, shift, J, P):
        m, r = self.model, self.r
        q, p = self.split(y)
        a = P.getDenseArray()
        a[:r, :r] = shift * self.eye
        a[:r, r:] = -self.eye
        a[r:, :r] = self.K
        a[r:, r:] = shift * self.eye + self.D
        if self.implicit_contact:
            z, v = m.constraint_state(t, q, p)
            d = m.constraints.dimension
            if d == 1:
                _, dz, dv = m.constraints.diagonal_jacobian(z, v)
                a[r:, :r] -= self.Bt @ (dz[:, None] * m.B)
                a[r:, r:] -= self.Bt @ (dv[:, None] * m.B)
            else:  # d x d blocks per constraint
                _, dz, dv = m.constraints.force_and_jacobian(z, v)
                blocks = m.B.reshape(-1, d, r)
                a[r:, :r] -= self.Bt @ np.einsum("jab,jbr->jar", dz, blocks).reshape(-1, r)
                a[r:, r:] -= self.Bt @ np.einsum("jab,jbr->jar", dv, blocks).reshape(-1, r)
        P.assemble()
        if J != P:
            J.assemble()
        return True

    @checked_by_the_integrator
    def rhsfunction(self, ts, t, y, g):
        out = g.getArray()
        out[: self.r] = 0.0
        out[self.r:] = self.forcing(t)
        if not self.implicit_contact and self.model.B.shape[0]:
            q, p = self.split(y)
            out[self.r:] += self.contact(t, q, p)


class _Monitor:
    """Samples (dense output, or the steps that land on them), the per-step hook, the law state. The
    problem says what (q, p) a state is (`coordinates`) and keeps the laws' state (`commit`): a
    ReducedProblem, or state_space.StateSpaceProblem (q = eta, p = eta')."""

    def __init__(self, problem, steps: StepMonitor, record, on_step, dense: bool, recorder=None, advice=""):
        self.problem, self.steps, self.record, self.on_step, self.dense = problem, steps, record, on_step, dense
        self.recorder, self.advice = recorder, advice
        self.work = None

    def __call__(self, ts, step, t, y):
        steps, problem = self.steps, self.problem
        if steps.failure:
            return
        a = y.getArray(readonly=True)
        if not steps.check_finite(ts, step, t, float(np.sum(np.abs(a))), self.advice):
            return
        for _, sample, exact in steps.samples_due(t):
            state = a
            if not exact and self.dense:
                if self.work is None:
                    self.work = y.duplicate()
                ts.interpolate(sample, self.work)
                state = self.work.getArray(readonly=True)
            self.record(sample, *problem.coordinates(sample, state))
        if steps.new_step():
            q, p = problem.coordinates(t, a, copy=False)
            problem.commit(t, q, p)
            if self.recorder is not None:
                self.recorder.on_step(t, q, p)
            if self.on_step is not None:
                stop = self.on_step(ts, t, q, p)
                if stop:
                    steps.stop(ts, t, stop)
        steps.report(step, t)


# The C context's counters, in the order a checkpoint stores them (c_counters), and the TS attribute
# under which the checkpoints find the context
C_COUNTERS = ("snes_solves", "newton", "ifunction", "ijacobian", "rhsfunction", "exact_solves", "factorizations",
              "matmult", "linear_shortcuts")
C_CONTEXT = "dbf_hpc_c_context"


def c_counters(ts) -> np.ndarray | None:
    """The C callbacks' counters of this TS's integration so far (C_COUNTERS order), or None."""
    fast = ts.getAttr(C_CONTEXT)
    return None if fast is None else np.array([fast.counters[name] for name in C_COUNTERS], dtype=np.int64)


def highest_mode_hz(model) -> float:
    """The frequency of the model's highest reference mode (Hz; |omega| of a complex one), 0 without
    modes: what scales an adaptive run's step floor (timestepping.configure). Not collective."""
    omega = np.abs(np.asarray(getattr(model, "basis_info", {}).get("omega", ()), dtype=complex))
    return float(omega.max()) / (2 * np.pi) if omega.size else 0.0


def integrate_reduced(model: ReducedModel, settings: IntegratorSettings, record=None, on_step=None, say=None,
                      resume: dict | None = None, *, recorder=None, due=None) -> dict:
    """Integrate from t = 0 (model.q0, model.p0) to t_end, calling record(t, q, p) at every sample
    time and on_step(ts, t, q, p) after every step (it may return a message to stop the run).
    `recorder` (recorder.ReducedRecorder) instead of `record`: the samples and the per-step impact
    statistics go to it (recorder.record, recorder.on_step); the C callbacks then do that work in C,
    in the recorder's own arrays. `due()`: the simulated time from which on on_step wants to be
    called (the C callbacks call it only then; -inf: at the end of this step).
    `resume` (from a checkpoint taken at the end of a step: t, dt, steps, next_sample, q, p and the
    failure counts so far) continues exactly where that step ended: same steps, same answer.
    Progress lines go to say(line) when given. Returns solver statistics. Runs on COMM_SELF.
    A state_space.StateSpaceModel (a gyroscopic structure's first-order form) integrates y = eta
    (its q; p is eta' from the equation) with StateSpaceProblem's callbacks or the C core's
    first-order mode, on the same TS, options and statistics."""
    first_order = getattr(model, "form", "") == "state_space"
    if (record is None) == (recorder is None):
        raise TypeError("integrate_reduced takes either record or recorder")
    if recorder is not None:
        record = recorder.record
    core = c_core(settings.callbacks, model.constraints.dimension)
    r = model.size
    implicit = settings.contact == "implicit"
    if first_order:
        from .state_space import StateSpaceProblem

        problem, n = StateSpaceProblem(model, implicit), r
        start = resume["q"] if resume else model.q0
    else:
        problem, n = ReducedProblem(model, implicit), 2 * r
        start = np.concatenate((resume["q"], resume["p"]) if resume else (model.q0, model.p0))
    comm = PETSc.COMM_SELF
    y = PETSc.Vec().createSeq(n, comm=comm)
    y.getArray()[:] = start
    F, G, work = y.duplicate(), y.duplicate(), y.duplicate()
    ts = PETSc.TS().create(comm=comm)
    J = fast = monitor = ksp = failed = None
    c_newton = viewers_off = False
    try:
        ts.setProblemType(PETSc.TS.ProblemType.NONLINEAR)
        ts.setType(PETSc.TS.Type.ARKIMEX)
        ts.setARKIMEXType(settings.scheme)
        ksp = ts.getSNES().getKSP()
        ksp.setType(PETSc.KSP.Type.PREONLY)
        if core is None:
            J = PETSc.Mat().createDense((n, n), comm=comm)
            J.setUp()
            ts.setIFunction(problem.ifunction, F)
            ts.setIJacobian(problem.ijacobian, J, J)
            ts.setRHSFunction(problem.rhsfunction, G)
            ksp.getPC().setType(PETSc.PC.Type.LU)
        else:
            fast = core.Problem(model, problem, implicit)
            ts.setAttr(C_CONTEXT, fast)   # the checkpoints read its counters (run.Checkpointing)
            J = fast.shell_matrix()
            fast.attach(ts, F, G, J, True)
            fast.set_pcshell(ksp.getPC())
            c_newton = not _user_solver_options()
            if c_newton:
                fast.set_snes_shell(ts.getSNES())
        dense = settings.scheme not in NO_DENSE_OUTPUT
        times = settings.sample_times
        first = resume["next_sample"] if resume else 0
        if not dense:  # the span starts at the initial time
            ts.setTimeSpan(np.concatenate([[resume["t"]], times[first:]]) if resume else times)
        steps = StepMonitor(times, first, resumed=bool(resume), say=say)
        if fast is None:
            monitor = _Monitor(problem, steps, record, on_step, dense, recorder, step_advice(settings))
            ts.setMonitor(monitor)
        else:
            stateful = getattr(model.constraints, "stateful", False)
            state = (lambda t, q, p: model.constraint_state(t, q)) if first_order else model.constraint_state
            commit = (lambda t, q, p: model.constraints.commit(*state(t, q, p))) if stateful else None
            steps.ts = ts
            fast.set_monitor(ts, work, steps, times, dense, record, recorder, on_step, due, commit, bool(resume))
        # Full Newton steps: a backtracking line search stalls on the kinks of piecewise laws
        # (measured on the paper's beam: 90 Newton failures in 3 s with bt, 16 with basic).
        # The step controller (docs/design.md, "The reduced integrator's fast path"): safety 0.8 and a
        # growth of at most 1.5 per step halve the rejections at contact onset for fewer Newton iterations.
        # petsc4py 3.18 exposes neither TSAdapt nor SNESLineSearch: defaults go through the options.
        defaults = {"ts_adapt_type": "basic" if settings.adaptive else "none", "snes_linesearch_type": "basic"}
        if settings.adaptive:
            defaults.update(ADAPT_DEFAULTS)
        configure(ts, settings, PREFIX, defaults, settings.adaptive, resume, steps, highest_mode_hz(model))
        c_newton = c_newton and ts.getSNES().getType() == "shell"
        if c_newton and not _user_viewers():
            # the *ViewFromOptions queries inside every stage solve cost more than the solve: off
            core.viewers_off()
            viewers_off = True
        try:
            wall = solve(ts, y, steps, WHAT, step_advice(settings))
        except SolverError:
            if fast is not None and fast.error is not None:
                raise fast.error from None
            raise
        finally:
            if viewers_off:
                core.viewers_pop()
            if fast is not None and fast.error is None:
                fast.sync()   # the samples still in the C buffer, the statistics' scalars
        if fast is not None:
            if fast.error is not None:
                raise fast.error
            steps.next = fast.next_sample
            if fast.nonfinite is not None:
                step, t = fast.nonfinite
                steps.failure = f"the state is not finite at t = {t:.6g} s (step {step}); {step_advice(settings)}"
            elif fast.stop_message:
                steps.failure = fast.stop_message
        before = resume or {}
        stats = {"steps": ts.getStepNumber(), "rejected_steps": ts.getStepRejections() + before.get("rejected", 0),
                 "snes_failures": ts.getSNESFailures() + before.get("snes_failures", 0),
                 "time_integration": wall + before.get("wall", 0.0),
                 "scheme": ts.getARKIMEXType(), "final_time": ts.getTime(),
                 "adaptive": settings.adaptive, "contact": settings.contact,
                 "callbacks": "python" if fast is None else "c",
                 "newton": "petsc" if fast is None or not c_newton else "c",
                 **({"form": "state_space"} if first_order else {})}
        stats["newton_iterations"] = ts.getSNESIterations() + int(before.get("newton_iterations", 0))
        if fast is not None:   # a resumed run's whole, as the other counts
            done = before.get("c_counters")
            stats["c_counters"] = {name: value + (int(done[C_COUNTERS.index(name)]) if done is not None else 0)
                                   for name, value in fast.counters.items()}
        reason = ts.getConvergedReason()
        steps.last_step = ts.getTimeStep()   # check_outcome: a run that failed at its floor says so
        if reason < 0:   # what failed, read before the TS goes (failure_advice)
            snes = ts.getSNES()
            failed = dict(snes_reason=snes.getConvergedReason(), snes_its=snes.getIterationNumber(),
                          step=ts.getTimeStep(), t=ts.getTime(), state=y.getArray(readonly=True).copy())
    finally:
        # ksp is our reference to the TS's own solver (dropped by Python after the TS, petsc4py 3.18 parks it
        # in PETSc's garbage: one KSP per integration in a long process)
        destroy(ts, ksp, y, F, G, J, work, monitor.work if monitor is not None else None)
    advice = (failure_advice(model, settings, reason, first_order, **failed) if failed is not None else
              f"check {LAW_SCALES} against the structure's own scales and units")
    # a failure the user's own solver options explain is not pinned on the input (FIRST_STEP_HINT)
    check_outcome(steps, reason, stats, settings.t_end, WHAT, advice, input_hint=not _user_options())
    return stats


def step_advice(settings: IntegratorSettings) -> str:
    """The change most likely to help a reduced run whose state became non-finite or whose solve PETSc
    stopped: explicit contact (unstable at steps longer than a contact lasts), a fixed step (too long),
    or, on adaptive implicit steps, which reject what they cannot resolve, the input's scales. Red team:
    each said "reduce [integrator] dt or rtol", rtol also for a fixed step, where it does nothing."""
    if settings.contact == "explicit":
        return ("set contact = \"implicit\" in [integrator] (an explicit contact force is unstable at steps longer than "
                "a contact lasts), or lower [integrator] dt")
    if not settings.adaptive:
        return (f"lower [integrator] dt (now {settings.dt:g} s), or set [integrator] adaptive = true, whose steps "
                f"shrink where a Newton solve fails")
    return (f"check {LAW_SCALES} against the structure's own scales and units (values beyond double precision), or "
            f"lower [integrator] rtol (now {settings.rtol:g})")


SNES_REASONS = {value: name for name, value in vars(PETSc.SNES.ConvergedReason).items() if isinstance(value, int)}
CONTACTS_NAMED = 3   # constraints in contact a failure line names (the count of the rest)


def _nearest_stop(constraints, z) -> str:
    """", the nearest its stop: constraint J (place, law), X m away" for the one-direction stops (the
    constraint a failed step most likely reached), or "" where there is none."""
    if constraints.dimension != 1:
        return ""
    gaps = []
    for j, law in enumerate(constraints.laws.laws):
        sides = ([law.clearance_plus - z[j]] if law.k_plus > 0 else []) + \
                ([z[j] + law.clearance_minus] if law.k_minus > 0 else [])
        if law.kind in ("deadband", "power", "hertz") and sides:
            gaps.append((min(sides), j))
    if not gaps:
        return ""
    gap, j = min(gaps)
    return (f", the nearest its stop: constraint {j + 1} ({constraints.labels[j]}, {constraints.laws.laws[j].kind}), "
            f"{gap:.3g} m away")


def _user_options() -> list:
    """The -rom_snes_/ksp_/pc_/ts_ options the user set, sorted, with their dash."""
    return sorted(f"-{name}" for name in PETSc.Options().getAll()
                  if name.startswith(tuple(PREFIX + kind for kind in ("snes_", "ksp_", "pc_", "ts_"))))


def failure_advice(model, settings: IntegratorSettings, reason: int, first_order: bool, snes_reason: int, snes_its: int,
                   step: float, t: float, state: np.ndarray) -> str:
    """What a reduced run that stopped (TS reason < 0) ran into and the one change most likely to help:
    the Newton solve's reason and the step it failed on, the constraints in contact at the last accepted
    state (their place and law), and, in this order, the user's own solver options (-rom_snes_max_it 1),
    explicit contact, a fixed step (lower dt, or adaptive steps, which shrink where Newton fails), or the
    laws' and loads' scales. Red team: every such stop said "reduce [integrator] dt or rtol, or try another
    scheme", rtol also for a fixed step, where it does nothing, and named neither the option that starved
    the Newton solve nor the constraint."""
    if reason == PETSc.TS.ConvergedReason.DIVERGED_STEP_REJECTED:
        what = (f"50 tries in a row at one step were rejected, the last of {step:.3g} s (its Newton solve: "
                f"{SNES_REASONS.get(snes_reason, snes_reason)}, {snes_its} iterations)")
    else:
        what = (f"the Newton solve of a step of {step:.3g} s failed ({SNES_REASONS.get(snes_reason, snes_reason)} after "
                f"{snes_its} iterations)")
    constraints = model.constraints
    if constraints.count:
        try:
            r = model.size
            q, p = (state, None) if first_order else (state[:r], state[r:])
            z, _ = model.constraint_state(t, q, p)
            touching = np.flatnonzero(constraints.in_contact(z))
        except (ValueError, TypeError, FloatingPointError):   # no state to say it from
            touching = None
        if touching is not None and touching.size:
            laws = constraints.laws.laws
            named = ", ".join(f"constraint {j + 1} ({constraints.labels[j]}, {laws[j].kind})"
                              for j in touching[:CONTACTS_NAMED])
            more = f" and {touching.size - CONTACTS_NAMED} more" if touching.size > CONTACTS_NAMED else ""
            what += f", in contact at its start: {named}{more}"
        elif touching is not None:
            what += f", no constraint in contact at its start{_nearest_stop(constraints, z)}"
    options = _user_options()
    if options:
        change = f"check the options given ({' '.join(options)}) first"
    elif settings.contact == "explicit" or not settings.adaptive:
        change = step_advice(settings)
    else:
        change = f"check {LAW_SCALES} against the structure's own scales and units"
    return f"{what}; {change}"
