"""plots.py: what a user types for --window, read or refused in one line that says what to type."""
import pytest

from dbf_hpc.errors import InputError
from dbf_hpc.plots import parse_window


def test_a_window_reads_either_end_left_open():
    assert parse_window("9:") == (9.0, float("inf"))
    assert parse_window(":1") == (float("-inf"), 1.0)
    assert parse_window("0.5:2") == (0.5, 2.0)
    assert parse_window(None) is None and parse_window("") is None


def test_a_window_of_one_time_asks_which_end_with_that_time():
    with pytest.raises(InputError) as refused:
        parse_window("5")
    assert "e.g. 5: (from 5 s) or :5 (to it)" in str(refused.value)


def test_a_window_that_is_no_time_is_refused_with_an_example_of_times():
    # New-user pass: "--window last" gave "e.g. last: (from last s) or :last (to it)", an example
    # that is itself refused.
    for text in ("last", "a", "9s"):
        with pytest.raises(InputError) as refused:
            parse_window(text)
        message = str(refused.value)
        assert message.startswith(f"--window {text!r}: give T0:T1 in seconds, e.g. 9: (from 9 s)"), message
        assert f"{text}:" not in message.split("e.g.")[1], message


def test_a_window_that_ends_before_it_starts_is_refused():
    for text in ("5:2", "1:1", "nan:1", "a:b"):
        with pytest.raises(InputError):
            parse_window(text)
