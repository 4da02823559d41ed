"""Virtual ZN-S tension meter: a hand-written Modbus RTU slave on a pseudo-terminal.

A pty moves bytes instantly, so this slave delays every reply by the real wire time: the reply's
last byte is due ``request wire time + turnaround + response wire time (+ faults.extra_delay_s)``
after the request's first bytes arrived (11 bits a character at the map's baud). The reply is
written in one piece at that moment (``loop.call_at`` a little early, then a short busy-wait, so it
lands within a fraction of a millisecond). The tensions are sampled from ``source()`` at the moment
the request has completed on the simulated wire.

Framing: function codes 3, 4 and 6 are 8 bytes, 16 is 9 + byte count; anything else is framed by
the 3.5-character silence (1.75 ms above 19200 baud). Frames with a bad CRC or for another unit are
ignored (counted). Served: FC 3 and 4 (same register image: the map's read block); exceptions
01 (function), 02 (address), 03 (quantity), 04 (the value cannot be encoded / source failed).

Run alone (prints ``meter: /dev/pts/N``; commands on stdin: ``drop on|off``, ``crc on|off``,
``delay SECONDS``, ``vanish``, ``restore``, ``value CH1 CH2``, ``counters``)::

    python -m drivers.sim.meter --map config/meters/zn-s.yaml --value 0.5,1.25 [--link PATH]
"""
from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections import deque
from dataclasses import dataclass
from typing import Any, Callable

from ..zns_map import MeterMap, crc_ok, with_crc
from .pty import PtyLink

log = logging.getLogger("hookwatch.sim.meter")

SPIN_S = 0.0015          # wake this early and busy-wait the rest (asyncio timers are ~1 ms coarse)
ON_TIME_S = 0.0003       # a reply later than this counts as late


@dataclass
class MeterFaults:
    drop_replies: bool = False      # requests are received and counted, never answered
    corrupt_crc: bool = False       # replies go out with a wrong CRC
    extra_delay_s: float = 0.0      # added to the honest reply time


def silence_s(baud: int) -> float:
    """Modbus RTU inter-frame silence t3.5 (fixed 1.75 ms above 19200 baud)."""
    return 3.5 * 11 / baud if baud <= 19200 else 0.00175


class VirtualMeter:
    def __init__(self, meter_map: MeterMap, source: Callable[[], tuple[float, float]],
                 link_path: str | None = None, *, spin_s: float = SPIN_S, link: Any = None):
        self.map = meter_map
        self.source = source
        # a pty by default; any link with PtyLink's interface (drivers.sim.loopback) may be given
        self.link = link if link is not None else PtyLink(link_path)
        self.faults = MeterFaults()
        self.spin_s = spin_s
        self.counters = {"requests": 0, "replies": 0, "exceptions": 0, "bad_crc": 0,
                         "other_unit": 0, "dropped": 0, "garbage": 0, "late_replies": 0,
                         "value_errors": 0}
        self.reply_lateness: deque[float] = deque(maxlen=10_000)   # write time − due time, s
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reading_fd: int | None = None
        self._buf = bytearray()
        self._t_first = 0.0
        self._t_last = 0.0
        self._silence: asyncio.TimerHandle | None = None
        self._timers: set[asyncio.TimerHandle] = set()
        fc, start, count = meter_map.read_block
        self._start, self._count = start, count

    # ------------------------------------------------------------------ lifecycle
    @property
    def device(self) -> str | None:
        return self.link.device

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        if not self.link.is_open:
            self.link.open()
        self._attach()

    async def stop(self) -> None:
        self._detach()
        self.link.close()

    def vanish(self) -> None:
        """The USB adapter is pulled out: the device node disappears, pending replies are lost."""
        self._detach()
        self.link.vanish()

    def restore(self) -> str:
        """Plugged back in: a new pty behind the same symlink."""
        dev = self.link.restore()
        if self._loop is not None:
            self._attach()
        return dev

    def _attach(self) -> None:
        if self._reading_fd is None and self.link.master is not None and self._loop is not None:
            self._reading_fd = self.link.master
            self._loop.add_reader(self._reading_fd, self._on_readable)

    def _detach(self) -> None:
        if self._reading_fd is not None and self._loop is not None:
            self._loop.remove_reader(self._reading_fd)
        self._reading_fd = None
        for h in list(self._timers):
            h.cancel()
        self._timers.clear()
        if self._silence is not None:
            self._silence.cancel()
            self._silence = None
        self._buf.clear()

    # ------------------------------------------------------------------ receiving
    def _on_readable(self) -> None:
        data = self.link.read_available()
        if not data:
            return
        now = time.monotonic()
        t35 = silence_s(self.map.baud)
        if self._buf and now - self._t_last > t35:
            # the rest of an old frame never came: a new frame starts here
            self.counters["garbage"] += 1
            self._buf.clear()
        if not self._buf:
            self._t_first = now
        self._buf += data
        self._t_last = now
        self._extract(now)
        if self._silence is not None:
            self._silence.cancel()
            self._silence = None
        if self._buf:
            self._silence = self._loop.call_at(now + t35, self._on_silence)

    def _expected_len(self) -> int | None:
        b = self._buf
        if len(b) < 2:
            return None
        fc = b[1]
        if fc in (3, 4, 6):
            return 8
        if fc == 16:
            return 9 + b[6] if len(b) >= 7 else None
        return None                      # unknown: framed by silence

    def _extract(self, now: float) -> None:
        while self._buf:
            n = self._expected_len()
            if n is None or len(self._buf) < n:
                return
            frame = bytes(self._buf[:n])
            if not crc_ok(frame):
                # misaligned or corrupted: drop everything received so far
                self.counters["bad_crc"] += 1
                self._buf.clear()
                return
            del self._buf[:n]
            self._handle(frame, self._t_first)
            self._t_first = now

    def _on_silence(self) -> None:
        self._silence = None
        frame = bytes(self._buf)
        self._buf.clear()
        if len(frame) < 4:
            self.counters["garbage"] += 1
        elif not crc_ok(frame):
            self.counters["bad_crc"] += 1
        else:
            self._handle(frame, self._t_first)

    # ------------------------------------------------------------------ answering
    def _handle(self, frame: bytes, t_first: float) -> None:
        unit, fc = frame[0], frame[1]
        if unit != self.map.unit_id:
            self.counters["other_unit"] += 1
            return
        self.counters["requests"] += 1
        t_req_end = t_first + self.map.wire_time_s(len(frame))
        if fc not in (3, 4):
            self._reply_at(t_req_end, self._exception(fc, 1))
            return
        address = int.from_bytes(frame[2:4], "big")
        qty = int.from_bytes(frame[4:6], "big")
        if not 1 <= qty <= 125:
            self._reply_at(t_req_end, self._exception(fc, 3))
        elif address < self._start or address + qty > self._start + self._count:
            self._reply_at(t_req_end, self._exception(fc, 2))
        else:
            self._reply_at(t_req_end, (fc, address - self._start, qty))

    def _exception(self, fc: int, code: int) -> bytes:
        self.counters["exceptions"] += 1
        return with_crc(bytes([self.map.unit_id, (fc | 0x80) & 0xFF, code]))

    def _reply_at(self, t_req_end: float, what) -> None:
        """Sample at the end of the request on the wire; write when the reply's last byte is due."""
        if self.faults.drop_replies:
            self.counters["dropped"] += 1
            return
        self._call_at(t_req_end, self._sample, t_req_end, what)

    def _call_at(self, when: float, fn, *args) -> None:
        h: asyncio.TimerHandle

        def run():
            self._timers.discard(h)
            fn(*args)

        h = self._loop.call_at(when, run)
        self._timers.add(h)

    def _sample(self, t_req_end: float, what) -> None:
        if isinstance(what, bytes):
            reply = what
        else:
            fc, off, qty = what
            try:
                ch1, ch2 = self.source()
                regs = self.map.encode(ch1, ch2)[off:off + qty]
            except Exception as e:                       # a value the registers cannot carry
                self.counters["value_errors"] += 1
                log.warning("virtual meter: cannot serve the values: %s", e)
                reply = self._exception(fc, 4)
            else:
                body = bytearray([self.map.unit_id, fc, 2 * qty])
                for r in regs:
                    body += int(r).to_bytes(2, "big")
                reply = with_crc(bytes(body))
        due = (t_req_end + self.map.turnaround_s + self.map.wire_time_s(len(reply))
               + max(0.0, float(self.faults.extra_delay_s)))
        self._call_at(due - self.spin_s, self._send, reply, due)

    def _send(self, reply: bytes, due: float) -> None:
        while time.monotonic() < due:
            pass
        if self.faults.corrupt_crc:
            reply = reply[:-2] + bytes([reply[-2] ^ 0xFF, reply[-1] ^ 0x5A])
        if self.link.write(reply) == len(reply):
            late = time.monotonic() - due
            self.reply_lateness.append(late)
            self.counters["replies"] += 1
            if late > ON_TIME_S:
                self.counters["late_replies"] += 1


# ---------------------------------------------------------------------------------- stand-alone
def _parse_pair(s: str) -> tuple[float, float]:
    a, b = (float(x) for x in s.split(","))
    return a, b


async def _serve(args) -> int:
    import signal
    import sys

    from ..zns_map import load_map

    m = load_map(args.map).with_overrides(baud=args.baud, unit_id=args.unit, parity=args.parity)
    value = list(_parse_pair(args.value))
    t0 = time.monotonic()

    def source():
        if args.ramp:
            dt = time.monotonic() - t0
            return tuple(((v + args.ramp * dt) % 5.0) for v in value)
        return value[0], value[1]

    meter = VirtualMeter(m, source, args.link)
    await meter.start()
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)

    def out(line: str) -> None:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()

    def on_command() -> None:
        line = sys.stdin.readline()
        if not line:
            loop.remove_reader(sys.stdin.fileno())
            return
        parts = line.split()
        if not parts:
            return
        cmd, rest = parts[0], parts[1:]
        try:
            if cmd == "drop":
                meter.faults.drop_replies = rest[0] == "on"
            elif cmd == "crc":
                meter.faults.corrupt_crc = rest[0] == "on"
            elif cmd == "delay":
                meter.faults.extra_delay_s = float(rest[0])
            elif cmd == "vanish":
                meter.vanish()
            elif cmd == "restore":
                out(f"meter: {meter.restore()}")
                return
            elif cmd == "value":
                value[:] = [float(rest[0]), float(rest[1])]
            elif cmd == "counters":
                lat = sorted(meter.reply_lateness)
                out("counters: " + json.dumps({**meter.counters, "lateness_ms_p50":
                                               lat[len(lat) // 2] * 1e3 if lat else math.nan}))
                return
            else:
                out(f"error: unknown command {cmd!r}")
                return
        except (IndexError, ValueError) as e:
            out(f"error: {line.strip()!r}: {e}")
            return
        out(f"ok: {line.strip()}")

    if args.commands:
        loop.add_reader(sys.stdin.fileno(), on_command)
    out(f"meter: {meter.device}")
    if args.link:
        out(f"link: {args.link}")
    await stop.wait()
    if args.commands:
        try:
            loop.remove_reader(sys.stdin.fileno())
        except (ValueError, OSError):
            pass
    await meter.stop()
    return 0


def main(argv: list[str] | None = None) -> int:
    import argparse

    from ..zns_map import DEFAULT_MAP_PATH, MapError

    ap = argparse.ArgumentParser(prog="python -m drivers.sim.meter",
                                 description="Virtual ZN-S meter (Modbus RTU slave) on a pty")
    ap.add_argument("--map", default=DEFAULT_MAP_PATH, help="register map (default: %(default)s)")
    ap.add_argument("--link", default=None, help="stable symlink to create for the device")
    ap.add_argument("--baud", type=int, default=None)
    ap.add_argument("--unit", type=int, default=None)
    ap.add_argument("--parity", default=None)
    ap.add_argument("--value", default="0.5,0.5", help="constant tensions CH1,CH2 in N")
    ap.add_argument("--ramp", type=float, default=0.0, help="add RATE N/s to both (wrapping at 5 N)")
    ap.add_argument("--no-commands", dest="commands", action="store_false",
                    help="do not read fault commands from stdin")
    args = ap.parse_args(argv)
    try:
        return asyncio.run(_serve(args))
    except MapError as e:
        print(f"error: {e}")
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
