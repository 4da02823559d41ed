"""The virtual ZN-S meter as a separate process on a pty: a real Modbus master (mbpoll) reads the
configured registers, protocol edge cases get the right exceptions, and the reply comes after the
real wire time at each baud rate."""
import os
import statistics
import subprocess
import time

import pytest
import serial

from conftest import ROOT
from drivers.meter.meter_map import DEFAULT_MAP_PATH, load_map, with_crc
from kit.meter import MeterProcess
from kit.tools import require_tool

MAPS = os.path.join(ROOT, "config", "meters")
SLOT_S = 0.020


def mbpoll(dev, *args, baud=115200, timeout="0.5"):
    exe = require_tool("mbpoll")
    r = subprocess.run([exe, "-m", "rtu", "-b", str(baud), "-P", "none", "-o", timeout, "-1", *args, dev],
                       capture_output=True, text=True, timeout=20)
    values = {}
    for line in r.stdout.splitlines():
        line = line.strip()
        if line.startswith("[") and "]:" in line:
            ref, val = line[1:].split("]:", 1)
            values[int(ref)] = val.strip()
    return r, values


def test_mbpoll_reads_float_channels(tmp_path):
    require_tool("mbpoll")
    with MeterProcess(tmp_path / "meter.log", "--value", "0.5,1.234") as mp:
        # holding registers (FC 3), big-endian words, 1-based references: ch1 at 1, ch2 at 3
        r, v = mbpoll(mp.device, "-a", "1", "-t", "4:float", "-B", "-r", "1", "-c", "2")
        assert r.returncode == 0, r.stdout + r.stderr
        assert float(v[1]) == pytest.approx(0.5) and float(v[3]) == pytest.approx(1.234, abs=1e-6)
        # the same image answers input registers (FC 4)
        r, v = mbpoll(mp.device, "-a", "1", "-t", "3:float", "-B", "-r", "1", "-c", "2")
        assert r.returncode == 0 and float(v[3]) == pytest.approx(1.234, abs=1e-6)
        # raw registers: 0.5f = 0x3F000000
        r, v = mbpoll(mp.device, "-a", "1", "-t", "4:hex", "-r", "1", "-c", "4")
        assert [v[i].lower() for i in (1, 2)] == ["0x3f00", "0x0000"]
        c = mp.counters()
        assert c["requests"] == c["replies"] == 3 and c["bad_crc"] == 0


def test_mbpoll_int16_with_decimal_point_register(tmp_path):
    require_tool("mbpoll")
    with MeterProcess(tmp_path / "meter.log", "--map", os.path.join(MAPS, "zn-s-int16-dp.yaml"),
                      "--value", "0.499,1.2345") as mp:
        r, v = mbpoll(mp.device, "-a", "1", "-t", "4", "-r", "1", "-c", "3")
        assert r.returncode == 0, r.stdout + r.stderr
        assert (v[1], v[2], v[3]) == ("499", "1234", "3")


def test_mbpoll_errors_wrong_address_and_unit(tmp_path):
    require_tool("mbpoll")
    with MeterProcess(tmp_path / "meter.log", "--value", "0.5,0.5") as mp:
        r, _ = mbpoll(mp.device, "-a", "1", "-t", "4", "-r", "5", "-c", "1")
        assert "Illegal data address" in r.stderr + r.stdout
        r, _ = mbpoll(mp.device, "-a", "1", "-t", "4", "-r", "1", "-c", "126")
        assert r.returncode != 0
        r, v = mbpoll(mp.device, "-a", "7", "-t", "4", "-r", "1", "-c", "1", timeout="0.1")
        assert not v and "timed out" in (r.stderr + r.stdout).lower()
        c = mp.counters()
        assert c["other_unit"] >= 1 and c["exceptions"] >= 1


def transact(ser, frame: bytes, n: int, timeout: float = 0.5) -> bytes:
    ser.reset_input_buffer()
    ser.timeout = timeout
    ser.write(frame)
    return ser.read(n)


def test_protocol_edges_raw(tmp_path):
    with MeterProcess(tmp_path / "meter.log", "--value", "1.0,2.0") as mp, \
            serial.Serial(mp.device, 115200, timeout=0.5) as ser:
        read4 = with_crc(bytes([1, 3, 0, 0, 0, 4]))
        ok = transact(ser, read4, 13)
        assert len(ok) == 13 and ok[:3] == bytes([1, 3, 8])
        # bad CRC: ignored and counted
        bad = read4[:-1] + bytes([read4[-1] ^ 0xFF])
        assert transact(ser, bad, 13, timeout=0.05) == b""
        # unknown function code (framed by the 3.5-character silence) → exception 01
        assert transact(ser, with_crc(bytes([1, 0x11])), 5) == with_crc(bytes([1, 0x91, 1]))
        # write single register: no writable registers → 01
        assert transact(ser, with_crc(bytes([1, 6, 0, 0, 0, 1])), 5) == with_crc(bytes([1, 0x86, 1]))
        # quantity 0 and 126 → 03; outside the block → 02
        assert transact(ser, with_crc(bytes([1, 3, 0, 0, 0, 0])), 5) == with_crc(bytes([1, 0x83, 3]))
        assert transact(ser, with_crc(bytes([1, 4, 0, 0, 0, 126])), 5) == with_crc(bytes([1, 0x84, 3]))
        assert transact(ser, with_crc(bytes([1, 3, 0, 3, 0, 2])), 5) == with_crc(bytes([1, 0x83, 2]))
        # another unit: silence
        assert transact(ser, with_crc(bytes([9, 3, 0, 0, 0, 4])), 13, timeout=0.05) == b""
        # a partial frame followed by silence, then a good one: the good one is answered
        ser.write(read4[:3])
        time.sleep(0.01)
        assert len(transact(ser, read4, 13)) == 13
        # faults: dropped replies, corrupted CRC, extra delay
        mp.command("drop on")
        assert transact(ser, read4, 13, timeout=0.05) == b""
        mp.command("drop off")
        mp.command("crc on")
        r = transact(ser, read4, 13)
        assert len(r) == 13 and r[:-2] == ok[:-2] and r[-2:] != ok[-2:]
        mp.command("crc off")
        mp.command("delay 0.03")
        t0 = time.monotonic()
        assert len(transact(ser, read4, 13)) == 13
        assert time.monotonic() - t0 >= 0.03
        mp.command("delay 0")
        c = mp.counters()
    assert c["bad_crc"] == 1 and c["other_unit"] == 1 and c["dropped"] == 1
    assert c["garbage"] == 1 and c["exceptions"] == 5


def measure_reply_times(dev: str, baud: int, n: int, count: int = 4) -> list[float]:
    req = with_crc(bytes([1, 3, 0, 0, 0, count]))
    n_resp = 5 + 2 * count
    times = []
    with serial.Serial(dev, baud, timeout=1.0) as ser:
        for _ in range(n):
            ser.reset_input_buffer()
            t0 = time.perf_counter()
            ser.write(req)
            data = ser.read(n_resp)
            t1 = time.perf_counter()
            assert len(data) == n_resp
            times.append(t1 - t0)
            time.sleep(0.003)
    return times


@pytest.mark.parametrize("baud", [9600, 19200, 38400, 115200])
def test_reply_time_is_the_wire_time(tmp_path, baud):
    m = load_map(DEFAULT_MAP_PATH).with_overrides(baud=baud)
    expected = m.poll_time_s()
    with MeterProcess(tmp_path / "meter.log", "--baud", str(baud), "--value", "0.5,0.5") as mp:
        # scheduling delays only ever add time: never faster than the wire (the ptys themselves
        # are instant), every request answered once; how close to the wire time the replies come
        # is bench/bench_sim.py's figure (reply lateness), not asserted on a loaded machine
        times = measure_reply_times(mp.device, baud, 40)
        med = statistics.median(times)
        print(f"\n{baud} baud: 4-register read, expected {expected * 1e3:.2f} ms, measured median "
              f"{med * 1e3:.2f} ms (min {min(times) * 1e3:.2f}, max {max(times) * 1e3:.2f})")
        c = mp.counters()
    print(f"meter reply lateness p50 {c['lateness_ms_p50']:.3f} ms")
    assert min(times) >= expected * 0.98, (min(times), expected)
    assert c["replies"] == 40
    if baud == 9600:
        # 8-byte request + 2 ms + 13-byte reply at 9600 baud = 26 ms: a 20 ms slot cannot hold it
        assert expected > SLOT_S and min(times) > SLOT_S
    else:
        assert expected < SLOT_S
