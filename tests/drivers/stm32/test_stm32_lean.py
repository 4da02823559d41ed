"""The STM32 link's lean hot path (issue 16): the whole-ACK fast decode gives exactly what the
streaming parser + decode_reply give; concurrent callers still get one exchange at a time in
order (the busy flag that replaced the lock), a cancelled waiter passes its turn on; steady
traffic keeps the keep-alive from firing; all against the virtual STM32 over the in-process link."""
import asyncio
import random

from drivers.sim.loopback import LoopbackLink
from drivers.sim.twin_stm32 import SimpleMotor, Stm32Firmware, VirtualStm32
from drivers.stm32 import protocol as p
from drivers.stm32.driver import Stm32Link
from drivers.stm32.wire import fast_ack


def run(coro, timeout=40.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


def _status(rng):
    return p.Status(actual_rpm=rng.randint(-60000, 60000) / 100, command_rpm=rng.randint(0, 60000) / 100,
                    enabled=rng.random() < 0.5, flags=p.Flag(rng.randrange(64)),
                    stop_reason=rng.choice([*p.StopReason, 77]), watchdog_ms=rng.randrange(65536),
                    rx_errors=rng.randrange(65536))


def test_fast_ack_equals_the_streaming_parser():
    rng = random.Random(16)
    for _ in range(2000):
        ack = p.encode_ack(rng.randrange(256), rng.choice(list(p.REQUEST_PAYLOAD)), _status(rng))
        want = p.decode_reply(p.FrameParser().feed(ack)[0])
        got = fast_ack(ack)
        assert got == want
        assert type(got.status.flags) is p.Flag and got.status.stop_reason == want.status.stop_reason
        assert type(got.status.stop_reason) is type(want.status.stop_reason)


def test_fast_ack_leaves_everything_else_to_the_parser():
    st = p.Status(10.0, 10.0, True, p.Flag.ENABLED, p.StopReason.NONE)
    ack = p.encode_ack(5, p.Cmd.SET_SPEED, st)
    bad_crc = ack[:-1] + bytes(((ack[-1] + 1) & 0xFF,))
    for data in (bad_crc, ack[:-1], ack + b"\x00", b"\x00" + ack[:-1], p.encode_nak(5, p.Cmd.SET_SPEED, 3),
                 ack[:4] + b"\x81" + ack[5:], p.req_ping(3) + bytes(ack[:23 - 9])):
        assert fast_ack(data) is None


async def _with_virtual_stm32(body):
    vs = VirtualStm32(Stm32Firmware(0.3), SimpleMotor(tau_s=0.05), link=LoopbackLink())
    await vs.start()
    link = Stm32Link(vs.device, timeout_s=0.05, watchdog_s=0.3)
    await link.open()
    try:
        return await body(link)
    finally:
        await link.close()
        await vs.stop()


def test_concurrent_calls_one_exchange_at_a_time_in_order():
    async def body(link):
        await link.stop("gateway start")
        await link.enable()
        order = []

        async def call(i, coro):
            st = await coro
            order.append((i, st is not None))
        tasks = [asyncio.create_task(call(i, link.set_speed(100.0 + i))) for i in range(5)]
        tasks.append(asyncio.create_task(call(5, link.read_status())))
        # a waiter cancelled while queued gives up its turn; the ones behind it still go
        victim = asyncio.create_task(link.set_speed(999.0))
        tasks.append(asyncio.create_task(call(6, link.set_speed(123.0))))
        await asyncio.sleep(0)
        victim.cancel()
        await asyncio.gather(*tasks)
        assert victim.cancelled()
        st = await link.read_status()
        return order, st, dict(link.counters), link.busy

    order, st, counters, busy = run(_with_virtual_stm32(body))
    assert order == [(i, True) for i in range(7)]
    assert st.command_rpm == 123.0              # the cancelled 999 rpm never went out
    assert counters["stale"] == 0 and counters["timeouts"] == 0 and counters["failed"] == 0
    assert not busy


def test_steady_traffic_no_keepalive_silence_keepalive():
    async def body(link):
        await link.stop("gateway start")
        await link.enable()
        for _ in range(40):                 # 0.8 s of SET_SPEED every 20 ms: no keep-alive
            assert await link.set_speed(50.0) is not None
            await asyncio.sleep(0.02)
        during = link.counters["keepalives"]
        await asyncio.sleep(0.6)            # silence: the keep-alive feeds the watchdog
        after = link.counters["keepalives"]
        st = await link.read_status()
        return during, after, st

    during, after, st = run(_with_virtual_stm32(body))
    assert during == 0
    assert after >= 3                       # every 0.15 s (half of the 0.3 s watchdog)
    assert st.enabled and not st.watchdog_tripped


def test_posted_speed_commands_collected_without_waiting():
    async def body(link):
        await link.stop("gateway start")
        await link.enable()
        got = []
        for i in range(30):                  # as the station: post, next slot collect
            assert link.post_speed(100.0 + i)
            assert not link.wire.watching        # the ACK does not wake the loop
            await asyncio.sleep(0.02)
            got.append(link.collect())
        acked_before = link.counters["acked"]
        st = await link.read_status()        # an awaited exchange watches the port again
        return got, acked_before, st, dict(link.counters), link.wire.watching

    got, acked_before, st, c, watching = run(_with_virtual_stm32(body))
    assert all(s is not None for s in got)
    assert [s.command_rpm for s in got] == [100.0 + i for i in range(30)]
    assert st.command_rpm == 129.0 and watching
    assert c["timeouts"] == 0 and c["stale"] == 0 and c["failed"] == 0 and acked_before >= 32


def test_posted_command_lost_reply_busy_link_and_a_pending_post_before_an_exchange():
    async def body(link, vs):
        await link.stop("gateway start")
        await link.enable()
        out = {}
        vs.faults.drop_next_replies = 1
        assert link.post_speed(80.0)
        await asyncio.sleep(0.03)
        out["lost"] = (link.collect(), link.counters["timeouts"], link.counters["failed"])
        # a post while an awaited exchange holds the link is refused (the slot counts a skip)
        t = asyncio.create_task(link.read_status())
        await asyncio.sleep(0)
        out["busy"] = link.post_speed(90.0)
        await t
        # a post not yet collected when an exchange comes: collected first, not stale
        assert link.post_speed(95.0)
        await asyncio.sleep(0.02)
        st = await link.stop("completed")
        out["after"] = (link.last_status.command_rpm if link.last_status else None, st.enabled,
                        link.counters["stale"], link.collect())
        out["nan"] = link.post_speed(float("nan"))
        return out

    async def main():
        vs = VirtualStm32(Stm32Firmware(0.3), SimpleMotor(tau_s=0.05), link=LoopbackLink())
        await vs.start()
        link = Stm32Link(vs.device, timeout_s=0.05, watchdog_s=0.3)
        await link.open()
        try:
            return await body(link, vs)
        finally:
            await link.close()
            await vs.stop()

    out = run(main())
    assert out["lost"] == (None, 1, 1)
    assert out["busy"] is False
    rpm, enabled, stale, again = out["after"]
    assert rpm == 0.0 and not enabled and stale == 0 and again is None
    assert out["nan"] is False


def test_a_drive_stopped_by_the_firmware_is_counted_and_said_once(caplog):
    """A stalled gateway thread (here: the loop blocked 0.5 s, beyond the 0.3 s watchdog) lets the
    firmware's watchdog stop the motor: the next status says so, and the link logs why (the
    tension falls next, and a protection stop may follow: the operator reads the cause)."""
    import logging
    import time

    async def body(link):
        await link.stop("gateway start")
        await link.enable()
        assert await link.set_speed(100.0) is not None
        time.sleep(0.5)                     # the whole thread stalls: no keep-alive either
        st = await link.set_speed(100.0)
        st2 = await link.read_status()
        return st, st2, dict(link.counters)

    with caplog.at_level(logging.WARNING, logger="hookwatch.stm32"):
        st, st2, c = run(_with_virtual_stm32(body))
    assert not st.enabled and st.watchdog_tripped and st.stop_reason == p.StopReason.WATCHDOG
    assert not st2.enabled
    assert c["drive_stops"] == 1
    lines = [r.getMessage() for r in caplog.records if "stopped on its own" in r.getMessage()]
    assert len(lines) == 1 and "WATCHDOG" in lines[0], lines


def test_a_watchdog_stop_only_the_gateways_own_stop_finds_is_said_with_the_measured_stall(caplog):
    """Issue 34 item 5: the gateway stalls longer than the watchdog (here: its thread blocked
    0.5 s, watchdog 0.3 s); its first frame after the stall is its own STOP (the protection stop
    the missing slots call for). The STOP's answer says the firmware had stopped the drive by
    itself (reason WATCHDOG, latched): that is a stop on its own all the same — counted, said
    once with the silence the link measured between its two frames (≥ the 0.5 s stall), and
    kept once for the station. A STOP of the gateway's own without a stall is no such stop."""
    import logging
    import time

    from gateway.core.ports import DriveStop

    async def body(link):
        await link.stop("gateway start")
        await link.enable()
        assert await link.set_speed(100.0) is not None
        assert await link.stop("completed") is not None          # the gateway's own stop: none
        calm = link.take_drive_stop()
        await link.enable()
        assert await link.set_speed(100.0) is not None
        t0 = time.monotonic()
        time.sleep(0.5)                     # the whole thread stalls: no keep-alive either
        st = await link.stop("protection stop")
        stall = time.monotonic() - t0
        return calm, st, link.take_drive_stop(), link.take_drive_stop(), stall, dict(link.counters)

    with caplog.at_level(logging.WARNING, logger="hookwatch.stm32"):
        calm, st, ds, again, stall, c = run(_with_virtual_stm32(body))
    assert calm is None
    assert not st.enabled and st.watchdog_tripped and st.stop_reason == p.StopReason.WATCHDOG
    assert isinstance(ds, DriveStop) and again is None and c["drive_stops"] == 1
    assert (ds.reason, ds.watchdog_s) == ("WATCHDOG", 0.3) and "WATCHDOG" in ds.flags
    # the silence is the stall, measured on the link's clock: at least the 0.5 s the thread slept
    assert ds.silence_s >= 0.5 and ds.gateway_stalled, ds
    ms = round(ds.silence_s * 1000)
    assert ds.words() == ("the drive stopped on its own (STM32 watchdog, 0.3 s without the gateway): "
                          f"the gateway stalled {ms} ms")
    assert ds.as_data() == {"reason": "WATCHDOG", "flags": ds.flags, "watchdog_s": 0.3, "silence_ms": ms,
                            "gateway_stalled": True, "why": ds.words()}
    lines = [r.getMessage() for r in caplog.records if "stopped on its own" in r.getMessage()]
    assert len(lines) == 1 and ds.words() in lines[0] and "stop reason WATCHDOG" in lines[0], lines


def test_a_drive_stop_says_its_cause_in_one_sentence():
    from gateway.core.ports import DriveStop

    line = DriveStop("WATCHDOG", "WATCHDOG", 1.5, 0.04)     # frames every 40 ms, yet the watchdog
    assert not line.gateway_stalled
    assert line.words() == ("the drive stopped on its own (STM32 watchdog, 1.5 s without the gateway): "
                            "the gateway's frames were at most 40 ms apart, so they did not reach the "
                            "STM32 (the serial line or its adapter)")
    assert DriveStop("STALL", "FAULT|STALL", 1.5, 0.02).words() == (
        "the drive stopped on its own (STM32 stall trip: the take-up was blocked)")
    assert DriveStop("OVERSPEED", "FAULT|OVERSPEED", 1.5, None).words() == (
        "the drive stopped on its own (STM32 overspeed trip)")
    assert DriveStop("WATCHDOG", "WATCHDOG", 1.5, None).words() == (
        "the drive stopped on its own (STM32 watchdog, 1.5 s without the gateway)")


def test_the_twins_own_stall_is_not_the_gateways_silence():
    """The virtual firmware's watchdog judges the gateway's silence on the wire. When the twin's
    own process stalls (a loaded machine; here: it is not ticked and its loop does not run for
    0.5 s) while the gateway keeps sending every 20 ms, the frames it then reads at once came one
    after another: no trip. A gateway that really falls silent for 0.5 s while the twin looks
    every 5 ms trips it."""
    import time

    from drivers.sim.loopback import take

    async def body():
        vs = VirtualStm32(Stm32Firmware(0.2), SimpleMotor(tau_s=0.05), link=LoopbackLink())
        dev = await vs.start(own_ticker=False)
        end = take(dev.split("://", 1)[1])
        seq = iter(range(1, 256))
        try:
            end.send(p.req_enable(next(seq)))
            for _ in range(10):
                vs.tick()
                time.sleep(0.005)
            assert vs.firmware.drive_enabled
            for _ in range(25):                          # the twin stalls, the gateway sends on
                end.send(p.req_set_speed(next(seq), 100.0))
                time.sleep(0.02)
            vs.tick()
            after_stall = (vs.firmware.drive_enabled, vs.firmware.counters["watchdog_trips"])
            for _ in range(100):                         # the gateway is silent, the twin looks
                vs.tick()
                time.sleep(0.005)
            after_silence = (vs.firmware.drive_enabled, vs.firmware.counters["watchdog_trips"])
            return after_stall, after_silence
        finally:
            end.close()
            await vs.stop()

    after_stall, after_silence = run(body())
    assert after_stall == (True, 0)
    assert after_silence == (False, 1)
