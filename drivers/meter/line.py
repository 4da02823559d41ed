"""The meter's serial line (the transport under ``drivers/meter/driver.py``; docs/protocols/zn-s.md,
"Adapters"): the port opened with pyserial (baud, parity, stop bits; exclusively: a port another
station or a probe holds is left as it is and said once with who holds it), put into low-latency
mode where the kernel offers it and into the kernel's RS-485 mode when ``meter.rs485`` asks for it
(a port that refuses is logged as an error once, ``rs485_error`` says why, and used as it is),
then served non-blocking on its file descriptor through the event loop.

The port vanishing (USB adapter pulled) shows as an error on read or write, or a hang-up: the
line is released, ``connected`` becomes False (``port_lost`` counted once), its receiver is told,
and a background task tries to reopen the path every ``reopen_interval_s`` until it exists again.
"""
from __future__ import annotations

import asyncio
import contextlib
import logging
import os
from typing import Any, Protocol

import serial

from ..serial.ttyio import PortInUse, hung_up, open_exclusive, set_low_latency, set_rs485
from .meter_map import MeterMap

log = logging.getLogger("hookwatch.meter")


def is_pty(path: str) -> bool:
    return os.path.realpath(path).startswith("/dev/pts/")


class LineReceiver(Protocol):
    """Where the line hands what happens (on the event loop; O(1), never raising)."""

    def received(self, data: bytes) -> None: ...
    def lost(self) -> None: ...


class MeterLine:
    """One meter's port: open (and reopened), watched, written, read, drained."""

    def __init__(self, port: str, meter_map: MeterMap, counters: dict[str, int], receiver: LineReceiver,
                 *, reopen_interval_s: float, rs485: Any = None) -> None:
        self.port = port
        self.map = meter_map
        self.counters = counters          # the meter's: port_lost, reopened, port_in_use, late_bytes
        self.receiver = receiver
        self.reopen_interval_s = reopen_interval_s
        #: the ``meter.rs485`` section (enabled, rts_on_send, rts_after_send, delay_*_s) or None
        self.rs485: Any = rs485 if rs485 is not None and getattr(rs485, "enabled", False) else None
        self.rs485_error: str | None = None
        self.low_latency = False
        self.connected = False
        self.parity_used = meter_map.parity
        self.fd: int | None = None
        self._ser: Any = None                # pyserial port (opens and configures the device)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._reopen_task: asyncio.Task[None] | None = None
        self._closed = False
        self._in_use_logged = False            # "in use by …" said for the current episode

    # ------------------------------------------------------------------ lifecycle
    async def open(self) -> None:
        """Open the port; if it is not there, keep trying in the background (never raises)."""
        self._loop = asyncio.get_running_loop()
        self._closed = False
        if not self._try_connect():
            log.warning("meter %s: cannot open the port; retrying every %.1f s", self.port,
                        self.reopen_interval_s)
            self.start_reopen()

    async def close(self) -> None:
        self._closed = True
        if self._reopen_task is not None:
            self._reopen_task.cancel()
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reopen_task
            self._reopen_task = None
        self.release()
        self.connected = False

    def release(self) -> None:
        """Stop watching and close the port (idempotent)."""
        if self.fd is not None and self._loop is not None:
            with contextlib.suppress(Exception):
                self._loop.remove_reader(self.fd)
        self.fd = None
        if self._ser is not None:
            with contextlib.suppress(Exception):
                self._ser.close()
        self._ser = None

    def _try_connect(self) -> bool:
        if "://" not in self.port and not os.path.exists(self.port):   # a URL: pyserial decides
            return False
        parity = self.map.parity
        if parity != "N" and is_pty(self.port):
            # A pseudo-terminal (the simulator) carries no parity bit, and some kernels refuse
            # PARENB on a pty (termios EINVAL, which also leaves pyserial's port locked).
            parity = "N"
            if self.parity_used != "N":
                log.info("meter %s: %s is a pseudo-terminal; parity %s not set there", self.port,
                         os.path.realpath(self.port), self.map.parity)
        self.parity_used = parity
        self.release()
        m = self.map
        try:
            # serial_for_url: a device path, or a pyserial URL (the back-to-back tests' hwloop://)
            # exclusively (flock, taken before any setting is applied): a port another station or
            # a probe holds is left as it is, and said once with who holds it
            ser = open_exclusive(self.port, baudrate=m.baud, bytesize=m.bytesize, parity=parity,
                                 stopbits=m.stopbits, timeout=0, write_timeout=0)
        except PortInUse as e:
            self.counters["port_in_use"] += 1
            if not self._in_use_logged:
                self._in_use_logged = True
                log.warning("meter %s: %s; not opened (retrying every %.1f s)", self.port, e,
                            self.reopen_interval_s)
            return False
        except (OSError, ValueError, serial.SerialException) as e:
            log.debug("meter %s: open failed: %r", self.port, e)
            return False
        loop = self._loop or asyncio.get_running_loop()
        self.low_latency = set_low_latency(ser, self.port, log)
        try:
            fd = ser.fileno()
            if self.rs485 is not None:
                self._set_rs485(fd)
            os.set_blocking(fd, False)
            loop.add_reader(fd, self.on_readable)
        except (OSError, ValueError) as e:
            log.debug("meter %s: cannot watch the port: %r", self.port, e)
            with contextlib.suppress(Exception):
                ser.close()
            return False
        self._ser, self.fd = ser, fd
        self.connected = True
        if self._in_use_logged:
            self._in_use_logged = False
            log.warning("meter %s: the port is free again: opened", self.port)
        return True

    def _set_rs485(self, fd: int) -> None:
        r = self.rs485
        err = set_rs485(fd, r.rts_on_send, r.rts_after_send, r.delay_before_send_s, r.delay_after_send_s)
        if err and err != self.rs485_error:
            log.error("meter %s: meter.rs485: %s; the port is used without it", self.port, err)
        self.rs485_error = err

    def start_reopen(self) -> None:
        if self._closed or self._loop is None:
            return
        if self._reopen_task is None or self._reopen_task.done():
            self._reopen_task = self._loop.create_task(self._reopen_loop())

    async def _reopen_loop(self) -> None:
        while not self._closed and not self.connected:
            await asyncio.sleep(self.reopen_interval_s)
            if self._closed:
                return
            if self._try_connect():
                self.counters["reopened"] += 1
                log.warning("meter %s: port reopened", self.port)
                return

    def port_lost(self, why: object) -> None:
        if self.connected:
            self.connected = False
            self.counters["port_lost"] += 1
            log.warning("meter %s: port lost (%s)", self.port, why)
        self.release()
        self.receiver.lost()
        self.start_reopen()

    # ------------------------------------------------------------------ bytes
    def write(self, data: bytes) -> int | None:
        """The bytes written (0: the write would block), or None: the port is gone (lost now)."""
        if self.fd is None:
            return None
        try:
            return os.write(self.fd, data)
        except BlockingIOError:
            return 0
        except OSError as e:
            self.port_lost(e)
            return None

    def _read_chunk(self, readable: bool) -> bytes:
        """What the OS holds for us now (b'' if nothing); a read error is the port going away, and
        so is an empty read when the port reports a hang-up. (With VMIN 0, as pyserial sets it, an
        empty read otherwise just means no data — also when the loop said "readable": under load
        the loop can run a readiness callback after :meth:`drain` in the same turn has already
        taken the bytes, and that stale event is no hang-up.)"""
        fd = self.fd
        if fd is None:
            return b""
        try:
            data = os.read(fd, 256)
        except BlockingIOError:
            return b""
        except OSError as e:
            self.port_lost(e)
            return b""
        if not data and readable and hung_up(fd):
            self.port_lost("end of file")
        return data

    def on_readable(self) -> None:
        data = self._read_chunk(True)
        if data:
            self.receiver.received(data)

    def drain(self) -> None:
        """Discard what the OS holds for us (a late reply), counting it as late bytes."""
        while self._read_chunk(False):
            self.counters["late_bytes"] += 1

    def flush_input(self) -> None:
        """Discard what the OS holds for us, so a late reply cannot be read as the next answer."""
        with contextlib.suppress(Exception):
            self._ser.reset_input_buffer()
