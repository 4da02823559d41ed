"""Back-to-back: each driver against its virtual twin, in one process, over a pseudo-terminal AND
over the in-process loopback link (drivers.sim.loopback, python-can's virtual bus idea) — the same
test body parametrized over both transports. The driver code is the production code path:
pymodbus' serial transport for the meter, fileno() + add_reader for the STM32 (a pyserial URL,
``hwloop://``, stands where a device path would)."""
import asyncio

import pytest

from drivers.meter.driver import ZnsMeter
from drivers.meter.meter_map import DEFAULT_MAP_PATH, load_map
from drivers.sim.loopback import LoopbackLink
from drivers.sim.meter import VirtualMeter
from drivers.sim.pty import PtyLink
from drivers.sim.twin_stm32 import SimpleMotor, Stm32Firmware, VirtualStm32
from drivers.stm32 import protocol as p
from drivers.stm32.driver import Stm32Link

TRANSPORTS = ("pty", "loopback")


def link_for(transport, tmp_path, name):
    return PtyLink(str(tmp_path / name)) if transport == "pty" else LoopbackLink()


def run(coro, timeout=40.0):
    return asyncio.run(asyncio.wait_for(coro, timeout))


async def until(cond, timeout=5.0):
    t_end = asyncio.get_running_loop().time() + timeout
    while not cond():
        assert asyncio.get_running_loop().time() < t_end, "condition not met"
        await asyncio.sleep(0.01)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_meter_driver_against_the_virtual_meter(transport, tmp_path):
    async def main():
        m = load_map(DEFAULT_MAP_PATH)
        values = [(0.412, 0.655)]
        vm = VirtualMeter(m, lambda: values[0], link=link_for(transport, tmp_path, "meter"))
        await vm.start()
        drv = ZnsMeter(vm.link.link_path if transport == "pty" else vm.device, m, timeout_s=0.2)
        await drv.open()
        try:
            assert drv.connected
            first = [await drv.read() for _ in range(10)]
            values[0] = (1.25, 2.5)
            changed = await drv.read()
            vm.faults.drop_replies = True              # a meter that hears but does not answer
            silent = await drv.read()
            vm.faults.drop_replies = False
            vm.faults.corrupt_crc = True               # a reply with a wrong CRC is no reading
            bad = await drv.read()
            vm.faults.corrupt_crc = False
            await asyncio.sleep(0.05)
            again = await drv.read()
        finally:
            await drv.close()
            await vm.stop()
        return first, changed, silent, bad, again, vm.counters

    first, changed, silent, bad, again, c = run(main())
    assert all(r is not None for r in first)
    assert [(r.ch1, r.ch2) for r in first] == [pytest.approx((0.412, 0.655), abs=1e-6)] * 10
    assert (changed.ch1, changed.ch2) == pytest.approx((1.25, 2.5), abs=1e-6)
    assert silent is None and bad is None
    assert again is not None and (again.ch1, again.ch2) == pytest.approx((1.25, 2.5), abs=1e-6)
    assert c["requests"] >= 14 and c["bad_crc"] == 0 and c["other_unit"] == 0


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_stm32_link_against_the_virtual_stm32(transport, tmp_path):
    async def main():
        motor = SimpleMotor(tau_s=0.05)
        vs = VirtualStm32(Stm32Firmware(0.3), motor, link=link_for(transport, tmp_path, "stm32"))
        await vs.start()
        port = vs.link.link_path if transport == "pty" else vs.device
        link = Stm32Link(port, timeout_s=0.05, watchdog_s=0.3)
        await link.open()
        out = {}
        try:
            await until(lambda: link.connected)
            st = await link.stop("gateway start")
            out["power_on"] = (st.enabled, st.stop_reason)
            st = await link.enable()
            out["enabled"] = (st.enabled, st.watchdog_ms, st.stop_reason)
            t_end = asyncio.get_running_loop().time() + 5.0
            while True:
                st = await link.set_speed(200.0)
                if st is not None and st.actual_rpm > 195 or asyncio.get_running_loop().time() > t_end:
                    break
                await asyncio.sleep(0.02)
            out["running"] = (st.command_rpm, st.running, st.actual_rpm)
            st = await link.stop("completed")
            out["stopped"] = (st.enabled, st.stop_reason, st.command_rpm)
            out["counters"] = dict(link.counters)
        finally:
            await link.close()
            await vs.stop()
        return out

    out = run(main())
    assert out["power_on"] == (False, p.StopReason.POWER_ON)
    assert out["enabled"] == (True, 300, p.StopReason.NONE)
    cmd, running, actual = out["running"]
    assert cmd == 200.0 and running and actual > 195
    assert out["stopped"] == (False, p.StopReason.TEST_END, 0)
    assert out["counters"]["naks"] == 0 and out["counters"]["crc_errors"] == 0


def test_loopback_link_vanishes_like_an_unplugged_adapter(tmp_path):
    """Reopening an unplugged loopback link fails; after restore the driver's end opens again."""
    import serial

    link = LoopbackLink()
    url = link.open()
    s = serial.serial_for_url(url, 115200, timeout=0)
    s.write(b"\x01\x02")
    assert link.read_available() == b"\x01\x02"
    link.write(b"\x03")
    assert s.read(1) == b"\x03"
    link.vanish()
    s.close()
    with pytest.raises(serial.SerialException, match="no such link"):
        serial.serial_for_url(url, 115200, timeout=0)
    assert link.restore() == url
    s = serial.serial_for_url(url, 115200, timeout=0)
    s.close()
    link.close()
