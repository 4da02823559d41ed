"""Run one or many stations in one process, each isolated in its own thread and event loop.

One station's dead meter, slow STM32 or crash never delays or stops another: each has its own
loop (a blocking call in one cannot hold another's timers), and a crashed station is restarted
by its supervisor after a back-off while the others run on.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import threading
import time
from collections.abc import Callable, Coroutine
from typing import Any, TypeVar

from ..plumbing.backoff import Backoff
from ..plumbing.osprio import freeze_heap, realtime_thread
from ..plumbing.threadloop import ThreadLoop
from .station import Station

T = TypeVar("T")

log = logging.getLogger("hookwatch.fleet")

#: how often a configuration deferred by a running test looks whether the test has ended (s)
DEFERRED_POLL_S = 0.2


class StationRunner:
    """A station on its own :class:`ThreadLoop`, restarted when it crashes."""

    def __init__(self, name: str, factory: Callable[[], Station], restart_backoff_s: float = 1.0,
                 max_slots: int | None = None, on_started: Callable[[Station], None] | None = None,
                 restart_backoff_max_s: float = 60.0, stable_after_s: float = 60.0,
                 rt_priority: int = 0, rt_optional: bool = False):
        self.name = name
        #: SCHED_FIFO priority of the slot-loop thread (0: normal scheduling; gateway/plumbing/osprio.py)
        self.rt_priority = rt_priority
        #: SCHED_FIFO only where permitted, a refusal logged at info level (``hookwatch demo``);
        #: False: a refusal is a warning (``hookwatch run --realtime`` asked for it)
        self.rt_optional = rt_optional
        self.factory = factory
        #: the first restart comes after ``restart_backoff_s``; each further crash in a row
        #: doubles it, up to ``restart_backoff_max_s``; an instance that ran ``stable_after_s``
        #: starts a new row (gateway/plumbing/backoff.py)
        self.restart = Backoff(restart_backoff_s, restart_backoff_max_s, stable_after_s)
        self.max_slots = max_slots
        self.on_started = on_started
        self.station: Station | None = None
        self.tl = ThreadLoop(f"station-{name}")
        self._stop: asyncio.Event | None = None
        self._stopping = threading.Event()
        self.crashes = 0
        self.restart_requested = False
        self.last_error: str | None = None
        self.finished = threading.Event()
        #: a new configuration that came during a test: applied when the test ends, never sooner
        self.deferred: Callable[[], None] | None = None
        #: a new configuration came before the loop ran: the first station is built from it
        self.reloaded_before_start = False
        self._deferred_task: asyncio.Task[None] | None = None

    @property
    def loop(self) -> asyncio.AbstractEventLoop | None:
        return self.tl.loop if self.tl.running else None

    @property
    def thread(self) -> threading.Thread:
        th = self.tl.thread
        if th is None:
            raise RuntimeError(f"station {self.name} was never started")
        return th

    def start(self) -> None:
        self.tl.start()
        fut = self.tl.submit(self._supervise())
        fut.add_done_callback(self._done)

    def _done(self, fut: concurrent.futures.Future[None]) -> None:
        self.finished.set()
        self.tl.stop()              # from the loop's own thread: stops it without waiting

    async def _supervise(self) -> None:
        self._stop = asyncio.Event()
        if self.rt_priority:
            why = realtime_thread(self.rt_priority)
            if why is None:
                log.info("%s: slot loop runs at SCHED_FIFO priority %d", self.name, self.rt_priority)
            else:
                log.log(logging.INFO if self.rt_optional else logging.WARNING,
                        "%s: slot loop at normal priority: SCHED_FIFO %d %s", self.name,
                        self.rt_priority, why)
        if self._stopping.is_set():
            return
        reloaded = self.reloaded_before_start
        while not self._stopping.is_set():
            t_start = time.monotonic()
            try:
                self.station = None
                self.station = self.factory()
                freeze_heap()          # no full GC pass walks the built station again
                self.station.reloaded = reloaded
                if self.on_started:
                    self.on_started(self.station)
                await self.station.run(self._stop, max_slots=self.max_slots)
                if self.restart_requested and not self._stopping.is_set():
                    self.restart_requested = False      # SIGHUP reload: rebuild from new config
                    reloaded = True
                    self._stop = asyncio.Event()
                    continue
                return
            except Exception as e:  # isolate: close, log, back off, restart this station only
                await self._after_crash(e, time.monotonic() - t_start)

    @property
    def crash_streak(self) -> int:
        """Crashes in a row (since the last instance that ran ``stable_after_s``)."""
        return self.restart.in_row

    async def _after_crash(self, e: Exception, ran_s: float) -> None:
        self.crashes += 1
        self.last_error = f"{type(e).__name__}: {e}"
        st = self.station
        if st is not None:
            # the crashed instance releases everything it holds (serial ports and their locks,
            # its PLC unit id, its MQTT client, its tasks) before another one is built
            try:
                await st.close()
            except Exception:
                log.exception("station %s: closing the crashed instance failed", self.name)
        self.station = None
        delay = self.restart.failed(ran_s)
        if self.crashes == 1:       # the traceback once; later crashes one line with the count
            log.error("station %s crashed; closed; restarting in %.1f s", self.name, delay,
                      exc_info=e)
        else:
            log.error("station %s crashed again (%d crashes, %d in a row): %s; closed; restarting "
                      "in %.1f s", self.name, self.crashes, self.crash_streak, self.last_error,
                      delay)
        assert self._stop is not None
        try:
            await asyncio.wait_for(self._stop.wait(), delay)
        except TimeoutError:
            pass

    def request_reload(self, factory: Callable[[], Station]) -> None:
        """A new configuration (any thread). The decision is taken on the station's own loop, so
        a test start cannot slip in between the check and the restart: an idle station restarts
        with ``factory`` (and emits ``config_reloaded``); one in a test keeps its parameters and
        restarts with ``factory`` when the test ends (:meth:`_after_test`) — never before."""
        def apply() -> None:
            self.factory = factory
            self.restart_requested = True
            log.info("%s: configuration reloaded; station restarts", self.name)
        self._when_idle(apply, factory)

    def request_stop_when_idle(self, on_idle: Callable[[], None]) -> None:
        """Stop the station once it is idle — now, or when its running test ends, never before —
        and call ``on_idle`` (on its loop) just before (a worker restarted for new software)."""
        def apply() -> None:
            log.info("%s: idle: the station stops for its restart", self.name)
            on_idle()
            self._stopping.set()
        self._when_idle(apply, None)

    def _when_idle(self, apply: Callable[[], None], factory: Callable[[], Station] | None) -> None:
        def on_loop() -> None:
            st = self.station
            self.deferred = None
            if st is None:
                if factory is not None:
                    self.factory = factory
                else:
                    apply()
                    if self._stop is not None:
                        self._stop.set()
            elif not st.reload_requested(apply):
                self.deferred = apply
                if self._deferred_task is None or self._deferred_task.done():
                    self._deferred_task = asyncio.ensure_future(self._after_test())
        if self.tl.running:
            self.tl.call_soon(on_loop)
        elif factory is not None:       # not started yet (a fleet's start barrier): it starts with it
            self.factory = factory
            self.reloaded_before_start = True   # and says so (``config_reloaded``)
        else:
            apply()

    async def _after_test(self) -> None:
        """The configuration deferred by a test applies once the station is idle (checked and
        applied in one step on its loop: no test start can come between)."""
        while self.deferred is not None and not self._stopping.is_set():
            await asyncio.sleep(DEFERRED_POLL_S)
            st, apply = self.station, self.deferred
            if st is not None and apply is not None and not st.busy:
                log.info("%s: the test ended: the deferred configuration applies", self.name)
                self.deferred = None
                st.reload_requested(apply)

    def request_stop(self) -> None:
        self._stopping.set()
        if self.tl.running and self._stop is not None:
            try:
                self.tl.call_soon(self._stop.set)
            except RuntimeError:
                pass

    def call(self, coro_factory: Callable[[], Coroutine[Any, Any, T]], timeout: float = 5.0) -> T:
        """Run a coroutine on this station's loop from another thread and wait for its result."""
        if not self.tl.running:
            raise RuntimeError(f"station {self.name} is not running")
        return self.tl.submit(coro_factory()).result(timeout)

    def progress(self) -> int:
        st = self.station
        return st.stats.slots if st is not None else -1


class Fleet:
    """The stations of one process, each on its own thread: a :class:`gateway.core.ports.Runtime`
    (``hookwatch run STATION.yaml``, or a fleet folder with ``--in-process``). ``reloader`` gives,
    on SIGHUP, the new factory of each station by name (raising ValueError: configuration kept)."""

    def __init__(self, runners: list[StationRunner],
                 reloader: Callable[[], dict[str, Callable[[], Station]]] | None = None) -> None:
        self.runners = runners
        self.reloader = reloader
        self._progress: dict[str, int] = {}
        self._started_any = False

    def start(self) -> None:
        for r in self.runners:
            r.start()

    def tick(self, now: float) -> None:
        """The test bookkeeping of ``--exit-when-done`` (restarts run on each station's thread)."""
        if any(r.station is not None and r.station.busy for r in self.runners):
            self._started_any = True

    def stop(self, timeout: float = 10.0) -> None:
        for r in self.runners:
            r.request_stop()
        t_end = time.monotonic() + timeout
        for r in self.runners:
            if r.tl.thread is not None:
                r.tl.thread.join(max(0.1, t_end - time.monotonic()))

    def alive(self) -> bool:
        return any(r.tl.running for r in self.runners)

    def ready(self) -> bool:
        return True

    def status(self) -> str:
        return f"running {len(self.runners)} station(s)"

    def healthy(self) -> bool:
        """True when every running station made progress since the last call (watchdog)."""
        ok = True
        last = self._progress
        for r in self.runners:
            p = r.progress()
            if r.tl.running and p <= last.get(r.name, -1) and p >= 0:
                ok = False
            last[r.name] = p
        return ok

    def tests_done(self) -> bool:
        """Every test started has ended (or every station has ended or failed a start)."""
        sts = [r.station for r in self.runners]
        if any(s is not None and s.busy for s in sts):
            return False
        return self._started_any or all(s is not None and bool(s.results or s.start_failures)
                                        for s in sts)

    def reload(self) -> None:
        """SIGHUP: each station decides on its own loop whether it restarts with its new
        configuration (idle) or keeps the parameters of its running test."""
        if self.reloader is None:
            return
        try:
            factories = self.reloader()
        except ValueError as e:
            log.error("reload refused, configuration kept: %s", e)
            return
        for r in self.runners:
            f = factories.get(r.name)
            if f is not None:
                r.request_reload(f)

    def report(self) -> dict[str, dict[str, Any] | None]:
        out: dict[str, dict[str, Any] | None] = {}
        for r in self.runners:
            st = r.station
            out[r.name] = None if st is None else dict(
                st.stats.summary(), results=st.results, start_failures=st.start_failures,
                meter=dict(st.meter.counters))
        return out
