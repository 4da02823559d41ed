"""Gateway-side driver of the ZN-S tension meter: a Modbus RTU master on pymodbus'
``AsyncModbusSerialClient``.

One read per 20 ms slot, never longer than ``timeout_s``, never raising:

* ``read()`` sends one FC 3/4 request for the map's whole block and returns
  ``Reading(ch1, ch2, rtt_s)`` or ``None``. Every failure is counted by kind (``counters``):
  ``timeouts`` (no byte came back), ``crc_errors`` (a reply of the right shape with a bad CRC),
  ``garbage`` (bytes that are not a reply from our unit), ``modbus_exceptions`` (the meter answered
  with an exception code; the last code is in ``last_exception_code``), ``decode_errors`` (registers
  that make no tension, e.g. NaN or a bad decimal-point register), ``stale_replies`` (a complete
  reply sooner than the wire can carry it: a late answer to an earlier request), ``port_lost``,
  ``reopened``, ``not_connected`` (reads skipped while the port is gone), ``late_bytes`` (bytes that
  arrived while no request was open; pymodbus discards them).
* A bad CRC or garbage ends the read at once (the bytes are inspected as they arrive), it does not
  wait for the timeout.
* The port vanishing (USB adapter pulled) is seen by pymodbus' transport (``ConnectionException``,
  OSError): ``connected`` becomes False, ``read()`` returns None at once, and a background task
  tries to reopen the path every ``REOPEN_INTERVAL_S`` until it exists again. Use a stable path
  (``/dev/serial/by-id/...`` or the simulator's symlink): a re-plugged adapter gets a new node.

Channel swapping is the station's business (``meter.swap_channels``), not the driver's.
Details and timings: ``docs/protocols/zn-s.md``.
"""
from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import time
from dataclasses import dataclass
from typing import Any

from .zns_map import DEFAULT_MAP_PATH, DecodeError, MeterMap, crc_ok, load_map

log = logging.getLogger("hookwatch.meter")

# Unconfigured, pymodbus logs an error with frame dumps for every failure: at 50 Hz that floods the
# journal. Quiet it unless someone has set a level on purpose.
_pm_log = logging.getLogger("pymodbus")
if _pm_log.level == logging.NOTSET:
    _pm_log.setLevel(logging.CRITICAL)

DEFAULT_TIMEOUT_S = 0.015
REOPEN_INTERVAL_S = 0.5
COUNTER_NAMES = ("reads", "reads_ok", "timeouts", "crc_errors", "garbage", "modbus_exceptions",
                 "decode_errors", "stale_replies", "port_lost", "reopened", "not_connected",
                 "late_bytes", "errors")


def _is_pty(path: str) -> bool:
    return os.path.realpath(path).startswith("/dev/pts/")


@dataclass(frozen=True, slots=True)
class Reading:
    ch1: float      # N
    ch2: float      # N
    rtt_s: float    # request handed to the port → reply decoded


class ZnsMeter:
    def __init__(self, port: str, meter_map: MeterMap, *, timeout_s: float = DEFAULT_TIMEOUT_S,
                 swap_channels: bool = False, reopen_interval_s: float = REOPEN_INTERVAL_S):
        self.port = port
        self.map = meter_map
        self.timeout_s = float(timeout_s)
        self.swap_channels = bool(swap_channels)      # applied by the station
        self.reopen_interval_s = reopen_interval_s
        self.connected = False
        self.counters: dict[str, int] = {k: 0 for k in COUNTER_NAMES}
        self.last_exception_code: int | None = None
        self.last_rtt_s = math.nan
        self._client: Any = None
        self._parity_used = meter_map.parity
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reopen_task: asyncio.Task | None = None
        self._closed = False
        # the open transaction
        self._pending = False
        self._rx_any = False
        self._fail: asyncio.Future | None = None
        fc, self._address, self._count = meter_map.read_block
        self._fc = fc
        self._resp_len = meter_map.response_bytes
        self._min_reply_s = 0.9 * meter_map.wire_time_s(meter_map.request_bytes + meter_map.response_bytes)
        if self.timeout_s < meter_map.poll_time_s():
            log.warning("meter %s: timeout_s %.1f ms is shorter than one poll on the wire "
                        "(%.1f ms at %d baud): every read will time out", port, self.timeout_s * 1e3,
                        meter_map.poll_time_s() * 1e3, meter_map.baud)

    @classmethod
    def from_config(cls, meter_cfg) -> "ZnsMeter":
        """From the station's ``meter:`` section (attributes port, map, baud, unit_id, parity,
        timeout_s, swap_channels; None = from the map / default). Raises MapError for a bad map."""
        path = getattr(meter_cfg, "map", None) or DEFAULT_MAP_PATH
        m = load_map(path).with_overrides(baud=getattr(meter_cfg, "baud", None),
                                          unit_id=getattr(meter_cfg, "unit_id", None),
                                          parity=getattr(meter_cfg, "parity", None))
        timeout = getattr(meter_cfg, "timeout_s", None)
        return cls(meter_cfg.port, m,
                   timeout_s=DEFAULT_TIMEOUT_S if timeout is None else float(timeout),
                   swap_channels=bool(getattr(meter_cfg, "swap_channels", False)))

    # ------------------------------------------------------------------ lifecycle
    async def open(self) -> None:
        """Open the port; if it is not there, keep trying in the background (never raises)."""
        self._loop = asyncio.get_running_loop()
        self._closed = False
        if self._client is None:
            self._client = self._make_client(self.map.parity)
        if not await self._try_connect():
            log.warning("meter %s: cannot open the port; retrying every %.1f s", self.port,
                        self.reopen_interval_s)
            self._start_reopen()

    def _make_client(self, parity: str):
        from pymodbus.client import AsyncModbusSerialClient
        from pymodbus.framer import FramerType

        m = self.map
        self._parity_used = parity
        return AsyncModbusSerialClient(
            self.port, framer=FramerType.RTU, baudrate=m.baud, bytesize=m.bytesize,
            parity=parity, stopbits=m.stopbits, name=f"meter {self.port}",
            # our own deadline (timeout_s) ends a read first; pymodbus' is only a backstop
            timeout=self.timeout_s + 1.0, retries=0,
            reconnect_delay=0,                 # we reopen ourselves, on our schedule
            trace_packet=self._trace_packet, trace_connect=self._trace_connect)

    async def close(self) -> None:
        self._closed = True
        if self._reopen_task is not None:
            self._reopen_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reopen_task
            self._reopen_task = None
        if self._client is not None:
            with contextlib.suppress(Exception):
                self._client.close()
        self.connected = False

    async def _try_connect(self) -> bool:
        if "://" not in self.port and not os.path.exists(self.port):   # a URL: pyserial decides
            return False
        parity = self.map.parity
        if parity != "N" and _is_pty(self.port):
            # A pseudo-terminal (the simulator) carries no parity bit, and some kernels refuse
            # PARENB on a pty (termios EINVAL, which also leaves pyserial's port locked).
            parity = "N"
            if self._parity_used != "N":
                log.info("meter %s: %s is a pseudo-terminal; parity %s not set there", self.port,
                         os.path.realpath(self.port), self.map.parity)
        if parity != self._parity_used:
            with contextlib.suppress(Exception):
                self._client.close()
            self._client = self._make_client(parity)
        ok = await self._connect_once()
        if ok:
            self.connected = True
        return ok

    async def _connect_once(self) -> bool:
        try:
            return bool(await asyncio.wait_for(self._client.connect(), 2.0))
        except Exception as e:      # SerialException (an OSError), termios.error, timeout
            log.debug("meter %s: open failed: %r", self.port, e)
            return False

    def _start_reopen(self) -> None:
        if self._closed or self._loop is None:
            return
        if self._reopen_task is None or self._reopen_task.done():
            self._reopen_task = self._loop.create_task(self._reopen_loop())

    async def _reopen_loop(self) -> None:
        while not self._closed and not self.connected:
            await asyncio.sleep(self.reopen_interval_s)
            if self._closed:
                return
            if await self._try_connect():
                self.counters["reopened"] += 1
                log.warning("meter %s: port reopened", self.port)
                return

    # ------------------------------------------------------------------ pymodbus hooks
    def _trace_connect(self, connected: bool) -> None:
        if connected:
            return
        if self.connected:
            self.connected = False
            self.counters["port_lost"] += 1
            log.warning("meter %s: port lost", self.port)
        self._fail_now("port_lost")
        self._start_reopen()

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if sending:
            return data
        if not self._pending:
            self.counters["late_bytes"] += 1
            return data
        self._rx_any = True
        unit = self.map.unit_id
        if data[0] != unit or (len(data) >= 2 and data[1] not in (self._fc, self._fc | 0x80)):
            self._fail_now("garbage")
        elif len(data) >= 2 and data[1] == (self._fc | 0x80):
            if len(data) >= 5 and not crc_ok(data[:5]):
                self._fail_now("crc")
        elif len(data) >= 3 and data[2] != 2 * self._count:
            self._fail_now("garbage")
        elif len(data) >= self._resp_len and not crc_ok(data[:self._resp_len]):
            self._fail_now("crc")
        return data

    def _fail_now(self, why: str) -> None:
        f = self._fail
        if f is not None and not f.done():
            f.set_result(why)

    # ------------------------------------------------------------------ reading
    async def read(self) -> Reading | None:
        """One poll. Reading or None (counted); never raises, never takes longer than timeout_s."""
        if self.connected and self._client is not None and not self._client.connected:
            self._trace_connect(False)       # pymodbus dropped the transport without telling us
        if not self.connected or self._client is None:
            self.counters["not_connected"] += 1
            self._start_reopen()
            return None
        if self._pending:                 # a concurrent caller: one transaction at a time
            self.counters["errors"] += 1
            return None
        self.counters["reads"] += 1
        loop = self._loop or asyncio.get_running_loop()
        self._rx_any = False
        self._fail = loop.create_future()
        self._pending = True
        t0 = time.monotonic()
        task = None
        try:
            if self._fc == 3:
                coro = self._client.read_holding_registers(self._address, count=self._count,
                                                           device_id=self.map.unit_id)
            else:
                coro = self._client.read_input_registers(self._address, count=self._count,
                                                         device_id=self.map.unit_id)
            task = loop.create_task(coro)
            done, _ = await asyncio.wait((task, self._fail), timeout=self.timeout_s,
                                         return_when=asyncio.FIRST_COMPLETED)
            rtt = time.monotonic() - t0
            if task in done:
                return self._result(task, rtt)
            why = self._fail.result() if self._fail.done() else "timeout"   # nothing, or too little
            self._count_failure(why)
            if why != "port_lost":
                self._flush_input()
            return None
        except Exception as e:            # never raise into the slot loop
            self.counters["errors"] += 1
            log.debug("meter %s: read failed: %r", self.port, e)
            return None
        finally:
            self._pending = False
            self._fail = None
            if task is not None and not task.done():
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
            # a late or partial reply must not poison the next read: drop whatever is buffered
            # (pymodbus also clears its buffer when it sends the next request)
            ctx = getattr(self._client, "ctx", None)
            if ctx is not None:
                ctx.recv_buffer = b""

    def _flush_input(self) -> None:
        """Discard what the OS holds for us, so a late reply cannot be read as the next answer."""
        with contextlib.suppress(Exception):
            self._client.ctx.transport.sync_serial.reset_input_buffer()

    def _count_failure(self, why: str) -> None:
        if why == "timeout":
            self.counters["timeouts"] += 1
        elif why == "crc":
            self.counters["crc_errors"] += 1
        elif why == "garbage":
            self.counters["garbage"] += 1
        elif why == "port_lost":
            pass                              # counted once in _trace_connect
        else:
            self.counters["errors"] += 1

    def _result(self, task: asyncio.Task, rtt: float) -> Reading | None:
        from pymodbus.exceptions import ConnectionException, ModbusIOException

        exc = task.exception()
        if exc is not None:
            if isinstance(exc, ConnectionException):
                if self.connected:
                    self.connected = False
                    self.counters["port_lost"] += 1
                self._start_reopen()
            elif isinstance(exc, ModbusIOException):
                self.counters["timeouts"] += 1
            else:
                self.counters["errors"] += 1
                log.debug("meter %s: %r", self.port, exc)
            return None
        resp = task.result()
        if resp is None or resp.isError():
            self.counters["modbus_exceptions"] += 1
            self.last_exception_code = getattr(resp, "exception_code", None)
            return None
        if rtt < self._min_reply_s:
            # faster than the wire can carry request and reply: the late answer to an earlier read
            self.counters["stale_replies"] += 1
            return None
        try:
            ch1, ch2 = self.map.decode(resp.registers)
        except DecodeError as e:
            self.counters["decode_errors"] += 1
            log.debug("meter %s: %s", self.port, e)
            return None
        if not (math.isfinite(ch1) and math.isfinite(ch2)):
            self.counters["decode_errors"] += 1
            return None
        self.counters["reads_ok"] += 1
        self.last_rtt_s = rtt
        return Reading(ch1, ch2, rtt)
