"""Run one or many stations in one process, each isolated in its own thread and event loop.

One station's dead meter, slow STM32 or crash never delays or stops another: each has its own
loop (a blocking call in one cannot hold another's timers), and a crashed station is restarted
by its supervisor after a back-off while the others run on.
"""
from __future__ import annotations

import asyncio
import logging
import threading
import time
from typing import Callable

from .station import Station

log = logging.getLogger("hookwatch.fleet")


class StationRunner:
    """A station in its own thread with its own asyncio loop, restarted when it crashes."""

    def __init__(self, name: str, factory: Callable[[], Station], restart_backoff_s: float = 5.0,
                 max_slots: int | None = None, on_started: Callable[[Station], None] | None = None):
        self.name = name
        self.factory = factory
        self.backoff = restart_backoff_s
        self.max_slots = max_slots
        self.on_started = on_started
        self.station: Station | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._stopping = threading.Event()
        self.thread = threading.Thread(target=self._main, name=f"station-{name}", daemon=True)
        self.crashes = 0
        self.restart_requested = False
        self.last_error: str | None = None
        self.finished = threading.Event()

    def start(self) -> None:
        self.thread.start()

    def _main(self) -> None:
        try:
            asyncio.run(self._supervise())
        finally:
            self.finished.set()

    async def _supervise(self) -> None:
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        if self._stopping.is_set():
            return
        while not self._stopping.is_set():
            try:
                self.station = self.factory()
                if self.on_started:
                    self.on_started(self.station)
                await self.station.run(self._stop, max_slots=self.max_slots)
                if self.restart_requested and not self._stopping.is_set():
                    self.restart_requested = False      # SIGHUP reload: rebuild from new config
                    self._stop = asyncio.Event()
                    continue
                return
            except Exception as e:  # isolate: log, back off, restart this station only
                self.crashes += 1
                self.last_error = f"{type(e).__name__}: {e}"
                log.exception("station %s crashed (%d); restarting in %.0f s", self.name,
                              self.crashes, self.backoff)
                try:
                    await asyncio.wait_for(self._stop.wait(), self.backoff)
                except asyncio.TimeoutError:
                    pass

    def request_stop(self) -> None:
        self._stopping.set()
        if self.loop is not None and self._stop is not None:
            try:
                self.loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:
                pass

    def call(self, coro_factory, timeout: float = 5.0):
        """Run a coroutine on this station's loop from another thread and wait for its result."""
        if self.loop is None:
            raise RuntimeError(f"station {self.name} is not running")
        fut = asyncio.run_coroutine_threadsafe(coro_factory(), self.loop)
        return fut.result(timeout)

    def progress(self) -> int:
        st = self.station
        return st.stats.slots if st is not None else -1


class Fleet:
    def __init__(self, runners: list[StationRunner]):
        self.runners = runners

    def start(self) -> None:
        for r in self.runners:
            r.start()

    def stop(self, timeout: float = 10.0) -> None:
        for r in self.runners:
            r.request_stop()
        t_end = time.monotonic() + timeout
        for r in self.runners:
            r.thread.join(max(0.1, t_end - time.monotonic()))

    def alive(self) -> bool:
        return any(r.thread.is_alive() for r in self.runners)

    def healthy(self, last: dict[str, int]) -> bool:
        """True when every running station made progress since the last call (watchdog)."""
        ok = True
        for r in self.runners:
            p = r.progress()
            if r.thread.is_alive() and p <= last.get(r.name, -1) and p >= 0:
                ok = False
            last[r.name] = p
        return ok
