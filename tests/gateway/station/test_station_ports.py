"""Port events (issue 12 item 10): a serial port lost and back between two link checks — a meter
gone for 0.5 s — still gives its port_lost / port_back pair (the drivers count every loss); a port
that stays lost gives port_lost once and port_back when it returns."""
import asyncio
import json

from gateway.core.control import ControlParams
from gateway.core.records import EventType
from gateway.station.station import Station, TestPlan
from kit.fakes import Capture, FakeMeter, FakeStm32
from kit.northbound import FAKE_PLANT_START
from kit.vclock import VirtualClock


def _station(tmp_path, out):
    return Station(station_id="ports", method={}, control=ControlParams(), meter=FakeMeter(),
                   stm32=FakeStm32(), records_dir=str(tmp_path), outputs=[out])


def _ports(out):
    return [(e.type, e.data["port"], bool(e.data.get("brief"))) for e in out.events
            if e.type in (EventType.PORT_LOST, EventType.PORT_BACK)]


def test_a_port_gone_for_half_a_second_gives_its_pair_of_events(tmp_path):
    out = Capture()
    st = _station(tmp_path, out)
    st.health.check_links()                               # first look: no event
    assert _ports(out) == []
    # the driver lost the port and reopened it between two checks (connected again by now)
    st.meter.counters["port_lost"] = 1
    st.health.check_links()
    assert _ports(out) == [(EventType.PORT_LOST, "meter", True), (EventType.PORT_BACK, "meter", True)]
    st.health.check_links()                               # nothing new: no repeat
    assert len(_ports(out)) == 2


def test_a_port_that_stays_lost_gives_one_lost_and_one_back(tmp_path):
    out = Capture()
    st = _station(tmp_path, out)
    st.health.check_links()
    st.stm32.connected = False
    st.stm32.counters["port_lost"] = 1
    st.health.check_links()
    st.health.check_links()
    assert _ports(out) == [(EventType.PORT_LOST, "stm32", False)]
    assert st.state.stm32_ok is False
    st.stm32.connected = True
    st.health.check_links()
    assert _ports(out) == [(EventType.PORT_LOST, "stm32", False), (EventType.PORT_BACK, "stm32", False)]
    assert st.state.stm32_ok is True


def test_a_protection_stop_for_a_vanished_meter_names_the_port_in_the_tests_own_events(tmp_path):
    """The meter port vanishes during a test: after 1 s of MISSING slots the protection stop ends
    the test. The test's own record (events.jsonl) names the port that caused it (``port_lost``
    before ``test_ended``) even when the stop comes before the once-a-second link check — as on a
    loaded box (ci: the stop came first). The virtual clock runs the slots flat out, so 51 slots
    take far less than the check's second of wall time."""
    tap = Capture()
    meter = FakeMeter()
    st = Station(station_id="vanish", method=dict(FAKE_PLANT_START), control=ControlParams(),
                 meter=meter, stm32=FakeStm32(), records_dir=str(tmp_path), outputs=[tap],
                 default_plan=TestPlan("S-1", "I", 0.5, 600.0), autostart=True)
    st.clock_factory = VirtualClock

    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(st.run(stop))
        while st.session is None or st.session.monitor.k < 100:
            assert not task.done(), task
            await asyncio.sleep(0)
        meter.value, meter.connected = None, False          # the port went away (EIO)
        meter.counters["port_lost"] = 1
        while not st.results:
            assert not task.done(), task
            await asyncio.sleep(0)
        stop.set()
        await task

    asyncio.run(asyncio.wait_for(main(), 120))
    res = st.results[0]
    assert res["end_reason"] == "protection stop" and res["method"]["stop_reasons"] == ["MISSING"], res
    types = [e.type for e in tap.events]
    assert types.index(EventType.PORT_LOST) < types.index(EventType.TEST_ENDED), types
    d = next(p for p in tmp_path.rglob("events.jsonl"))
    kinds = [json.loads(line)["type"] for line in d.read_text().splitlines()]
    assert kinds.index("port_lost") < kinds.index("test_ended"), kinds
