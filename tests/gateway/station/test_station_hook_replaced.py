"""`hook_replaced` (a Sparkplug DCMD, MQTT or CLI command) closes the end-of-life alarm of the
replaced hook through the one command path; without an alarm it is refused with NO_ALARM."""
import asyncio
import json

from gateway.core.control import ControlParams
from gateway.core.records import Command, CommandKind, EventType
from gateway.station.command_desk import CODE
from gateway.station.station import Station
from kit.fakes import Capture, QuietStm32, TimedMeter


def test_hook_replaced_closes_the_alarm_and_is_refused_without_one(tmp_path):
    out = Capture()
    st = Station(station_id="hr", method={}, control=ControlParams(), meter=TimedMeter(slow=()),
                 stm32=QuietStm32(), records_dir=str(tmp_path), outputs=[out])
    st.board.emit(EventType.END_OF_LIFE, k=600, k_life=600, t_life=12.0, sample_id="S-1")
    assert st.state.alarm == "unacknowledged"   # ISA-18.2 (was "active")

    async def main():
        first = await st.submit(Command(CommandKind.HOOK_REPLACED, "sparkplug"))
        second = await st.submit(Command(CommandKind.HOOK_REPLACED, "sparkplug"))
        return first, second

    first, second = asyncio.run(main())
    assert first.ok and st.state.alarm == "normal"   # ISA-18.2: closed (was "none")
    with open(tmp_path / "hr" / "alarm.json") as f:
        assert json.load(f)["alarm"] == "normal"
    cleared = [e for e in out.events if e.type == EventType.ALARM_CLEARED]
    assert len(cleared) == 1 and cleared[0].data["reason"] == "hook_replaced"
    assert not second.ok and second.code == CODE["NO_ALARM"]
