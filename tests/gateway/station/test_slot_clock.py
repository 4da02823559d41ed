"""The slot scheduler: absolute deadlines (no drift), each reading in its own slot, an overrun
makes MISSING slots and never shifts the grid. The real Station loop, with an in-process meter
whose reads take a controlled time (the wire-level drivers are tested against the virtual devices
elsewhere)."""
import asyncio
import math

from gateway.control import ControlParams
from gateway.station.clock import SlotClock
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
