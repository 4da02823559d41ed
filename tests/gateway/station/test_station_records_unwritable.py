"""Issue 21 item 6: a start into a records folder that cannot be written (a real read-only file
system: tests run as root, so a chmod would not stop them) is refused with ``start_failed`` and
its reason, ``disk_ok`` turns false with one ``disk_full`` event, nothing crashes and the station
runs on; once the folder can be written again the next start records its test."""
import asyncio
import os
import subprocess

from gateway.core.control import ControlParams
from gateway.core.records import Command, CommandKind, EventType
from gateway.core.records import TestState as TState
from gateway.station.station import Station, TestPlan
from kit.fakes import Capture, FakeMeter, FakeStm32
from kit.northbound import FAKE_PLANT_START
from kit.smallfs import small_tmpfs
from kit.vclock import VirtualClock


def remount(path, mode):
    subprocess.run(["mount", "-o", f"remount,{mode}", path], check=True, capture_output=True)


def test_a_start_into_a_read_only_records_folder_is_refused_and_the_station_runs_on(tmp_path):
    with small_tmpfs(tmp_path / "fs", "4m") as fs:
        os.makedirs(os.path.join(fs, "ro"))            # the station's folder exists, then ro
        remount(fs, "ro")
        st = Station(station_id="ro", method=dict(FAKE_PLANT_START), control=ControlParams(),
                     meter=FakeMeter(), stm32=FakeStm32(), records_dir=fs,
                     default_plan=TestPlan("S-1", "I", 0.5, 600.0), autostart=True)
        st.clock_factory = VirtualClock
        tap = Capture()
        st.outputs.append(tap)
        seen = {}

        async def main():
            stop = asyncio.Event()
            task = asyncio.create_task(st.run(stop))
            while not st.start_failures:
                assert not task.done(), task
                await asyncio.sleep(0)
            seen["state"] = (st.state.state, st.state.disk_ok, st.busy)
            seen["slots_at_refusal"] = st.stats.slots
            while st.stats.slots < seen["slots_at_refusal"] + 200:   # it runs on
                assert not task.done(), task
                await asyncio.sleep(0)
            remount(fs, "rw")
            reply = await st.submit(Command(CommandKind.START, "cli", {"sample_id": "S-2", "t_set": 0.5}))
            seen["reply"] = reply.ok
            while st.session is None:
                assert not task.done() and len(st.start_failures) == 1, st.start_failures
                await asyncio.sleep(0)
            seen["disk_ok_after"] = st.state.disk_ok
            stop.set()
            await task

        try:
            asyncio.run(asyncio.wait_for(main(), 120))
        finally:
            subprocess.run(["mount", "-o", "remount,rw", fs], capture_output=True)
        assert seen["state"] == (TState.IDLE, False, False)
        f = st.start_failures[0]
        assert f["sample_id"] == "S-1"
        assert f["reason"].startswith("records folder cannot be written: Read-only file system"), f
        types = [e.type for e in tap.events]
        fails = [e for e in tap.events if e.type == EventType.START_FAILED]
        assert len(fails) == 1 and fails[0].data["reason"] == f["reason"]
        full = [e for e in tap.events if e.type == EventType.DISK_FULL]
        assert len(full) == 1 and full[0].data["store"] == "records"
        assert types.index(EventType.DISK_FULL) < types.index(EventType.START_FAILED)
        # writable again: the next start records its test, the disk state is good again
        assert seen["reply"] and seen["disk_ok_after"]
        assert EventType.DISK_OK in types and EventType.TEST_STARTED in types
        assert [d for d in os.listdir(os.path.join(fs, "ro")) if d.endswith("S-2")]
        assert not [d for d in os.listdir(os.path.join(fs, "ro")) if d.endswith("S-1")]
