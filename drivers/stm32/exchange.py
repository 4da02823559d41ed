"""The STM32 link's exchanges (the middle of its three layers: the transaction manager over
:class:`~drivers.stm32.wire.Stm32Wire`; docs/protocols/stm32.md).

One exchange at a time (a busy flag; a concurrent caller waits its turn in FIFO order): a fresh
sequence number per command, a reply timeout ``timeout_s``, ``retries`` with the *same* sequence
number (the firmware answers a duplicate again without acting twice) as long as they fit in the
call's budget ``budget_s`` (just under one 20 ms slot). The uncontended exchange takes no lock
object (issue 16, ``bench/bench_slot_cpu.py``).

Posted speed commands (the station's per-slot SET_SPEED): :meth:`Exchanges.post_speed` writes the
frame and returns at once; the port is taken off the event loop's watch list meanwhile, so the
ACK arriving ~3 ms later does not wake the process; :meth:`Exchanges.collect` (called in the next
slot, when the process is awake anyway) reads it from the port without waiting. A missing ACK is
counted (``timeouts`` and ``failed``), a NAK as ``naks``; no retry — the next slot's command is
the retry. Any awaited exchange first collects a posted command and watches the port again.
"""
from __future__ import annotations

import asyncio
import logging
import math
import random
from collections import deque
from collections.abc import Callable

from .protocol import Cmd, Reply, Status, exchange_time_s
from .wire import Stm32Wire, frame

log = logging.getLogger("hookwatch.stm32")

_TIMEOUT = object()
_CRC_BAD = object()
_LOST = object()
_SET_SPEED = int(Cmd.SET_SPEED)


class Exchanges:
    """Requests and their replies over one wire: matching by sequence number and command,
    timeouts, retries, the turn order of concurrent callers, posted SET_SPEEDs.

    ``accept``: where the status of a collected posted command goes (the link's drive state);
    ``sent``: told the loop time of every frame written (the keep-alive's clock)."""

    def __init__(self, wire: Stm32Wire, counters: dict[str, int], *, timeout_s: float,
                 retries: int, budget_s: float, accept: Callable[[Status | None], Status | None],
                 sent: Callable[[float], None]) -> None:
        self.wire = wire
        self.counters = counters
        self.timeout_s = timeout_s
        self.retries = retries
        self.budget_s = budget_s
        self._accept = accept
        self._sent = sent
        self.last_nak: Reply | None = None
        self.last_rtt_s: float = math.nan
        self.rtts: deque[float] = deque(maxlen=1000)
        self.busy = False                    # an exchange holds the link
        self._seq = random.randrange(256)   # a restarted gateway does not repeat the last seq
        self._turns: deque[asyncio.Future[None]] = deque()   # callers waiting for the link, in order
        self._waiter: tuple[int, int, asyncio.Future[object]] | None = None
        self._min_attempt: dict[int, float] = {}
        self._posted: tuple[int, float] | None = None    # (seq, time sent) of a posted SET_SPEED
        self._posted_reply: Reply | None = None
        self._loop: asyncio.AbstractEventLoop | None = None

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop

    # ------------------------------------------------------------------ what the wire delivers
    def take(self, rep: Reply) -> None:
        w = self._waiter
        if w is not None and rep.seq == w[0] and rep.request == w[1] and not w[2].done():
            w[2].set_result(rep)
            return
        p = self._posted
        if p is not None and rep.seq == p[0] and rep.request == _SET_SPEED and self._posted_reply is None:
            self._posted_reply = rep
            return
        self.counters["stale"] += 1     # a late reply to an exchange that timed out

    def damaged(self) -> None:
        self._resolve(_CRC_BAD)

    def abort(self) -> None:
        """The port is gone (or closed): the exchange in progress ends, nothing stays posted."""
        self._posted = None
        self._resolve(_LOST)

    def _resolve(self, value: object) -> None:
        w = self._waiter
        if w is not None and not w[2].done():
            w[2].set_result(value)

    # ------------------------------------------------------------------ posted speed commands
    def post_speed(self, payload: bytes) -> bool:
        """SET_SPEED without waiting for the ACK; never blocks, never raises. False (not sent)
        while another exchange holds the link, the port is gone or the write would block."""
        loop, wire = self._loop, self.wire
        if not wire.connected or self.busy or wire.fd is None or loop is None:
            return False
        if self._posted is not None:
            self.collect()
            if wire.fd is None:
                return False
        wire.unwatch()
        wire.flush(idle=True)
        seq = self._next_seq()
        done = wire.write(frame(seq, _SET_SPEED, payload))
        if not done:
            if done is False:
                self.counters["failed"] += 1
            return False
        now = loop.time()
        self.counters["sent"] += 1
        self._posted = (seq, now)
        self._posted_reply = None
        self._sent(now)
        return True

    def collect(self) -> Status | None:
        """The status from the ACK of the posted command, read from the port without waiting;
        None if nothing is posted or no valid ACK has come (counted)."""
        if self._posted is None:
            return None
        while self._posted_reply is None:
            got = self.wire.read_now()
            if got is None:
                return None             # the port is gone (counted as lost)
            if not got:
                break
        rep, self._posted, self._posted_reply = self._posted_reply, None, None
        if rep is None:
            self.counters["timeouts"] += 1
            self.counters["failed"] += 1
            return None
        if not rep.ok:
            self.counters["naks"] += 1
            self.last_nak = rep
            log.warning("stm32 %s: SET_SPEED refused: %s", self.wire.port, getattr(rep.error, "name", rep.error))
            return None
        self.counters["acked"] += 1
        return self._accept(rep.status)

    def _watch(self) -> None:
        """Before an awaited exchange: a posted command collected, the port watched again."""
        if self._posted is not None:
            self.collect()
        self.wire.watch()

    # ------------------------------------------------------------------ exchange
    def _next_seq(self) -> int:
        self._seq = (self._seq + 1) & 0xFF
        return self._seq

    async def _wait_turn(self, loop: asyncio.AbstractEventLoop) -> None:
        """Wait until the exchange in progress (and those queued before us) are done; the link
        is then handed to us (``busy`` stays set)."""
        fut: asyncio.Future[None] = loop.create_future()
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
        self.busy = False

    async def exchange(self, cmd: Cmd, payload: bytes = b"") -> Reply | None:
        """One request and its reply (an ACK or a NAK), or None: no valid reply within the
        budget (counted), or the port is gone."""
        loop, wire = self._loop, self.wire
        if not wire.connected or loop is None:
            return None
        if self.busy:
            await self._wait_turn(loop)
        else:
            self.busy = True
        try:
            if not wire.connected:
                return None
            if not wire.watching:
                self._watch()
                if wire.fd is None:
                    return None
            return await self._attempts(loop, cmd, payload)
        finally:
            self._hand_on()

    async def _attempts(self, loop: asyncio.AbstractEventLoop, cmd: Cmd, payload: bytes) -> Reply | None:
        t0 = loop.time()
        deadline = t0 + self.budget_s
        c = int(cmd)
        min_attempt = self._min_attempt.get(c)
        if min_attempt is None:
            min_attempt = self._min_attempt[c] = exchange_time_s(cmd, self.wire.baud) + 0.001
        self.wire.flush(idle=True)
        seq = self._next_seq()
        data = frame(seq, c, payload)
        attempt = 0
        try:
            while True:
                fut: asyncio.Future[object] = loop.create_future()
                self._waiter = (seq, c, fut)
                done = self.wire.write(data)     # None: released while we waited, or lost now
                if done is None:
                    return None
                if not done:
                    fut.set_result(_TIMEOUT)
                now = loop.time()
                self.counters["sent"] += 1
                self._sent(now)
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
                        return res
                    self.counters["naks"] += 1
                    self.last_nak = res
                    log.warning("stm32 %s: %s refused: %s", self.wire.port, cmd.name,
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

    def _timeout_flush(self, fut: asyncio.Future[object]) -> None:
        if fut.done():
            return
        # an idle gap: give up on partial frames, maybe the reply is hidden behind a false start
        self.wire.flush()
        if not fut.done():
            fut.set_result(_TIMEOUT)
