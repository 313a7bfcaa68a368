"""One time-stepping layer for both integrators (rom_integrator.py, fom_integrator.py): the settings, the TS
configuration with the code's scoped defaults, the failure policy, sampling at fixed times,
progress lines, and what a run reports when it cannot reach t_end.

Failure policy. Adaptive steps: a failed Newton solve shrinks the step (down to a floor where the
run stops with an error); failures are counted and reported. Fixed steps: retrying the same step
would loop for ever, so the first failure ends the run with an error. At most 50 rejections in a
row within one step. A state that is not finite ends the run at once.

The settings and the monitor's bookkeeping are not collective; configure and solve are collective on
the TS's communicator (COMM_SELF for a reduced case, rom_integrator.py).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from petsc4py import PETSc

from .errors import InputError, SolverError, check_number
from .petsctools import frames_released, options_defaults

ARKIMEX_TYPES = ("1bee", "a2", "l2", "ars122", "2c", "2d", "2e", "prssp2", "3", "bpr3", "ars443", "4", "5")
NO_DENSE_OUTPUT = ("prssp2", "bpr3", "ars443")  # also without an embedded error estimate
RTOL_FLOOR = 1e-14          # a relative error control tighter than this is below double precision's reach
# The least absolute tolerance (modal units, m kg^(1/2)): PETSc's error norm divides by atol + rtol |y| and
# squares, so near y = 0 (a run from rest) a tiny atol overflows it. Red team: atol = 1e-200 on the paper's
# beam failed in its first step as "PETSc error 72; reduce [integrator] dt or rtol", advice that cannot help
# (1e-100 still ran). 1e-30 is below any state a model resolves (a displacement of 1e-30 m is 1e-15 of a
# proton) and far from the overflow. Derived settings (the error estimate's richer run, the tolerance mode)
# are kept at it, not refused.
ATOL_FLOOR = 1e-30
# A run that must take more steps than this is refused before it starts (at ~20 us a step, 1e10 steps
# are more than two days); STEPS_PER_PERIOD steps resolve one period of the fastest forcing.
MAX_STEPS = 1e10
STEPS_PER_PERIOD = 20
# Both stall guards of an adaptive run measure its steps against one scale (step_scale): [integrator]
# dt, the user's first step, or where smaller 1/STEPS_PER_PERIOD of the period of the model's highest
# reference mode (red team: the 9-stop paper beam at 150 modes, 6235 Hz, with dt = 1 s took its healthy
# 5e-6 s steps, 1e-4 of the period, and was stopped as a crawl; it finishes in 8 s).
# An adaptive step is kept between the scale x MIN_STEP_FRACTION and 10 samples. PETSc accepts a step
# at that floor even when its error is above rtol/atol, so a model that wants steps below it (a
# contact law far too stiff or damped for its time scale, an extreme load) crawls at the floor with no
# error: FLOOR_STEPS steps in a row there stop the run (StepMonitor.report). The floor was dt x 1e-8
# alone (red team: the paper's beam with 1e12 N/m stops and dt = 1 s, whose impacts want 3e-10 s steps,
# took 12 steps at 1e-8 s without error control and finished with exit 0, w at the stop 1.4 % of its
# peak off the same run at dt = 1e-4 s). It never falls below TIME_ULPS rounding units of t_end, where
# t + step could not be told from t.
MIN_STEP_FRACTION = 1e-8
TIME_ULPS = 16
FLOOR_STEPS = 1000
# A run whose steps hover just above the floor crawls as well (red team: 1e12 N on the paper's beam under
# -rom_snes_max_it 1 with the Python callbacks took steps of 5e-11 to 1.5e-10 s, 50 to 150 times the
# floor, at t = 0.0212 s for 10 minutes, ETA growing): STALL_STEPS steps that together advance less
# than STALL_STEPS x scale x STALL_FRACTION (a mean step below the scale x 1e-5) stop it too.
STALL_FRACTION = 1e-5
STALL_STEPS = 10000
MAX_SAMPLES = 1e9           # 8 GB a series
CALLBACKS = ("auto", "c", "python")
# The step controller's defaults for the reduced model (scoped to -rom_, the user's options win):
# measured in docs/design.md "Rejected steps".
ADAPT_DEFAULTS = {"ts_adapt_safety": "0.8", "ts_adapt_clip": "0.1,1.5"}
# TS options that [integrator] sets (option -> its key). The reduced run's error estimate integrates a
# richer model with settings derived from [integrator] (accuracy.rich_settings: rtol and atol 10 times
# tighter, a fixed step or the adaptive step's upper limit 4 times shorter): such an option would set
# the run and the richer run alike, and the stored estimate would claim a tolerance neither had (red team: -rom_ts_rtol 0.1 was
# estimated "against 13 basis vectors at rtol 1e-07"). They are refused by name (refuse_settings_options).
SETTINGS_OPTIONS = {"ts_rtol": "rtol", "ts_atol": "atol", "ts_dt": "dt", "ts_max_time": "t_end"}


@dataclass(frozen=True)
class IntegratorSettings:
    """t_end (s); dt: the fixed step, or the first step of an adaptive run (s; at most its upper limit,
    10 samples); scheme: the ARKIMEX type of the reduced model; adaptive: error-controlled steps (the
    reduced model; the full-order loop takes fixed steps dt); rtol, atol: the adaptive error control;
    contact: the contact force on the "implicit" or "explicit" side of the reduced model's IMEX split;
    sample_dt: the output interval (s); callbacks: the reduced model's TS callbacks, "c" (the compiled
    fast path), "python" (the reference) or "auto" (C when built); max_step_scale: the adaptive step's
    upper limit (10 samples, or -<prefix>ts_adapt_dt_max) times this, in (0, 1] (the error estimate's
    richer run takes accuracy.RICH_STEP times shorter steps where the run's are at the limit)."""

    t_end: float
    dt: float = 1e-4
    scheme: str = "3"
    adaptive: bool = True
    rtol: float = 1e-6
    atol: float = 1e-9
    contact: str = "implicit"
    sample_dt: float = 1e-3
    callbacks: str = "auto"
    max_step_scale: float = 1.0

    def __post_init__(self):
        for name in ("t_end", "dt", "sample_dt", "atol"):
            object.__setattr__(self, name, check_number(f"IntegratorSettings {name}", getattr(self, name), 0.0,
                                                        above=True))
        object.__setattr__(self, "max_step_scale", check_number("IntegratorSettings max_step_scale",
                                                                self.max_step_scale, 0.0, above=True))
        if self.max_step_scale > 1:
            raise InputError(f"IntegratorSettings max_step_scale must be at most 1, got {self.max_step_scale!r}")
        object.__setattr__(self, "rtol", check_number("IntegratorSettings rtol", self.rtol))   # its range: below
        object.__setattr__(self, "scheme", str(self.scheme).lower())
        if not isinstance(self.adaptive, (bool, np.bool_)):
            raise InputError(f"IntegratorSettings adaptive must be True or False, got {self.adaptive!r}")
        if self.contact not in ("implicit", "explicit"):
            raise InputError(f'IntegratorSettings contact must be "implicit" or "explicit", got {self.contact!r}')
        if self.t_end / self.sample_dt > MAX_SAMPLES:   # before the sample times are made (memory)
            raise InputError(f"[output] sample_dt = {self.sample_dt:g} s gives {self.t_end / self.sample_dt:.2g} "
                             f"samples over t_end = {self.t_end:g} s, more than {MAX_SAMPLES:g}: sample less often")
        if self.atol < ATOL_FLOOR:
            raise InputError(f"[integrator] atol = {self.atol:g} is below {ATOL_FLOOR:g}, below any state a model "
                             f"resolves (modal units, m kg^(1/2)), and overflows the error norm near rest: give at "
                             f"least {ATOL_FLOOR:g} (rtol alone controls the error where the state is larger)")
        if self.rtol >= 1:   # red team: "rtol = 1 cannot be met in double precision: give a value from 1e-14 to 1"
            raise InputError(f"[integrator] rtol = {self.rtol:g} is a relative error of 100 % or more, no error "
                             f"control: give a value below 1 (e.g. 1e-6)")
        if self.rtol < RTOL_FLOOR:
            raise InputError(f"[integrator] rtol = {self.rtol:g} cannot be met in double precision: give at least "
                             f"{RTOL_FLOOR:g}")
        if self.callbacks not in CALLBACKS:
            raise InputError(f"[integrator] callbacks {self.callbacks!r}: choose one of {', '.join(CALLBACKS)}")
        if self.scheme not in ARKIMEX_TYPES:
            raise InputError(f"[integrator] scheme {self.scheme!r} is not an ARKIMEX type; "
                             f"choose one of {', '.join(ARKIMEX_TYPES)}")
        if self.adaptive and self.scheme in NO_DENSE_OUTPUT:
            raise InputError(f"[integrator] scheme {self.scheme} has no embedded error estimate: "
                             f"set adaptive = false (fixed step dt) or choose an adaptive scheme")

    @property
    def sample_times(self) -> np.ndarray:
        return sample_times(self.t_end, self.sample_dt)


def check_work(settings: IntegratorSettings, fastest_hz: float, adaptive: bool) -> None:
    """An InputError, before any work, for a run that cannot finish in reasonable time: a fixed step
    takes t_end / dt steps; an adaptive one at least STEPS_PER_PERIOD per period of the fastest
    forcing. Either must stay below MAX_STEPS. (The sample count, at most MAX_SAMPLES, the settings
    check themselves.)"""
    steps = settings.t_end / settings.dt if not adaptive else settings.t_end * fastest_hz * STEPS_PER_PERIOD
    if steps > MAX_STEPS:
        cause = (f"a fixed step of {settings.dt:g} s" if not adaptive else
                 f"{STEPS_PER_PERIOD} steps per period of the {fastest_hz:g} Hz forcing")
        raise InputError(f"the run would take at least {steps:.2g} steps ({cause} over t_end = {settings.t_end:g} s), "
                         f"more than the {MAX_STEPS:g} a run may take: shorten t_end, lengthen dt, or check the "
                         f"excitation frequency")


def sample_times(t_end: float, sample_dt: float) -> np.ndarray:
    """0, sample_dt, 2 sample_dt, ... and t_end itself."""
    count = int(math.floor(t_end / sample_dt * (1 + 1e-12))) + 1
    times = np.arange(count) * sample_dt
    return times if math.isclose(times[-1], t_end) else np.append(times, t_end)


def sample_count(t_end: float, sample_dt: float) -> int:
    """len(sample_times(t_end, sample_dt)), without making the array."""
    count = int(math.floor(t_end / sample_dt * (1 + 1e-12))) + 1
    return count if math.isclose((count - 1) * sample_dt, t_end) else count + 1


def refuse_settings_options(prefix: str, adaptive: bool) -> None:
    """An InputError naming a -<prefix> option that would override what [integrator] sets (SETTINGS_OPTIONS),
    or a -<prefix>ts_adapt_type that contradicts [integrator] adaptive ("none" on an adaptive run, a
    controller on a fixed-step one). Not collective (the options are the same on every rank)."""
    options = PETSc.Options(prefix)
    for name, key in SETTINGS_OPTIONS.items():
        if options.hasName(name):
            raise InputError(f"-{prefix}{name}: set [integrator] {key} instead (--set integrator.{key}=...); the "
                             f"option would also override the error estimate's richer run, which is integrated "
                             f"more accurately than the run, and the estimate would not hold")
    if options.hasName("ts_adapt_type") and (options.getString("ts_adapt_type") == "none") == adaptive:
        raise InputError(f"-{prefix}ts_adapt_type {options.getString('ts_adapt_type')}: set [integrator] adaptive = "
                         f"{'false' if adaptive else 'true'} instead (--set integrator.adaptive=...); the option "
                         f"would also override the error estimate's richer run, and the estimate would not hold")


def checked_by_the_integrator(callback):
    """A TS callback's floating-point overflow stays quiet: the integrator checks its numbers itself (a
    non-finite residual fails the step, which is retried smaller; a non-finite state ends the run with
    one line, StepMonitor.check_finite). Red team: a Hunt-Crossley alpha of 1e308 printed numpy's
    "RuntimeWarning: overflow encountered in multiply" before the run's one-line error."""
    import functools

    @functools.wraps(callback)
    def quiet(*args):
        with np.errstate(over="ignore", invalid="ignore"):
            return callback(*args)
    return quiet


def step_scale(dt: float, fastest_hz: float = 0.0) -> float:
    """The step an adaptive run's stall guards measure against (s): [integrator] dt, or where smaller
    1/STEPS_PER_PERIOD of the period of `fastest_hz` (the model's highest reference mode; 0: dt). The
    floor is MIN_STEP_FRACTION of it, a crawl a mean step below STALL_FRACTION of it."""
    if fastest_hz > 0 and math.isfinite(fastest_hz):
        return min(dt, 1.0 / (STEPS_PER_PERIOD * fastest_hz))
    return dt


def step_floor(settings: IntegratorSettings, fastest_hz: float = 0.0) -> float:
    """The least step an adaptive run may take (s), before the options: MIN_STEP_FRACTION of
    step_scale(dt, fastest_hz), never below TIME_ULPS rounding units of t_end."""
    return max(step_scale(settings.dt, fastest_hz) * MIN_STEP_FRACTION, TIME_ULPS * float(np.spacing(settings.t_end)))


def step_cap(settings: IntegratorSettings) -> float:
    """The most an adaptive step may take (s), before the options: 10 samples times max_step_scale."""
    return settings.sample_dt * 10 * settings.max_step_scale


def cap_refusal(settings: IntegratorSettings, fastest_hz: float = 0.0) -> str | None:
    """The line an adaptive run is refused with whose step cap (step_cap) is not above its floor
    (step_floor with `fastest_hz`, the model's highest reference mode), or None. PETSc's own "Maximum
    time step ... must greater than minimum time step ...; check the -rom_ options" blamed options
    nobody gave (red team: t_end = 1e-9 s). Not collective."""
    cap, floor = step_cap(settings), step_floor(settings, fastest_hz)
    if cap > floor:
        return None
    return (f"[integrator] t_end = {settings.t_end:g} s: its output samples, {settings.sample_dt:g} s apart, cap an "
            f"adaptive step at {cap:g} s, not above the smallest step it may take ({floor:g} s): give a longer t_end "
            f"or [output] sample_dt, or a fixed step ([integrator] adaptive = false)")


def cap_refused_below_hz(settings: IntegratorSettings) -> float | None:
    """The highest reference-mode frequency (Hz) up to which cap_refusal refuses these settings, from
    the settings alone (the frequency is known only once the basis is): None where no frequency is
    refused (the usual case: the cap is above [integrator] dt x MIN_STEP_FRACTION), math.inf where
    every one is (the cap within TIME_ULPS rounding units of t_end). The floor is the larger of dt and
    1/STEPS_PER_PERIOD of the period, times MIN_STEP_FRACTION: a cap C at most dt x MIN_STEP_FRACTION
    is refused for a frequency f up to MIN_STEP_FRACTION / (STEPS_PER_PERIOD C). Not collective."""
    cap = step_cap(settings)
    if cap <= TIME_ULPS * float(np.spacing(settings.t_end)):
        return math.inf
    if cap > settings.dt * MIN_STEP_FRACTION:
        return None
    return MIN_STEP_FRACTION / (STEPS_PER_PERIOD * cap)


def configure(ts: PETSc.TS, settings: IntegratorSettings, prefix: str, defaults: dict, adaptive: bool,
              start: dict | None = None, steps: "StepMonitor | None" = None, fastest_hz: float = 0.0) -> None:
    """What every integrator's TS gets: time span, first step, tolerances, the failure policy, the
    Newton tolerances, then the code's defaults (scoped to `prefix`, only where the user set
    nothing) and the user's options; a user option [integrator] sets is refused
    (refuse_settings_options). `start` (t, dt, steps) continues a checkpointed run. `steps`, on an
    adaptive run, watches the step-size floor (FLOOR_STEPS) and the crawl just above it (STALL_STEPS).
    Both, and the controller's own floor, scale with step_scale(dt, fastest_hz): dt or, where smaller,
    1/STEPS_PER_PERIOD of the period of `fastest_hz` (Hz, the model's highest reference mode; 0: dt
    alone)."""
    refuse_settings_options(prefix, adaptive)
    ts.setTime(start["t"] if start else 0.0)
    ts.setTimeStep(start["dt"] if start else settings.dt)
    if start:
        ts.setStepNumber(start["steps"])
    ts.setMaxTime(settings.t_end)
    ts.setMaxSteps(10**9)
    ts.setExactFinalTime(PETSc.TS.ExactFinalTime.MATCHSTEP)
    ts.setTolerances(rtol=settings.rtol, atol=settings.atol)
    ts.setErrorIfStepFails(False)
    ts.setMaxSNESFailures(-1 if adaptive else 1)
    ts.setMaxStepRejections(50)  # consecutive, within one step: bounds the retries of a hopeless step
    scale = step_scale(settings.dt, fastest_hz)
    nominal = step_floor(settings, fastest_hz)
    if adaptive:  # a fixed step needs no limits (and dt may exceed 10 samples); dt does not raise the cap
        refusal = cap_refusal(settings, fastest_hz)
        if refusal:   # run.cap_refusal_before_basis says it before the basis where it is certain
            raise InputError(refusal)
        cap = settings.sample_dt * 10
        ts.setStepLimits(nominal, max(nominal, cap))
    ts.getSNES().setTolerances(rtol=1e-10, atol=1e-14, max_it=20)
    with options_defaults(prefix, defaults):
        ts.setOptionsPrefix(prefix)
        ts.setFromOptions()
    if adaptive and settings.max_step_scale < 1:   # after the options: it scales -<prefix>ts_adapt_dt_max too
        low, high = ts.getStepLimits()
        ts.setStepLimits(low, max(low, high * settings.max_step_scale))
    if adaptive and not start:   # the first step is dt, within the limits (PETSc takes it as given): at most the
        # cap, at least the floor (red team: dt = 5e-324 s, a denormal, made the implicit stages' shift a/dt infinite:
        # every Newton solve failed at t = 0, and the run ended after its basis blaming the constraint laws)
        low, high = ts.getStepLimits()
        ts.setTimeStep(max(low, min(settings.dt, high)))
    if adaptive and steps is not None:
        # the floor the controller has, which -<prefix>ts_adapt_dt_min raises (a crawl there went
        # unseen; red team); below the nominal floor a run crawls whatever the floor
        floor = ts.getStepLimits()[0]
        steps.ts, steps.floor = ts, max(floor, nominal)
        steps.stall_step, steps.stall_scale = max(steps.floor, scale * STALL_FRACTION), scale
        if floor > nominal:
            steps.floor_source = f"-{prefix}ts_adapt_dt_min"
        elif nominal > scale * MIN_STEP_FRACTION:
            steps.floor_source = f"{TIME_ULPS} rounding units of [integrator] t_end"
        elif scale < settings.dt:
            steps.floor_source = (f"{MIN_STEP_FRACTION:g} x 1/{STEPS_PER_PERIOD} of the highest reference mode's "
                                  f"period")
        else:
            steps.floor_source = f"[integrator] dt x {MIN_STEP_FRACTION:g}"
        # a user's Newton or step options can starve the step too (-rom_snes_max_it 1): name them
        steps.floor_options = sorted(f"-{name}" for name in PETSc.Options().getAll()
                                     if name.startswith((prefix + "snes_", prefix + "ksp_", prefix + "ts_")))


class StepMonitor:
    """The part of a TS monitor both integrators share: which sample times the step that just ended
    has passed, a stop request with its message, non-finite states, and progress lines every 5 s.

    times         all sample times of the run
    first_sample  the index of the first sample still to take (a resumed run has taken some)
    resumed       a resumed run's first monitor call is the checkpointed step itself: not a new step
    say           where progress lines go (None: no progress)
    """

    def __init__(self, times: np.ndarray, first_sample: int = 0, resumed: bool = False, say=None):
        self.times, self.next = times, first_sample
        self.resumed_step = resumed
        self.failure = None
        self.say = say
        self.start = self.last_report = time.perf_counter()
        self.first_step = self.first_time = None
        self.tol = 1e-9 * times[-1]
        self.ts = self.floor = self.floor_since = None   # configure sets ts and floor on an adaptive run
        self.stall_step, self.window = None, None        # configure sets stall_step; window: (step, t)
        self.stall_scale = None                          # the step stall_step is STALL_FRACTION of
        self.floor_source, self.floor_options = "", []
        self.last_step = None                            # the integrator's TS step when it ended

    def samples_due(self, t: float):
        """(index, sample time, whether it is the step's own time) of every sample up to t."""
        while self.next < self.times.size and self.times[self.next] <= t + self.tol:
            sample = self.times[self.next]
            yield self.next, sample, abs(sample - t) <= self.tol
            self.next += 1

    def new_step(self) -> bool:
        """False once, for the checkpointed step a resumed run starts from."""
        if self.resumed_step:
            self.resumed_step = False
            return False
        return True

    def stop(self, ts: PETSc.TS, t: float, message: str) -> None:
        """End the run after this step with `message` as its error."""
        self.failure = message
        ts.setMaxTime(t)

    def check_finite(self, ts: PETSc.TS, step: int, t: float, norm: float, advice: str) -> bool:
        if math.isfinite(norm):
            return True
        self.stop(ts, t, f"the state is not finite at t = {t:.6g} s (step {step}); {advice}")
        return False

    def report(self, step: int, t: float) -> None:
        """Progress every 5 s, and the stop of a run stuck at the step-size floor (FLOOR_STEPS). Called
        after every step (Python callbacks) or every 64 (C); the same steps on every rank."""
        self._check_floor(step, t)
        now = time.perf_counter()
        if self.first_step is None:  # a resumed run starts at its checkpoint, not at 0
            self.first_step, self.first_time = step, t
        if self.say is None or now - self.last_report <= 5.0 or t <= self.first_time:
            return
        self.last_report = now
        t_end = self.times[-1]
        rate = (step - self.first_step) / (now - self.start)
        eta = (now - self.start) * (t_end - t) / (t - self.first_time)
        self.say(f"  t = {t:.4g} s of {t_end:g} s ({100 * t / t_end:.0f} %), {rate:.0f} steps/s, ETA {eta:.0f} s")

    def _check_floor(self, step: int, t: float) -> None:
        if self.floor is None or self.failure:
            return
        if self.ts.getTimeStep() > self.floor * (1 + 1e-9):
            self.floor_since = None
        elif self.floor_since is None:
            self.floor_since = step
        elif step - self.floor_since >= FLOOR_STEPS:
            self.stop(self.ts, t, _floor_message(self.floor, self.floor_source, step - self.floor_since, t,
                                                 self.floor_options))
            return
        if self.stall_step is None:
            return
        if self.window is None:
            self.window = (step, t)
        elif step - self.window[0] >= STALL_STEPS:
            steps, advanced = step - self.window[0], t - self.window[1]
            if advanced < steps * self.stall_step:
                given = f"the options given ({' '.join(self.floor_options)}), " if self.floor_options else ""
                self.stop(self.ts, t, f"the time step stayed near its floor for {steps} steps up to t = {t:.6g} s "
                                      f"(a mean step of {advanced / steps:.3g} s, below {STALL_FRACTION:g} x "
                                      f"{self.stall_scale:.3g} s, the smaller of [integrator] dt and 1/"
                                      f"{STEPS_PER_PERIOD} of the highest reference mode's period), where the "
                                      f"error cannot be kept within rtol and atol and the run would crawl: check "
                                      f"{given}{LAW_SCALES} against the structure's own scales and units, or "
                                      f"lower [integrator] dt if the model is that fast")
            else:
                self.window = (step, t)


# What makes a model too fast for the step floor. Friction's slope at rest is mu F_n / v_reg (mu k delta / v_reg
# in a round hole): red team, v_reg = 1e-12 m/s crawled at the floor and the line named only k, alpha and c.
LAW_SCALES = ("the constraint laws' stiffness, damping and friction regularization (k, alpha, c; v_reg) and the "
              "loads")


def _floor_message(floor: float, source: str, steps: int, t: float, options=()) -> str:
    given = f"the options given ({' '.join(options)}), " if options else ""
    return (f"the time step stayed at its floor ({floor:.3g} s, {source}) for {steps} "
            f"steps at t = {t:.6g} s, where the error cannot be kept within rtol and atol and the run would crawl: "
            f"check {given}{LAW_SCALES} against the structure's own scales and units, or lower [integrator] dt if "
            f"the model is that fast")


# What a failure in the first step points to: the input, not the step or the tolerance
FIRST_STEP_HINT = ("; it failed in its first step, which points to the input: check the excitation's amplitude (psd "
                   "of a random load), the [initial] amplitude and velocity, and the units of the model (K, M, the "
                   "laws' stiffness)")


def solve(ts: PETSc.TS, y: PETSc.Vec, monitor: StepMonitor, what: str, advice: str) -> float:
    """ts.solve(y), a PETSc error turned into a SolverError that says what to change. Returns the
    wall time. A failure the monitor recorded is left for `check_outcome`."""
    start, t0 = time.perf_counter(), ts.getTime()
    try:
        with frames_released():   # a callback's exception must not keep its TS past the TS's destroy
            ts.solve(y)
    except PETSc.Error as e:
        if monitor.failure is None:
            # red team: psd = 1e200 on the 2-D tube failed here as "PETSc error 71; reduce [integrator] dt or
            # rtol", naming nothing of the input that caused it
            hint = FIRST_STEP_HINT if ts.getTime() == t0 else ""
            raise SolverError(f"the {what} failed at t = {ts.getTime():.6g} s: PETSc error {e.ierr}; {advice}{hint}") \
                from None
    return time.perf_counter() - start


def check_outcome(monitor: StepMonitor, reason: int, stats: dict, t_end: float, what: str, advice: str,
                  input_hint: bool = True) -> None:
    """A SolverError if the run stopped (the monitor's message) or did not reach t_end; an adaptive run
    that failed with its step below the floor (monitor.last_step) gets the floor's message. A run that
    stopped in its first step adds FIRST_STEP_HINT unless `input_hint` is False (the advice already names
    the cause: the user's own solver options)."""
    if monitor.failure:
        raise SolverError(monitor.failure)
    if reason < 0 and monitor.floor is not None and monitor.last_step is not None and \
            monitor.last_step < monitor.floor * (1 + 1e-9):
        # PETSc cuts a step whose Newton failed by 4 without its floor: 50 failures in a row took the
        # step to 1e-41 s (Hunt-Crossley alpha 1e308 with dt = 1 s), and "reduce [integrator] dt" said
        # nothing true; it is the floor's stop, with the floor's causes
        given = f"the options given ({' '.join(monitor.floor_options)}), " if monitor.floor_options else ""
        raise SolverError(f"the time step fell below its floor ({monitor.floor:.3g} s, {monitor.floor_source}) to "
                          f"{monitor.last_step:.3g} s at t = {stats['final_time']:.6g} s, the Newton solve failing at "
                          f"every step ({stats['snes_failures']} Newton failures, {stats['rejected_steps']} rejected "
                          f"steps): check {given}{LAW_SCALES} against the structure's own scales and units, or lower "
                          f"[integrator] dt if the model is that fast")
    if reason < 0 or monitor.next < monitor.times.size:
        if stats["final_time"] == monitor.times[0] and input_hint:
            advice += FIRST_STEP_HINT
        raise SolverError(f"the {what} stopped at t = {stats['final_time']:.6g} s of {t_end:g} s "
                          f"(TS reason {reason}, {stats['snes_failures']} Newton failures, "
                          f"{stats['rejected_steps']} rejected steps): {advice}")
