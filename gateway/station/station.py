"""The station runtime: drivers → method → outputs, one record per 20 ms slot, flowing one way.

Per slot k (deadline t0 + k·Ts on a monotonic clock):
  1. poll the meter (its reading belongs to slot k; none → MISSING);
  2. the controller computes the speed command. An STM32 port that can post it
     (:class:`~gateway.ports.Stm32PostingPort`, the real driver) gets it written at once, and
     its reply is collected after the next slot's poll, when the process is awake anyway (no
     wake-up of its own); any other port gets it through the station's one STM32 sender task and
     a one-slot "latest value" box (:class:`LatestValue`). Either way the slot loop never waits
     for the STM32, and a command that cannot go out (the link busy with another exchange, or
     replaced in the box by a newer one: never queued) is counted in
     ``SlotStats.stm32_busy_skips``;
  3. during a test, the streaming method core gates the slot and updates baseline/life;
  4. the slot record goes to the fan-out (recorder first, then MQTT, Modbus TCP, …).

Test lifecycle: idle → starting (a :class:`StartAttempt`, METHOD.md §3a: zero check with the motor
off, spin-up with the loop closed; nothing recorded; a refusal or a timeout is `start_failed` and
idle again) → slot 0 once the tension has settled (a :class:`TestSession`) → baseline search →
monitoring → end of life (runs on to t_end) → completed | aborted (protection stop; operator, PLC,
MES stop or clean shutdown: `end_slot` in the sidecar, §3; gateway restart after a crash). The end-of-life
alarm lives in the station's :class:`AlarmStore`. Everything here runs on the station's own loop;
other threads reach it only through ``gateway.threadloop`` (commands: :meth:`Station.submit`;
uplink changes: :meth:`Station.set_uplink`; reloads: :meth:`Station.reload_requested`).
"""
from __future__ import annotations

import asyncio
import logging
import math
import os
import statistics
import time
from collections import deque
from collections.abc import Callable, Coroutine
from dataclasses import dataclass, field, replace
from typing import Any

from ..control import Controller, ControlParams
from ..method.core import SlotOut, StreamingMonitor
from ..method.params import MethodParams
from ..method.start import FAILED, SETTLED, SPIN_UP, ZERO_CHECK
from ..ports import MeterPort, MeterReading, Output, StationLimits, Stm32Port, Stm32PostingPort, Stm32Status
from ..records import Command, CommandKind, CommandReply, Event, EventType, SlotRecord, StationState, TestState
from ..threadloop import call_soon_on
from .alarms import AlarmStore
from .clock import SlotClock
from .commands import ALARM_COMMAND_EVENTS, Rejection, validate
from .fanout import Fanout
from .recorder import TestRecorder, recover_incomplete, utc_iso
from .session import RecorderOutput, StartAttempt, TestPlan, TestSession

__all__ = ["Station", "TestPlan", "TestSession", "SlotStats"]

log = logging.getLogger("hookwatch.station")

#: the zero check (METHOD.md §3a) measures the yarn at rest: it begins once the take-up has been
#: commanded off for REST_S and the STM32 reports no more than REST_RPM (a test stopped a moment
#: ago, a gateway restarted after a crash: the yarn is still under tension while the take-up
#: runs down)
REST_S = 1.0
REST_RPM = 1.0


@dataclass
class SlotStats:
    """Scheduling figures, for logs and benchmarks."""
    slots: int = 0
    filled: int = 0
    overrun_slots: int = 0
    lateness: deque = field(default_factory=lambda: deque(maxlen=200_000))
    rtt: deque = field(default_factory=lambda: deque(maxlen=200_000))
    #: speed commands never sent: replaced in the sender's box by a newer one, or not postable
    #: (the link busy with another exchange, or its port gone)
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


class Station:
    def __init__(self, *, station_id: str, method: dict[str, Any], control: ControlParams,
                 meter: MeterPort, stm32: Stm32Port, records_dir: str,
                 swap_channels: bool = False, outputs: list[Output] | None = None,
                 flush_interval_s: float = 1.0, default_plan: TestPlan | None = None,
                 limits: StationLimits | None = None, identity: dict[str, Any] | None = None,
                 idle_status_interval_s: float = 0.5, autostart: bool = False) -> None:
        self.id = station_id
        self.method_values = dict(method)          # §10 values without t_set / t_end
        self.control_params = control
        self.ts = float(method.get("ts", 0.02))
        self.meter = meter
        self.stm32 = stm32
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
        self.state = StationState(station=station_id)
        self.stats = SlotStats()
        self.results: list[dict[str, Any]] = []
        #: the one alarm store (alarm.json in the station's folder)
        self.alarms = AlarmStore(os.path.join(self.station_dir, "alarm.json"), station_id)
        #: the running test, if any
        self.session: TestSession | None = None
        #: the start in progress (§3a), if any: before slot 0, nothing recorded
        self.starting: StartAttempt | None = None
        #: starts that failed (§3a): {"sample_id", "reason", "source"}
        self.start_failures: list[dict[str, Any]] = []
        self._recorder_out = RecorderOutput()
        self.fanout = Fanout(station_id, self.outputs, head=(self._recorder_out,))
        #: the one STM32 sender (started by run()) and its box: a speed (rpm) or _READ_STATUS
        self._stm32_box = LatestValue()
        self._stm32_sender_task: asyncio.Task[None] | None = None
        self._stm32_busy = False        # the sender has a job on the link
        #: the STM32 port posts the speed command without waiting (the real driver)
        self._stm32_post = isinstance(stm32, Stm32PostingPort)
        self._speed_act = math.nan
        self._speed_cmd = 0.0
        self._k = 0                     # the loop's current slot
        self._motor_off_k = 0           # loop slot of the last stop command to the take-up
        self._last_state_push = 0.0
        #: the ports' last seen state and loss count (_link_health)
        self._port_seen: dict[str, bool | None] = {"meter": None, "stm32": None}
        self._port_lost_seen: dict[str, int] = {}
        self._uplinks: dict[str, bool] = {}
        self._disks: dict[str, bool] = {}
        self._stop_evt: asyncio.Event | None = None
        self._closed = False
        self.clock: SlotClock | None = None
        #: makes the slot clock (a benchmark replaces it with a virtual clock that runs flat out)
        self.clock_factory: Callable[..., Any] = SlotClock
        #: where in the 20 ms slot this station's deadlines fall (0 … 1), on a process-wide grid
        self.slot_phase = 0.0
        #: set by the runner when this station replaces one whose configuration was reloaded
        self.reloaded = False

    # ---------------------------------------------------------------- the running test
    @property
    def monitor(self) -> StreamingMonitor | None:
        return self.session.monitor if self.session is not None else None

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

    # ---------------------------------------------------------------- outputs
    def _emit_event(self, etype: EventType, k: int | None = None, *, of_test: str | None = None,
                    **data: Any) -> Event:
        """One event to the alarm store and every output; ``of_test``: the test it belongs to
        when that is not the running one (a cut-off test closed at start-up)."""
        ev = Event(type=etype, station=self.id, wall_time=time.time(),
                   test_id=of_test if of_test is not None else self.test_id, k=k, data=data)
        log.info("%s: %s %s", self.id, etype.value, data or "")
        self.alarms.on_event(ev)              # the alarm store first: outputs read it
        self.state.alarm = self.alarms.state.value
        self.state.warning_alarm = self.alarms.warning.state.value
        self.fanout.event(ev)
        return ev

    def _push_state(self) -> None:
        self._last_state_push = time.monotonic()
        self.fanout.state(replace(self.state))

    def set_uplink(self, name: str, ok: bool) -> None:
        """An uplink (MQTT) reports its connection (on this loop, via the thread hand-over); it
        reaches every output through the state (``StationState.mqtt_ok``), e.g. the PLC's status."""
        if self._uplinks.get(name) == ok:
            return
        self._uplinks[name] = ok
        self.state.mqtt_ok = bool(self._uplinks.get("mqtt", False))
        self._push_state()

    def set_disk(self, store: str, ok: bool, info: dict[str, Any] | None = None) -> None:
        """A store (``records``: the running test's recorder; ``outbox``: the MQTT outbox) reports
        that its disk can (not) be written; on this loop (the outbox calls from its pump thread
        through the thread hand-over). One ``disk_full``/``disk_ok`` event per transition of a
        store; ``StationState.disk_ok`` is False while any store cannot write."""
        if self._disks.get(store, True) == ok:
            return
        self._disks[store] = ok
        info = dict(info or {})
        data: dict[str, Any] = {"store": store, "reason": info.get("reason")}
        if ok:
            data.update({k: info[k] for k in ("duration_s", "lost_rows") if k in info})
        self._emit_event(EventType.DISK_OK if ok else EventType.DISK_FULL, **data)
        self.state.disk_ok = all(self._disks.values())
        self._push_state()

    def _watch_recorder_disk(self, rec: TestRecorder) -> None:
        loop = asyncio.get_running_loop()
        # called from inside the recorder's writes (within the fan-out): decided on the next turn
        def on_disk_state(ok: bool, info: dict[str, Any]) -> None:
            call_soon_on(loop, self.set_disk, "records", ok, info)
        rec.on_disk_state = on_disk_state
        self.set_disk("records", rec.disk_ok, {"reason": "the test folder cannot be written"}
                      if not rec.disk_ok else {})

    def _restore_alarm(self) -> None:
        rec = self.alarms.restore()
        self.state.alarm = rec.state.value
        self.state.warning_alarm = self.alarms.warning.state.value
        if rec.active:
            st = self.state
            st.alarm = rec.state.value
            st.test_id = rec.test_id
            st.sample_id = rec.sample_id
            st.t_life = rec.t_life

    # ---------------------------------------------------------------- commands
    def intake_rejected(self, data: dict[str, Any]) -> None:
        """A command source refused a request before it became a command (malformed, too large:
        code 9); it is a ``command_rejected`` event like every other refusal. On this loop."""
        self._emit_event(EventType.COMMAND_REJECTED, **data)

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
                                     t_end=float(a.get("t_end") or (self.default_plan.t_end if self.default_plan
                                                                    else self.limits.t_end_default_s))),
                            source=cmd.source)
        elif cmd.kind == CommandKind.STOP:
            if self.starting is not None:
                await self._start_failed(f"start cancelled by command ({cmd.source})")
            else:
                await self.end_test("stopped by command", source=cmd.source)
        elif cmd.kind == CommandKind.ACK:
            self._emit_event(EventType.ALARM_ACK, source=cmd.source)
            self._push_state()
        elif cmd.kind == CommandKind.HOOK_REPLACED:
            self._emit_event(EventType.ALARM_CLEARED, source=cmd.source, reason="hook_replaced")
            self._push_state()
        elif cmd.kind in ALARM_COMMAND_EVENTS:      # ISA-18.2 shelve / unshelve / out of service
            data: dict[str, Any] = {"source": cmd.source}
            if cmd.args.get("alarm") is not None:
                data["alarm"] = str(cmd.args["alarm"])
            if cmd.kind == CommandKind.SHELVE:
                data["until"] = time.time() + float(cmd.args["duration_s"])
            self._emit_event(ALARM_COMMAND_EVENTS[cmd.kind], **data)
            self._push_state()
        elif cmd.kind == CommandKind.SETPOINT:
            if self.default_plan is not None:
                self.default_plan = replace(self.default_plan, t_set=float(cmd.args["t_set"]))
        return CommandReply(True, "", cmd.request_id)

    def validate(self, cmd: Command) -> Rejection | None:
        """The one validation shared by CLI, MQTT and PLC (gateway/station/commands.py)."""
        return validate(cmd, self.limits, self.state)

    # ---------------------------------------------------------------- reload
    def reload_requested(self, apply: Callable[[], None]) -> bool:
        """A new configuration is ready (called on this station's loop, so no start can slip in
        between the check and the decision). Idle: ``apply()`` is called and the station stops
        (its runner rebuilds it from the new configuration); in a test: kept, False."""
        if self.busy:
            log.info("%s: in a test; keeps the parameters it started with", self.id)
            return False
        apply()
        if self._stop_evt is not None:
            self._stop_evt.set()
        return True

    # ---------------------------------------------------------------- test lifecycle
    def start_test(self, plan: TestPlan, source: str = "station") -> None:
        """Begin the start of a test (§3a): the zero check with the motor off (when ``zero_check``
        is on), then the spin-up with the loop closed; slot 0 comes once the tension has settled
        (:meth:`_begin_test`). Nothing is recorded before it."""
        att = StartAttempt.begin(plan, self.method_values, self.control_params, self.id, source)
        self.starting = att
        st = self.state
        if self.alarms.highest() is not None:        # a new test: the hook was replaced
            self._emit_event(EventType.ALARM_CLEARED, reason="new test started")
        st.state = TestState.STARTING
        st.test_id, st.sample_id, st.grade = None, plan.sample_id, plan.grade
        st.t_set, st.t_end = plan.t_set, plan.t_end
        st.status = st.end_reason = None
        self._emit_event(EventType.TEST_STARTING, sample_id=plan.sample_id, grade=plan.grade,
                         t_set=plan.t_set, t_end=plan.t_end, zero_check=att.params.zero_check,
                         start_timeout=att.params.start_timeout)
        self._push_state()
        if att.seq.phase == SPIN_UP:          # no zero check: the spin-up begins at once
            self._enable_motor(att)

    def _enable_motor(self, att: StartAttempt) -> None:
        att.motor_enabled = True
        asyncio.get_running_loop().create_task(self._safe_stm32(self.stm32.enable()))

    def _begin_test(self, att: StartAttempt) -> None:
        """The tension has settled: the next slot is the test's slot 0 (log, method, t_life clock)."""
        plan = att.plan
        info = att.seq.sidecar()
        sess = TestSession.begin(station_id=self.id, station_dir=self.station_dir, plan=plan,
                                 method_values=self.method_values, control=self.control_params,
                                 identity=self.identity, flush_interval_s=self.flush_interval_s,
                                 controller=att.controller, start_info=info)
        self.starting = None
        self.session = sess            # the test's slot 0 is the next slot the loop processes
        self._recorder_out.recorder = sess.recorder
        self._watch_recorder_disk(sess.recorder)
        st = self.state
        st.state = TestState.BASELINE_SEARCH
        st.test_id, st.sample_id, st.grade = sess.test_id, plan.sample_id, plan.grade
        st.t_set, st.t_end = plan.t_set, plan.t_end
        st.mu_ss = st.mu_th = st.t_life = None
        st.k_b = None
        st.status = st.end_reason = None
        st.protection_stop = st.stopped = False
        st.headroom = st.t_cross = None
        st.wear_warning = False
        st.elapsed_s = 0.0
        self._emit_event(EventType.TEST_STARTED, k=0, sample_id=plan.sample_id, grade=plan.grade,
                         t_set=plan.t_set, t_end=plan.t_end, source=att.source, **info)

    async def _start_failed(self, reason: str) -> None:
        """The start is refused, timed out or cancelled (§3a): motor stopped, nothing recorded,
        `start_failed` with the reason, idle again."""
        att = self.starting
        if att is None:
            return
        self.starting = None
        self._speed_cmd = 0.0
        self._motor_off_k = self._k
        self._stm32_box.clear()         # no speed command after the STOP
        await self._safe_stm32(self.stm32.stop(reason))
        st = self.state
        st.state = TestState.IDLE
        st.status = None
        st.end_reason = reason
        self.start_failures.append({"sample_id": att.plan.sample_id, "reason": reason,
                                    "source": att.source})
        extra: dict[str, Any] = {"zero_offsets_n": att.seq.offsets} if att.seq.offsets else {}
        self._emit_event(EventType.START_FAILED, reason=reason, sample_id=att.plan.sample_id,
                         t_set=att.plan.t_set, spin_up_s=att.seq.spin_slots * self.ts, **extra)
        self._push_state()

    async def end_test(self, reason: str, source: str = "station") -> dict[str, Any] | None:
        """End the running test (completed at t_end, or aborted) and write its result."""
        sess = self.session
        if sess is None:
            return None
        mon = sess.monitor
        self._motor_off_k = self._k
        self._stm32_box.clear()         # no speed command after the STOP
        await self._safe_stm32(self.stm32.stop(reason))
        if reason in ("completed", "protection stop"):
            res = mon.close()          # slots up to the planned end that never came: MISSING
        else:                          # ended on purpose (§3): end_slot into the sidecar
            res = sess.end_on_purpose()
        test_status = "completed" if reason == "completed" else "aborted"
        out = {"test_id": sess.test_id, "station": self.id, "test_status": test_status,
               "end_reason": reason, "closed_utc": utc_iso(), "method": res.as_dict(),
               "sample_id": sess.plan.sample_id, "grade": sess.plan.grade, "t_set": sess.plan.t_set}
        st = self.state
        st.state = TestState.COMPLETED if test_status == "completed" else TestState.ABORTED
        st.status = res.status
        st.end_reason = reason
        st.stopped = res.stop_reasons == ["STOPPED"]
        self._emit_event(EventType.TEST_ENDED, k=mon.k - 1, reason=reason, source=source,
                         test_status=test_status, result=res.as_dict())
        sess.recorder.close(out)
        self.results.append(out)
        self.session = None
        self._recorder_out.recorder = None
        self._speed_cmd = 0.0
        self._push_state()
        return out

    # ---------------------------------------------------------------- the slot loop
    async def _safe_stm32(self, coro: Coroutine[Any, Any, Stm32Status | None]) -> Stm32Status | None:
        try:
            return await coro
        except Exception as e:  # a driver must not raise, but never let it kill the loop
            log.error("%s: STM32 call failed: %s", self.id, e)
            return None

    async def _poll_status(self) -> None:
        """The STM32's status while the take-up is off (idle, before the zero check): its actual
        speed (NaN when it does not answer)."""
        st = await self._safe_stm32(self.stm32.read_status())
        rpm = getattr(st, "actual_rpm", None) if st is not None else None
        self._speed_act = float(rpm) if rpm is not None else math.nan

    async def _send_speed(self, rpm: float) -> None:
        st = await self._safe_stm32(self.stm32.set_speed(rpm))
        if st is not None:
            self._speed_act = float(st.actual_rpm)

    def _post_speed(self, rpm: float) -> bool:
        try:
            return bool(self.stm32.post_speed(rpm))      # type: ignore[attr-defined]
        except Exception as e:  # a driver must not raise, but never let it kill the loop
            log.error("%s: STM32 post failed: %s", self.id, e)
            return False

    def _collect_speed(self) -> None:
        """The reply to the speed command posted in the previous slot (if any, without waiting)."""
        try:
            st = self.stm32.collect()                    # type: ignore[attr-defined]
        except Exception as e:
            log.error("%s: STM32 collect failed: %s", self.id, e)
            return
        if st is not None:
            self._speed_act = float(st.actual_rpm)

    async def _stm32_sender(self) -> None:
        """The one STM32 sender: takes the newest job from the box, one at a time, for the
        station's lifetime (no task per slot)."""
        box = self._stm32_box
        while True:
            job = await box.get()
            self._stm32_busy = True
            try:
                if job is _READ_STATUS:
                    await self._poll_status()
                else:
                    await self._send_speed(job)
            finally:
                self._stm32_busy = False

    async def _stop_stm32_sender(self, grace_s: float = 0.5) -> None:
        """The box emptied, a job on the link given up to ``grace_s`` to finish, the sender
        ended."""
        task, self._stm32_sender_task = self._stm32_sender_task, None
        self._stm32_box.clear()
        if task is None:
            return
        t_end = time.monotonic() + grace_s
        while self._stm32_busy and not task.done() and time.monotonic() < t_end:
            await asyncio.sleep(0.005)
        task.cancel()
        try:
            await task
        except (asyncio.CancelledError, Exception):
            pass

    def _stm32_idle(self) -> bool:
        return not self._stm32_busy and self._stm32_box.empty

    def _process(self, k: int, reading: MeterReading | None, lateness: float) -> SlotRecord:
        """Everything after the poll of slot k (pure computation plus buffered output)."""
        present = reading is not None
        if reading is not None:
            t1, t2 = (reading.ch2, reading.ch1) if self.swap else (reading.ch1, reading.ch2)
            t1, t2 = float(t1), float(t2)
        else:
            t1 = t2 = math.nan
        sess = self.session
        q, mask, ratio, mu = 0, 0, None, None
        y, sat = math.nan, False
        self._k = k
        if self.starting is not None:
            y, sat = self._start_slot(self.starting, k, present, t1, t2)
        if sess is not None and sess.k_start is None:
            sess.k_start = k
        kt = k - sess.k_start if sess is not None and sess.k_start is not None else k
        if sess is not None:
            out = sess.monitor.push(present, t1, t2)
            q, mask, ratio, mu = out.q, out.mask, out.ratio, out.mu
            tm = (t1 + t2) / 2.0 if present else None
            speed = self._speed_act if math.isfinite(self._speed_act) else self._speed_cmd
            c = sess.controller.step(tm, speed)
            y, sat = c.y, c.saturated
            self._speed_cmd = c.u
            self._handle_method_events(sess, out, kt)
        self.state.saturation = sat
        rec = SlotRecord(k=kt, t=round(kt * self.ts + min(lateness, self.ts / 2 - 1e-4), 4)
                         if sess is not None else k * self.ts,
                         present=present, t1=t1, t2=t2, q=q, mask=mask, ratio=ratio, mu=mu,
                         mean_filt=y, speed_cmd=self._speed_cmd, speed_act=self._speed_act,
                         saturated=sat, lateness_s=lateness,
                         rtt_s=reading.rtt_s if reading is not None else math.nan)
        self.fanout.record(rec)
        return rec

    def _start_slot(self, att: StartAttempt, k: int, present: bool, t1: float,
                    t2: float) -> tuple[float, bool]:
        """One slot of the start sequence (§3a); the decisions it leads to are taken in
        :meth:`_after_slot`. Returns (y, saturated) of the controller (NaN while the motor is off)."""
        seq = att.seq
        if seq.phase == ZERO_CHECK:
            self._speed_cmd = 0.0
            if not att.zero_begun and att.reason is None:
                # the zero check judges the yarn at rest through an open port: it waits (at most
                # start_timeout) for the meter's port and for the take-up to have run down
                att.wait_slots += 1
                port_ok = bool(self.meter.connected)
                moving = math.isfinite(self._speed_act) and abs(self._speed_act) > REST_RPM
                if port_ok and not moving and (k - self._motor_off_k) * self.ts >= REST_S:
                    att.zero_begun = True
                elif att.wait_slots * self.ts >= att.params.start_timeout:
                    t = f"{att.params.start_timeout:g} s"
                    att.reason = (f"zero check not possible: the meter's port is not open after {t}"
                                  if not port_ok else f"zero check not possible: the take-up still "
                                  f"turns after {t} ({self._speed_act:.0f} rpm)")
                    return math.nan, False
                else:
                    return math.nan, False
            seq.zero_slot(present, t1, t2)
            return math.nan, False
        if seq.phase != SPIN_UP:
            return math.nan, False
        speed = self._speed_act if math.isfinite(self._speed_act) else self._speed_cmd
        c = att.controller.step((t1 + t2) / 2.0 if present else None, speed)
        self._speed_cmd = c.u
        seq.spin_slot(present, t1, t2, c.y)
        return c.y, c.saturated

    def _handle_method_events(self, sess: TestSession, out: SlotOut, kt: int) -> None:
        mon = sess.monitor
        st = self.state
        st.elapsed_s = (kt + 1) * self.ts
        for e in out.events:
            if e == "baseline":
                st.state = TestState.MONITORING
                st.mu_ss, st.mu_th, st.k_b = mon.mu_ss, mon.mu_th, mon.k_b
                self._emit_event(EventType.BASELINE, k=kt, mu_ss=mon.mu_ss, mu_th=mon.mu_th,
                                 k_b=mon.k_b, stable_first=mon.stable_first)
                self._push_state()
            elif e == "end_of_life" and mon.k_life is not None:
                st.state = TestState.END_OF_LIFE
                st.t_life = mon.k_life * self.ts
                self._emit_event(EventType.END_OF_LIFE, k=kt, k_life=mon.k_life, t_life=st.t_life,
                                 mu_ss=mon.mu_ss, mu_th=mon.mu_th, sample_id=sess.plan.sample_id)
                self._push_state()
            elif e == "window" and out.window is not None:
                # §5a, informative: every window's headroom and projection reach the outputs
                w = out.window
                if w.headroom is not None:
                    st.headroom, st.t_cross = w.headroom, w.t_cross
                self._push_state()
            elif e == "wear_warning" and (wear := mon.wear) is not None and wear.warn_slot is not None:
                st.wear_warning = True
                self._emit_event(EventType.WEAR_WARNING, k=kt, warn_slot=wear.warn_slot,
                                 t_warn=(wear.warn_slot + 1) * self.ts, headroom=wear.headroom,
                                 t_cross=wear.t_cross, h_warn=sess.params.h_warn,
                                 n_warn=sess.params.n_warn, mu_ss=mon.mu_ss, mu_th=mon.mu_th,
                                 sample_id=sess.plan.sample_id)
                self._push_state()
            elif e == "protection_stop":
                st.protection_stop = True
                r = mon.result()
                self._emit_event(EventType.PROTECTION_STOP, k=kt, stop_reasons=r.stop_reasons)

    async def _after_slot(self) -> None:
        """Lifecycle decisions after a slot: the start sequence's, protection stop, planned end."""
        att = self.starting
        if att is not None:
            ph = att.seq.phase
            if att.reason is not None:
                await self._start_failed(att.reason)
            elif ph == SPIN_UP and not att.motor_enabled:
                self._enable_motor(att)
            elif ph == SETTLED:
                self._begin_test(att)
                self._push_state()
            elif ph == FAILED:
                # a silent meter is named with its port and settings (drivers/zns.py diagnosis)
                note = getattr(self.meter, "diagnosis", lambda: None)()
                await self._start_failed((att.seq.reason or "start failed") + (f": {note}" if note else ""))
            return
        mon = self.monitor
        if mon is None:
            return
        if mon.stop_slot is not None:
            # §3: command the motor to stop at once, then close the test
            await self.end_test("protection stop")
        elif mon.finished:
            await self.end_test("completed")

    def _link_health(self) -> None:
        """Port state to events and the station state, checked once a second. A port lost and back
        between two checks (a meter gone for 0.5 s) still gives its ``port_lost``/``port_back``
        pair: the drivers count every loss (``counters["port_lost"]``)."""
        changed = False
        for port, drv in (("meter", self.meter), ("stm32", self.stm32)):
            ok = bool(drv.connected)
            was = self._port_seen.get(port)
            lost_n = int(drv.counters.get("port_lost", 0))
            lost_before = self._port_lost_seen.get(port, lost_n)
            if was is not None:
                if ok != was:
                    self._emit_event(EventType.PORT_BACK if ok else EventType.PORT_LOST, port=port)
                elif ok and lost_n > lost_before:    # lost and back since the last check
                    self._emit_event(EventType.PORT_LOST, port=port, brief=True,
                                     times=lost_n - lost_before)
                    self._emit_event(EventType.PORT_BACK, port=port, brief=True)
            if ok != was:
                changed = True
            self._port_seen[port] = ok
            self._port_lost_seen[port] = lost_n
        self.state.meter_ok = bool(self._port_seen["meter"])
        self.state.stm32_ok = bool(self._port_seen["stm32"])
        if changed:
            self._push_state()

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

        if self.starting is not None:
            await step("start", self._start_failed("gateway shutdown before slot 0"))
        if self.session is not None:
            await step("test", self.end_test("gateway shutdown"))
        self.starting = None
        self.session = None
        self._recorder_out.recorder = None
        await step("stm32 sender", self._stop_stm32_sender())
        await step("stm32 stop", self._safe_stm32(self.stm32.stop("gateway shutdown")))
        await step("meter port", self.meter.close())
        await step("stm32 port", self.stm32.close())
        await step("outputs", self.fanout.stop())
        log.info("%s: slot stats %s", self.id, self.stats.summary())

    async def _run(self, stop: asyncio.Event, max_slots: int | None) -> None:
        for d, res in recover_incomplete(self.station_dir):
            self._emit_event(EventType.TEST_ENDED, of_test=res["test_id"], reason="gateway restart",
                             test_status="aborted", test_dir=d, result=res.get("method"),
                             sample_id=res.get("sample_id"), grade=res.get("grade"),
                             t_set=res.get("t_set"))
        self._restore_alarm()
        await self.fanout.start()
        if self.reloaded:
            self._emit_event(EventType.CONFIG_RELOADED)
        await self.meter.open()
        await self.stm32.open()
        # make sure the motor is stopped when the gateway starts
        await self._safe_stm32(self.stm32.stop("gateway start"))
        if self._stm32_sender_task is None:
            self._stm32_sender_task = asyncio.get_running_loop().create_task(
                self._stm32_sender(), name=f"{self.id} stm32 sender")
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
        clock = self.clock
        k = 0
        last_idle_status = 0.0
        while not stop.is_set() and (max_slots is None or k < max_slots):
            lateness = await clock.wait_for(k)
            if lateness > self.ts / 2:
                # overrun: the slots whose window has passed are MISSING; never shift the grid
                k_now = clock.slot_at(clock.clock())
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
            if self._stm32_post:
                self._collect_speed()
            self.stats.slots += 1
            if reading is not None:
                self.stats.filled += 1
                if reading.rtt_s is not None:
                    self.stats.rtt.append(reading.rtt_s)
            self._process(k, reading, lateness)
            mon = self.monitor
            att = self.starting
            if ((mon is not None and mon.stop_slot is None and not mon.finished)
                    or (att is not None and att.motor_enabled and att.seq.motor_on)):
                if self._stm32_post:
                    if not self._post_speed(self._speed_cmd):   # the link busy or gone
                        self.stats.stm32_busy_skips += 1
                elif self._stm32_box.put(self._speed_cmd):     # never waits for the link
                    self.stats.stm32_busy_skips += 1
            await self._after_slot()
            now = time.monotonic()
            waiting = att is not None and self.starting is att and not att.zero_begun
            if ((not self.busy or waiting) and now - last_idle_status
                    >= (min(0.2, self.idle_status_interval_s) if waiting
                        else self.idle_status_interval_s)):
                last_idle_status = now
                if self._stm32_idle():
                    self._stm32_box.put(_READ_STATUS)
            if now - self._last_state_push >= 1.0:
                self._link_health()
                for name in self.alarms.expired(time.time()):   # a shelving ran out
                    self._emit_event(EventType.ALARM_UNSHELVED, alarm=name, expired=True)
                self._push_state()
            k += 1
