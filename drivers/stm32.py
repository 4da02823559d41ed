"""Gateway side of the STM32 link (docs/protocols/stm32.md): an asyncio client that never blocks
the event loop and never raises.

The port is opened with pyserial (settings, exclusive lock) and then served non-blocking: the
loop's ``add_reader`` feeds a streaming :class:`FrameParser`, requests are written with
``os.write`` (a UART's kernel buffer takes a 11-byte frame at once). One exchange at a time (an
asyncio lock): a fresh sequence number per command, a reply timeout ``timeout_s``, ``retries``
with the *same* sequence number (the firmware answers a duplicate again without acting twice) as
long as they fit in the call's budget ``budget_s`` (just under one 20 ms slot).

A vanished port (read/write error, hang-up) sets ``connected = False``; calls then return None at
once, and a background task reopens the port every ``reopen_s`` (0.5 s).

Keep-alive: the same background task guarantees the firmware watchdog never trips in normal
operation. While the firmware reports ``enabled`` it sends a PING whenever no frame went out for
half the watchdog period (the smaller of the configured and the firmware-reported one). The
station's own traffic (SET_SPEED every slot) normally keeps it from ever firing;
``keepalive()`` does the same check on demand.
"""
from __future__ import annotations

import asyncio
import logging
import math
import os
import random
import statistics
from collections import deque
from typing import Any

from .stm32_protocol import (
    DEFAULT_BAUD,
    Cmd,
    FrameParser,
    ProtocolError,
    Reply,
    Status,
    StopReason,
    decode_reply,
    encode_frame,
    exchange_time_s,
    speed_payload,
    watchdog_payload,
)

log = logging.getLogger("hookwatch.stm32")

_TIMEOUT = object()
_CRC_BAD = object()
_LOST = object()


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
            "failed": 0}
        self.last_status: Status | None = None
        self.last_nak: Reply | None = None
        self.last_rtt_s: float = math.nan
        self.rtts: deque = deque(maxlen=1000)
        self._ser = None
        self._fd: int | None = None
        self._parser = FrameParser()
        self._seq = random.randrange(256)   # a restarted gateway does not repeat the last seq
        self._lock: asyncio.Lock | None = None
        self._waiter: tuple[int, int, asyncio.Future] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task | None = None
        self._wake: asyncio.Event | None = None
        self._closed = False
        self._last_tx = 0.0
        self._was_enabled = False
        self._want_enabled = False
        self._open_error_logged = False

    @classmethod
    def from_config(cls, cfg) -> Stm32Link:
        def get(name, default):
            v = getattr(cfg, name, None)
            return default if v is None else v
        return cls(cfg.port, baud=int(get("baud", DEFAULT_BAUD)),
                   timeout_s=float(get("timeout_s", 0.01)), retries=int(get("retries", 1)),
                   watchdog_s=float(get("watchdog_s", 0.2)),
                   budget_s=float(get("budget_s", 0.018)))

    # ------------------------------------------------------------------ port
    async def open(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._lock = asyncio.Lock()
        self._wake = asyncio.Event()
        self._closed = False
        self._try_open()
        if self._task is None:
            self._task = self._loop.create_task(self._supervise(), name=f"stm32 {self.port}")

    def _try_open(self) -> bool:
        import serial

        try:
            # serial_for_url: a device path as serial.Serial, or a pyserial URL (hwloop:// in tests)
            ser = serial.serial_for_url(self.port, self.baud, bytesize=8, parity="N", stopbits=1,
                                        timeout=0, write_timeout=0, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as e:
            if not self._open_error_logged:
                log.warning("stm32 %s: cannot open (%s); retrying every %.1f s", self.port, e,
                            self.reopen_s)
                self._open_error_logged = True
            return False
        self._open_error_logged = False
        self._ser = ser
        fd = self._fd = ser.fileno()
        os.set_blocking(fd, False)
        self._parser.reset()
        self._ev_loop().add_reader(fd, self._on_readable)
        self.connected = True
        log.info("stm32 %s: open at %d baud", self.port, self.baud)
        return True

    def _ev_loop(self) -> asyncio.AbstractEventLoop:
        """The loop open() bound (the port is only opened after it)."""
        if self._loop is None:
            raise RuntimeError(f"stm32 {self.port}: open() was not called")
        return self._loop

    def _release(self) -> None:
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
        if self._wake is not None:
            self._wake.set()

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
            self._port_lost("hang-up")
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
            w = self._waiter
            if w is not None and rep.seq == w[0] and rep.request == w[1] and not w[2].done():
                w[2].set_result(rep)
            else:
                self.counters["stale"] += 1     # a late reply to an exchange that timed out

    # ------------------------------------------------------------------ exchange
    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    async def _exchange(self, cmd: Cmd, payload: bytes = b"") -> Reply | None:
        loop = self._loop
        if not self.connected or self._lock is None or loop is None:
            return None
        async with self._lock:
            if not self.connected:
                return None
            t0 = loop.time()
            deadline = t0 + self.budget_s
            min_attempt = exchange_time_s(cmd, self.baud) + 0.001
            self._deliver(self._parser.flush())    # the line was idle: no partial frame is real
            seq = self._next_seq()
            frame = encode_frame(seq, cmd, payload)
            attempt = 0
            try:
                while True:
                    fut = loop.create_future()
                    self._waiter = (seq, int(cmd), fut)
                    if self._fd is None:     # released while the lock was awaited
                        return None
                    try:
                        os.write(self._fd, frame)
                    except BlockingIOError:
                        fut.set_result(_TIMEOUT)
                    except OSError as e:
                        self._port_lost(e)
                        return None
                    self._last_tx = loop.time()
                    self.counters["sent"] += 1
                    wait = max(0.0, min(self.timeout_s, deadline - loop.time()))
                    h = loop.call_later(wait, self._timeout_flush, fut)
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
        if self._wake is not None and rep.status.enabled != self._was_enabled:
            self._wake.set()        # the keep-alive starts or stops
        self._was_enabled = rep.status.enabled
        return rep.status

    # ------------------------------------------------------------------ API
    async def enable(self) -> Status | None:
        """Set the firmware watchdog to the configured period (unless it already has it), then
        ENABLE (speed command 0). Up to 3 calls if there is no answer at all."""
        self._want_enabled = True
        st = self.last_status
        if st is None or st.watchdog_ms != int(round(self.watchdog_s * 1000)):
            await self._status(Cmd.SET_WATCHDOG, watchdog_payload(self.watchdog_s), attempts=2)
        return await self._status(Cmd.ENABLE, attempts=3)

    async def disable(self) -> Status | None:
        self._want_enabled = False          # no keep-alive from now on, whatever the answer
        return await self._status(Cmd.DISABLE, attempts=3)

    async def set_speed(self, rpm: float) -> Status | None:
        try:
            payload = speed_payload(float(rpm))
        except (TypeError, ValueError):
            self.counters["failed"] += 1
            log.warning("stm32 %s: set_speed(%r) not sent: not a finite number", self.port, rpm)
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
        if not self.armed or self._loop is None or self._lock is None:
            return None
        if self._loop.time() - self._last_tx < self.keepalive_interval_s or self._lock.locked():
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
                wake = self._wake     # set by open() (a second open() replaces it)
                if wake is None:
                    return
                wake.clear()
                try:
                    await asyncio.wait_for(wake.wait(), delay)
                except TimeoutError:
                    pass
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("stm32 %s: supervisor", self.port)
                await asyncio.sleep(self.reopen_s)

    # ------------------------------------------------------------------ figures
    def rtt_summary(self) -> dict[str, float]:
        r = sorted(self.rtts)
        if not r:
            return {"n": 0}
        return {"n": len(r), "median_ms": statistics.median(r) * 1e3,
                "p90_ms": r[int(0.9 * (len(r) - 1))] * 1e3, "max_ms": r[-1] * 1e3}
