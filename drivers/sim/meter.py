"""Virtual ZN-S tension meter: a hand-written Modbus RTU slave on a pseudo-terminal.

A pty moves bytes instantly, so this slave delays every reply by the real wire time: the reply's
last byte is due ``request wire time + turnaround + response wire time (+ faults.extra_delay_s)``
after the request's first bytes arrived (11 bits a character at the map's baud). The reply is
written in one piece at that moment by :class:`ReplyWriter`, one thread per process shared by every
virtual meter in it: it sleeps in the kernel (a monotonic timed wait with 1 µs timer slack) until
``WAKE_EARLY_S`` before the due time and spins only that last bit, so a reply lands within a
fraction of a millisecond without burning a core (the asyncio loop's timers are 1 ms coarse; a
busy-wait of 1.5 ms per reply cost 7–10 % of a core per meter). The tensions are sampled from ``source()`` at the moment
the request has completed on the simulated wire, or up to ``SAMPLE_EARLY_S`` (1 ms) before it
(the plant steps 2 ms; this keeps the event loop's timer granularity out of the reply timing).

A request sent at another baud than the meter's is line noise to a real meter: the pty carries
the client's line settings (its termios speed, read through the master), and a request written at
another speed is dropped unanswered (counted as ``wrong_baud``), as on a real bus.

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
import ctypes
import heapq
import itertools
import json
import logging
import math
import os
import sys
import termios
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..meter.meter_map import DEFAULT_MAP_PATH, MapError, MeterMap, crc_ok, load_map, with_crc
from .pty import PtyLink

log = logging.getLogger("hookwatch.sim.meter")

WAKE_EARLY_S = 0.00002  # the writer thread wakes this early from its kernel sleep and spins the rest
SAMPLE_EARLY_S = 0.001   # the values may be sampled this much before the request's end on the wire
ON_TIME_S = 0.0003       # a reply later than this counts as late
REALTIME_PRIORITY = 10      # SCHED_FIFO priority of the reply writer where permitted
SWITCH_INTERVAL_S = 0.0002  # GIL hand-over bound in a process that hosts virtual meters


def _set_timer_slack(ns: int) -> None:
    """Linux: this thread's timer slack (default 50 µs) — how late the kernel may wake a sleep."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(29, ctypes.c_ulong(ns), 0, 0, 0)     # PR_SET_TIMERSLACK
    except (OSError, AttributeError):
        pass


def _ask_realtime() -> bool:
    """Ask for SCHED_FIFO for this thread (Linux, root or CAP_SYS_NICE): on a loaded machine an
    ordinary thread can wait milliseconds for a CPU after its sleep ends; a real-time one is
    woken at once. Safe because the thread sleeps between replies and spins at most
    ``WAKE_EARLY_S`` per reply. Without the permission it stays an ordinary thread."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
        return True
    except (AttributeError, OSError):
        return False


class ReplyWriter:
    """Writes timed replies: ``submit(due, fn)`` runs ``fn()`` on the writer thread as close to
    ``due`` (time.monotonic) as the machine allows: a timed wait in the kernel until
    ``WAKE_EARLY_S`` before, then a short spin. One thread per process (``shared()``) serves every
    virtual meter in it, in due order; ``fn`` must be short (a pty write and counters).

    ``lock`` serialises the writes with a meter detaching its pty (so a reply is never written to
    a descriptor that was closed and reused)."""

    _instance: ReplyWriter | None = None
    _instance_lock = threading.Lock()

    def __init__(self, wake_early_s: float = WAKE_EARLY_S):
        self.wake_early_s = wake_early_s
        self.lock = threading.Lock()
        self._cond = threading.Condition(threading.Lock())
        self._heap: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = itertools.count()
        self._thread: threading.Thread | None = None
        self.realtime = False
        self.oversleep: deque[float] = deque(maxlen=10_000)   # wake time − planned wake time, s

    @classmethod
    def shared(cls) -> ReplyWriter:
        with cls._instance_lock:
            if cls._instance is None:
                cls._instance = cls()
            return cls._instance

    def start(self) -> None:
        """Start the thread (idempotent; ``submit`` starts it too)."""
        with self._cond:
            self._start_locked()

    def _start_locked(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            if sys.getswitchinterval() > SWITCH_INTERVAL_S:
                # the writer must get the GIL within a fraction of the 0.3 ms budget
                sys.setswitchinterval(SWITCH_INTERVAL_S)
            self._thread = threading.Thread(target=self._run, name="sim-reply-writer", daemon=True)
            self._thread.start()

    def submit(self, due: float, fn: Callable[[], None]) -> None:
        with self._cond:
            self._start_locked()
            item = (due, next(self._seq), fn)
            heapq.heappush(self._heap, item)
            if self._heap[0] is item:
                self._cond.notify()

    def _run(self) -> None:
        _set_timer_slack(1000)
        self.realtime = _ask_realtime()
        mono = time.monotonic
        heap = self._heap
        while True:
            with self._cond:
                while True:
                    if not heap:
                        self._cond.wait()
                        continue
                    due = heap[0][0]
                    wake = due - self.wake_early_s
                    now = mono()
                    if now < wake:
                        self._cond.wait(wake - now)
                        if heap and heap[0][0] == due and mono() >= wake:
                            self.oversleep.append(mono() - wake)
                        continue
                    fn = heapq.heappop(heap)[2]
                    break
            while mono() < due:
                pass
            try:
                fn()
            except Exception:                           # noqa: BLE001 — never kill the writer
                log.exception("virtual meter: reply writer")


@dataclass
class MeterFaults:
    drop_replies: bool = False      # requests are received and counted, never answered
    corrupt_crc: bool = False       # replies go out with a wrong CRC
    extra_delay_s: float = 0.0      # added to the honest reply time


@dataclass
class AdapterPlay:
    """The USB–RS-485 adapter between the bus and the gateway, as the scenario plays it.

    ``echo``: the adapter hears its own transmission on the 2-wire bus and hands it back: every
    byte the gateway writes comes back to it, as it leaves on the wire, before the meter's reply.
    ``latency_s``: the adapter's latency timer (FTDI: 16 ms by default): a short packet (a reply
    is 9 bytes, far below the 62 that fill a USB packet) waits in the chip until the timer
    expires; modelled as its worst case, every received chunk reaching the gateway that much
    after its last byte. 0: a board UART, or an FTDI whose timer udev set to 1 ms (then 0.001)."""
    echo: bool = False
    latency_s: float = 0.0


def silence_s(baud: int) -> float:
    """Modbus RTU inter-frame silence t3.5 (fixed 1.75 ms above 19200 baud)."""
    return 3.5 * 11 / baud if baud <= 19200 else 0.00175


class VirtualMeter:
    def __init__(self, meter_map: MeterMap, source: Callable[[], tuple[float, float]],
                 link_path: str | None = None, *, writer: ReplyWriter | None = None, link: Any = None):
        self.map = meter_map
        self.source = source
        # a pty by default; any link with PtyLink's interface (drivers.sim.loopback) may be given
        self.link = link if link is not None else PtyLink(link_path)
        self.faults = MeterFaults()
        self.adapter = AdapterPlay()
        self.writer = writer or ReplyWriter.shared()
        self._gen = 0                      # bumped on detach: replies of an older pty are dropped
        self.counters = {"requests": 0, "replies": 0, "exceptions": 0, "bad_crc": 0,
                         "other_unit": 0, "dropped": 0, "garbage": 0, "late_replies": 0,
                         "value_errors": 0, "echoed_bytes": 0, "wrong_baud": 0}
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
        self._speed = getattr(termios, f"B{meter_map.baud}", None)

    # ------------------------------------------------------------------ lifecycle
    @property
    def device(self) -> str | None:
        return self.link.device

    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self.writer.start()
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
        with self.writer.lock:
            self._gen += 1
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

    def lateness_summary_ms(self) -> dict[str, float]:
        """Reply write time − due time over the last 10 000 replies: p50, p99, max in ms."""
        lat = sorted(self.reply_lateness)
        if not lat:
            return {}
        return {"n": len(lat), "p50": lat[len(lat) // 2] * 1e3,
                "p99": lat[min(len(lat) - 1, int(len(lat) * 0.99))] * 1e3, "max": lat[-1] * 1e3}

    # ------------------------------------------------------------------ receiving
    def _on_readable(self) -> None:
        data = self.link.read_available()
        if not data:
            return
        now = time.monotonic()
        if not self._client_speed_ok():
            # sent at another baud: noise on the bus, never a request
            self.counters["wrong_baud"] += 1
            self._buf.clear()
            return
        if self.adapter.echo:
            # our bytes come back as they leave on the wire (and through the adapter's timer)
            due = now + self.map.wire_time_s(len(data)) + max(0.0, self.adapter.latency_s)
            gen = self._gen
            self.writer.submit(due, lambda: self._send_echo(data, gen))
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
            self._silence = self._ev_loop().call_at(now + t35, self._on_silence)

    def _client_speed_ok(self) -> bool:
        """The client set the meter's baud on its end of the pty (True where that cannot be read:
        a loopback link, or a rate termios has no constant for)."""
        fd = self.link.master
        if self._speed is None or fd is None or not isinstance(self.link, PtyLink):
            return True
        try:
            attrs = termios.tcgetattr(fd)
        except (termios.error, OSError):
            return True
        return attrs[5] == self._speed

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
        # sampled up to SAMPLE_EARLY_S before the request completes on the simulated wire (at
        # 115200 baud at once): the loop's timers are ~1 ms coarse and a busy loop may be later
        # still, and the reply is due only turnaround + reply wire time after this moment
        when = t_req_end - SAMPLE_EARLY_S
        if when <= time.monotonic():
            self._sample(t_req_end, what)
        else:
            self._call_at(when, self._sample, t_req_end, what)

    def _ev_loop(self) -> asyncio.AbstractEventLoop:
        """The loop start() bound; timers are only armed by callbacks that start() registered."""
        if self._loop is None:
            raise RuntimeError("simulated meter not started")
        return self._loop

    def _call_at(self, when: float, fn, *args) -> None:
        h: asyncio.TimerHandle

        def run():
            self._timers.discard(h)
            fn(*args)

        h = self._ev_loop().call_at(when, run)
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
               + max(0.0, float(self.faults.extra_delay_s)) + max(0.0, self.adapter.latency_s))
        gen = self._gen
        self.writer.submit(due, lambda: self._send(reply, due, gen))

    def _send_echo(self, data: bytes, gen: int) -> None:
        """On the writer thread: the adapter hands our own request back."""
        with self.writer.lock:
            if gen != self._gen:
                return
            n = self.link.write(data)
        self.counters["echoed_bytes"] += max(0, n)

    def _send(self, reply: bytes, due: float, gen: int) -> None:
        """On the writer thread, at ``due``."""
        if self.faults.corrupt_crc:
            reply = reply[:-2] + bytes([reply[-2] ^ 0xFF, reply[-1] ^ 0x5A])
        with self.writer.lock:
            if gen != self._gen:
                return                    # the pty was closed (vanish/stop) since it was scheduled
            n = self.link.write(reply)
        if n == len(reply):
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
