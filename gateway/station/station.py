"""The station runtime: drivers → method → outputs, one record per 20 ms slot, flowing one way.

:class:`Station` is the slot loop. Per slot k (deadline t0 + k·Ts on a monotonic clock):
  1. poll the meter (its reading belongs to slot k; none → MISSING);
  2. the start sequence or the running test computes the slot (:class:`~.lifecycle.TestLifecycle`:
     the method core gates the slot and updates baseline/life, the controller computes the speed
     command), which goes to the STM32 through :class:`~.stm32link.Stm32Drive` without waiting
     (a command that cannot go out is counted in ``SlotStats.stm32_busy_skips``);
  3. the slot record goes to the fan-out (recorder first, then MQTT, Modbus TCP, …);
  4. the lifecycle's decisions (slot 0, a failed start, protection stop, planned end).

Beside it, each in its own module: the start sequence (:mod:`.starting`, a pure state machine),
the test's transitions (:mod:`.lifecycle`), the one place the state changes and events leave
(:mod:`.status`), ports/uplinks/disks (:mod:`.health`), the command table (:mod:`.dispatch`).
The end-of-life alarm lives in the station's :class:`~.alarm_store.AlarmStore`. Everything here runs on
the station's own loop; other threads reach it only through ``gateway.plumbing.threadloop`` (commands:
:meth:`Station.submit`; uplink changes: :meth:`Station.set_uplink`; reloads:
:meth:`Station.reload_requested`).
"""
from __future__ import annotations

import asyncio
import logging
import math
import os
import time
from collections.abc import Callable, Coroutine, Iterable
from typing import Any

from ..core.control import Controller, ControlParams
from ..core.method.core import StreamingMonitor
from ..core.method.params import MethodParams
from ..core.method.prior import PastTest, PriorEntry
from ..core.ports import MeterPort, MeterReading, Output, StationLimits, Stm32Port
from ..core.records import Command, CommandReply, EventType, SlotRecord, StationState
from ..plumbing import ratelog
from .alarm_store import AlarmStore
from .clock import LateStarts, SlotClock, SlotStats
from .command_desk import CommandDesk, validate
from .dispatch import HANDLERS
from .fanout import Fanout
from .health import Health
from .lifecycle import TestLifecycle, TestSetup
from .recorder import TestRecorder, recover_incomplete
from .session import RecorderOutput, TestPlan, TestSession
from .starting import StartAttempt
from .status import StatusBoard
from .stm32link import LatestValue, Stm32Drive

__all__ = ["LatestValue", "SlotStats", "Station", "TestPlan", "TestSession"]

log = logging.getLogger("hookwatch.station")


class Station:
    """One station's slot loop and the test it runs (see the module doc)."""

    def __init__(self, *, station_id: str, method: dict[str, Any], control: ControlParams, meter: MeterPort,
                 stm32: Stm32Port, records_dir: str, swap_channels: bool = False, outputs: list[Output] | None = None,
                 flush_interval_s: float = 1.0, default_plan: TestPlan | None = None, restart_on_replace: bool = False,
                 limits: StationLimits | None = None, identity: dict[str, Any] | None = None, autostart: bool = False,
                 idle_status_interval_s: float = 0.5, priors: Iterable[PriorEntry] = ()) -> None:
        self.id = station_id
        self.method_values = dict(method)          # §10 values without t_set / t_end
        self.control_params = control
        self.ts = float(method.get("ts", 0.02))
        self.meter, self.stm32 = meter, stm32
        self.records_dir = records_dir
        self.station_dir = os.path.join(records_dir, station_id)
        self.swap = swap_channels
        self.outputs: list[Output] = list(outputs or [])
        self.flush_interval_s = flush_interval_s
        self.default_plan = default_plan
        #: what commands are checked against (built once from the configuration)
        self.limits = limits if limits is not None else StationLimits.from_values(
            method, t_end_default_s=default_plan.t_end if default_plan else 36000.0)
        self.identity = identity or {}
        self.idle_status_interval_s = idle_status_interval_s
        self.autostart = autostart
        self.stats = SlotStats()
        #: overruns are logged once per window with a count (not a line per late slot)
        self.late_starts = LateStarts(ratelog.WINDOW_S, lambda line: log.warning("%s: %s", station_id, line))
        self._recorder_out = RecorderOutput()
        self.fanout = Fanout(station_id, self.outputs, head=(self._recorder_out,))
        #: the one place the state changes; the ports, uplinks and disks; the STM32 transport
        self.board = StatusBoard(station_id, AlarmStore(os.path.join(self.station_dir, "alarm.json"),
                                                        station_id), self.fanout, lambda: self.test_id)
        self.health = Health(self.board, meter, stm32)
        self.link = Stm32Drive(station_id, stm32)
        #: every door's commands: once, one at a time, validated once, rate-limited, refusals counted
        self.desk = CommandDesk(lambda cmd: validate(cmd, self.limits, self.state), self._act,
                                lambda data: self.board.emit_data(EventType.COMMAND_REJECTED, data))
        #: the start or the test in progress, its method and its speed command
        self.tests = TestLifecycle(
            TestSetup(station_id, self.station_dir, self.ts, self.method_values, control,
                      self.identity, flush_interval_s), self.board, self.health, self.link, meter,
            self._recorder_out)
        self.tests.priors.entries, self.tests.restart_on_replace = tuple(priors), bool(restart_on_replace)
        self._stop_evt: asyncio.Event | None = None
        self._closed = False
        self.clock: SlotClock | None = None
        #: makes the slot clock (a benchmark replaces it with a virtual clock that runs flat out)
        self.clock_factory: Callable[..., Any] = SlotClock
        #: where in the 20 ms slot this station's deadlines fall (0 … 1), on a process-wide grid
        self.slot_phase = 0.0
        #: set by the runner when this station replaces one whose configuration was reloaded
        self.reloaded = False

    # ---------------------------------------------------------------- what outputs read
    @property
    def state(self) -> StationState:
        return self.board.state

    @property
    def alarms(self) -> AlarmStore:
        """The one alarm store (alarm.json in the station's folder)."""
        return self.board.alarms

    @alarms.setter
    def alarms(self, store: AlarmStore) -> None:
        self.board.alarms = store

    @property
    def session(self) -> TestSession | None:
        """The running test, if any."""
        return self.tests.session

    @property
    def starting(self) -> StartAttempt | None:
        """The start in progress (§3a, nothing recorded), if any."""
        return self.tests.starting

    @property
    def results(self) -> list[dict[str, Any]]:
        return self.tests.results

    @property
    def start_failures(self) -> list[dict[str, Any]]:
        """Starts that failed (§3a): {"sample_id", "reason", "source"}."""
        return self.tests.start_failures

    @property
    def monitor(self) -> StreamingMonitor | None:
        return self.tests.monitor

    @property
    def controller(self) -> Controller | None:
        return self.session.controller if self.session is not None else None

    @property
    def recorder(self) -> TestRecorder | None:
        return self.session.recorder if self.session is not None else None

    @property
    def plan(self) -> TestPlan | None:
        """The plan of the running test, or of the start in progress."""
        src = self.session or self.starting
        return src.plan if src is not None else None

    @property
    def params(self) -> MethodParams | None:
        src = self.session or self.starting
        return src.params if src is not None else None

    @property
    def test_id(self) -> str | None:
        return self.session.test_id if self.session is not None else None

    @property
    def in_test(self) -> bool:
        return self.session is not None

    @property
    def busy(self) -> bool:
        """A test is starting or running."""
        return self.session is not None or self.starting is not None

    # ---------------------------------------------------------------- from outputs (this loop)
    def set_uplink(self, name: str, ok: bool) -> None:
        """An uplink (MQTT) reports its connection (via the thread hand-over)."""
        self.health.set_uplink(name, ok)

    def set_disk(self, store: str, ok: bool, info: dict[str, Any] | None = None) -> None:
        """A store (``records``, ``outbox``) reports whether its disk can be written."""
        self.health.set_disk(store, ok, info)

    def site_lives(self, tests: tuple[Any, ...]) -> None:
        """The site's lives (the MQTT output, via the hand-over) join the §7a history."""
        self.tests.priors.set_site(tuple(t for t in tests if isinstance(t, PastTest)))

    def refused(self, data: dict[str, Any]) -> None:
        """A door refused a request before it became a command (malformed, too large: code 9); it
        is a (bounded) ``command_rejected`` event like every other refusal."""
        self.desk.refused(data)

    async def submit(self, cmd: Command) -> CommandReply:
        """The one command path of every door (the :class:`~.commands.CommandDesk`): one at a
        time, a repeated request_id once, validated once, rate-limited per source, then carried
        out (``dispatch.HANDLERS``)."""
        return await self.desk.submit(cmd)

    async def _act(self, cmd: Command) -> None:
        await HANDLERS[cmd.kind](self, cmd)

    def reload_requested(self, apply: Callable[[], None]) -> bool:
        """A new configuration is ready (on this loop, so no start can slip in between the check
        and the decision). Idle: ``apply()`` is called and the station stops (its runner
        rebuilds it from the new configuration); in a test: kept, False."""
        if self.busy:
            log.info("%s: in a test; keeps the parameters it started with", self.id)
            return False
        apply()
        if self._stop_evt is not None:
            self._stop_evt.set()
        return True

    # ---------------------------------------------------------------- tests (gateway/station/lifecycle.py)
    def start_test(self, plan: TestPlan, source: str = "station") -> None:
        self.tests.start_test(plan, source)

    async def stop_test(self, source: str, test_id: str | None = None) -> None:
        await self.tests.stop_test(source, test_id)

    async def end_test(self, reason: str, source: str = "station") -> dict[str, Any] | None:
        return await self.tests.end_test(reason, source)

    # ---------------------------------------------------------------- the slot loop
    async def run(self, stop: asyncio.Event, max_slots: int | None = None) -> None:
        """Run the slot loop until ``stop`` is set (or ``max_slots`` have passed)."""
        self._stop_evt = stop
        self._closed = False
        try:
            await self._run(stop, max_slots)
        finally:
            await self.close()

    async def close(self) -> None:
        """Close this instance completely, also after a crash at any point of :meth:`run`: the
        running test (or start) is ended, the STM32 call awaited or cancelled, the take-up
        stopped, both serial ports closed (their locks released) and every output that started
        stopped (the PLC unit id unregistered, the MQTT client disconnected). Each step runs
        even when an earlier one fails; a second call does nothing."""
        if self._closed:
            return
        self._closed = True

        async def step(what: str, coro: Coroutine[Any, Any, Any]) -> None:
            try:
                await coro
            except Exception:
                log.exception("%s: closing: %s failed", self.id, what)

        await step("test", self.tests.close("gateway shutdown"))
        await step("stm32 sender", self.link.close())
        await step("stm32 stop", self.link.call(self.stm32.stop("gateway shutdown")))
        await step("meter port", self.meter.close())
        await step("stm32 port", self.stm32.close())
        await step("outputs", self.fanout.stop())
        self.late_starts.due(time.monotonic(), force=True)
        self.health.check_meter_reads()     # the failed reads since the last check are said too
        log.info("%s: slot stats %s", self.id, self.stats.summary())

    async def _open(self) -> None:
        """Before the first slot: cut-off tests closed, alarms restored, outputs and ports open."""
        for d, res in recover_incomplete(self.station_dir):
            self.board.emit(EventType.TEST_ENDED, of_test=res["test_id"], reason="gateway restart",
                            test_status="aborted", test_dir=d, result=res.get("method"),
                            sample_id=res.get("sample_id"), grade=res.get("grade"),
                            t_set=res.get("t_set"))
        self.board.restore_alarm()
        await self.fanout.start()
        if self.reloaded:
            self.board.emit(EventType.CONFIG_RELOADED)
        await self.meter.open()
        await self.stm32.open()
        await self.link.call(self.stm32.stop("gateway start"))   # the motor stopped at start
        self.link.start()
        if self.default_plan is not None and self.autostart:
            self.start_test(self.default_plan)
        self.health.check_links()
        self.board.push()

    async def _run(self, stop: asyncio.Event, max_slots: int | None) -> None:
        await self._open()
        # the grid starts after the start-up work (files, fsync), so slot 0 is not already late;
        # stations of one process are spread over the slot (slot_phase) so their deadlines do
        # not all fall at the same instant and queue behind each other
        now = time.monotonic()
        self.clock = (SlotClock(self.ts, t0=now + (self.slot_phase * self.ts - now) % self.ts)
                      if self.clock_factory is SlotClock else self.clock_factory(self.ts))
        clock, tests, link, stats = self.clock, self.tests, self.link, self.stats
        k = 0
        last_idle_status = 0.0
        while not stop.is_set() and (max_slots is None or k < max_slots):
            lateness = await clock.wait_for(k)
            if lateness > self.ts / 2:
                # overrun: the slots whose window has passed are MISSING; never shift the grid
                k_now = clock.slot_at(clock.clock())
                self.late_starts.add(time.monotonic(), k, lateness, max(0, k_now - k))
                for kk in range(k, k_now):
                    stats.slots += 1
                    stats.overrun_slots += 1
                    self._process(kk, None, lateness)
                    await tests.after_slot()
                k = k_now
                continue
            stats.lateness.append(lateness)
            reading = await self.meter.read()
            link.collect()
            stats.slots += 1
            if reading is not None:
                stats.filled += 1
                if reading.rtt_s is not None:
                    stats.rtt.append(reading.rtt_s)
            self._process(k, reading, lateness)
            att = tests.starting
            if tests.drives_motor and not link.command(tests.speed_cmd):   # never waits for the link
                stats.stm32_busy_skips += 1
            await tests.after_slot()
            now = time.monotonic()
            waiting = att is not None and tests.starting is att and att.waiting_for_rest
            if ((not self.busy or waiting) and now - last_idle_status
                    >= (min(0.2, self.idle_status_interval_s) if waiting
                        else self.idle_status_interval_s)):
                last_idle_status = now
                link.request_status()
            if now - self.board.last_push >= 1.0:
                self.late_starts.due(now)
                self.health.check_links()
                for name in self.alarms.expired(time.time()):   # a shelving ran out
                    self.board.emit(EventType.ALARM_UNSHELVED, alarm=name, expired=True)
                self.board.push()
            k += 1

    def _process(self, k: int, reading: MeterReading | None, lateness: float) -> SlotRecord:
        """Everything after the poll of slot k (pure computation plus buffered output)."""
        present = reading is not None
        if reading is not None:
            t1, t2 = (reading.ch2, reading.ch1) if self.swap else (reading.ch1, reading.ch2)
            t1, t2 = float(t1), float(t2)
        else:
            t1 = t2 = math.nan
        in_test = self.tests.session is not None
        r = self.tests.slot(k, present, t1, t2)
        self.board.update(saturation=r.saturated)
        rec = SlotRecord(k=r.kt, t=round(r.kt * self.ts + min(lateness, self.ts / 2 - 1e-4), 4)
                         if in_test else k * self.ts,
                         present=present, t1=t1, t2=t2, q=r.q, mask=r.mask, ratio=r.ratio, mu=r.mu,
                         mean_filt=r.y, speed_cmd=self.tests.speed_cmd,
                         speed_act=self.link.speed_act, saturated=r.saturated, lateness_s=lateness,
                         rtt_s=reading.rtt_s if reading is not None else math.nan)
        self.fanout.record(rec)
        return rec
