"""The one restart back-off (gateway/plumbing/backoff.py), used by a station's runner and a fleet's
supervisor alike."""
import math

import pytest

from gateway.plumbing.backoff import Backoff
from gateway.station.fleet import StationRunner


def test_the_wait_doubles_in_a_row_up_to_its_cap_and_a_stable_run_starts_a_new_row():
    b = Backoff(1.0, 10.0, stable_s=60.0)
    assert [b.failed(ran_s=1.0) for _ in range(6)] == [1.0, 2.0, 4.0, 8.0, 10.0, 10.0]
    assert b.in_row == 6
    assert b.failed(ran_s=60.0) == 1.0 and b.in_row == 1      # it ran long enough: a new row
    b.reset()
    assert b.in_row == 0 and b.failed() == 1.0


def test_without_a_stable_time_only_reset_ends_a_row():
    b = Backoff(0.5, 30.0)
    assert b.stable_s == math.inf
    assert [b.failed(ran_s=1e9) for _ in range(4)] == [0.5, 1.0, 2.0, 4.0]


def test_a_zero_back_off_restarts_at_once_and_nonsense_is_refused():
    assert Backoff(0.0, 0.0).failed() == 0.0
    for base, cap in ((-1.0, 5.0), (5.0, 1.0), (math.nan, 1.0)):
        with pytest.raises(ValueError):
            Backoff(base, cap)


def test_the_station_runner_and_the_supervisor_use_it():
    """A runner's restarts go through its Backoff: its crash streak is the back-off's row (the
    supervisor's use is checked by tests/test_architecture.py)."""
    r = StationRunner("x", lambda: None, restart_backoff_s=0.25, restart_backoff_max_s=1.0, stable_after_s=5.0)
    assert isinstance(r.restart, Backoff)
    assert [r.restart.failed(0.1) for _ in range(4)] == [0.25, 0.5, 1.0, 1.0] and r.crash_streak == 4
