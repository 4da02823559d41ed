"""The end-of-life alarm survives a gateway restart: active (or acknowledged) until a new test
starts, so the PLC and the MES see the same alarm after the restart, and an ACK is accepted."""
import asyncio
import json
import time

from gateway.core.control import ControlParams
from gateway.core.records import Command, CommandKind, Event, EventType
from gateway.station.station import Station, TestPlan
from kit.fakes import QuietStm32, TimedMeter


def _station(tmp_path, plan=None):
    return Station(station_id="al", method={}, control=ControlParams(), meter=TimedMeter(slow=()),
                   stm32=QuietStm32(), records_dir=str(tmp_path), default_plan=plan)


def _run(st, n=20, before=None):
    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(st.run(stop, max_slots=n))
        out = None
        if before is not None:
            while st.clock is None:
                await asyncio.sleep(0.005)
            out = await before(st)
        await task
        return out
    return asyncio.run(main())


def test_alarm_restored_after_restart_then_acknowledged_then_cleared_by_a_new_test(tmp_path):
    first = _station(tmp_path)
    # what the end of life does: the event goes to the station's one alarm store
    first.alarms.on_event(Event(EventType.END_OF_LIFE, "al", time.time(), "T-1", 6170,
                                {"k_life": 6170, "t_life": 123.4, "sample_id": "S-1"}))
    # a new gateway process: the alarm is still active, for the PLC registers and MQTT state
    second = _station(tmp_path)

    async def ack(st):
        assert st.state.alarm == "unacknowledged" and st.state.t_life == 123.4   # ISA-18.2 (was "active")
        return await st.submit(Command(CommandKind.ACK, "plc:127.0.0.1"))

    reply = _run(second, before=ack)
    assert reply.ok, reply
    assert second.state.alarm == "acknowledged"
    with open(tmp_path / "al" / "alarm.json") as f:
        assert json.load(f)["alarm"] == "acknowledged"
    # a third start: still acknowledged; a new test (hook replaced) clears it
    third = _station(tmp_path, plan=TestPlan("S-2", "I", 0.5, 100.0))

    async def start(st):
        assert st.state.alarm == "acknowledged"
        return await st.submit(Command(CommandKind.START, "mqtt",
                                       {"sample_id": "S-2", "grade": "I", "t_set": 0.5}))

    assert _run(third, before=start).ok
    assert third.state.alarm == "normal"   # ISA-18.2: closed (was "none")
    with open(tmp_path / "al" / "alarm.json") as f:
        assert json.load(f)["alarm"] == "normal"
