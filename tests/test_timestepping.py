"""The time-stepping layer (timestepping.py): settings validated once, and runs that cannot finish
in reasonable time refused before any work, with what to change."""
import pytest

from dbf_hpc.errors import InputError
from dbf_hpc.timestepping import IntegratorSettings, check_work


@pytest.mark.parametrize("rtol", [1e-300, 0.0, 1.5])
def test_a_tolerance_double_precision_cannot_meet_is_refused(rtol):
    with pytest.raises(InputError, match="cannot be met in double precision"):
        IntegratorSettings(t_end=1.0, rtol=rtol)


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
