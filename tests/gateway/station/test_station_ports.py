"""Port events (issue 12 item 10): a serial port lost and back between two link checks — a meter
gone for 0.5 s — still gives its port_lost / port_back pair (the drivers count every loss); a port
that stays lost gives port_lost once and port_back when it returns."""
from gateway.control import ControlParams
from gateway.records import EventType
from gateway.station.station import Station
from kit.fakes import Capture, FakeMeter, FakeStm32


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
