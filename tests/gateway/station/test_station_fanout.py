"""The station's fan-out and state flow: a failing output never stops the station (logged once,
counted), the recorder is an ordinary output, the MQTT link and reloads reach outputs as state
and events, and a reload is decided on the station's own loop."""
import asyncio
import logging

from gateway.core.control import ControlParams
from gateway.core.records import EventType
from gateway.station.station import Station, TestPlan
from kit.fakes import Capture, QuietStm32, TimedMeter


class Broken(Capture):
    def on_record(self, rec):
        raise RuntimeError("broken output")

    def on_event(self, ev):
        raise RuntimeError("broken output")


def _station(tmp_path, outputs, plan=None):
    # the timed meter is no plant: no zero check, a start settles at once (METHOD.md §3a)
    return Station(station_id="fo", method={"zero_check": False, "settle_band": 0.5, "settle_time": 0.1},
                   control=ControlParams(), meter=TimedMeter(slow=()),
                   stm32=QuietStm32(), records_dir=str(tmp_path), outputs=outputs,
                   default_plan=plan, autostart=plan is not None)


def _run(st, n, during=None):
    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(st.run(stop, max_slots=n))
        out = None
        if during is not None:
            while st.clock is None:
                await asyncio.sleep(0.005)
            out = await during(st, stop)
        await task
        return out
    return asyncio.run(main())


def test_a_failing_output_is_logged_once_counted_and_never_stops_the_station(tmp_path, caplog):
    good = Capture()
    st = _station(tmp_path, [Broken(), good], plan=TestPlan("S-1", "I", 0.5, 0.4))
    with caplog.at_level(logging.ERROR, logger="hookwatch.station"):
        _run(st, 40)
    assert len(good.records) == 40 and st.stats.slots == 40
    assert st.fanout.failures["Broken.record"] == 40 and st.fanout.failures["Broken.event"] >= 2
    failed_lines = [r for r in caplog.records if "failed on record" in r.getMessage()]
    assert len(failed_lines) == 1
    assert any("Broken.record ×40" in r.getMessage() for r in caplog.records)
    # the recorder is an output like the others: the test it recorded reads back
    assert [e.type for e in good.events][:2] == [EventType.TEST_STARTING, EventType.TEST_STARTED]
    assert st.results and st.results[0]["test_status"] == "completed"


def test_uplink_state_and_config_reloaded_reach_the_outputs(tmp_path):
    out = Capture()
    st = _station(tmp_path, [out])
    st.reloaded = True

    async def during(st, stop):
        st.set_uplink("mqtt", True)
        return st.state.mqtt_ok

    assert _run(st, 10, during) is True
    assert out.events[0].type == EventType.CONFIG_RELOADED
    assert any(s.mqtt_ok for s in out.states) and not out.states[0].mqtt_ok


def test_a_reload_restarts_an_idle_station_and_spares_one_in_a_test(tmp_path):
    applied = []

    async def idle(st, stop):
        return st.reload_requested(lambda: applied.append("idle"))

    st = _station(tmp_path, [])
    assert _run(st, 2000, idle) is True and applied == ["idle"]
    assert st.stats.slots < 2000            # it stopped for its runner to rebuild it

    async def busy(st, stop):
        kept = st.reload_requested(lambda: applied.append("busy"))
        stop.set()
        return kept

    st2 = _station(tmp_path / "b", [], plan=TestPlan("S-2", "I", 0.5, 600.0))
    assert _run(st2, 2000, busy) is False and applied == ["idle"]
