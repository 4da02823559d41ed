"""The slot scheduler: absolute deadlines (no drift), each reading in its own slot, an overrun
makes MISSING slots and never shifts the grid. The real Station loop, with an in-process meter
whose reads take a controlled time (the wire-level drivers are tested against the virtual devices
elsewhere)."""
import asyncio
import logging
import math
import re

from gateway.core.control import ControlParams
from gateway.plumbing import ratelog
from gateway.station.clock import LateStarts, SlotClock
from gateway.station.station import Station, TestPlan
from kit.fakes import Capture, QuietStm32, TimedMeter


def test_deadlines_come_from_t0_not_from_the_last_wakeup():
    now = [100.0]
    c = SlotClock(0.02, clock=lambda: now[0])
    assert c.deadline(0) == 100.0
    assert c.deadline(50_000) == 100.0 + 50_000 * 0.02       # no accumulated rounding
    now[0] = 100.0 + 7 * 0.02 + 0.009
    assert c.slot_at(now[0]) == 7
    now[0] = 100.0 + 7 * 0.02 + 0.011
    assert c.slot_at(now[0]) == 8


def test_late_starts_are_one_line_at_once_then_one_count_line_per_window():
    late = LateStarts(60.0)
    assert late.add(0.0, 10, 0.031, 1) == "slot 10 started 31 ms late: 1 slot(s) recorded as MISSING"
    assert late.add(1.0, 20, 0.075, 3) is None and late.add(2.0, 30, 0.012, 1) is None
    assert late.due(59.0) is None                      # the window is still open
    assert late.due(60.0) == ("2 more late slot start(s) in the last 60 s: 4 slot(s) recorded as "
                              "MISSING, the worst 75 ms late, the last at slot 30")
    assert late.due(61.0) is None                      # said once
    assert late.add(70.0, 90, 0.02, 1) is not None     # a new window: at once again
    assert late.due(130.0) is None                     # nothing counted: no count line
    late.add(140.0, 100, 0.02, 1)
    late.add(141.0, 101, 0.02, 2)
    assert "1 more late slot start(s)" in late.due(142.0, force=True)    # at close


def test_many_overruns_are_a_few_log_lines_with_every_missing_slot_counted(tmp_path, caplog, monkeypatch):
    """A loaded box overruns often: the log says so once per window with the counts (not one
    WARNING per late slot); the counts add up to the slots recorded as MISSING."""
    monkeypatch.setattr(ratelog, "WINDOW_S", 3600.0)
    slow = set(range(20, 200, 6))                      # 30 overruns of ~3 slots each
    meter = TimedMeter(slow=slow)
    st = Station(station_id="late", method={}, control=ControlParams(), meter=meter,
                 stm32=QuietStm32(), records_dir=str(tmp_path), outputs=[Capture()])
    caplog.set_level(logging.WARNING, logger="hookwatch.station")

    async def main():
        await st.run(asyncio.Event(), max_slots=400)

    asyncio.run(main())
    lines = [r.getMessage() for r in caplog.records if "late" in r.getMessage()]
    assert len(lines) == 2, lines                      # the first at once, the count at close
    first = re.search(r"(\d+) slot\(s\) recorded as MISSING", lines[0])
    rest = re.search(r"(\d+) more late slot start\(s\) .*: (\d+) slot\(s\) recorded as MISSING", lines[1])
    assert first and rest, lines
    assert int(rest.group(1)) + 1 >= len(slow) // 2   # most slow reads overran (a loaded box: more)
    assert int(first.group(1)) + int(rest.group(2)) == st.stats.overrun_slots


def test_overrun_makes_missing_slots_and_keeps_the_grid(tmp_path):
    meter = TimedMeter(slow={40, 120})
    cap = Capture()
    st = Station(station_id="clk", method={}, control=ControlParams(), meter=meter,
                 stm32=QuietStm32(), records_dir=str(tmp_path), outputs=[cap],
                 default_plan=TestPlan("C-1", "I", 0.5, 100.0), autostart=True)
    n = 250

    async def main():
        stop = asyncio.Event()
        await st.run(stop, max_slots=n)

    asyncio.run(main())
    recs = cap.recs
    ks = [r.k for r in recs]
    # one record per slot, contiguous: the grid never shifts
    assert ks == list(range(len(ks))) and len(ks) >= n - 1
    missing = [r.k for r in recs if not r.present]
    # each slow read covers its own slot and overruns the next ones: those are MISSING
    assert st.stats.overrun_slots >= 4 and len(missing) == st.stats.overrun_slots
    assert all(not math.isfinite(r.t1) for r in recs if not r.present)
    # no drift: the k-th poll started at t0 + k·Ts, never before, also after overruns. How late
    # is the machine's (a poll that starts more than Ts/2 late is an overrun, above); a grid that
    # drifted would put every poll of a stretch late, a loaded machine only some of them
    t0 = st.clock.t0
    polled = [r for r in recs if r.present]
    off = [t_call - (t0 + r.k * 0.02) for r, t_call in zip(polled, meter.call_times)]
    assert off and min(off) >= 0, min(off)
    for i in range(0, len(off) - 24, 25):
        assert min(off[i:i + 25]) < 0.010, (polled[i].k, off[i:i + 25])
    # the recorded timestamps put every reading back into its own slot
    assert all(math.floor(r.t / 0.02 + 0.5) == r.k for r in polled)
