"""The STM32 link's transport and framing (the lowest of the link's three layers, as pymodbus
layers transport → framer → transaction; docs/protocols/stm32.md).

:class:`Stm32Wire` opens the port with pyserial (settings, exclusive lock, low-latency mode where
the kernel offers it) and then serves it non-blocking: the loop's ``add_reader`` feeds a streaming
:class:`~drivers.stm32.protocol.FrameParser`; a whole ACK read in one chunk is checked and decoded
straight from the bytes (:func:`fast_ack`: the usual case, the streaming parser handles everything
else: split frames, garbage, NAKs). Every decoded reply, a damaged frame and a lost port go to its
:class:`Receiver` (the link). A read or write error or a hang-up is the port lost: released,
``connected = False``, counted once.
"""
from __future__ import annotations

import asyncio
import logging
import os
import struct
from collections.abc import Iterable
from typing import Any, Protocol

import serial

from ..serial.crc import crc16_modbus
from ..serial.ttyio import hung_up, open_exclusive, set_low_latency
from .protocol import (
    ACK_LEN,
    RPM_SCALE,
    Cmd,
    Flag,
    Frame,
    FrameParser,
    ProtocolError,
    Reply,
    Status,
    StopReason,
    decode_reply,
)

log = logging.getLogger("hookwatch.stm32")

#: an ACK frame starts with these three bytes (start, LEN of its payload)
_ACK_HEAD = bytes((0xA5, 0x5A, ACK_LEN - 7))
_ACK_TYPE = int(Cmd.ACK)
#: the status inside an ACK frame: after start (2), LEN, SEQ, type and the request's command
_ACK_STATUS = struct.Struct("<iiHBHH")
_ACK_STATUS_AT = 6
_flag_cache: dict[int, Flag] = {}
_reason_cache: dict[int, StopReason | int] = {}


def _flags(v: int) -> Flag:
    f = _flag_cache.get(v)
    if f is None:
        f = Flag(v)
        if len(_flag_cache) < 1024:
            _flag_cache[v] = f
    return f


def flag_names(f: Flag) -> str:
    return "|".join(m.name or "" for m in Flag if m in f) or "none"


def _stop_reason(v: int) -> StopReason | int:
    r = _reason_cache.get(v)
    if r is None:
        try:
            r = StopReason(v)
        except ValueError:
            r = v
        _reason_cache[v] = r        # one byte: at most 256 entries
    return r


def fast_ack(data: bytes) -> Reply | None:
    """``data`` is exactly one whole ACK frame with a good CRC: its Reply (equal to what
    FrameParser + decode_reply give), else None (then the streaming parser decides)."""
    if len(data) != ACK_LEN or data[4] != _ACK_TYPE or not data.startswith(_ACK_HEAD):
        return None
    c = crc16_modbus(memoryview(data)[2:ACK_LEN - 2])
    if data[ACK_LEN - 2] != (c & 0xFF) or data[ACK_LEN - 1] != (c >> 8):
        return None
    act, cmd, flags, reason, wd, rxe = _ACK_STATUS.unpack_from(data, _ACK_STATUS_AT)
    return Reply(data[3], True, data[5],
                 status=Status(act / RPM_SCALE, cmd / RPM_SCALE, bool(flags & Flag.ENABLED),
                               _flags(flags), _stop_reason(reason), wd, rxe))


def frame(seq: int, cmd: int, payload: bytes) -> bytes:
    """encode_frame without its argument checks (the link's own commands are valid)."""
    body = bytes((len(payload), seq, cmd)) + payload
    c = crc16_modbus(body)
    return b"\xA5\x5A" + body + bytes((c & 0xFF, c >> 8))


class Receiver(Protocol):
    """What the wire hands up (on the event loop, O(1), never raising)."""

    def reply(self, rep: Reply) -> None: ...
    def damaged(self) -> None: ...
    def lost(self) -> None: ...


class Stm32Wire:
    """The port: open, watched or not, written, read; framing of what comes back."""

    def __init__(self, port: str, baud: int, reopen_s: float, counters: dict[str, int],
                 receiver: Receiver) -> None:
        self.port = port
        self.baud = baud
        self.reopen_s = reopen_s
        self.counters = counters            # the link's: port_lost, crc_errors, bad_replies
        self.receiver = receiver
        self.connected = False
        self.low_latency = False             # the kernel took low-latency mode for the port
        self.watching = False                # the port is on the event loop's reader list
        self.fd: int | None = None
        self._ser: Any = None                # the pyserial port (open_exclusive's)
        self._parser = FrameParser()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._open_error_logged = False

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop

    def open(self) -> bool:
        """Open the port and watch it (False: not there, in use or refused; said once)."""
        if self._loop is None:
            raise RuntimeError(f"stm32 {self.port}: open() was not called")
        try:
            # serial_for_url: a device path as serial.Serial, or a pyserial URL (hwloop:// in tests)
            ser = open_exclusive(self.port, baudrate=self.baud, bytesize=8, parity="N", stopbits=1,
                                 timeout=0, write_timeout=0)
        except (serial.SerialException, OSError, ValueError) as e:
            if not self._open_error_logged:
                log.warning("stm32 %s: cannot open (%s); retrying every %.1f s", self.port, e,
                            self.reopen_s)
                self._open_error_logged = True
            return False
        self._open_error_logged = False
        self._ser = ser
        # a USB adapter's driver hands received bytes over at once (a pty refuses: logged at debug)
        self.low_latency = set_low_latency(ser, self.port, log)
        fd = self.fd = ser.fileno()
        os.set_blocking(fd, False)
        self._parser.reset()
        self._loop.add_reader(fd, self.on_readable)
        self.watching = True
        self.connected = True
        log.info("stm32 %s: open at %d baud", self.port, self.baud)
        return True

    def release(self) -> None:
        self.watching = False
        if self.fd is not None and self._loop is not None:
            try:
                self._loop.remove_reader(self.fd)
            except Exception:
                pass
        self.fd = None
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:
                pass
        self._ser = None

    def port_lost(self, why: object) -> None:
        if not self.connected:
            return
        self.connected = False
        self.counters["port_lost"] += 1
        log.warning("stm32 %s: port lost (%s); reopening every %.1f s", self.port, why, self.reopen_s)
        self.release()
        self.receiver.lost()

    # ------------------------------------------------------------------ watching
    def watch(self) -> None:
        if not self.watching and self.fd is not None and self._loop is not None:
            self._loop.add_reader(self.fd, self.on_readable)
            self.watching = True

    def unwatch(self) -> None:
        """Off the loop's reader list: a reply arriving does not wake the process."""
        if self.watching and self.fd is not None and self._loop is not None:
            try:
                self._loop.remove_reader(self.fd)
            except Exception:   # a closed loop: nothing to watch anyway
                pass
        self.watching = False

    # ------------------------------------------------------------------ write, read
    def write(self, data: bytes) -> bool | None:
        """True: written; False: the write would block; None: the port is gone (lost now)."""
        if self.fd is None:
            return None
        try:
            os.write(self.fd, data)
        except BlockingIOError:
            return False
        except OSError as e:
            self.port_lost(e)
            return None
        return True

    def read_now(self) -> bool | None:
        """Read what the port holds, without waiting: True: bytes taken; False: none there (VMIN
        0; a hang-up shows as an error); None: the port is gone (lost now)."""
        if self.fd is None:
            return None
        try:
            data = os.read(self.fd, 4096)
        except BlockingIOError:
            return False
        except OSError as e:
            self.port_lost(e)
            return None
        if not data:
            return False
        self.ingest(data)
        return True

    def on_readable(self) -> None:
        if self.fd is None:    # released: the reader is removed with the fd
            return
        try:
            data = os.read(self.fd, 4096)
        except BlockingIOError:
            return
        except OSError as e:
            self.port_lost(e)
            return
        if not data:
            if hung_up(self.fd):    # else a stale readiness event: the bytes were read already
                self.port_lost("hang-up")
            return
        self.ingest(data)

    # ------------------------------------------------------------------ framing
    def ingest(self, data: bytes) -> None:
        if not self._parser.pending:
            rep = fast_ack(data)        # the usual case: one whole ACK in one read
            if rep is not None:
                self.receiver.reply(rep)
                return
        crc_before = self._parser.crc_errors
        self._deliver(self._parser.feed(data))
        if self._parser.crc_errors != crc_before:
            self.counters["crc_errors"] += self._parser.crc_errors - crc_before
            self.receiver.damaged()    # the reply we wait for was probably damaged: retry now

    def flush(self, idle: bool = False) -> None:
        """An idle gap on the line: no partial frame is real; a reply hidden behind a false start
        is delivered. ``idle``: only when a partial frame is pending (before a request)."""
        if not idle or self._parser.pending:
            self._deliver(self._parser.flush())

    def _deliver(self, frames: Iterable[Frame]) -> None:
        for fr in frames:
            try:
                rep = decode_reply(fr)
            except ProtocolError as e:
                self.counters["bad_replies"] += 1
                log.debug("stm32 %s: %s", self.port, e)
                continue
            self.receiver.reply(rep)
