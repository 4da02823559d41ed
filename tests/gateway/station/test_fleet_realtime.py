"""A station runner's SCHED_FIFO where it is refused: a warning when it was asked for
(`hookwatch run --realtime`), one info line when it is taken only where permitted
(`hookwatch demo`: `rt_optional`, as the demo said nothing of it before it ran through drive)."""
import logging
import threading

import pytest

from gateway.plumbing.osprio import MAX_PRIORITY
from gateway.station.fleet import StationRunner


@pytest.mark.parametrize(("optional", "level"), [(False, logging.WARNING), (True, logging.INFO)])
def test_a_refused_realtime_priority_is_said_at_its_level(caplog, optional, level):
    built = threading.Event()

    def factory():
        built.set()
        raise RuntimeError("no station here")

    # a priority beyond the maximum: refused by gateway.plumbing.osprio.realtime_thread on every box
    r = StationRunner("rt", factory, rt_priority=MAX_PRIORITY + 1, rt_optional=optional,
                      restart_backoff_s=30.0)
    with caplog.at_level(logging.INFO, logger="hookwatch.fleet"):
        r.start()
        assert built.wait(10)
        r.request_stop()
        r.thread.join(10)
    assert not r.thread.is_alive()
    said = [rec for rec in caplog.records if "slot loop at normal priority" in rec.getMessage()]
    assert [rec.levelno for rec in said] == [level], said
    assert f"SCHED_FIFO {MAX_PRIORITY + 1} priority {MAX_PRIORITY + 1} outside" in said[0].getMessage()
