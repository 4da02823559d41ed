"""Gateway-side driver of the ZN-S tension meter: a lean Modbus RTU master (one request shape, one
reply shape) straight on the serial port's file descriptor, driven by the event loop.

One read per 20 ms slot, never longer than ``timeout_s``, never raising:

* ``read()`` writes the one FC 3/4 request for the map's whole block (built once, CRC from
  ``drivers/serial/crc.py``) and returns ``Reading(ch1, ch2, rtt_s)`` or ``None``. Every failure is
  counted by kind (``counters``): ``timeouts`` (no complete reply in time), ``crc_errors`` (a reply
  of the right shape with a bad CRC), ``garbage`` (bytes that are not a reply from our unit),
  ``modbus_exceptions`` (the meter answered with an exception code; the last code is in
  ``last_exception_code``), ``decode_errors`` (registers that make no tension, e.g. NaN or a bad
  decimal-point register), ``stale_replies`` (a complete reply sooner than the wire can carry it:
  a late answer to an earlier request — only where the timing is physical, ``timing_physical``:
  not on a pty or a pyserial URL, nor on a port whose replies all come sooner than the wire
  allows, a virtual port, where replies are paired with their request by shape alone),
  ``port_lost``, ``reopened``, ``not_connected`` (reads skipped while the port is gone),
  ``port_in_use`` (opening attempts refused: another process holds the port's exclusive lock —
  said once per episode with who holds it), ``late_bytes`` (chunks of bytes that arrived while no
  request was open; discarded).
* A bad CRC or garbage ends the read at once (the bytes are inspected as they arrive), it does not
  wait for the timeout.
* The port vanishing (USB adapter pulled) shows as an error on read or write: ``connected``
  becomes False, ``read()`` returns None at once, and a background task tries to reopen the path
  every ``REOPEN_INTERVAL_S`` until it exists again. Use a stable path (``/dev/serial/by-id/...``
  or the simulator's symlink): a re-plugged adapter gets a new node.

Two parts: :class:`~drivers.meter.line.MeterLine` (``drivers/meter/line.py``) is the port — opened,
reopened, watched, written, drained, put into low-latency and RS-485 mode — and hands the bytes
that arrive to :class:`ZnsMeter`, the Modbus RTU transaction on it (one request, its reply checked
as it arrives, the decoded reading, the counters and the diagnosis of a read that gave none).

Why not pymodbus' client (it was used until issue 16): its transaction layer (a task, a framer, a
PDU object and a transaction record per request) cost ≈ 0.4 ms of CPU per read, a large part of
a station's slot budget (bench/bench_slot_cpu.py); the one exchange this driver needs is ~150
lines. pyserial opens and configures the port (baud, parity, stop bits).

Real adapters (``docs/protocols/zn-s.md``, "Adapters"): the port is put into low-latency mode
where the kernel offers it (a pty refuses it: logged once at debug); ``local_echo`` checks and
discards the echo of our own request that an adapter on a 2-wire bus may hand back before the reply
(as pymodbus' ``handle_local_echo``; a wrong echo counts as ``garbage``); ``rs485`` puts a board
UART into the kernel's RS-485 mode (TIOCSRS485, RTS direction control) — a port that refuses it is
logged as an error once (``rs485_error`` says why) and used as it is.

Channel swapping is the station's business (``meter.swap_channels``), not the driver's.
Details and timings: ``docs/protocols/zn-s.md``.
"""
from __future__ import annotations

import asyncio
import logging
import math
import time
from typing import Any

from gateway.core.ports import MeterReading

from ..serial.crc import crc16_modbus
from .line import MeterLine, is_pty
from .meter_map import DEFAULT_MAP_PATH, DecodeError, MeterMap, load_map

log = logging.getLogger("hookwatch.meter")

DEFAULT_TIMEOUT_S = 0.015
REOPEN_INTERVAL_S = 0.5
#: complete replies sooner than the wire can carry them (and more of them than paced ones) after
#: which a port's timing is taken as not physical (a virtual port; ``timing_physical``)
FAST_RUN = 5
COUNTER_NAMES = ("reads", "reads_ok", "timeouts", "crc_errors", "garbage", "modbus_exceptions",
                 "decode_errors", "stale_replies", "port_lost", "reopened", "not_connected",
                 "late_bytes", "errors", "port_in_use")


#: one poll: ch1, ch2 (N) and rtt_s (request handed to the port → reply decoded); the type of the
#: MeterPort contract (gateway/core/ports.py)
Reading = MeterReading


def _crc_ok(frame: bytes | bytearray, n: int) -> bool:
    """The first n bytes end with their CRC-16/MODBUS (low byte first)."""
    c = crc16_modbus(memoryview(frame)[:n - 2])
    return frame[n - 2] == (c & 0xFF) and frame[n - 1] == (c >> 8)


def build_request(unit: int, fc: int, address: int, count: int) -> bytes:
    body = bytes((unit, fc, address >> 8, address & 0xFF, count >> 8, count & 0xFF))
    c = crc16_modbus(body)
    return body + bytes((c & 0xFF, c >> 8))


class ZnsMeter:
    def __init__(self, port: str, meter_map: MeterMap, *, timeout_s: float = DEFAULT_TIMEOUT_S,
                 swap_channels: bool = False, reopen_interval_s: float = REOPEN_INTERVAL_S,
                 local_echo: bool = False, rs485: Any = None):
        self.port = port
        self.local_echo = bool(local_echo)
        self._last_failure: str | None = None
        self._last_cause: str | None = None    # why the latest read that gave nothing did
        self.map = meter_map
        self.timeout_s = float(timeout_s)
        self.swap_channels = bool(swap_channels)      # applied by the station
        self.reopen_interval_s = reopen_interval_s
        self.counters: dict[str, int] = {k: 0 for k in COUNTER_NAMES}
        #: the port (open, reopened, watched, written, drained): drivers/meter/line.py
        self.line = MeterLine(port, meter_map, self.counters, self, reopen_interval_s=reopen_interval_s,
                              rs485=rs485)
        self.last_exception_code: int | None = None
        self.last_rtt_s = math.nan
        # the open transaction
        self._pending = False
        self._rx = bytearray()
        self._echo_left = 0                  # bytes of our own request still to come back (local_echo)
        self._fail: asyncio.Future | None = None
        fc, self._address, self._count = meter_map.read_block
        self._fc = fc
        self._unit = meter_map.unit_id
        self._request = build_request(self._unit, fc, self._address, self._count)
        self._resp_len = meter_map.response_bytes
        self._min_reply_s = 0.9 * meter_map.wire_time_s(meter_map.request_bytes + meter_map.response_bytes)
        #: the port carries bytes at the wire's pace, so a reply sooner than the wire can carry it
        #: is a late answer to an earlier request (``stale_replies``). False where the timing is
        #: not physical: a pty or a pyserial URL from the start; any other port once FAST_RUN of
        #: its complete replies, and most of them, came sooner than the wire allows (a USB CDC
        #: meter, a virtual COM port, a device server; on a paced line a reply that early is a
        #: rare late answer) — logged once. Replies are then paired with their request by shape
        #: alone: input drained before each request, unit, function code, byte count and CRC.
        self.timing_physical = not (is_pty(port) or "://" in port)
        self._paced = 0                        # complete replies that took the wire time or more
        self._fast = 0                         # complete replies sooner than the wire
        #: the last read timed out: a reply sooner than the wire now is most likely its late
        #: answer (a USB adapter's latency timer over the timeout), no sign of a virtual port
        self._after_timeout = False
        if self.timeout_s < meter_map.poll_time_s():
            log.warning("meter %s: timeout_s %.1f ms is shorter than one poll on the wire "
                        "(%.1f ms at %d baud): every read will time out", port, self.timeout_s * 1e3,
                        meter_map.poll_time_s() * 1e3, meter_map.baud)

    @property
    def last_failure(self) -> str | None:
        """Why the latest read gave nothing (None: it gave a reading)."""
        return self._last_failure

    @last_failure.setter
    def last_failure(self, why: str | None) -> None:
        self._last_failure = why
        if why is not None:
            self._last_cause = why

    @classmethod
    def from_config(cls, meter_cfg) -> ZnsMeter:
        """From the station's ``meter:`` section (attributes port, map, baud, unit_id, parity,
        timeout_s, swap_channels; None = from the map / default). Raises MapError for a bad map."""
        path = getattr(meter_cfg, "map", None) or DEFAULT_MAP_PATH
        m = load_map(path).with_overrides(baud=getattr(meter_cfg, "baud", None),
                                          unit_id=getattr(meter_cfg, "unit_id", None),
                                          parity=getattr(meter_cfg, "parity", None))
        timeout = getattr(meter_cfg, "timeout_s", None)
        return cls(meter_cfg.port, m,
                   timeout_s=DEFAULT_TIMEOUT_S if timeout is None else float(timeout),
                   swap_channels=bool(getattr(meter_cfg, "swap_channels", False)),
                   local_echo=bool(getattr(meter_cfg, "local_echo", False)),
                   rs485=getattr(meter_cfg, "rs485", None))

    # ------------------------------------------------------------------ the port
    @property
    def connected(self) -> bool:
        return self.line.connected

    @connected.setter
    def connected(self, value: bool) -> None:
        self.line.connected = value

    @property
    def low_latency(self) -> bool:
        return self.line.low_latency

    @property
    def rs485(self) -> Any:
        """The ``meter.rs485`` section in use (enabled), or None."""
        return self.line.rs485

    @property
    def rs485_error(self) -> str | None:
        """Why the port refused the kernel's RS-485 mode (None: it did not)."""
        return self.line.rs485_error

    async def open(self) -> None:
        """Open the port; if it is not there, keep trying in the background (never raises)."""
        await self.line.open()

    async def close(self) -> None:
        await self.line.close()

    def lost(self) -> None:
        self._fail_now("port_lost")

    def settings_text(self) -> str:
        """Where and how the meter is asked: ``/dev/… at 115200 8N1, unit 1``."""
        m = self.map
        return f"{self.port} at {m.baud} {m.bytesize}{self.line.parity_used}{m.stopbits}, unit {self._unit}"

    def diagnosis(self) -> str | None:
        """One sentence on why the latest read gave no reading (None after a good one), naming the
        port and its settings — what a silent meter looks like to an operator."""
        return self._sentence(self.last_failure)

    def failure_text(self) -> str | None:
        """:meth:`diagnosis` of the latest read that gave no reading, even if a good read came
        after it (None: none failed yet) — what the station's counted line says."""
        return self._sentence(self._last_cause)

    def _sentence(self, why: str | None) -> str | None:
        where = self.settings_text()
        if why is None:
            return None
        if why == "timeout":
            return f"meter not answering on {where}"
        if why == "stale":
            return (f"replies on {where} came sooner than {self.map.baud} baud can carry them: late "
                    "answers to earlier requests (a meter slower than the slot)")
        if why in ("not_connected", "port_lost"):
            return f"meter port {self.port} is not open (unplugged, or a wrong path)"
        if why == "garbage":
            return (f"the bytes on {where} are no reply of this unit (another unit ID or baud, or the "
                    "adapter's own echo: meter.local_echo)")
        if why == "crc":
            return f"replies on {where} fail their CRC (wiring, termination or baud)"
        if why == "exception":
            return f"the meter on {where} answers Modbus exception {self.last_exception_code:02d}"
        return f"the meter on {where} gives no usable reading ({why})"

    # ------------------------------------------------------------------ receiving
    def received(self, data: bytes) -> None:
        """Bytes from the line: the reply inspected as it arrives (a bad CRC or garbage ends the
        read at once)."""
        if not self._pending:
            self.counters["late_bytes"] += 1
            return
        if self._echo_left:
            # the echo of our own request comes first: check and drop it
            k = min(self._echo_left, len(data))
            at = len(self._request) - self._echo_left
            if data[:k] != self._request[at:at + k]:
                self._fail_now("garbage")
                return
            self._echo_left -= k
            data = data[k:]
            if not data:
                return
        rx = self._rx
        rx += data
        fc = self._fc
        if rx[0] != self._unit or (len(rx) >= 2 and rx[1] != fc and rx[1] != (fc | 0x80)):
            self._fail_now("garbage")
        elif len(rx) >= 2 and rx[1] == (fc | 0x80):
            if len(rx) >= 5:
                self._fail_now("exception" if _crc_ok(rx, 5) else "crc")
        elif len(rx) >= 3 and rx[2] != 2 * self._count:
            self._fail_now("garbage")
        elif len(rx) >= self._resp_len:
            self._fail_now("ok" if _crc_ok(rx, self._resp_len) else "crc")

    def _fail_now(self, why: str) -> None:
        f = self._fail
        if f is not None and not f.done():
            f.set_result(why)

    # ------------------------------------------------------------------ reading
    async def read(self) -> Reading | None:
        """One poll. Reading or None (counted); never raises, never takes longer than timeout_s."""
        line = self.line
        if not line.connected or line.fd is None:
            self.counters["not_connected"] += 1
            self.last_failure = "not_connected"
            line.start_reopen()
            return None
        if self._pending:                 # a concurrent caller: one transaction at a time
            self.counters["errors"] += 1
            return None
        self.counters["reads"] += 1
        loop = asyncio.get_running_loop()
        line.drain()
        if line.fd is None:              # lost while draining
            return None
        self._rx.clear()
        self._echo_left = len(self._request) if self.local_echo else 0
        fut = self._fail = loop.create_future()
        self._pending = True
        timer = None
        try:
            t0 = time.monotonic()
            n = line.write(self._request)
            if n is None:                 # the port is gone (lost now)
                return None
            if n != len(self._request):
                self.counters["errors"] += 1
                return None
            timer = loop.call_at(loop.time() + self.timeout_s, self._fail_now, "timeout")
            why = await fut
            rtt = time.monotonic() - t0
            self.last_failure = None if why == "ok" else why
            if why == "ok":
                return self._result(rtt)
            if why == "exception":
                self.counters["modbus_exceptions"] += 1
                self.last_exception_code = self._rx[2]
                return None
            self._count_failure(why)
            if why != "port_lost":
                line.flush_input()
            return None
        except Exception as e:            # never raise into the slot loop
            self.counters["errors"] += 1
            log.debug("meter %s: read failed: %r", self.port, e)
            return None
        finally:
            if timer is not None:
                timer.cancel()
            self._pending = False
            self._fail = None

    def _count_failure(self, why: str) -> None:
        if why == "timeout":
            self.counters["timeouts"] += 1
            self._after_timeout = True
        elif why == "crc":
            self.counters["crc_errors"] += 1
        elif why == "garbage":
            self.counters["garbage"] += 1
        elif why == "port_lost":
            pass                              # counted once by the line (MeterLine.port_lost)
        else:
            self.counters["errors"] += 1

    def _result(self, rtt: float) -> Reading | None:
        after_timeout, self._after_timeout = self._after_timeout, False
        if self.timing_physical:
            if rtt >= self._min_reply_s:
                self._paced += 1
            else:
                # only a fast reply with no read left unanswered before it says "virtual port": the
                # one right after a timeout is that read's late answer on any paced line (an FTDI
                # at a 16 ms latency timer and a 15 ms timeout gives nothing else)
                self._fast += 0 if after_timeout else 1
                if self._fast >= FAST_RUN and self._fast > self._paced:
                    self.timing_physical = False
                    log.warning("meter %s: every reply came sooner than %d baud can carry (%d of "
                                "%d under %.1f ms): a virtual port? Replies are paired with their "
                                "request by their shape only from now on", self.port, self.map.baud,
                                self._fast, self._fast + self._paced, self._min_reply_s * 1e3)
                else:
                    # faster than the wire can carry request and reply: the late answer to an
                    # earlier read
                    self.counters["stale_replies"] += 1
                    self.last_failure = "stale"
                    return None
        rx = self._rx
        regs = [(rx[i] << 8) | rx[i + 1] for i in range(3, 3 + 2 * self._count, 2)]
        try:
            ch1, ch2 = self.map.decode(regs)
        except DecodeError as e:
            self.counters["decode_errors"] += 1
            self.last_failure = "decode"
            log.debug("meter %s: %s", self.port, e)
            return None
        if not (math.isfinite(ch1) and math.isfinite(ch2)):
            self.counters["decode_errors"] += 1
            self.last_failure = "decode"
            return None
        self.counters["reads_ok"] += 1
        self.last_rtt_s = rtt
        return Reading(ch1, ch2, rtt)
