"""The station's one STM32 sender (issue 16): the slot loop hands each slot's speed command over a
one-slot "latest value" box and never waits for the link; a command still waiting when a newer
one comes is replaced (never queued behind the one on the wire) and counted; a STOP withdraws a
command not yet sent. The station runs on a virtual clock flat out; the STM32 port is held on the
wire by the test."""
import asyncio

from gateway.core.control import ControlParams
from gateway.station.station import Station, TestPlan
from gateway.station.stm32link import LatestValue
from kit.fakes import FakeMeter
from kit.vclock import VirtualClock

FAST = {"w_ss": 0.2, "w_hold": 0.4, "tau": 0.2, "settle_time": 0.1, "start_timeout": 3.0,
        "zero_check": False}


def test_latest_value_newest_wins_and_counts_the_replaced():
    async def main():
        box = LatestValue()
        assert box.empty
        assert box.put(1.0) is False
        assert box.put(2.0) is True and box.put(3.0) is True
        assert await box.get() == 3.0 and box.empty
        getter = asyncio.create_task(box.get())
        await asyncio.sleep(0)
        assert not getter.done()          # waits for a value
        box.put(4.0)
        assert await getter == 4.0
        box.put(5.0)
        box.clear()                       # withdrawn: not counted as superseded
        assert box.empty
        return box.superseded
    assert asyncio.run(main()) == 2


class Meter(FakeMeter):
    """The kit's constant meter, counting its reads."""
    reads = 0

    async def read(self):
        self.reads += 1
        return await super().read()


class HeldStm32:
    """SET_SPEED stays on the wire until the test opens ``gate``; every command is logged with
    the meter read count at which it went out."""

    def __init__(self, meter):
        self.connected, self.counters, self.meter = True, {}, meter
        self.gate = asyncio.Event()
        self.sent = []                    # (rpm, meter reads when it went out)
        self.calls = []
        self.on_wire = 0

    async def open(self):
        pass

    async def close(self):
        pass

    async def enable(self):
        self.calls.append("enable")

    async def stop(self, reason=""):
        self.calls.append(f"stop:{reason}:{len(self.sent)}")

    async def read_status(self):
        return None

    async def set_speed(self, rpm):
        self.sent.append((rpm, self.meter.reads))
        self.on_wire += 1
        try:
            await self.gate.wait()
        finally:
            self.on_wire -= 1


def _station(tmp_path, name):
    """A station whose test starts at once (no zero check), on the virtual clock, with the held
    STM32 port (a fake without post_speed: the sender box path)."""
    meter = Meter()
    stm = HeldStm32(meter)
    st = Station(station_id=name, method=FAST, control=ControlParams(), meter=meter, stm32=stm,
                 records_dir=str(tmp_path), default_plan=TestPlan("S-1", "I", 0.5, 100.0),
                 autostart=True)
    st.clock_factory = VirtualClock
    assert not st.link.posting
    return st, meter, stm


def test_the_slot_loop_never_waits_for_the_stm32_and_the_newest_command_wins(tmp_path):
    st, meter, stm = _station(tmp_path, "snd")
    seen = {}

    async def main():
        stop = asyncio.Event()
        stm.gate.clear()
        task = asyncio.create_task(st.run(stop))
        # the first command goes out and stays on the wire; the loop runs on regardless
        while meter.reads < 300:
            await asyncio.sleep(0)
        seen["sent_while_held"] = len(stm.sent)
        seen["on_wire"] = stm.on_wire
        seen["skips_while_held"] = st.stats.stm32_busy_skips
        seen["reads_while_held"] = meter.reads
        seen["box_full"] = not st.link.box.empty
        stm.gate.set()                    # the link answers again
        reads_at_release = meter.reads
        while len(stm.sent) < seen["sent_while_held"] + 20:
            await asyncio.sleep(0)
        seen["next_after_release"] = stm.sent[seen["sent_while_held"]]
        seen["reads_at_release"] = reads_at_release
        stop.set()
        await task

    asyncio.run(asyncio.wait_for(main(), 60))
    assert seen["sent_while_held"] == 1 and seen["on_wire"] == 1      # nothing queued behind it
    assert seen["reads_while_held"] >= 300                             # the loop never waited
    assert seen["box_full"]                                            # the newest one waits
    # every slot of the test put a command; all but the one on the wire and the newest replaced
    assert seen["skips_while_held"] >= 250
    assert st.link.box.superseded == st.stats.stm32_busy_skips
    assert st.stats.summary()["stm32_busy_skips"] == st.stats.stm32_busy_skips
    # the command sent after the release is the newest of its time, not the oldest held one
    rpm, at = seen["next_after_release"]
    assert at >= seen["reads_at_release"]
    assert stm.calls[-1].startswith("stop:gateway shutdown")


def test_a_stop_withdraws_a_speed_command_not_yet_sent(tmp_path):
    st, meter, stm = _station(tmp_path, "snd2")

    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(st.run(stop))
        while meter.reads < 100:
            await asyncio.sleep(0)
        assert not st.link.box.empty            # a command waits behind the held one
        await st.end_test("stopped by command")
        assert st.link.box.empty                # withdrawn by the STOP
        n = len(stm.sent)
        stm.gate.set()
        for _ in range(50):
            await asyncio.sleep(0)
        after = len(stm.sent) - n
        stop.set()
        await task
        return after

    after = asyncio.run(asyncio.wait_for(main(), 60))
    assert after == 0                             # no SET_SPEED after the STOP
    assert any(c.startswith("stop:stopped by command") for c in stm.calls)
