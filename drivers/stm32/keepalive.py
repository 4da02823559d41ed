"""The STM32 link's state over time (the top of its three layers; docs/protocols/stm32.md): one
background task that reopens a lost port every ``reopen_s`` and feeds the firmware watchdog, and
the drive's enabled state it follows.

Keep-alive: the firmware watchdog never trips in normal operation. While the firmware reports
``enabled`` (and the gateway asked for it: ``enable()``, no ``stop()``/``disable()`` since) a PING
goes out whenever no frame went out for half the watchdog period (the smaller of the configured
and the firmware-reported one). The station's own traffic (SET_SPEED every slot) normally keeps it
from ever firing, and, since every frame sent pushes the task's wake-up out (:meth:`sent`), from
even waking up; :meth:`KeepAlive.keepalive` does the same check on demand. A drive that stops on
its own while the gateway wants it enabled (the firmware watchdog, a fault) is counted
(``drive_stops``) and said — and so is one the gateway's own STOP only found (a stall of the
gateway longer than the watchdog: the firmware stopped the drive first and its status still says
WATCHDOG when the STOP's answer comes). The time between two frames the gateway sent is measured
on the link's clock; the longest since the drive was enabled goes with the stop
(:class:`gateway.core.ports.DriveStop`, its sentence), for the station to say why its test ended.
"""
from __future__ import annotations

import asyncio
import logging
from typing import Protocol

from gateway.core.ports import DriveStop

from .protocol import Status, StopReason
from .wire import flag_names

log = logging.getLogger("hookwatch.stm32")

#: the keep-alive's wake-up is pushed out by a frame sent when it would come within this time
_KEEPALIVE_PUSH_S = 0.05
#: the firmware's own stops: never the answer to a command of the gateway
OWN_STOPS = frozenset({StopReason.WATCHDOG, StopReason.STALL, StopReason.OVERSPEED})


def _set_none(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


class KeptLink(Protocol):
    """What the keep-alive needs of the link (``drivers.stm32.driver.Stm32Link``)."""
    port: str
    watchdog_s: float
    reopen_s: float
    keepalive_enabled: bool
    counters: dict[str, int]
    last_status: Status | None

    @property
    def connected(self) -> bool: ...
    @property
    def busy(self) -> bool: ...
    def reopen(self) -> bool: ...
    async def ping(self) -> Status | None: ...
    async def read_status(self) -> Status | None: ...


class KeepAlive:
    """The reopen and keep-alive task of one link, and the drive's enabled state."""

    def __init__(self, link: KeptLink) -> None:
        self.link = link
        self.want_enabled = False            # enable() called, no stop()/disable() since
        self.last_tx = 0.0                   # loop time of the latest frame written
        #: the longest time between two frames written since the drive was last seen enabled
        self.longest_gap_s = 0.0
        #: the newest stop of the drive on its own, until the station takes it
        self.drive_stop: DriveStop | None = None
        self._was_enabled = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._closed = False
        # the task's nap: its future (resolved early by poke), its timer and wake-up time
        self._nap: asyncio.Future[None] | None = None
        self._nap_h: asyncio.TimerHandle | None = None
        self._nap_at = 0.0

    @property
    def interval_s(self) -> float:
        wd = self.link.watchdog_s
        st = self.link.last_status
        if st is not None and st.watchdog_ms > 0:
            wd = min(wd, st.watchdog_ms / 1000.0)
        return wd / 2.0

    @property
    def armed(self) -> bool:
        """Keep-alive wanted: enable() was called (no stop()/disable() since) and the firmware
        last reported the drive enabled."""
        st = self.link.last_status
        return self.want_enabled and self.link.connected and st is not None and st.enabled

    def accept(self, st: Status) -> None:
        """A status the firmware reported: the keep-alive starts or stops with the drive; a stop
        the gateway did not ask for — or one the firmware made before the gateway's own STOP
        came (its reason is its own: WATCHDOG, STALL, OVERSPEED) — is counted and said (the
        tension falls next), and kept for the station (:attr:`drive_stop`)."""
        if st.enabled != self._was_enabled:
            self.poke()
            if st.enabled:
                self.longest_gap_s = 0.0         # a new run of the drive: its own silences
            elif self.want_enabled or st.stop_reason in OWN_STOPS:
                self._stopped_on_its_own(st)
        self._was_enabled = st.enabled

    def _stopped_on_its_own(self, st: Status) -> None:
        link = self.link
        link.counters["drive_stops"] += 1
        why = str(getattr(st.stop_reason, "name", st.stop_reason))
        wd = st.watchdog_ms / 1000.0 if st.watchdog_ms > 0 else link.watchdog_s
        self.drive_stop = ds = DriveStop(why, flag_names(st.flags), wd,
                                         self.longest_gap_s if self.longest_gap_s > 0 else None)
        log.warning("stm32 %s: %s (stop reason %s, flags %s; %d such stops)", link.port,
                    ds.words(), why, ds.flags, link.counters["drive_stops"])

    def sent(self, now: float) -> None:
        """A frame went out at loop time ``now``: it feeds the watchdog, so the wake-up moves;
        while the drive runs, the time since the frame before is measured (its longest)."""
        if self._was_enabled and self.last_tx > 0 and now - self.last_tx > self.longest_gap_s:
            self.longest_gap_s = now - self.last_tx
        self.last_tx = now
        if self._nap_h is not None and self._nap_at - now < _KEEPALIVE_PUSH_S:
            self._push_nap(now + self.interval_s)

    async def keepalive(self) -> Status | None:
        """PING if the firmware is enabled and nothing went out for half the watchdog period."""
        if not self.armed or self._loop is None:
            return None
        if self._loop.time() - self.last_tx < self.interval_s or self.link.busy:
            return None     # recent traffic (or an exchange in progress) feeds the watchdog
        self.link.counters["keepalives"] += 1
        return await self.link.ping()

    # ------------------------------------------------------------------ the task
    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._closed = False
        if self._task is None:
            self._task = loop.create_task(self._run(loop), name=f"stm32 {self.link.port}")

    async def stop(self) -> None:
        self._closed = True
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except (asyncio.CancelledError, Exception):
                pass
            self._task = None

    async def _run(self, loop: asyncio.AbstractEventLoop) -> None:
        link = self.link
        while not self._closed:
            try:
                if not link.connected:
                    await asyncio.sleep(link.reopen_s)
                    if not self._closed and link.reopen():
                        link.counters["reopened"] += 1
                        log.info("stm32 %s: port back", link.port)
                        await link.read_status()
                    continue
                if link.keepalive_enabled and self.armed:
                    due = self.last_tx + self.interval_s
                    if loop.time() >= due:
                        await self.keepalive()
                        due = self.last_tx + self.interval_s
                    delay = min(max(0.002, due - loop.time()), 0.5)
                else:
                    delay = 0.5
                await self._nap_for(loop, delay)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("stm32 %s: supervisor", link.port)
                await asyncio.sleep(link.reopen_s)

    async def _nap_for(self, loop: asyncio.AbstractEventLoop, delay: float) -> None:
        """The task's wait: ``delay`` s, or until :meth:`poke`; a frame sent meanwhile may push
        the wake-up out (:meth:`sent`), so steady traffic never wakes it."""
        fut: asyncio.Future[None] = loop.create_future()
        self._nap = fut
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

    def poke(self) -> None:
        """Wake the task now (port lost, the firmware's enabled state changed). A poke while it
        is not napping is not needed: it re-reads the state before every nap."""
        fut = self._nap
        if fut is not None and not fut.done():
            fut.set_result(None)
