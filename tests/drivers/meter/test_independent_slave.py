"""Issue 27.8: any correct Modbus RTU slave is read, and issue 27.3: a port is never shared.

The slave here is pymodbus' own serial server (no code of this project on its side) in a process
of its own, behind socat's pair of pseudo-terminals (tests/kit/pymodbus_slave.py): its replies are
not paced at any baud. The station once refused every one of them as a "stale reply" (sooner than
the wire can carry it) and said nothing. The assertions are counts (every read accounted for, no
reply refused), never a timing figure."""
import asyncio
import logging
import os
import subprocess
import sys
import termios

import pytest

from drivers.meter.driver import FAST_RUN, ZnsMeter
from drivers.meter.meter_map import DEFAULT_MAP_PATH, load_map
from kit.pymodbus_slave import pymodbus_meter
from kit.tools import require_tool

FAILURES = ("timeouts", "crc_errors", "garbage", "modbus_exceptions", "decode_errors", "stale_replies",
            "errors")


@pytest.fixture
def slave(tmp_path):
    require_tool("socat")
    with pymodbus_meter(tmp_path, ch1=0.5, ch2=0.25) as path:
        yield path


def _reads(path, n, *, physical=None, baud=None):
    async def main():
        mp = load_map(DEFAULT_MAP_PATH)
        m = ZnsMeter(path, mp.with_overrides(baud=baud) if baud else mp, timeout_s=0.1 if baud else 0.015)
        if physical is not None:
            m.timing_physical = physical        # as on a port whose kind is not known
        await m.open()
        try:
            out = []
            for _ in range(n):
                out.append(await m.read())
                await asyncio.sleep(0.02)
            return m, out
        finally:
            await m.close()
    return asyncio.run(main())


def test_the_driver_reads_pymodbus_serial_server_on_a_pty_pair(slave):
    m, out = _reads(slave, 60)
    c = m.counters
    good = [r for r in out if r is not None]
    assert m.timing_physical is False                 # a pty: no wire pacing to judge replies by
    assert c["stale_replies"] == 0, c
    assert c["reads"] == 60 and c["not_connected"] == 0, c
    # every read accounted for: a reading, or a failure counted by its cause
    assert len(good) == c["reads_ok"] == c["reads"] - sum(c[k] for k in FAILURES), c
    assert good, c
    assert all((r.ch1, r.ch2) == (0.5, 0.25) for r in good), good[:3]


def test_a_port_whose_replies_all_beat_the_wire_is_taken_as_virtual_and_said_once(slave, caplog):
    """A port not known as a pty (a USB CDC meter, a device server): FAST_RUN of its complete
    replies, and most of them, came sooner than the wire allows — it is a virtual port, said
    once, and read from then on (only those first fast replies were refused, counted). The map
    says 9600 baud (a pty carries any): request and reply take 22 ms on such a wire, and
    pymodbus' replies come far sooner however loaded this machine is."""
    caplog.set_level(logging.WARNING, "hookwatch.meter")
    m, out = _reads(slave, 40, physical=True, baud=9600)
    c = m.counters
    assert m.timing_physical is False
    assert c["stale_replies"] == FAST_RUN - 1, c
    lines = [r.getMessage() for r in caplog.records if "sooner than 9600 baud can carry" in r.getMessage()]
    assert len(lines) == 1 and "a virtual port?" in lines[0], lines
    assert c["reads_ok"] == c["reads"] - sum(c[k] for k in FAILURES) and c["reads_ok"] >= 40 - FAST_RUN, c


# ------------------------------------------------------------------------------ 27.3: exclusive
HOLDER = """
import serial, sys
s = serial.Serial(sys.argv[1], 19200, exclusive=True)
print("held", flush=True)
sys.stdin.read()
"""


def test_a_port_another_process_holds_is_not_opened_nor_reconfigured(slave, caplog):
    """A process holds the meter's port (exclusively, at 19200 baud): the driver does not open
    it, leaves its settings alone (still 19200, not the map's 115200), counts the refusals and
    says once who holds it. Once the holder is gone, the port opens."""
    caplog.set_level(logging.WARNING, "hookwatch.meter")
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, slave], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().startswith("held")

        async def main():
            m = ZnsMeter(slave, load_map(DEFAULT_MAP_PATH), reopen_interval_s=0.05)
            await m.open()
            try:
                for _ in range(5):
                    assert await m.read() is None
                    await asyncio.sleep(0.02)
                return m
            finally:
                await m.close()
        m = asyncio.run(main())
        assert not m.connected and m.counters["port_in_use"] >= 2, m.counters
        fd = os.open(slave, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            assert termios.tcgetattr(fd)[4] == termios.B19200     # the holder's baud, untouched
        finally:
            os.close(fd)
        said = [r.getMessage() for r in caplog.records if "is in use by" in r.getMessage()]
        assert len(said) == 1 and f"pid {holder.pid} (" in said[0], said
    finally:
        holder.stdin.close()
        holder.wait(10)
        holder.stdout.close()
    m, out = _reads(slave, 5)
    assert m.counters["port_in_use"] == 0 and any(r is not None for r in out), m.counters


def test_late_answers_after_timeouts_never_make_a_paced_line_virtual():
    """On a paced line whose adapter holds every reply past the timeout (an FTDI at its 16 ms
    latency timer, a 15 ms timeout), every complete reply is the late answer to the read that
    timed out just before: sooner than the wire after the *next* request. Those must stay refused
    as stale, however many there are — taking them for a virtual port's pace (as the rule did)
    turned them into readings one request old."""
    m = ZnsMeter("/dev/ttyUSB-not-opened", load_map(DEFAULT_MAP_PATH), timeout_s=0.015)
    assert m.timing_physical is True
    m._rx = bytearray(m._resp_len)              # the reply's content is never reached: refused first
    fast = m._min_reply_s / 2
    for _ in range(5 * FAST_RUN):
        m._count_failure("timeout")             # the read times out ...
        assert m._result(fast) is None          # ... and its late answer meets the next one
    assert m.timing_physical is True
    assert m.counters["stale_replies"] == 5 * FAST_RUN and m.counters["reads_ok"] == 0
