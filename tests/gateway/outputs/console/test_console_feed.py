"""The console's hand-over and min/max-decimated series (pure, no I/O)."""
from __future__ import annotations

import math

from gateway.core import records
from gateway.core.records import Event, EventType, SlotRecord, StationState
from gateway.outputs.console.feed import HANDOVER_SLOTS, MAX_BUCKETS, ConsoleOutput, Series, StationFeed


def rec(k, mu=0.35, q=1):
    return SlotRecord(k=k, t=k * 0.02, present=True, t1=0.4, t2=0.6, q=q, mask=0, ratio=1.5,
                      mu=mu if q else None, mean_filt=0.5, speed_cmd=100.0, speed_act=99.0,
                      saturated=False)


def test_ten_hour_series_is_bounded_and_keeps_a_one_slot_spike():
    s = Series(0.02)
    n = 10 * 3600 * 50
    spike = 1_234_567
    for k in range(n):
        s.add(rec(k, 0.9 if k == spike else 0.35))
    assert len(s.buckets) <= MAX_BUCKETS
    rows = s.rows()
    assert rows[0][0] == 0.0 and rows[-1][0] > 35000
    assert max(r[2] for r in rows) == 0.9            # the spike survives decimation
    assert min(r[1] for r in rows) == 0.35
    assert s.n_slots == n and s.n_valid == n


def test_changes_are_incremental_until_a_merge():
    s = Series(0.02, max_buckets=8)
    for k in range(5):
        s.add(rec(k))
    start, rows = s.take_changes()
    assert start == 0 and len(rows) == 5
    assert s.take_changes() is None
    s.add(rec(5))
    start, rows = s.take_changes()
    assert start == 5 and len(rows) == 1
    gen = s.gen
    for k in range(6, 9):
        s.add(rec(k))
    assert s.gen == gen + 1 and s.width == 2 and len(s.buckets) == 5


def test_handover_is_bounded_and_ordered():
    feed = StationFeed("x")
    out = ConsoleOutput(feed)
    out.on_event(Event(EventType.TEST_STARTED, "x", 0.0, "t1", 0, {"t_set": 0.5}))
    for k in range(HANDOVER_SLOTS + 10):
        out.on_record(rec(k, q=k % 2))
    out.on_state(StationState("x", state=records.TestState.MONITORING, mu_ss=0.35, mu_th=0.44))
    assert len(feed.q) == HANDOVER_SLOTS and feed.dropped == 12
    feed.drain()
    # the test-start event was the oldest item and was dropped: the console shows nothing running
    assert feed.series.n_slots == 0 and feed.summary()["handover_dropped"] == 12
    feed2 = StationFeed("y")
    o2 = ConsoleOutput(feed2)
    o2.on_event(Event(EventType.TEST_STARTED, "y", 0.0, "t1", 0, {"t_set": 0.5}))
    for k in range(100):
        o2.on_record(rec(k, mu=0.3 + k / 1000))
    o2.on_event(Event(EventType.BASELINE, "y", 0.0, "t1", 60, {"mu_ss": 0.35, "mu_th": 0.44,
                                                               "k_b": 60, "stable_first": 10}))
    feed2.drain()
    sm = feed2.summary()
    assert sm["slots"] == 100 and sm["filled"] == 100 and feed2.markers["t_b"] == 60 * 0.02
    assert math.isclose(sm["mu_now"], 0.3 + 74.5 / 1000, abs_tol=1e-6)   # median of the last 50


def test_curve_rebuilt_from_the_recorder_log_after_a_loss(tmp_path):
    """The hand-over overflows mid-test (console stalled): the series comes back from the log on
    disk (read while the recorder still writes it) plus the live tail, from slot 0, no gap."""
    from gateway.outputs.console.feed import series_from_log
    from gateway.station.recorder import TestRecorder

    td = tmp_path / "T1"
    r = TestRecorder(str(td), {"test_id": "T1"}, flush_interval_s=0.0)
    feed = StationFeed("x")
    out = ConsoleOutput(feed)
    out.on_event(Event(EventType.TEST_STARTED, "x", 0.0, "T1", 0, {"t_set": 0.5}))
    live = Series(0.02)
    n = HANDOVER_SLOTS + 3000
    for k in range(n):
        rc = rec(k, mu=0.35 + (k % 7) / 1000)
        r.on_record(rc)
        live.add(rc)
        if k == 10:
            feed.drain()              # the console saw the start, then stalls
        out.on_record(rc)
    r.flush(force=True)
    assert feed.dropped > 0
    feed.drain()
    assert feed.pending is not None and feed.running
    for k in range(n, n + 500):        # live records go on while the log is read
        rc = rec(k, mu=0.36)
        live.add(rc)
        out.on_record(rc)
    feed.drain()
    disk = series_from_log(str(td / "log.csv.gz"), 0.02)   # the recorder has not closed the file
    assert disk.n_slots == n
    gen = feed.series.gen
    feed.rebuild_from(disk)
    assert feed.pending is None and feed.series.gen > gen and feed.rebuilds == 1
    assert feed.series.n_slots == n + 500
    assert feed.series.rows() == live.rows()
    r.close({"test_id": "T1"})
