"""The station runtime: drivers → method → outputs, one record per 20 ms slot, flowing one way.

Per slot k (deadline t0 + k·Ts on a monotonic clock):
  1. poll the meter (its reading belongs to slot k; none → MISSING);
  2. the controller computes the speed command; it is sent to the STM32 in the background
     (a separate serial port: it overlaps with the next poll, so both fit in the slot);
  3. during a test, the streaming method core gates the slot and updates baseline/life;
  4. the slot record goes to every output (recorder, MQTT, Modbus TCP).

Test lifecycle: idle → baseline search → monitoring → end of life (runs on to t_end) →
completed | aborted (protection stop, operator stop, gateway restart).
"""
from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import statistics
import time
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from .. import __version__
from ..control import ControlParams, Controller
from ..method.core import StreamingMonitor
from ..method.params import MethodParams
from ..records import (Command, CommandKind, CommandReply, Event, EventType, SlotRecord,
                       StationState, TestState)
from .clock import SlotClock
from .recorder import TestRecorder, new_test_dir, recover_incomplete, utc_iso

log = logging.getLogger("hookwatch.station")


class MeterPort(Protocol):
    connected: bool
    counters: dict

    async def open(self) -> None: ...
    async def read(self) -> Any: ...      # object with .ch1, .ch2 (N) and .rtt_s, or None
    async def close(self) -> None: ...


class Stm32Port(Protocol):
    connected: bool
    counters: dict

    async def open(self) -> None: ...
    async def enable(self) -> Any: ...
    async def set_speed(self, rpm: float) -> Any: ...   # status with .actual_rpm, or None
    async def stop(self, reason: str = "") -> Any: ...
    async def read_status(self) -> Any: ...
    async def close(self) -> None: ...


@dataclass
class TestPlan:
    __test__ = False  # not a pytest test class
    sample_id: str
    grade: str | None
    t_set: float
    t_end: float


@dataclass
class SlotStats:
    """Scheduling figures, for logs and benchmarks."""
    slots: int = 0
    filled: int = 0
    overrun_slots: int = 0
    lateness: deque = field(default_factory=lambda: deque(maxlen=200_000))
    rtt: deque = field(default_factory=lambda: deque(maxlen=200_000))
    stm32_busy_skips: int = 0

    def summary(self) -> dict[str, Any]:
        lat = sorted(self.lateness)

        def pct(p):
            return lat[min(len(lat) - 1, int(p * len(lat)))] * 1e3 if lat else math.nan

        return {"slots": self.slots, "filled": self.filled,
                "filled_ratio": self.filled / self.slots if self.slots else math.nan,
                "overrun_slots": self.overrun_slots,
                "lateness_ms_p50": pct(0.5), "lateness_ms_p99": pct(0.99),
                "lateness_ms_max": lat[-1] * 1e3 if lat else math.nan,
                "rtt_ms_median": statistics.median(self.rtt) * 1e3 if self.rtt else math.nan,
                "stm32_busy_skips": self.stm32_busy_skips}


class Station:
    def __init__(self, *, station_id: str, method: dict[str, Any], control: ControlParams,
                 meter: MeterPort, stm32: Stm32Port, records_dir: str,
                 swap_channels: bool = False, outputs: list | None = None,
                 flush_interval_s: float = 1.0, default_plan: TestPlan | None = None,
                 grades: tuple[str, ...] = ("I", "II"), full_scale: float = 5.0,
                 identity: dict[str, Any] | None = None, idle_status_interval_s: float = 0.5,
                 autostart: bool = False):
        self.id = station_id
        self.method_values = dict(method)          # §10 values without t_set / t_end
        self.control_params = control
        self.ts = float(method.get("ts", 0.02))
        self.meter = meter
        self.stm32 = stm32
        self.records_dir = records_dir
        self.station_dir = os.path.join(records_dir, station_id)
        self.swap = swap_channels
        self.outputs = list(outputs or [])
        self.flush_interval_s = flush_interval_s
        self.default_plan = default_plan
        self.grades = grades
        self.full_scale = full_scale
        self.identity = identity or {}
        self.idle_status_interval_s = idle_status_interval_s
        self.autostart = autostart
        self.state = StationState(station=station_id)
        self.stats = SlotStats()
        self.results: list[dict[str, Any]] = []
        # test
        self.monitor: StreamingMonitor | None = None
        self.controller: Controller | None = None
        self.recorder: TestRecorder | None = None
        self.plan: TestPlan | None = None
        self.params: MethodParams | None = None
        self.k_start: int | None = None
        self.test_id: str | None = None
        self._stm32_task: asyncio.Task | None = None
        self._speed_act = math.nan
        self._speed_cmd = 0.0
        self._running = False
        self._last_state_push = 0.0
        self._meter_was_ok: bool | None = None
        self._stm32_was_ok: bool | None = None
        self._pending: list[Command] = []
        self._done = None
        self.clock: SlotClock | None = None
        #: makes the slot clock (a benchmark replaces it with a virtual clock that runs flat out)
        self.clock_factory = SlotClock
        #: where in the 20 ms slot this station's deadlines fall (0 … 1), on a process-wide grid
        self.slot_phase = 0.0

    # ---------------------------------------------------------------- outputs
    def _emit_event(self, etype: EventType, k: int | None = None, **data) -> Event:
        ev = Event(type=etype, station=self.id, wall_time=time.time(), test_id=self.test_id, k=k,
                   data=data)
        log.info("%s: %s %s", self.id, etype.value, data or "")
        if self.recorder is not None:
            self.recorder.on_event(ev)
        for o in self.outputs:
            try:
                o.on_event(ev)
            except Exception:  # an output must never stop the station
                log.exception("%s: output %r failed on event", self.id, o)
        return ev

    def _push_state(self) -> None:
        self._last_state_push = time.monotonic()
        for o in self.outputs:
            try:
                o.on_state(replace(self.state))
            except Exception:
                log.exception("%s: output %r failed on state", self.id, o)

    # ---------------------------------------------------------------- alarm (kept across restarts)
    @property
    def _alarm_path(self) -> str:
        return os.path.join(self.station_dir, "alarm.json")

    def _set_alarm(self, value: str, **info) -> None:
        """Change the end-of-life alarm state and keep it on disk, so that after a gateway restart
        the PLC and the MES still see an active (or acknowledged) alarm until a new test starts."""
        self.state.alarm = value
        rec = {"alarm": value, "test_id": self.test_id, "sample_id": self.state.sample_id,
               "utc": utc_iso(), **info}
        try:
            os.makedirs(self.station_dir, exist_ok=True)
            tmp = self._alarm_path + ".tmp"
            with open(tmp, "w", encoding="utf-8") as f:
                json.dump(rec, f)
            os.replace(tmp, self._alarm_path)
        except OSError as e:
            log.error("%s: cannot keep the alarm state in %s: %s", self.id, self._alarm_path, e)

    def _restore_alarm(self) -> None:
        try:
            with open(self._alarm_path, encoding="utf-8") as f:
                rec = json.load(f)
        except FileNotFoundError:
            return
        except (OSError, ValueError) as e:
            log.error("%s: alarm state %s unreadable (%s); starting with none", self.id,
                      self._alarm_path, e)
            return
        if rec.get("alarm") in ("active", "acknowledged"):
            st = self.state
            st.alarm = rec["alarm"]
            st.test_id = rec.get("test_id")
            st.sample_id = rec.get("sample_id")
            st.t_life = rec.get("t_life")
            log.info("%s: end-of-life alarm of test %s restored: %s", self.id, st.test_id, st.alarm)

    # ---------------------------------------------------------------- commands
    async def submit(self, cmd: Command) -> CommandReply:
        """One command path for CLI, MQTT and PLC: validate, then act, with the same events."""
        reply = self.validate(cmd)
        if reply is not None:
            self._emit_event(EventType.COMMAND_REJECTED, command=cmd.kind.value, source=cmd.source,
                             reason=reply.reason)
            return reply
        if cmd.kind == CommandKind.START:
            a = cmd.args
            self.start_test(TestPlan(sample_id=str(a["sample_id"]), grade=a.get("grade"),
                                     t_set=float(a["t_set"]),
                                     t_end=float(a.get("t_end") or (self.default_plan.t_end if self.default_plan else 36000.0))))
        elif cmd.kind == CommandKind.STOP:
            await self.end_test("stopped by command", source=cmd.source)
        elif cmd.kind == CommandKind.ACK:
            self._set_alarm("acknowledged")
            self._emit_event(EventType.ALARM_ACK, source=cmd.source)
            self._push_state()
        elif cmd.kind == CommandKind.SETPOINT:
            if self.default_plan is not None:
                self.default_plan = replace(self.default_plan, t_set=float(cmd.args["t_set"]))
        return CommandReply(True, "", cmd.request_id)

    def validate(self, cmd: Command) -> CommandReply | None:
        """The one validation shared by CLI, MQTT and PLC (gateway/station/commands.py)."""
        from .commands import validate as shared_validate
        return shared_validate(cmd, self)

    # ---------------------------------------------------------------- test lifecycle
    def start_test(self, plan: TestPlan) -> None:
        values = dict(self.method_values)
        values["t_set"] = plan.t_set
        values["t_end"] = plan.t_end
        from ..method.params import build_params
        p = build_params(values, f"station {self.id}")
        self.k_start = None            # the test's slot 0 is the next slot the loop processes
        start_wall = time.time()
        self.test_id, test_dir = new_test_dir(self.station_dir, plan.sample_id, start_wall)
        self.plan, self.params = plan, p
        self.monitor = StreamingMonitor(p)
        self.controller = Controller(self.control_params, plan.t_set)
        meta = {
            "station": self.id, **{k: v for k, v in self.identity.items() if k != "id"},
            "test_id": self.test_id, "sample_id": plan.sample_id, "grade": plan.grade,
            "t_set": plan.t_set, "start_time": utc_iso(start_wall),
            "software": f"hookwatch {__version__}",
            "method": {k: v for k, v in p.as_dict().items()},
            "control": self.control_params.as_dict(),
        }
        self.recorder = TestRecorder(test_dir, meta,
                                     self.flush_interval_s)
        st = self.state
        if st.alarm != "none":
            self._set_alarm("none")
            self._emit_event(EventType.ALARM_CLEARED, reason="new test started")
        st.state = TestState.BASELINE_SEARCH
        st.test_id, st.sample_id, st.grade = self.test_id, plan.sample_id, plan.grade
        st.t_set, st.t_end = plan.t_set, plan.t_end
        st.mu_ss = st.mu_th = st.t_life = None
        st.k_b = None
        st.status = st.end_reason = None
        st.protection_stop = False
        st.elapsed_s = 0.0
        self._emit_event(EventType.TEST_STARTED, k=0, sample_id=plan.sample_id, grade=plan.grade,
                         t_set=plan.t_set, t_end=plan.t_end)
        self._push_state()
        asyncio.get_running_loop().create_task(self._safe_stm32(self.stm32.enable()))

    async def end_test(self, reason: str, source: str = "station") -> dict[str, Any] | None:
        """End the running test (completed at t_end, or aborted) and write its result."""
        if self.monitor is None:
            return None
        mon = self.monitor
        await self._safe_stm32(self.stm32.stop(reason))
        res = mon.close()              # slots up to the planned end that never came: MISSING
        test_status = "completed" if reason == "completed" else "aborted"
        out = {"test_id": self.test_id, "station": self.id, "test_status": test_status,
               "end_reason": reason, "closed_utc": utc_iso(), "method": res.as_dict(),
               "sample_id": self.plan.sample_id, "grade": self.plan.grade, "t_set": self.plan.t_set}
        st = self.state
        st.state = TestState.COMPLETED if test_status == "completed" else TestState.ABORTED
        st.status = res.status
        st.end_reason = reason
        self._emit_event(EventType.TEST_ENDED, k=mon.k - 1, reason=reason, source=source,
                         test_status=test_status, result=res.as_dict())
        if self.recorder is not None:
            self.recorder.close(out)
        self.results.append(out)
        self.monitor = None
        self.controller = None
        self.recorder = None
        self._speed_cmd = 0.0
        self._push_state()
        return out

    # ---------------------------------------------------------------- the slot loop
    async def _safe_stm32(self, coro):
        try:
            return await coro
        except Exception as e:  # a driver must not raise, but never let it kill the loop
            log.error("%s: STM32 call failed: %s", self.id, e)
            return None

    async def _send_speed(self, rpm: float) -> None:
        st = await self._safe_stm32(self.stm32.set_speed(rpm))
        if st is not None:
            self._speed_act = float(getattr(st, "actual_rpm", math.nan))

    def _process(self, k: int, reading, lateness: float) -> SlotRecord:
        """Everything after the poll of slot k (pure computation plus buffered output)."""
        present = reading is not None
        if present:
            t1, t2 = (reading.ch2, reading.ch1) if self.swap else (reading.ch1, reading.ch2)
            t1, t2 = float(t1), float(t2)
        else:
            t1 = t2 = math.nan
        mon = self.monitor
        ctl = self.controller
        q, mask, ratio, mu = 0, 0, None, None
        y, sat = math.nan, False
        if mon is not None and self.k_start is None:
            self.k_start = k
        kt = k - self.k_start if mon is not None else k
        if mon is not None:
            out = mon.push(present, t1, t2)
            q, mask, ratio, mu = out.q, out.mask, out.ratio, out.mu
            tm = (t1 + t2) / 2.0 if present else None
            speed = self._speed_act if math.isfinite(self._speed_act) else self._speed_cmd
            c = ctl.step(tm, speed)
            y, sat = c.y, c.saturated
            self._speed_cmd = c.u
            self._handle_method_events(out.events, kt)
        rec = SlotRecord(k=kt, t=round(kt * self.ts + min(lateness, self.ts / 2 - 1e-4), 4)
                         if mon is not None else k * self.ts,
                         present=present, t1=t1, t2=t2, q=q, mask=mask, ratio=ratio, mu=mu,
                         mean_filt=y, speed_cmd=self._speed_cmd, speed_act=self._speed_act,
                         saturated=sat, lateness_s=lateness,
                         rtt_s=getattr(reading, "rtt_s", math.nan) if present else math.nan)
        if self.recorder is not None:
            self.recorder.on_record(rec)
        for o in self.outputs:
            try:
                o.on_record(rec)
            except Exception:
                log.exception("%s: output %r failed on record", self.id, o)
        return rec

    def _handle_method_events(self, events: list[str], kt: int) -> None:
        mon = self.monitor
        st = self.state
        st.elapsed_s = (kt + 1) * self.ts
        for e in events:
            if e == "baseline":
                st.state = TestState.MONITORING
                st.mu_ss, st.mu_th, st.k_b = mon.mu_ss, mon.mu_th, mon.k_b
                self._emit_event(EventType.BASELINE, k=kt, mu_ss=mon.mu_ss, mu_th=mon.mu_th,
                                 k_b=mon.k_b, stable_first=mon.stable_first)
                self._push_state()
            elif e == "end_of_life":
                st.state = TestState.END_OF_LIFE
                st.t_life = mon.k_life * self.ts
                self._set_alarm("active", t_life=st.t_life)
                self._emit_event(EventType.END_OF_LIFE, k=kt, k_life=mon.k_life, t_life=st.t_life,
                                 mu_ss=mon.mu_ss, mu_th=mon.mu_th, sample_id=self.plan.sample_id)
                self._push_state()
            elif e == "protection_stop":
                st.protection_stop = True
                r = mon.result()
                self._emit_event(EventType.PROTECTION_STOP, k=kt, stop_reasons=r.stop_reasons)

    async def _after_slot(self) -> None:
        """Lifecycle decisions after a slot: protection stop, planned end."""
        mon = self.monitor
        if mon is None:
            return
        if mon.stop_slot is not None:
            # §3: command the motor to stop at once, then close the test
            await self.end_test("protection stop")
        elif mon.finished:
            await self.end_test("completed")

    def _link_health(self) -> None:
        m_ok = bool(getattr(self.meter, "connected", False))
        s_ok = bool(getattr(self.stm32, "connected", False))
        changed = False
        if m_ok != self._meter_was_ok:
            if self._meter_was_ok is not None:
                self._emit_event(EventType.PORT_BACK if m_ok else EventType.PORT_LOST, port="meter")
            self._meter_was_ok = m_ok
            changed = True
        if s_ok != self._stm32_was_ok:
            if self._stm32_was_ok is not None:
                self._emit_event(EventType.PORT_BACK if s_ok else EventType.PORT_LOST, port="stm32")
            self._stm32_was_ok = s_ok
            changed = True
        self.state.meter_ok, self.state.stm32_ok = m_ok, s_ok
        if changed:
            self._push_state()

    async def run(self, stop: asyncio.Event, max_slots: int | None = None) -> None:
        """Run the slot loop until ``stop`` is set (or ``max_slots`` have passed)."""
        for d, res in recover_incomplete(self.station_dir):
            self._emit_event(EventType.TEST_ENDED, reason="gateway restart", test_status="aborted",
                             test_dir=d, result=res.get("method"))
        self._restore_alarm()
        for o in self.outputs:
            await o.start()
        await self.meter.open()
        await self.stm32.open()
        # make sure the motor is stopped when the gateway starts
        await self._safe_stm32(self.stm32.stop("gateway start"))
        if self.default_plan is not None and self.autostart:
            self.start_test(self.default_plan)
        self._link_health()
        self._push_state()
        # the grid starts after the start-up work (files, fsync), so slot 0 is not already late;
        # stations of one process are spread over the slot (slot_phase) so their deadlines do
        # not all fall at the same instant and queue behind each other
        if self.clock_factory is SlotClock:
            now = time.monotonic()
            self.clock = SlotClock(self.ts, t0=now + (self.slot_phase * self.ts - now) % self.ts)
        else:
            self.clock = self.clock_factory(self.ts)
        k = 0
        last_idle_status = 0.0
        try:
            while not stop.is_set() and (max_slots is None or k < max_slots):
                lateness = await self.clock.wait_for(k)
                if lateness > self.ts / 2:
                    # overrun: the slots whose window has passed are MISSING; never shift the grid
                    k_now = self.clock.slot_at(self.clock.clock())
                    log.warning("%s: slot %d started %.0f ms late: %d slot(s) recorded as MISSING",
                                self.id, k, lateness * 1e3, max(0, k_now - k))
                    for kk in range(k, k_now):
                        self.stats.slots += 1
                        self.stats.overrun_slots += 1
                        self._process(kk, None, lateness)
                        await self._after_slot()
                    k = k_now
                    continue
                self.stats.lateness.append(lateness)
                reading = await self.meter.read()
                self.stats.slots += 1
                if reading is not None:
                    self.stats.filled += 1
                    if getattr(reading, "rtt_s", None) is not None:
                        self.stats.rtt.append(reading.rtt_s)
                self._process(k, reading, lateness)
                if self.monitor is not None and self.monitor.stop_slot is None and not self.monitor.finished:
                    if self._stm32_task is None or self._stm32_task.done():
                        self._stm32_task = asyncio.get_running_loop().create_task(self._send_speed(self._speed_cmd))
                    else:
                        self.stats.stm32_busy_skips += 1
                await self._after_slot()
                now = time.monotonic()
                if self.monitor is None and now - last_idle_status >= self.idle_status_interval_s:
                    last_idle_status = now
                    if self._stm32_task is None or self._stm32_task.done():
                        self._stm32_task = asyncio.get_running_loop().create_task(
                            self._safe_stm32(self.stm32.read_status()))
                if now - self._last_state_push >= 1.0:
                    self._link_health()
                    self._push_state()
                k += 1
        finally:
            if self.monitor is not None:
                await self.end_test("gateway shutdown")
            if self._stm32_task is not None:
                try:
                    await asyncio.wait_for(self._stm32_task, 0.5)
                except (asyncio.TimeoutError, Exception):
                    pass
            await self._safe_stm32(self.stm32.stop("gateway shutdown"))
            await self.meter.close()
            await self.stm32.close()
            for o in self.outputs:
                try:
                    await o.stop()
                except Exception:
                    log.exception("%s: output %r failed to stop", self.id, o)
            log.info("%s: slot stats %s", self.id, self.stats.summary())
