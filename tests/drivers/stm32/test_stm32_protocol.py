"""STM32 link protocol (docs/protocols/stm32.md) and the firmware state machine: pure, no I/O."""
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as hs

from drivers.sim.twin_stm32 import SimpleMotor, Stm32Firmware
from drivers.stm32 import protocol as p


# ---------------------------------------------------------------------------------------- CRC, frames
def test_crc16_modbus_check_value():
    assert p.crc16(b"123456789") == 0x4B37          # CRC-16/MODBUS catalogue check value
    assert p.crc16(b"") == 0xFFFF
    from pymodbus.framer.rtu import FramerRTU  # an independent implementation (wire order)
    for data in (b"\x00\x01\x01", bytes(range(40)), b"\xa5\x5a" * 9):
        c = p.crc16(data)
        assert FramerRTU.compute_CRC(data) == ((c & 0xFF) << 8) | (c >> 8)


def test_documented_example_frames():
    # the hex examples in docs/protocols/stm32.md
    assert p.req_ping(0x01).hex(" ") == "a5 5a 00 01 01 b1 90"
    assert p.req_enable(0x02).hex(" ") == "a5 5a 00 02 10 71 6c"
    assert p.req_set_speed(0x07, 123.45).hex(" ") == "a5 5a 04 07 12 39 30 00 00 eb e7"
    assert p.req_stop(0x08, p.StopReason.PROTECTION).hex(" ") == "a5 5a 01 08 13 07 cc e8"
    assert p.req_set_watchdog(0x09, 0.2).hex(" ") == "a5 5a 02 09 14 c8 00 49 98"
    st = p.Status(120.5, 121.0, True, p.Flag.ENABLED | p.Flag.RUNNING, p.StopReason.NONE, 200, 0)
    assert p.encode_ack(0x07, p.Cmd.SET_SPEED, st).hex(" ") == \
        "a5 5a 10 07 80 12 12 2f 00 00 44 2f 00 00 03 00 00 c8 00 00 00 7c fe"
    assert p.encode_nak(0x0A, p.Cmd.SET_SPEED, p.NakCode.OUT_OF_RANGE).hex(" ") == \
        "a5 5a 02 0a 81 12 03 42 91"


@pytest.mark.parametrize("build,cmd", [
    (lambda s: p.req_ping(s), p.Cmd.PING), (lambda s: p.req_read_status(s), p.Cmd.READ_STATUS),
    (lambda s: p.req_enable(s), p.Cmd.ENABLE), (lambda s: p.req_disable(s), p.Cmd.DISABLE),
    (lambda s: p.req_set_speed(s, 250.25), p.Cmd.SET_SPEED),
    (lambda s: p.req_stop(s, p.StopReason.TEST_END), p.Cmd.STOP),
    (lambda s: p.req_set_watchdog(s, 0.35), p.Cmd.SET_WATCHDOG)])
def test_requests_round_trip(build, cmd):
    for seq in (0, 1, 128, 255):
        raw = build(seq)
        assert len(raw) == p.request_len(cmd)
        req = p.decode_request(p.decode_frame(raw))
        assert req.seq == seq and req.cmd == cmd
    req = p.decode_request(p.decode_frame(build(3)))
    if cmd == p.Cmd.SET_SPEED:
        assert req.rpm == 250.25
    if cmd == p.Cmd.STOP:
        assert req.reason == p.StopReason.TEST_END
    if cmd == p.Cmd.SET_WATCHDOG:
        assert req.watchdog_ms == 350


@given(act=hs.floats(-600, 600), cmd=hs.floats(0, 600), flags=hs.integers(0, 0x3F),
       reason=hs.sampled_from(list(p.StopReason)), wd=hs.integers(20, 60000),
       rxe=hs.integers(0, 0xFFFF), seq=hs.integers(0, 255))
def test_status_round_trip(act, cmd, flags, reason, wd, rxe, seq):
    st = p.Status(round(act, 2), round(cmd, 2), bool(flags & 1), p.Flag(flags), reason, wd, rxe)
    rep = p.decode_reply(p.decode_frame(p.encode_ack(seq, p.Cmd.READ_STATUS, st)))
    assert rep.ok and rep.seq == seq and rep.request == p.Cmd.READ_STATUS
    assert rep.status == st


def test_nak_round_trip_and_bad_replies():
    rep = p.decode_reply(p.decode_frame(p.encode_nak(9, p.Cmd.STOP, p.NakCode.BAD_LENGTH)))
    assert not rep.ok and rep.error == p.NakCode.BAD_LENGTH and rep.request == p.Cmd.STOP
    with pytest.raises(p.ProtocolError):
        p.decode_reply(p.Frame(1, p.Cmd.ACK, b"\x00" * 3))
    with pytest.raises(p.ProtocolError):
        p.decode_reply(p.Frame(1, p.Cmd.PING, b""))
    bad = bytearray(p.req_ping(1))
    bad[-1] ^= 1
    with pytest.raises(p.ProtocolError, match="CRC"):
        p.decode_frame(bytes(bad))


def test_request_errors_carry_nak_codes():
    with pytest.raises(p.ProtocolError) as e:
        p.decode_request(p.Frame(1, 0x55, b""))
    assert e.value.code == p.NakCode.UNKNOWN_COMMAND
    with pytest.raises(p.ProtocolError) as e:
        p.decode_request(p.Frame(1, p.Cmd.SET_SPEED, b"\x01\x02"))
    assert e.value.code == p.NakCode.BAD_LENGTH


def test_speed_resolution_and_non_finite():
    assert p.rpm_to_wire(123.456) == 12346 and p.rpm_from_wire(12346) == 123.46
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError):
            p.rpm_to_wire(bad)


def test_wire_times_at_115200():
    assert p.request_len(p.Cmd.SET_SPEED) == 11 and p.ACK_LEN == 23
    assert p.exchange_time_s(p.Cmd.SET_SPEED) == pytest.approx(34 * 10 / 115200)   # 2.95 ms
    assert p.exchange_time_s(p.Cmd.READ_STATUS) == pytest.approx(30 * 10 / 115200)


# ---------------------------------------------------------------------------------------- parser
def test_parser_split_frames_and_garbage():
    frames = [p.req_set_speed(i, i * 1.5) for i in range(20)]
    stream = b"\x00\xa5\xa5\x5a\xff" + b"junk".join(frames) + b"\xa5"
    par = p.FrameParser()
    got = []
    for i in range(0, len(stream), 3):          # 3-byte chunks split every frame
        got += par.feed(stream[i:i + 3])
    assert [f.encode() for f in got] == frames
    assert par.pending == 1                     # a trailing A5 may start the next frame


def test_parser_resyncs_after_false_start_swallowing_a_frame():
    real = p.req_ping(5)
    # a false start claiming 20 payload bytes: the real frame lies inside its span
    stream = b"\xa5\x5a\x14\x00\x00" + real + bytes(30)
    par = p.FrameParser()
    assert [f.encode() for f in par.feed(stream)] == [real]
    assert par.crc_errors >= 1


def test_parser_flush_after_gap_finds_frame_behind_long_false_start():
    real = p.req_ping(6)
    par = p.FrameParser()
    assert par.feed(b"\xa5\x5a\x20" + real) == []     # waits for 39 bytes
    assert [f.encode() for f in par.flush()] == [real]
    assert par.pending == 0


def test_parser_rejects_corrupted_frame():
    bad = bytearray(p.req_set_speed(1, 100))
    bad[6] ^= 0x10
    par = p.FrameParser()
    assert par.feed(bytes(bad)) == [] and par.crc_errors == 1
    assert par.flush() == []


frame_st = hs.builds(lambda seq, cmd, payload: p.encode_frame(seq, cmd, payload),
                     hs.integers(0, 255), hs.integers(0, 255), hs.binary(max_size=p.MAX_PAYLOAD))


@settings(max_examples=300, deadline=None)
@given(parts=hs.lists(hs.tuples(hs.binary(max_size=40), frame_st), max_size=8),
       tail=hs.binary(max_size=40), cuts=hs.lists(hs.integers(1, 64), max_size=30))
def test_parser_random_streams(parts, tail, cuts):
    """Garbage and valid frames, cut at random points: never raises, finds every frame in order."""
    stream = b"".join(g + f for g, f in parts) + tail
    par = p.FrameParser()
    got = []
    pos = 0
    for c in cuts:
        got += par.feed(stream[pos:pos + c])
        pos += c
    got += par.feed(stream[pos:])
    got += par.flush()
    found = [f.encode() for f in got]
    it = iter(found)
    assert all(any(x == f for x in it) for _, f in parts), (found, parts)   # in-order subsequence
    assert par.pending == 0


@settings(max_examples=200, deadline=None)
@given(data=hs.binary(max_size=400))
def test_parser_never_raises_on_noise(data):
    par = p.FrameParser()
    for i in range(0, len(data), 7):
        par.feed(data[i:i + 7])
    par.flush()
    assert par.pending == 0


# ---------------------------------------------------------------------------------------- firmware
class Seq:
    def __init__(self):
        self.n = 0

    def __call__(self):
        self.n = (self.n + 1) & 0xFF
        return self.n


def reply(fw, raw, now):
    out = fw.handle(raw, now)
    return p.decode_reply(p.decode_frame(out)) if out is not None else None


def test_firmware_enable_speed_stop():
    fw, s = Stm32Firmware(), Seq()
    r = reply(fw, p.req_read_status(s()), 0.0)
    assert r.ok and not r.status.enabled and r.status.stop_reason == p.StopReason.POWER_ON
    r = reply(fw, p.req_set_speed(s(), 100), 0.01)       # not enabled: acknowledged, not applied
    assert r.ok and r.status.command_rpm == 0 and fw.drive_rpm == 0
    r = reply(fw, p.req_enable(s()), 0.02)
    assert r.status.enabled and r.status.flags & p.Flag.ENABLED and r.status.stop_reason == p.StopReason.NONE
    r = reply(fw, p.req_set_speed(s(), 100), 0.03)
    assert r.status.command_rpm == 100 and fw.drive_rpm == 100 and fw.drive_enabled
    fw.measure(99.0, False, 0.04)
    r = reply(fw, p.req_stop(s(), p.StopReason.PROTECTION), 0.05)
    assert not r.status.enabled and r.status.stop_reason == p.StopReason.PROTECTION
    assert r.status.running and r.status.actual_rpm == 99.0   # still coasting down
    assert fw.drive_rpm == 0 and not fw.drive_enabled
    r = reply(fw, p.req_set_speed(s(), 100), 0.06)
    assert fw.drive_rpm == 0 and not r.status.enabled        # stays stopped until ENABLE


def test_firmware_naks():
    fw, s = Stm32Firmware(max_rpm=600), Seq()
    r = reply(fw, p.req_set_speed(s(), 600.01), 0.0)
    assert not r.ok and r.error == p.NakCode.OUT_OF_RANGE
    r = reply(fw, p.req_set_speed(s(), -1), 0.0)
    assert r.error == p.NakCode.OUT_OF_RANGE
    r = reply(fw, p.encode_frame(s(), 0x42), 0.0)
    assert r.error == p.NakCode.UNKNOWN_COMMAND and r.request == 0x42
    r = reply(fw, p.encode_frame(s(), p.Cmd.SET_SPEED, b"\x01"), 0.0)
    assert r.error == p.NakCode.BAD_LENGTH
    r = reply(fw, p.req_stop(s(), p.StopReason.WATCHDOG), 0.0)   # not a reason the gateway gives
    assert r.error == p.NakCode.OUT_OF_RANGE
    r = reply(fw, p.req_set_watchdog(s(), 0.001), 0.0)
    assert r.error == p.NakCode.OUT_OF_RANGE


def test_firmware_bad_crc_not_answered_but_counted():
    fw = Stm32Firmware()
    bad = bytearray(p.req_enable(1))
    bad[-2] ^= 0xFF
    assert fw.handle(bytes(bad), 0.0) is None
    assert not fw.enabled and fw.counters["rx_errors"] == 1
    assert reply(fw, p.req_read_status(2), 0.0).status.rx_errors == 1


@pytest.mark.parametrize("watchdog_s", [0.2, 0.05, 1.0])
def test_firmware_watchdog(watchdog_s):
    fw, s = (Stm32Firmware() if watchdog_s == 0.2 else Stm32Firmware(watchdog_s)), Seq()
    t = 10.0
    reply(fw, p.req_enable(s()), t)
    reply(fw, p.req_set_speed(s(), 150), t)
    # commands every half period keep it alive for a long time
    for i in range(1, 50):
        fw.tick(t + i * watchdog_s / 2 - 1e-6)
        r = reply(fw, p.req_set_speed(s(), 150), t + i * watchdog_s / 2)
        assert r.status.enabled, i
    t_last = t + 49 * watchdog_s / 2
    fw.tick(t_last + watchdog_s - 0.001)
    assert fw.enabled and fw.drive_rpm == 150
    fw.tick(t_last + watchdog_s)
    assert not fw.enabled and fw.drive_rpm == 0 and fw.stop_reason == p.StopReason.WATCHDOG
    r = reply(fw, p.req_set_speed(s(), 150), t_last + watchdog_s + 0.5)
    st = r.status
    assert not st.enabled and st.watchdog_tripped and st.stop_reason == p.StopReason.WATCHDOG
    assert fw.drive_rpm == 0                       # stays stopped until ENABLE
    r = reply(fw, p.req_enable(s()), t_last + watchdog_s + 0.6)
    assert r.status.enabled and not r.status.watchdog_tripped and r.status.stop_reason == p.StopReason.NONE


def test_firmware_watchdog_late_command_does_not_hide_trip():
    """No tick in between: the command arriving after the deadline finds the motor stopped."""
    fw = Stm32Firmware(0.2)
    reply(fw, p.req_enable(1), 0.0)
    reply(fw, p.req_set_speed(2, 100), 0.0)
    r = reply(fw, p.req_set_speed(3, 100), 0.25)
    assert not r.status.enabled and r.status.stop_reason == p.StopReason.WATCHDOG


def test_firmware_watchdog_settable_by_command():
    fw = Stm32Firmware()
    r = reply(fw, p.req_set_watchdog(1, 0.5), 0.0)
    assert r.status.watchdog_ms == 500
    reply(fw, p.req_enable(2), 0.0)
    fw.tick(0.45)
    assert fw.enabled
    fw.tick(0.5)
    assert not fw.enabled and fw.stop_reason == p.StopReason.WATCHDOG


def test_firmware_watchdog_idle_when_disabled():
    fw = Stm32Firmware()
    reply(fw, p.req_read_status(1), 0.0)
    fw.tick(100.0)
    assert fw.stop_reason == p.StopReason.POWER_ON and not fw.watchdog_tripped


def test_firmware_duplicate_not_applied_twice():
    fw = Stm32Firmware(0.2)
    reply(fw, p.req_enable(1), 0.0)
    r1 = reply(fw, p.req_set_speed(2, 100), 0.01)
    r2 = reply(fw, p.req_set_speed(2, 100), 0.02)      # retry: the reply of the first was lost
    assert r1.seq == r2.seq == 2 and r2.ok and r2.status.command_rpm == 100
    assert fw.counters["executed"] == 2 and fw.counters["duplicates"] == 1
    # an ENABLE acted on, its reply lost; the watchdog stops the motor; then the retry arrives:
    # it is answered (with the current status) but does not enable the motor again
    reply(fw, p.req_stop(3), 0.03)
    reply(fw, p.req_enable(4), 0.04)
    fw.tick(0.25)
    assert fw.stop_reason == p.StopReason.WATCHDOG
    r = reply(fw, p.req_enable(4), 0.26)
    assert r.ok and not r.status.enabled and r.status.stop_reason == p.StopReason.WATCHDOG
    assert fw.counters["duplicates"] == 2
    # a new sequence number is a new command
    assert reply(fw, p.req_enable(5), 0.27).status.enabled
    # same seq but a different command or payload is not a duplicate
    reply(fw, p.req_set_speed(6, 100), 0.28)
    assert reply(fw, p.req_set_speed(6, 120), 0.29).status.command_rpm == 120
    # the same frame long after is not a retry (a restarted gateway)
    reply(fw, p.req_stop(7), 0.30)
    assert reply(fw, p.req_enable(7), 0.31).status.enabled
    assert reply(fw, p.req_enable(7), 2.0).status.enabled


def test_firmware_stall_trip_and_overspeed():
    fw = Stm32Firmware(10.0, stall_trip_s=0.5)
    reply(fw, p.req_enable(1), 0.0)
    reply(fw, p.req_set_speed(2, 100), 0.0)
    fw.measure(0.0, True, 0.1)
    st = fw.status()
    assert st.stalled and st.enabled and not st.fault
    fw.measure(0.0, True, 0.59)
    assert fw.enabled
    fw.measure(0.0, True, 0.6)
    st = fw.status()
    assert not st.enabled and st.fault and st.stop_reason == p.StopReason.STALL
    reply(fw, p.req_enable(3), 1.0)
    fw.measure(0.0, False, 1.0)
    assert not fw.status().fault and not fw.status().stalled
    fw.measure(700.0, False, 1.1)
    st = fw.status()
    assert st.overspeed and st.fault and st.stop_reason == p.StopReason.OVERSPEED


def test_firmware_rejects_bad_watchdog_at_construction():
    with pytest.raises(ValueError, match="watchdog_s"):
        Stm32Firmware(0.0)


def test_simple_motor_first_order():
    t = [0.0]
    m = SimpleMotor(tau_s=0.1, clock=lambda: t[0])
    m.enable(True)
    m.set_command(200)
    t[0] = 0.1
    assert m.speed_rpm == pytest.approx(200 * (1 - 2.718281828 ** -1), rel=1e-6)
    t[0] = 2.0
    assert m.speed_rpm == pytest.approx(200, abs=1e-3)
    m.stalled = True
    t[0] = 3.0
    assert m.speed_rpm == pytest.approx(200 * 2.718281828 ** -10, rel=1e-6)


def test_status_struct_layout():
    assert p.STATUS_LEN == 15 and struct.calcsize("<iiHBHH") == 15


def test_doc_example_exchange_replays():
    """The hex example in docs/protocols/stm32.md is what the firmware really answers."""
    import os
    import re

    from conftest import ROOT
    with open(os.path.join(ROOT, "docs", "protocols", "stm32.md"), encoding="utf-8") as f:
        text = f.read()
    block = text.split("## Example exchange")[1].split("```")[1]
    fw = Stm32Firmware()
    t, expect, n = 0.0, None, 0
    for line in block.strip().splitlines():
        if line.startswith("#"):
            m = re.match(r"# t=([\d.]+)", line)
            t = float(m.group(1)) if m else t
            m = re.search(r"the drive measures ([\d.]+) rpm", line)
            if m:
                fw.measure(float(m.group(1)), False, t)
            continue
        raw = bytes.fromhex(line[3:])
        if line.startswith("->"):
            expect = fw.handle(raw, t)
        else:
            assert raw == expect, line
            p.decode_reply(p.decode_frame(raw))
            n += 1
    assert n == 8
