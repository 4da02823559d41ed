"""The station's side of its STM32 port: how the per-slot speed command reaches the take-up.

An STM32 port that can post the command (:class:`~gateway.core.ports.Stm32PostingPort`, the real
driver) gets it written at once, and its reply is collected after the next slot's poll, when the
process is awake anyway (no wake-up of its own). Any other :class:`~gateway.core.ports.Stm32Port`
gets it through one sender task and a one-slot "latest value" box (:class:`LatestValue`). Either
way the slot loop never waits for the STM32, and a command that cannot go out (the link busy with
another exchange, or replaced in the box by a newer one: never queued) is reported to the caller,
which counts it (``SlotStats.stm32_busy_skips``). The same sender reads the STM32's status while
the take-up is off (idle, before the zero check). A driver that raises never reaches the slot
loop: the call is logged and counts as "no reply".
"""
from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Coroutine
from typing import Any

from ..core.ports import DriveStop, Stm32DriveStops, Stm32Port, Stm32PostingPort, Stm32Status

__all__ = ["LatestValue", "Stm32Drive"]

log = logging.getLogger("hookwatch.station")

#: the job "read the STM32's status" in the sender's box (otherwise the box holds a speed, rpm)
_READ_STATUS = object()


class LatestValue:
    """A one-slot "latest value" hand-over between coroutines of one event loop: :meth:`put`
    never blocks and replaces a value not yet taken (it returns True then, and counts it in
    ``superseded``); :meth:`get` waits for a value and takes it. Nothing ever queues: a consumer
    that is slow only ever finds the newest value."""

    __slots__ = ("_value", "_full", "_waiter", "superseded")

    def __init__(self) -> None:
        self._value: Any = None
        self._full = False
        self._waiter: asyncio.Future[None] | None = None
        self.superseded = 0

    @property
    def empty(self) -> bool:
        return not self._full

    def put(self, value: Any) -> bool:
        replaced = self._full
        if replaced:
            self.superseded += 1
        self._value, self._full = value, True
        w = self._waiter
        if w is not None and not w.done():
            w.set_result(None)
        return replaced

    def clear(self) -> None:
        """Drop a value not yet taken (not counted: withdrawn, not superseded)."""
        self._value, self._full = None, False

    async def get(self) -> Any:
        while not self._full:
            w = self._waiter = asyncio.get_running_loop().create_future()
            try:
                await w
            finally:
                self._waiter = None
        v = self._value
        self._value, self._full = None, False
        return v


class Stm32Drive:
    """The STM32 port as the slot loop uses it (see the module doc). ``speed_act`` is the
    take-up's last reported speed, rpm (NaN while it does not answer)."""

    def __init__(self, station_id: str, port: Stm32Port) -> None:
        self.id = station_id
        self.port = port
        #: the port posts the speed command without waiting (the real driver)
        self.posting = isinstance(port, Stm32PostingPort)
        #: the port says when the drive stopped on its own (the real driver)
        self.tells_stops = isinstance(port, Stm32DriveStops)
        #: the sender's box: a speed (rpm) or the status read
        self.box = LatestValue()
        self.busy = False               # the sender has a job on the link
        self.speed_act = math.nan
        self._task: asyncio.Task[None] | None = None
        self._calls: set[asyncio.Task[Any]] = set()

    # ---------------------------------------------------------------- awaited calls
    async def call(self, coro: Coroutine[Any, Any, Stm32Status | None]) -> Stm32Status | None:
        """One awaited call of the port; a driver that raises (it must not) gives None."""
        try:
            return await coro
        except Exception as e:
            log.error("%s: STM32 call failed: %s", self.id, e)
            return None

    async def stop(self, reason: str) -> Stm32Status | None:
        """Stop the take-up; a speed command not yet sent is withdrawn first (none after the STOP)."""
        self.box.clear()
        return await self.call(self.port.stop(reason))

    def enable_soon(self) -> None:
        """Enable the take-up (the spin-up, §3a) without waiting for the reply."""
        t = asyncio.get_running_loop().create_task(self.call(self.port.enable()))
        self._calls.add(t)
        t.add_done_callback(self._calls.discard)

    # ---------------------------------------------------------------- per slot, never waiting
    def command(self, rpm: float) -> bool:
        """The slot's speed command; False when it could not go out (counted by the caller)."""
        if self.posting:
            try:
                return bool(self.port.post_speed(rpm))      # type: ignore[attr-defined]
            except Exception as e:
                log.error("%s: STM32 post failed: %s", self.id, e)
                return False
        return not self.box.put(rpm)

    def collect(self) -> None:
        """The reply to the speed command posted in the previous slot (if any, without waiting)."""
        if not self.posting:
            return
        try:
            st = self.port.collect()                        # type: ignore[attr-defined]
        except Exception as e:
            log.error("%s: STM32 collect failed: %s", self.id, e)
            return
        if st is not None:
            self.speed_act = float(st.actual_rpm)

    def take_drive_stop(self) -> DriveStop | None:
        """A stop of the drive on its own the port saw and nobody took yet (once), or None."""
        if not self.tells_stops:
            return None
        try:
            return self.port.take_drive_stop()                # type: ignore[attr-defined]
        except Exception as e:
            log.error("%s: STM32 take_drive_stop failed: %s", self.id, e)
            return None

    @property
    def idle(self) -> bool:
        return not self.busy and self.box.empty

    def request_status(self) -> None:
        """Read the STM32's status when the link has nothing else to do."""
        if self.idle:
            self.box.put(_READ_STATUS)

    # ---------------------------------------------------------------- the sender task
    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._sender(),
                                                                name=f"{self.id} stm32 sender")

    async def _sender(self) -> None:
        """The one STM32 sender: takes the newest job from the box, one at a time, for the
        station's lifetime (no task per slot)."""
        while True:
            job = await self.box.get()
            self.busy = True
            try:
                if job is _READ_STATUS:
                    st = await self.call(self.port.read_status())
                    rpm = getattr(st, "actual_rpm", None) if st is not None else None
                    self.speed_act = float(rpm) if rpm is not None else math.nan
                else:
                    st = await self.call(self.port.set_speed(job))
                    if st is not None:
                        self.speed_act = float(st.actual_rpm)
            finally:
                self.busy = False

    async def close(self, grace_s: float = 0.5) -> None:
        """The box emptied, a job on the link given up to ``grace_s`` to finish, the sender
        ended."""
        task, self._task = self._task, None
        self.box.clear()
        if task is None:
            return
        t_end = time.monotonic() + grace_s
        while self.busy and not task.done() and time.monotonic() < t_end:
            await asyncio.sleep(0.005)
        task.cancel()
        try:
            await task
        except (asyncio.CancelledError, Exception):
            pass
