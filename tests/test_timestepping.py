"""The time-stepping layer (timestepping.py): settings validated once, and runs that cannot finish
in reasonable time refused before any work, with what to change."""
import math
import re

import pytest

from dbf_hpc.errors import InputError
from dbf_hpc.timestepping import IntegratorSettings, check_work


@pytest.mark.parametrize("rtol", [1e-300, 0.0])
def test_a_tolerance_double_precision_cannot_meet_is_refused(rtol):
    with pytest.raises(InputError, match="cannot be met in double precision: give at least 1e-14$"):
        IntegratorSettings(t_end=1.0, rtol=rtol)


@pytest.mark.parametrize("rtol", [1.0, 1.5])
def test_a_relative_tolerance_of_100_percent_or_more_is_refused_as_no_error_control(rtol):
    # Red team: rtol = 1 was "cannot be met in double precision: give a value from 1e-14 to 1"
    with pytest.raises(InputError, match="is a relative error of 100 % or more, no error control: give a value below 1"):
        IntegratorSettings(t_end=1.0, rtol=rtol)


def test_an_absolute_tolerance_below_any_resolved_state_is_refused_and_derived_ones_stop_at_the_floor():
    # Red team: atol = 1e-200 on the paper's beam failed in its first step with "PETSc error 72; reduce
    # [integrator] dt or rtol" (the error norm over atol overflows near rest), advice that cannot help
    from dbf_hpc.accuracy import rich_settings
    from dbf_hpc.timestepping import ATOL_FLOOR

    for atol in (1e-200, 1e-300, 9.9e-31):
        with pytest.raises(InputError, match=f"^\\[integrator\\] atol = {atol:g} is below 1e-30, below any state"):
            IntegratorSettings(t_end=1.0, atol=atol)
    at_floor = IntegratorSettings(t_end=1.0, atol=ATOL_FLOOR)
    assert rich_settings(at_floor, 0.5).atol == ATOL_FLOOR          # the richer run keeps the floor
    assert rich_settings(IntegratorSettings(t_end=1.0), 0.5).atol == pytest.approx(1e-10, abs=0)


@pytest.mark.parametrize("settings,fastest,adaptive,message", [
    (dict(t_end=0.1, dt=1e-12), 0.0, False, "a fixed step of 1e-12 s"),
    (dict(t_end=0.1), 1e12, True, "20 steps per period of the 1e\\+12 Hz forcing"),
    (dict(t_end=1e4, sample_dt=1e-6), 1.0, True, "gives 1e\\+10 samples"),
])
def test_a_run_that_cannot_finish_is_refused_naming_its_step_count(settings, fastest, adaptive, message):
    # Red team: 1e12 Hz over 0.1 s, or a fixed dt of 1e-12 s, ran with an ETA of 290 days.
    with pytest.raises(InputError, match=message):
        check_work(IntegratorSettings(**settings), fastest, adaptive)


def test_the_papers_runs_pass_the_work_check():
    check_work(IntegratorSettings(t_end=10.0, sample_dt=1e-3), 1.0, True)
    check_work(IntegratorSettings(t_end=0.2, dt=2e-6, adaptive=False, sample_dt=1e-4), 1.0, False)


@pytest.mark.parametrize("option,value,adaptive,names", [
    ("ts_rtol", "0.1", True, "set \\[integrator\\] rtol instead"),
    ("ts_atol", "1", True, "set \\[integrator\\] atol instead"),
    ("ts_dt", "1e-3", False, "set \\[integrator\\] dt instead"),
    ("ts_max_time", "5", True, "set \\[integrator\\] t_end instead"),
    ("ts_adapt_type", "none", True, "set \\[integrator\\] adaptive = false instead"),
    ("ts_adapt_type", "basic", False, "set \\[integrator\\] adaptive = true instead"),
])
def test_an_option_that_would_loosen_the_estimates_richer_run_too_is_refused_by_name(option, value, adaptive, names):
    # The error estimate's richer run is integrated 10 times tighter (a 4 times shorter fixed step)
    # than the run, from [integrator]; a -rom_ts_ option would set both runs alike. Red team: with
    # -rom_ts_rtol 0.1 the stored estimate said "against 13 basis vectors at rtol 1e-07".
    from petsc4py import PETSc

    from dbf_hpc.timestepping import configure

    options = PETSc.Options()
    ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
    options.setValue("rom_" + option, value)
    try:
        with pytest.raises(InputError, match=f"-rom_{option}( {value})?: " + names):
            configure(ts, IntegratorSettings(t_end=1.0, adaptive=adaptive), "rom_", {}, adaptive)
    finally:
        options.delValue("rom_" + option)
        ts.destroy()


@pytest.mark.parametrize("adaptive,kind", [(True, "dsp"), (False, "none")])
def test_a_step_controller_that_agrees_with_integrator_adaptive_is_the_users(adaptive, kind):
    from petsc4py import PETSc

    from dbf_hpc.timestepping import configure

    options = PETSc.Options()
    ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
    ts.setType(PETSc.TS.Type.ARKIMEX)
    options.setValue("rom_ts_adapt_type", kind)
    try:
        configure(ts, IntegratorSettings(t_end=1.0, adaptive=adaptive), "rom_", {"ts_adapt_type": "basic"}, adaptive)
        assert options.getString("rom_ts_adapt_type") == kind      # the user's, not the code's default
        assert ts.getTolerances()[0] == 1e-6                        # [integrator] rtol
    finally:
        options.delValue("rom_ts_adapt_type")
        ts.destroy()


@pytest.mark.parametrize("dt_min,floor,source", [(None, 1e-12, r"\[integrator\] dt x 1e-08"),
                                                 (1e-9, 1e-9, "-rom_ts_adapt_dt_min"),
                                                 (1e-20, 1e-12, r"\[integrator\] dt x 1e-08")])
def test_a_step_held_at_the_controllers_floor_for_floor_steps_stops_the_run_naming_that_floor(dt_min, floor, source):
    # PETSc accepts a step at its floor without error control. Red team: the watch took the floor as
    # dt x 1e-8 whatever -rom_ts_adapt_dt_min said, so a Hunt-Crossley alpha of 1e308 under
    # -rom_ts_adapt_dt_min 1e-9 crawled at 1e-9 s for ever (the step never sat at 1e-12 s). A floor
    # lowered below dt x 1e-8 still stops there: steps that short make no progress on any scene.
    import numpy as np
    from petsc4py import PETSc

    from dbf_hpc.timestepping import FLOOR_STEPS, StepMonitor, configure

    options = PETSc.Options()
    ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
    ts.setType(PETSc.TS.Type.ARKIMEX)
    if dt_min is not None:
        options.setValue("rom_ts_adapt_dt_min", dt_min)
    try:
        settings = IntegratorSettings(t_end=1.0, dt=1e-4, adaptive=True)
        monitor = StepMonitor(np.linspace(0.0, 1.0, 11))
        configure(ts, settings, "rom_", {"ts_adapt_type": "basic"}, True, steps=monitor)
        assert monitor.floor == pytest.approx(floor, rel=1e-12, abs=0)
        ts.setTimeStep(2 * floor)                       # above the floor: no count
        for step in range(2 * FLOOR_STEPS):
            monitor.report(step, 0.5)
        assert monitor.failure is None
        ts.setTimeStep(floor)                           # held at the floor: FLOOR_STEPS steps, then the stop
        for step in range(2 * FLOOR_STEPS, 3 * FLOOR_STEPS + 1):
            monitor.report(step, 0.5)
        assert monitor.failure is not None
        assert re.search(rf"stayed at its floor \({floor:.3g} s, {source}\) for {FLOOR_STEPS} steps at t = 0.5 s",
                         monitor.failure), monitor.failure
    finally:
        if dt_min is not None:
            options.delValue("rom_ts_adapt_dt_min")
        ts.destroy()


def test_a_large_first_step_does_not_make_the_fast_modes_healthy_steps_a_crawl():
    # Red team: the 9-stop paper beam at 150 modes (highest 6235 Hz) with [integrator] dt = 1 s (the
    # first step of an adaptive run) took its healthy steps of 5e-6 s, 1/32 of that mode's period, and
    # was stopped as a crawl (a mean step below dt x 1e-5 = 1e-5 s); it finishes in 8 s. The crawl's
    # scale is the smaller of dt and 1/STEPS_PER_PERIOD of the highest mode's period: steps that resolve
    # the model's own fastest vibration never stop it, and steps 1e-5 times below still do.
    import numpy as np
    from petsc4py import PETSc

    from dbf_hpc.timestepping import STALL_FRACTION, STALL_STEPS, STEPS_PER_PERIOD, StepMonitor, configure

    fastest = 6235.0
    scale = 1.0 / (STEPS_PER_PERIOD * fastest)
    # healthy steps under dt = 1 s; steps above the floor (dt x 1e-8) but 2e5 times below the scale under dt = 1 ms
    for dt, hover, stops in ((1.0, 1.0 / (32 * fastest), False), (1e-3, 0.5 * scale * STALL_FRACTION, True)):
        ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
        ts.setType(PETSc.TS.Type.ARKIMEX)
        try:
            settings = IntegratorSettings(t_end=1.0, dt=dt, adaptive=True)
            monitor = StepMonitor(np.linspace(0.0, 1.0, 11))
            configure(ts, settings, "rom_", {"ts_adapt_type": "basic"}, True, steps=monitor, fastest_hz=fastest)
            ts.setTimeStep(hover)
            for step in range(0, 3 * STALL_STEPS, 64):   # the C callbacks report every 64 steps
                monitor.report(step, 0.1 + step * hover)
                if monitor.failure:
                    break
            assert (monitor.failure is not None) == stops, (hover, monitor.failure)
            if stops:
                assert f"below {STALL_FRACTION:g} x {scale:.3g} s" in monitor.failure, monitor.failure
        finally:
            ts.destroy()


@pytest.mark.parametrize("dt,t_end,fastest,floor,source", [
    (1.0, 1.0, 6235.0, 1e-8 / (20 * 6235.0), r"1e-08 x 1/20 of the highest reference mode's period"),
    (1e-4, 1.0, 9.8, 1e-12, r"\[integrator\] dt x 1e-08"),
    (1e-4, 1e6, 0.0, 16 * 2.0**-33, r"16 rounding units of \[integrator\] t_end")])
def test_the_step_floor_and_the_crawl_are_measured_against_one_scale_the_smaller_of_dt_and_the_fast_modes_period(
        dt, t_end, fastest, floor, source):
    # Red team: the crawl's scale was the smaller of dt and 1/20 of the highest mode's period, but the
    # floor (PETSc's, and the watch's) stayed dt x 1e-8: under dt = 1 s a step of 1e-8 s, 1e-5 of a
    # 6235 Hz mode's period, was the floor, where PETSc accepts steps without error control. Both are
    # now fractions of the same scale; a floor never falls below 16 rounding units of t_end (16 x 2^-33 s
    # at t_end = 1e6 s), where t + step could no longer be told from t.
    import numpy as np
    from petsc4py import PETSc

    from dbf_hpc.timestepping import MIN_STEP_FRACTION, STALL_FRACTION, StepMonitor, configure, step_scale

    ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
    ts.setType(PETSc.TS.Type.ARKIMEX)
    try:
        settings = IntegratorSettings(t_end=t_end, dt=dt, adaptive=True, sample_dt=t_end / 10)
        monitor = StepMonitor(np.linspace(0.0, t_end, 11))
        configure(ts, settings, "rom_", {"ts_adapt_type": "basic"}, True, steps=monitor, fastest_hz=fastest)
        scale = step_scale(dt, fastest)
        assert scale == pytest.approx(min(dt, 1 / (20 * fastest)) if fastest else dt, rel=1e-12, abs=0)
        assert ts.getStepLimits()[0] == pytest.approx(floor, rel=1e-12, abs=0)     # PETSc's floor ...
        assert monitor.floor == pytest.approx(floor, rel=1e-12, abs=0)             # ... is the one watched
        assert re.fullmatch(source, monitor.floor_source), monitor.floor_source
        assert monitor.stall_step == pytest.approx(max(floor, scale * STALL_FRACTION), rel=1e-12, abs=0)
        assert monitor.floor <= scale * MIN_STEP_FRACTION or "rounding" in monitor.floor_source
    finally:
        ts.destroy()


def _first_step_difference(folder, changes: list, first: float = 1.0) -> float:
    """The paper's beam (0.2 s, `changes`) run with the first steps dt = `first` and 1e-4 s: the relative
    difference of w at the stop between the two (the same on every rank)."""
    import h5py
    from mpi4py import MPI

    from dbf_hpc.accuracy import relative_difference
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene
    from test_run import PAPER

    w = {}
    for dt in (1e-4, first):
        out = folder / f"dt{dt:g}.h5"
        run(load_scene(PAPER, ["basis.cache=off", "basis.estimate=false", "output.snapshots=0", "integrator.t_end=0.2",
                               *changes, f"integrator.dt={dt}"]), str(out), progress=False)
        if MPI.COMM_WORLD.rank == 0:
            with h5py.File(out, "r") as f:
                w[dt] = f["constraints/displacement"][:]
    return MPI.COMM_WORLD.bcast(relative_difference(w[first], w[1e-4]) if w else None, root=0)


def test_a_stiff_stops_impacts_take_the_short_steps_they_need_under_a_first_step_of_1_s(shared_tmp_path):
    # Red team: the paper's beam with 1e12 N/m stops. Its impacts want steps near 3e-10 s; with
    # [integrator] dt = 1 s (an adaptive run's first step only) the floor was dt x 1e-8 = 1e-8 s, and the
    # run took 12 steps there without error control and ended with exit 0, w at the stop 1.4 % of its
    # peak off the same run started at dt = 1e-4 s. The floor is now 1e-8 of 1/20 of the 6th mode's
    # period (5.1e-11 s): the two first steps give one answer (measured 1.2e-4 apart).
    difference = _first_step_difference(shared_tmp_path, ["constraint.k_minus=1e12", "constraint.k_plus=1e12"])
    assert difference < 1e-3, difference


def test_a_run_whose_newton_failures_cut_the_step_below_its_floor_is_the_floors_stop_not_reduce_dt():
    # PETSc cuts a step whose Newton solve failed by 4, without its lower limit: Hunt-Crossley alpha
    # 1e308 with dt = 1 s ended after 50 such cuts in a row at a step of 1e-41 s, and the line said
    # "reduce [integrator] dt or rtol". A run that ends with its step below the floor gets the floor's
    # line (the floor, where it comes from, the causes to check); one that ends above it keeps its own.
    import numpy as np
    from petsc4py import PETSc

    from dbf_hpc.errors import SolverError
    from dbf_hpc.timestepping import StepMonitor, check_outcome, configure

    stats = {"final_time": 0.105, "snes_failures": 103, "rejected_steps": 103}
    for last, expected in ((1e-41, r"^the time step fell below its floor \(1e-12 s, \[integrator\] dt x 1e-08\) to 1e-41 s "
                                    r"at t = 0.105 s, the Newton solve failing at every step \(103 Newton failures, 103 "
                                    r"rejected steps\): check the constraint laws' stiffness, damping and friction "
                                    r"regularization \(k, alpha, c; v_reg\)"),
                           (1e-6, r"^the reduced integration stopped at t = 0.105 s of 0.2 s \(TS reason -2, .*: reduce")):
        ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
        ts.setType(PETSc.TS.Type.ARKIMEX)
        try:
            monitor = StepMonitor(np.linspace(0.0, 0.2, 11))
            configure(ts, IntegratorSettings(t_end=0.2, dt=1e-4, adaptive=True), "rom_", {"ts_adapt_type": "basic"},
                      True, steps=monitor)
        finally:
            ts.destroy()
        monitor.last_step = last
        with pytest.raises(SolverError, match=expected):
            check_outcome(monitor, -2, stats, 0.2, "reduced integration", "reduce [integrator] dt or rtol")


def test_a_first_step_beyond_ten_samples_neither_raises_the_step_cap_nor_is_taken_whole():
    # The cap of 10 sample intervals bounds the span ARKIMEX's dense output interpolates the samples
    # over (its error is not controlled); it was max(dt, 10 samples), so dt = 1 s raised it to 1 s.
    import numpy as np
    from petsc4py import PETSc

    from dbf_hpc.timestepping import StepMonitor, configure

    for dt, first in ((1.0, 2e-4), (1e-4, 1e-4)):
        ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
        ts.setType(PETSc.TS.Type.ARKIMEX)
        try:
            settings = IntegratorSettings(t_end=0.2, dt=dt, sample_dt=2e-5, adaptive=True)
            configure(ts, settings, "rom_", {"ts_adapt_type": "basic"}, True, steps=StepMonitor(np.zeros(1)))
            assert ts.getStepLimits()[1] == pytest.approx(2e-4, rel=1e-12)
            assert ts.getTimeStep() == pytest.approx(first, rel=1e-12)
        finally:
            ts.destroy()


@pytest.mark.parametrize("dt", [5e-324, 1e-310])
def test_a_first_step_below_the_step_floor_is_taken_at_the_floor_and_gives_the_ordinary_first_steps_answer(
        shared_tmp_path, dt):
    # Red team: [integrator] dt = 5e-324 s (a denormal) or 1e-310 s was taken as the first step, below the floor
    # (16 rounding units of t_end): the implicit stages' shift a/dt overflowed, every Newton solve failed at t = 0,
    # and the run ended after its basis with "the time step fell below its floor ... check the constraint laws'
    # stiffness". The first step is now at least the floor; the run gives the answer of a first step of 1e-4 s
    # within 100 rtol of w's peak (another history of steps: measured 1.2e-5 on one rank, 3.6e-5 on two; a first
    # step of 1e-15 s, above the floor, 7.5e-6).
    import numpy as np
    from petsc4py import PETSc

    from dbf_hpc.timestepping import StepMonitor, configure, step_floor

    ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
    ts.setType(PETSc.TS.Type.ARKIMEX)
    try:
        settings = IntegratorSettings(t_end=0.2, dt=dt, adaptive=True)
        configure(ts, settings, "rom_", {"ts_adapt_type": "basic"}, True, steps=StepMonitor(np.zeros(1)))
        assert ts.getTimeStep() == ts.getStepLimits()[0] == step_floor(settings) > dt
    finally:
        ts.destroy()
    if dt == 5e-324:   # (both dt start at the floor: one run)
        difference = _first_step_difference(shared_tmp_path, [], first=dt)
        assert difference < 1e-4, difference

def test_the_paper_beams_response_does_not_depend_on_an_adaptive_runs_first_step(shared_tmp_path):
    # [integrator] dt is only the first step of an adaptive run: dt = 1 s and 1e-4 s must give one answer.
    # With the cap raised to dt = 1 s the run took 205 steps instead of 1099 and w at the stop was 1.0e-4
    # of its peak off (the samples interpolated over up to 50 intervals); now 1.1e-5, where dt = 1e-5 s
    # and 1e-4 s differ by 3e-6.
    difference = _first_step_difference(shared_tmp_path, [])
    assert difference < 3e-5, difference


def test_a_contact_too_damped_for_any_step_under_a_first_step_of_1_s_stops_at_the_floor_of_the_fast_modes_period(
        shared_tmp_path):
    # Hunt-Crossley alpha = 1e308 s/m with dt = 1 s: the floor the run stops at is 1e-8 of 1/20 of the
    # period of the highest mode of the basis, the pinned beam's 6th, f_6 = (6 pi / L)^2 sqrt(EI / rho A)
    # / 2 pi = 9.7977 Hz (was dt x 1e-8 = 1e-8 s); one line with what to change, no output, no lock.
    # Its first step is 10 samples (2e-4 s), and the Newton solve fails at its first contact however
    # short the step: PETSc cut it by 4 fifty times in a row, below the floor to 1e-41 s, and the line
    # said "reduce [integrator] dt or rtol"; it is the floor's stop, with the floor's causes.
    import math

    from conftest import rank0_files
    from dbf_hpc.errors import SolverError
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene
    from test_run import PAPER

    f6 = (6 * math.pi) ** 2 * math.sqrt(117e9 * 8.78e-16 / (11800.0 * 2.9e-7)) / (2 * math.pi)
    scene = load_scene(PAPER, ["basis.cache=off", "basis.estimate=false", "output.snapshots=0", "integrator.t_end=0.2",
                               "integrator.dt=1", "constraint.damping=hunt_crossley", "constraint.alpha=1e308"])
    with pytest.raises(SolverError) as stopped:
        run(scene, str(shared_tmp_path / "hc.h5"), progress=False)
    line = str(stopped.value)
    assert "\n" not in line, line
    # which of the floor's two stops ends it depends on the step history (1 rank: the Newton failures)
    assert re.match(rf"the time step (stayed at|fell below) its floor \({1e-8 / (20 * f6):.3g} s, 1e-08 x 1/20 of the "
                    rf"highest reference mode's period\)", line), line
    assert "reduce [integrator] dt or rtol" not in line, line
    assert "t = 0.105" in line and "(k, alpha, c; v_reg)" in line and "lower [integrator] dt" in line, line
    assert "the samples up to the failure are in" in line and line.endswith("hc.h5.partial)"), line
    assert rank0_files(shared_tmp_path) == ["hc.h5.partial"], "no output, no lock: the samples named in the line"


@pytest.mark.launcher
def test_a_crawl_under_a_first_step_of_1_s_ends_the_command_on_two_ranks_with_one_line(tmp_path):
    # The same stop from the command line on 2 ranks: exit 1, one line, no output and no lock.
    from test_cli import PAPER, dbf_hpc

    done = dbf_hpc("run", PAPER, "-q", "-o", str(tmp_path / "hc.h5"), "--set=basis.cache=off",
                   "--set=basis.estimate=false", "--set=output.snapshots=0", "--set=integrator.t_end=0.2",
                   "--set=integrator.dt=1", "--set=constraint.damping=hunt_crossley", "--set=constraint.alpha=1e308",
                   ranks=2)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1, done.stderr
    assert re.match(r"dbf-hpc: error: the time step (stayed at|fell below) its floor \(5.1e-11 s, 1e-08 x 1/20 of "
                    r"the highest reference mode's period\)", lines[0]), lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hc.h5.partial"]


def test_steps_hovering_just_above_the_floor_stop_the_run_as_a_crawl_and_healthy_short_steps_do_not():
    # Red team: 1e12 N on the paper's beam under -rom_snes_max_it 1 with the Python callbacks took steps
    # of 5e-11 to 1.5e-10 s (50 to 150 times the 1e-12 s floor, never at it) at t = 0.0212 s for 10
    # minutes: the floor's watch never counted them. A mean step below dt x STALL_FRACTION over
    # STALL_STEPS steps advances the run by nothing it could finish: it stops with the cause.
    import numpy as np
    from petsc4py import PETSc

    from dbf_hpc.timestepping import STALL_FRACTION, STALL_STEPS, StepMonitor, configure

    ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
    ts.setType(PETSc.TS.Type.ARKIMEX)
    try:
        settings = IntegratorSettings(t_end=1.0, dt=1e-4, adaptive=True)
        monitor = StepMonitor(np.linspace(0.0, 1.0, 11))
        configure(ts, settings, "rom_", {"ts_adapt_type": "basic"}, True, steps=monitor)
        healthy = 1e-4 * STALL_FRACTION * 2          # short steps that still advance: an impact resolved
        ts.setTimeStep(healthy)
        for step in range(0, 3 * STALL_STEPS, 64):   # the C callbacks report every 64 steps
            monitor.report(step, 0.5 + step * healthy)
        assert monitor.failure is None
        hover, t0, first = 100 * monitor.floor, 0.5 + 3 * STALL_STEPS * healthy, 3 * STALL_STEPS
        ts.setTimeStep(hover)
        for step in range(first, first + 2 * STALL_STEPS + 1):
            monitor.report(step, t0 + (step - first) * hover)
            if monitor.failure:
                break
        assert monitor.failure is not None and step - first <= 2 * STALL_STEPS
        assert re.search(r"stayed near its floor for \d+ steps up to t = 0\.5\d* s \(a mean step of 1e-10 s",
                         monitor.failure), monitor.failure
    finally:
        ts.destroy()


@pytest.mark.parametrize("scale", [0.0, -0.25, 1.5, float("nan"), True])
def test_an_upper_step_limit_scale_outside_0_to_1_is_refused(scale):
    with pytest.raises(InputError, match="max_step_scale"):
        IntegratorSettings(t_end=1.0, max_step_scale=scale)


@pytest.mark.parametrize("dt_max,limit", [(None, 10 * 1e-3 / 4), (0.5, 0.5 / 4)])
def test_the_richer_runs_upper_step_limit_is_rich_step_times_lower_than_the_runs_even_under_dt_max(dt_max, limit):
    # A run at the upper limit (10 samples, or -rom_ts_adapt_dt_max) has no error control there: the
    # estimate's richer run must take shorter steps there, not the same ones (accuracy.rich_settings).
    from petsc4py import PETSc

    from dbf_hpc.accuracy import RICH_STEP, rich_settings
    from dbf_hpc.timestepping import configure

    assert RICH_STEP == 4
    options = PETSc.Options()
    if dt_max is not None:
        options.setValue("rom_ts_adapt_dt_max", dt_max)
    try:
        settings = IntegratorSettings(t_end=1.0, sample_dt=1e-3)
        for which, expected in ((settings, 4 * limit), (rich_settings(settings, 0.5), limit)):
            ts = PETSc.TS().create(comm=PETSc.COMM_SELF)
            ts.setType(PETSc.TS.Type.ARKIMEX)
            try:
                configure(ts, which, "rom_", {"ts_adapt_type": "basic"}, True)
                assert ts.getStepLimits()[1] == pytest.approx(expected, rel=1e-12)
            finally:
                ts.destroy()
    finally:
        if dt_max is not None:
            options.delValue("rom_ts_adapt_dt_max")


def test_a_petsc_error_in_the_first_step_points_to_the_input_that_caused_it(shared_tmp_path):
    # Red team: a random load of psd 1e301 (N/m)^2/Hz on the paper's beam (1e200 on the 2-D tube) failed in
    # its first step as "PETSc error 72; reduce [integrator] dt or rtol": the load's size, not the step, is at
    # fault, and a first-step stop that PETSc did not raise already said so
    import os

    from dbf_hpc.errors import SolverError
    from dbf_hpc.run import run
    from dbf_hpc.scene import load_scene

    paper = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "jobs", "paper_beam.toml")
    scene = load_scene(paper, [f"basis.cache={shared_tmp_path / 'cache'}", "integrator.t_end=0.05",
                               "excitation.kind=random", "excitation.amplitude=0", "excitation.frequency_hz=0",
                               "excitation.band=[0.0, 9.0]", "excitation.psd=1e301", "basis.estimate=false"])
    with pytest.raises(SolverError) as info:
        run(scene, str(shared_tmp_path / "out.h5"), progress=False)
    message = str(info.value)
    assert message.startswith("the time integration failed at t = 0 s: PETSc error")
    assert "it failed in its first step, which points to the input" in message and "psd" in message
    assert not os.path.exists(shared_tmp_path / "out.h5")


def test_a_sample_is_taken_at_a_step_only_within_round_off_of_it_however_short_the_run():
    # Red team: the tolerance was 1e-9 s for every run shorter than 1 s, so a run of 2 us whose steps are 0.1 ns
    # took each sample up to 10 steps early, as if at the step: a micro-beam's free vibration was 1.4 % off
    import numpy as np

    from dbf_hpc.timestepping import StepMonitor

    times = np.arange(11) * 1e-8   # t_end = 1e-7 s
    monitor = StepMonitor(times)
    assert [(i, exact) for i, _, exact in monitor.samples_due(0.0)] == [(0, True)]
    assert list(monitor.samples_due(0.95e-8)) == [], "the sample at 1e-8 s is 0.5 ns after this step"
    assert [(i, exact) for i, _, exact in monitor.samples_due(1e-8 * (1 + 1e-15))] == [(1, True)]
    assert [i for i, _, exact in monitor.samples_due(3.5e-8) if not exact] == [2, 3]


@pytest.mark.parametrize("t_end, dt, sample_dt, scale, below", [
    (1e-9, 1e-4, 1e-13, 1.0, 500.0),        # the red team's t_end = 1e-9 s: refused up to the 500 Hz mode
    (1e-9, 1e-4, 1e-13, 0.25, 2000.0),      # the estimate's richer run: a cap 4 times lower
    (2e-9, 1e-4, 2e-13, 1.0, None),         # a cap above dt x 1e-8: never refused
    (10.0, 1e-4, 1e-3, 1.0, None),          # the paper's run
    (1.0, 1e-3, 1e-3, 1e-20, math.inf)])    # a cap within t_end's rounding units: refused at any frequency
def test_the_frequency_up_to_which_a_step_cap_is_refused_is_where_the_integrators_refusal_changes(
        t_end, dt, sample_dt, scale, below):
    # cap_refused_below_hz decides from the settings alone (before the basis, run.cap_refusal_before_basis)
    # what configure's cap_refusal decides with the highest reference mode's frequency: refused below it,
    # accepted above it, at every frequency, never at any where it is None.
    from dbf_hpc.timestepping import cap_refusal, cap_refused_below_hz

    settings = IntegratorSettings(t_end=t_end, dt=dt, sample_dt=sample_dt, max_step_scale=scale)
    found = cap_refused_below_hz(settings)
    assert found == (pytest.approx(below, rel=1e-12) if below not in (None, math.inf) else below)
    for hz in (0.0, 1.0, 9.8, 100.0, 499.0, 501.0, 1999.0, 2001.0, 1e4, 1e7, 1e12):
        refused = cap_refusal(settings, hz) is not None
        if found is None or hz > found * (1 + 1e-9):
            assert not refused, (hz, cap_refusal(settings, hz))
        elif hz < found * (1 - 1e-9):
            assert refused, hz
