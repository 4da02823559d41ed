"""Gateway side of the STM32 link (docs/protocols/stm32.md): an asyncio client that never blocks
the event loop and never raises.

The port is opened with pyserial (settings, exclusive lock) and then served non-blocking: the
loop's ``add_reader`` feeds a streaming :class:`FrameParser`, requests are written with
``os.write`` (a UART's kernel buffer takes a 11-byte frame at once). One exchange at a time (a
busy flag; a concurrent caller waits its turn in FIFO order): a fresh sequence number per
command, a reply timeout ``timeout_s``, ``retries`` with the *same* sequence number (the firmware
answers a duplicate again without acting twice) as long as they fit in the call's budget
``budget_s`` (just under one 20 ms slot).

Lean on the hot path (issue 16, ``bench/bench_slot_cpu.py``): the uncontended exchange takes no
lock object, a whole ACK read in one chunk is checked and decoded straight from the bytes (the
streaming parser handles everything else: split frames, garbage, NAKs), and while commands flow
the keep-alive's wake-up is pushed out from the transmit path instead of waking the loop.

Posted speed commands (the station's per-slot SET_SPEED): :meth:`Stm32Link.post_speed` writes the
frame and returns at once; the port is taken off the event loop's watch list meanwhile, so the
ACK arriving ~3 ms later does not wake the process; :meth:`Stm32Link.collect` (called in the next
slot, when the process is awake anyway) reads it from the port without waiting. A missing ACK is
counted (``timeouts`` and ``failed``), a NAK as ``naks``; no retry — the next slot's command is
the retry. Any awaited exchange (ENABLE, STOP, READ_STATUS, the keep-alive) first collects a
posted command and watches the port again. This saves one process wake-up per slot, the largest
single CPU cost of a slot on a loaded 2-core box.

A vanished port (read/write error, hang-up) sets ``connected = False``; calls then return None at
once, and a background task reopens the port every ``reopen_s`` (0.5 s).

Keep-alive: the same background task guarantees the firmware watchdog never trips in normal
operation. While the firmware reports ``enabled`` it sends a PING whenever no frame went out for
half the watchdog period (the smaller of the configured and the firmware-reported one). The
station's own traffic (SET_SPEED every slot) normally keeps it from ever firing (and, since every
frame sent pushes the check out, from even waking up); ``keepalive()`` does the same check on
demand.
"""
from __future__ import annotations

import asyncio
import logging
import math
import os
import random
import statistics
import struct
from collections import deque
from typing import Any

import serial

from .crc import crc16_modbus
from .stm32_protocol import (
    ACK_LEN,
    DEFAULT_BAUD,
    RPM_SCALE,
    Cmd,
    Flag,
    FrameParser,
    ProtocolError,
    Reply,
    Status,
    StopReason,
    decode_reply,
    exchange_time_s,
    speed_payload,
    watchdog_for,
    watchdog_payload,
)
from .ttyio import hung_up, open_exclusive, set_low_latency

log = logging.getLogger("hookwatch.stm32")

_TIMEOUT = object()
_CRC_BAD = object()
_LOST = object()

#: an ACK frame starts with these three bytes (start, LEN of its payload)
_ACK_HEAD = bytes((0xA5, 0x5A, ACK_LEN - 7))
_ACK_TYPE = int(Cmd.ACK)
_SET_SPEED = int(Cmd.SET_SPEED)
#: the status inside an ACK frame: after start (2), LEN, SEQ, type and the request's command
_ACK_STATUS = struct.Struct("<iiHBHH")
_ACK_STATUS_AT = 6
#: the keep-alive's wake-up is pushed out by a frame sent when it would come within this time
_KEEPALIVE_PUSH_S = 0.05
_flag_cache: dict[int, Flag] = {}
_reason_cache: dict[int, StopReason | int] = {}


def _flags(v: int) -> Flag:
    f = _flag_cache.get(v)
    if f is None:
        f = Flag(v)
        if len(_flag_cache) < 1024:
            _flag_cache[v] = f
    return f


def _flag_names(f: Flag) -> str:
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


def _frame(seq: int, cmd: int, payload: bytes) -> bytes:
    """encode_frame without its argument checks (the link's own commands are valid)."""
    body = bytes((len(payload), seq, cmd)) + payload
    c = crc16_modbus(body)
    return b"\xA5\x5A" + body + bytes((c & 0xFF, c >> 8))


def _set_none(fut: asyncio.Future) -> None:
    if not fut.done():
        fut.set_result(None)


def stop_reason_code(reason: str | int | StopReason = "") -> StopReason:
    """The station's stop reason text → the code sent with STOP."""
    if isinstance(reason, int):
        try:
            return StopReason(int(reason))
        except ValueError:
            return StopReason.COMMAND
    r = (reason or "").lower()
    if "protection" in r:
        return StopReason.PROTECTION
    if r == "completed":
        return StopReason.TEST_END
    if r.startswith("gateway"):
        return StopReason.GATEWAY
    return StopReason.COMMAND


class Stm32Link:
    def __init__(self, port: str, baud: int = DEFAULT_BAUD, timeout_s: float = 0.01,
                 retries: int = 1, watchdog_s: float = 0.2, *, budget_s: float = 0.018,
                 reopen_s: float = 0.5, keepalive: bool = True):
        self.port = port
        self.baud = int(baud)
        self.timeout_s = float(timeout_s)
        self.retries = max(0, int(retries))
        self.watchdog_s = float(watchdog_s)
        self.budget_s = max(float(budget_s), self.timeout_s)
        self.reopen_s = float(reopen_s)
        self.keepalive_enabled = keepalive
        self.connected = False
        self.counters: dict[str, int] = {
            "sent": 0, "acked": 0, "naks": 0, "timeouts": 0, "crc_errors": 0, "retries": 0,
            "port_lost": 0, "reopened": 0, "stale": 0, "bad_replies": 0, "keepalives": 0,
            "failed": 0, "drive_stops": 0}
        self.last_status: Status | None = None
        self.last_nak: Reply | None = None
        self.last_rtt_s: float = math.nan
        self.rtts: deque = deque(maxlen=1000)
        self._ser = None
        self._fd: int | None = None
        self._parser = FrameParser()
        self._seq = random.randrange(256)   # a restarted gateway does not repeat the last seq
        self._busy = False                   # an exchange holds the link
        self._turns: deque[asyncio.Future] = deque()   # callers waiting for the link, in order
        self._waiter: tuple[int, int, asyncio.Future] | None = None
        self._min_attempt: dict[int, float] = {}
        self._watching = False               # the port is on the event loop's reader list
        self._posted: tuple[int, float] | None = None    # (seq, time sent) of a posted SET_SPEED
        self._posted_reply: Reply | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task | None = None
        # the supervisor's nap: its future (resolved early by _poke), its timer and wake-up time
        self._nap: asyncio.Future | None = None
        self._nap_h: asyncio.TimerHandle | None = None
        self._nap_at = 0.0
        self._closed = False
        self._last_tx = 0.0
        self._was_enabled = False
        self._want_enabled = False
        self._open_error_logged = False
        self.low_latency = False             # the kernel took low-latency mode for the port

    @classmethod
    def from_config(cls, cfg, *, watchdog_s: float | None = None) -> Stm32Link:
        """``watchdog_s``: the period to set at enable (the station's, derived from its
        protection stop when ``stm32.watchdog_s`` is null); else the section's, else the one
        for the method's default protection stop (1 s + WATCHDOG_MARGIN_S)."""
        def get(name, default):
            v = getattr(cfg, name, None)
            return default if v is None else v
        if watchdog_s is None:
            watchdog_s = float(get("watchdog_s", watchdog_for(1.0)))
        return cls(cfg.port, baud=int(get("baud", DEFAULT_BAUD)),
                   timeout_s=float(get("timeout_s", 0.01)), retries=int(get("retries", 1)),
                   watchdog_s=watchdog_s,
                   budget_s=float(get("budget_s", 0.018)))

    # ------------------------------------------------------------------ port
    async def open(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._closed = False
        self._try_open()
        if self._task is None:
            self._task = self._loop.create_task(self._supervise(), name=f"stm32 {self.port}")

    def _try_open(self) -> bool:
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
        fd = self._fd = ser.fileno()
        os.set_blocking(fd, False)
        self._parser.reset()
        self._ev_loop().add_reader(fd, self._on_readable)
        self._watching = True
        self.connected = True
        log.info("stm32 %s: open at %d baud", self.port, self.baud)
        return True

    def _ev_loop(self) -> asyncio.AbstractEventLoop:
        """The loop open() bound (the port is only opened after it)."""
        if self._loop is None:
            raise RuntimeError(f"stm32 {self.port}: open() was not called")
        return self._loop

    def _release(self) -> None:
        self._posted = None
        self._watching = False
        if self._fd is not None and self._loop is not None:
            try:
                self._loop.remove_reader(self._fd)
            except Exception:
                pass
        self._fd = None
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:
                pass
        self._ser = None

    def _port_lost(self, why: Any) -> None:
        if not self.connected:
            return
        self.connected = False
        self.counters["port_lost"] += 1
        log.warning("stm32 %s: port lost (%s); reopening every %.1f s", self.port, why, self.reopen_s)
        self._release()
        self._resolve(_LOST)
        self._poke()

    async def close(self) -> None:
        self._closed = True
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):
                pass
            self._task = None
        self._resolve(_LOST)
        self._release()
        self.connected = False

    # ------------------------------------------------------------------ receive
    def _resolve(self, value) -> None:
        w = self._waiter
        if w is not None and not w[2].done():
            w[2].set_result(value)

    def _on_readable(self) -> None:
        if self._fd is None:    # released: the reader is removed with the fd
            return
        try:
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return
        except OSError as e:
            self._port_lost(e)
            return
        if not data:
            if hung_up(self._fd):    # else a stale readiness event: the bytes were read already
                self._port_lost("hang-up")
            return
        self._ingest(data)

    def _ingest(self, data: bytes) -> None:
        if not self._parser.pending:
            rep = fast_ack(data)        # the usual case: one whole ACK in one read
            if rep is not None:
                self._take(rep)
                return
        crc_before = self._parser.crc_errors
        self._deliver(self._parser.feed(data))
        if self._parser.crc_errors != crc_before:
            self.counters["crc_errors"] += self._parser.crc_errors - crc_before
            self._resolve(_CRC_BAD)    # the reply we wait for was probably damaged: retry now

    def _deliver(self, frames) -> None:
        for fr in frames:
            try:
                rep = decode_reply(fr)
            except ProtocolError as e:
                self.counters["bad_replies"] += 1
                log.debug("stm32 %s: %s", self.port, e)
                continue
            self._take(rep)

    def _take(self, rep: Reply) -> None:
        w = self._waiter
        if w is not None and rep.seq == w[0] and rep.request == w[1] and not w[2].done():
            w[2].set_result(rep)
            return
        p = self._posted
        if p is not None and rep.seq == p[0] and rep.request == _SET_SPEED and self._posted_reply is None:
            self._posted_reply = rep
            return
        self.counters["stale"] += 1     # a late reply to an exchange that timed out

    # ------------------------------------------------------------------ posted speed commands
    def post_speed(self, rpm: float) -> bool:
        """SET_SPEED without waiting for the ACK (see the module doc); never blocks, never
        raises. False (not sent) while another exchange holds the link, the port is gone, the
        speed is not a finite number or the write would block."""
        loop, fd = self._loop, self._fd
        if not self.connected or self._busy or fd is None or loop is None:
            return False
        payload = self._speed_payload(rpm)
        if payload is None:
            return False
        if self._posted is not None:
            self.collect()
            if self._fd is None:
                return False
        if self._watching:
            try:
                loop.remove_reader(fd)
            except Exception:   # a closed loop: nothing to watch anyway
                pass
            self._watching = False
        if self._parser.pending:
            self._deliver(self._parser.flush())    # the line was idle: no partial frame is real
        seq = self._next_seq()
        try:
            os.write(fd, _frame(seq, _SET_SPEED, payload))
        except BlockingIOError:
            self.counters["failed"] += 1
            return False
        except OSError as e:
            self._port_lost(e)
            return False
        now = self._last_tx = loop.time()
        self.counters["sent"] += 1
        self._posted = (seq, now)
        self._posted_reply = None
        if self._nap_h is not None and self._nap_at - now < _KEEPALIVE_PUSH_S:
            self._push_nap(now + self.keepalive_interval_s)
        return True

    def collect(self) -> Status | None:
        """The status from the ACK of the command :meth:`post_speed` sent, read from the port
        without waiting; None if nothing is posted or no valid ACK has come (counted)."""
        p = self._posted
        if p is None:
            return None
        fd = self._fd
        while fd is not None and self._posted_reply is None:
            try:
                data = os.read(fd, 4096)
            except BlockingIOError:
                break
            except OSError as e:
                self._port_lost(e)
                return None
            if not data:        # VMIN 0: nothing there (a hang-up shows as an error)
                break
            self._ingest(data)
            fd = self._fd
        rep, self._posted, self._posted_reply = self._posted_reply, None, None
        if rep is None:
            self.counters["timeouts"] += 1
            self.counters["failed"] += 1
            return None
        if not rep.ok:
            self.counters["naks"] += 1
            self.last_nak = rep
            log.warning("stm32 %s: SET_SPEED refused: %s", self.port, getattr(rep.error, "name", rep.error))
            return None
        self.counters["acked"] += 1
        return self._accept_status(rep.status)

    def _watch(self) -> None:
        """Before an awaited exchange: a posted command collected, the port watched again."""
        if self._posted is not None:
            self.collect()
        if not self._watching and self._fd is not None and self._loop is not None:
            self._loop.add_reader(self._fd, self._on_readable)
            self._watching = True

    # ------------------------------------------------------------------ exchange
    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    async def _wait_turn(self) -> None:
        """Wait until the exchange in progress (and those queued before us) are done; the link
        is then handed to us (``_busy`` stays set)."""
        fut = self._ev_loop().create_future()
        self._turns.append(fut)
        try:
            await fut
        except asyncio.CancelledError:
            if fut.done() and not fut.cancelled():
                self._hand_on()          # handed the link, then cancelled: pass it on
            raise

    def _hand_on(self) -> None:
        """The exchange is done: the link to the next caller waiting, or free."""
        turns = self._turns
        while turns:
            f = turns.popleft()
            if not f.done():
                f.set_result(None)
                return
        self._busy = False

    async def _exchange(self, cmd: Cmd, payload: bytes = b"") -> Reply | None:
        loop = self._loop
        if not self.connected or loop is None:
            return None
        if self._busy:
            await self._wait_turn()
        else:
            self._busy = True
        try:
            if not self.connected:
                return None
            if not self._watching:
                self._watch()
                if self._fd is None:
                    return None
            t0 = loop.time()
            deadline = t0 + self.budget_s
            c = int(cmd)
            min_attempt = self._min_attempt.get(c)
            if min_attempt is None:
                min_attempt = self._min_attempt[c] = exchange_time_s(cmd, self.baud) + 0.001
            if self._parser.pending:
                self._deliver(self._parser.flush())    # the line was idle: no partial frame is real
            seq = self._next_seq()
            frame = _frame(seq, c, payload)
            attempt = 0
            try:
                while True:
                    fut = loop.create_future()
                    self._waiter = (seq, c, fut)
                    if self._fd is None:     # released while we waited for our turn
                        return None
                    try:
                        os.write(self._fd, frame)
                    except BlockingIOError:
                        fut.set_result(_TIMEOUT)
                    except OSError as e:
                        self._port_lost(e)
                        return None
                    now = self._last_tx = loop.time()
                    self.counters["sent"] += 1
                    if self._nap_h is not None and self._nap_at - now < _KEEPALIVE_PUSH_S:
                        self._push_nap(now + self.keepalive_interval_s)
                    wait = min(self.timeout_s, deadline - now)
                    h = loop.call_at(now + (wait if wait > 0.0 else 0.0), self._timeout_flush, fut)
                    try:
                        res = await fut
                    finally:
                        h.cancel()
                    if res is _LOST:
                        return None
                    if isinstance(res, Reply):
                        self.last_rtt_s = loop.time() - t0
                        self.rtts.append(self.last_rtt_s)
                        if res.ok:
                            self.counters["acked"] += 1
                            self.last_status = res.status
                            return res
                        self.counters["naks"] += 1
                        self.last_nak = res
                        log.warning("stm32 %s: %s refused: %s", self.port, cmd.name,
                                    getattr(res.error, "name", res.error))
                        return res
                    if res is _TIMEOUT:
                        self.counters["timeouts"] += 1
                    attempt += 1
                    if attempt > self.retries or deadline - loop.time() < min_attempt:
                        self.counters["failed"] += 1
                        return None
                    self.counters["retries"] += 1
            finally:
                self._waiter = None
        finally:
            self._hand_on()

    def _timeout_flush(self, fut: asyncio.Future) -> None:
        if fut.done():
            return
        # an idle gap: give up on partial frames, maybe the reply is hidden behind a false start
        self._deliver(self._parser.flush())
        if not fut.done():
            fut.set_result(_TIMEOUT)

    async def _status(self, cmd: Cmd, payload: bytes = b"", attempts: int = 1) -> Status | None:
        """The status from the ACK, or None. ``attempts`` > 1 repeats the call (a new SEQ each
        time) when it got no answer at all — for ENABLE and STOP, whose effect matters."""
        for _ in range(max(1, attempts)):
            try:
                rep = await self._exchange(cmd, payload)
            except Exception:   # never raise into the station
                log.exception("stm32 %s: %s failed", self.port, cmd.name)
                return None
            if rep is not None:
                break
            if not self.connected:
                return None
        if rep is None or not rep.ok or rep.status is None:    # an ACK always carries a status
            return None
        return self._accept_status(rep.status)

    def _accept_status(self, st: Status | None) -> Status | None:
        if st is None:
            return None
        self.last_status = st
        if st.enabled != self._was_enabled:
            self._poke()            # the keep-alive starts or stops
            if self._was_enabled and self._want_enabled:
                # stopped by the firmware, not asked for: say why (the tension falls next)
                self.counters["drive_stops"] += 1
                why = getattr(st.stop_reason, "name", st.stop_reason)
                log.warning("stm32 %s: the drive stopped on its own: %s (flags %s; %d such stops)",
                            self.port, why, _flag_names(st.flags), self.counters["drive_stops"])
        self._was_enabled = st.enabled
        return st

    # ------------------------------------------------------------------ API
    async def enable(self) -> Status | None:
        """Set the firmware watchdog to the configured period (unless it already has it), then
        ENABLE (speed command 0). Up to 3 calls if there is no answer at all."""
        self._want_enabled = True
        want = int(round(self.watchdog_s * 1000))
        st = self.last_status
        if st is None or st.watchdog_ms != want:
            await self._status(Cmd.SET_WATCHDOG, watchdog_payload(self.watchdog_s), attempts=2)
        st = await self._status(Cmd.ENABLE, attempts=3)
        if st is not None and st.watchdog_ms != want:
            # the SET_WATCHDOG before went unanswered (or the firmware restarted since): the
            # drive now runs on the firmware's period, so set ours (allowed while enabled)
            st = await self._status(Cmd.SET_WATCHDOG, watchdog_payload(self.watchdog_s),
                                    attempts=2) or st
        return st

    async def disable(self) -> Status | None:
        self._want_enabled = False          # no keep-alive from now on, whatever the answer
        return await self._status(Cmd.DISABLE, attempts=3)

    def _speed_payload(self, rpm: float) -> bytes | None:
        try:
            return speed_payload(float(rpm))
        except (TypeError, ValueError):
            self.counters["failed"] += 1
            log.warning("stm32 %s: set_speed(%r) not sent: not a finite number", self.port, rpm)
            return None

    async def set_speed(self, rpm: float) -> Status | None:
        payload = self._speed_payload(rpm)
        if payload is None:
            return None
        return await self._status(Cmd.SET_SPEED, payload)

    async def stop(self, reason: str | int = "") -> Status | None:
        """STOP with the reason code (up to 3 calls if unanswered). The keep-alive ends at once,
        so even a STOP that never arrives stops the motor by the firmware watchdog."""
        self._want_enabled = False
        return await self._status(Cmd.STOP, bytes((int(stop_reason_code(reason)),)), attempts=3)

    async def read_status(self) -> Status | None:
        return await self._status(Cmd.READ_STATUS)

    async def ping(self) -> Status | None:
        return await self._status(Cmd.PING)

    async def set_watchdog(self, seconds: float) -> Status | None:
        return await self._status(Cmd.SET_WATCHDOG, watchdog_payload(seconds))

    # ------------------------------------------------------------------ keep-alive, reopen
    @property
    def keepalive_interval_s(self) -> float:
        wd = self.watchdog_s
        st = self.last_status
        if st is not None and st.watchdog_ms > 0:
            wd = min(wd, st.watchdog_ms / 1000.0)
        return wd / 2.0

    @property
    def armed(self) -> bool:
        """Keep-alive wanted: enable() was called (no stop()/disable() since) and the firmware
        last reported the drive enabled."""
        return (self._want_enabled and self.connected and self.last_status is not None
                and self.last_status.enabled)

    async def keepalive(self) -> Status | None:
        """PING if the firmware is enabled and nothing went out for half the watchdog period."""
        if not self.armed or self._loop is None:
            return None
        if self._loop.time() - self._last_tx < self.keepalive_interval_s or self._busy:
            return None     # recent traffic (or an exchange in progress) feeds the watchdog
        self.counters["keepalives"] += 1
        return await self._status(Cmd.PING)

    async def _supervise(self) -> None:
        loop = self._loop       # started by open(), which sets it
        if loop is None:
            return
        while not self._closed:
            try:
                if not self.connected:
                    await asyncio.sleep(self.reopen_s)
                    if not self._closed and self._try_open():
                        self.counters["reopened"] += 1
                        log.info("stm32 %s: port back", self.port)
                        await self._status(Cmd.READ_STATUS)
                    continue
                if self.keepalive_enabled and self.armed:
                    due = self._last_tx + self.keepalive_interval_s
                    if loop.time() >= due:
                        await self.keepalive()
                        due = self._last_tx + self.keepalive_interval_s
                    delay = min(max(0.002, due - loop.time()), 0.5)
                else:
                    delay = 0.5
                await self._nap_for(loop, delay)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("stm32 %s: supervisor", self.port)
                await asyncio.sleep(self.reopen_s)

    async def _nap_for(self, loop: asyncio.AbstractEventLoop, delay: float) -> None:
        """The supervisor's wait: ``delay`` s, or until :meth:`_poke`; a frame sent meanwhile
        may push the wake-up out (:meth:`_push_nap`), so steady traffic never wakes it."""
        fut = self._nap = loop.create_future()
        self._nap_at = loop.time() + delay
        self._nap_h = loop.call_at(self._nap_at, _set_none, fut)
        try:
            await fut
        finally:
            if self._nap_h is not None:
                self._nap_h.cancel()
            self._nap = self._nap_h = None

    def _push_nap(self, at: float) -> None:
        fut, loop = self._nap, self._loop
        if fut is None or fut.done() or loop is None or self._nap_h is None:
            return
        self._nap_h.cancel()
        self._nap_at = at
        self._nap_h = loop.call_at(at, _set_none, fut)

    def _poke(self) -> None:
        """Wake the supervisor now (port lost, the firmware's enabled state changed). A poke
        while it is not napping is not needed: it re-reads the state before every nap."""
        fut = self._nap
        if fut is not None and not fut.done():
            fut.set_result(None)

    # ------------------------------------------------------------------ figures
    def rtt_summary(self) -> dict[str, float]:
        r = sorted(self.rtts)
        if not r:
            return {"n": 0}
        return {"n": len(r), "median_ms": statistics.median(r) * 1e3,
                "p90_ms": r[int(0.9 * (len(r) - 1))] * 1e3, "max_ms": r[-1] * 1e3}
