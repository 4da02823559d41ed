"""A station's tests, from the start to the end: idle → starting → running → completed | aborted.

A start (:class:`~.starting.StartAttempt`, METHOD.md §3a: zero check with the motor off, spin-up
with the loop closed; nothing recorded; a refusal, a timeout or a records folder that cannot be
written is ``start_failed`` and idle again) → slot 0 once the tension has settled (a
:class:`~.session.TestSession`) → baseline search → monitoring → end of life (runs on to t_end)
→ completed | aborted (protection stop; operator, PLC, MES stop or clean shutdown: ``end_slot`` in
the sidecar, §3). :class:`TestLifecycle` holds the start or the test in progress, computes the
method and the speed command of each slot (:meth:`TestLifecycle.slot`) and takes the decisions
after it (:meth:`TestLifecycle.after_slot`); the slot loop (:class:`~.station.Station`) calls it.
Every state change goes through the station's :class:`~.status.StatusBoard`.
"""
from __future__ import annotations

import asyncio
import logging
import math
import os
from dataclasses import dataclass
from typing import Any

from ..core.control import ControlParams
from ..core.method.core import StreamingMonitor
from ..core.ports import MeterPort
from ..core.records import EventType
from .health import Health
from .hook_log import append_hook, next_sample_id
from .priors import PriorBook, life_kind
from .recorder import disk_thread, utc_iso
from .session import RecorderOutput, TestPlan, TestSession
from .starting import StartAttempt, StartStep
from .status import StatusBoard
from .stm32link import Stm32Drive

__all__ = ["SlotResult", "TestLifecycle", "TestSetup"]

log = logging.getLogger("hookwatch.station")

#: a clean stop waits this long at most for an end of the test already under way (a command's)
CLOSE_WAIT_S = 5.0


@dataclass(frozen=True)
class TestSetup:
    """What every test of a station is built from (its configuration)."""
    __test__ = False  # not a pytest test class
    station_id: str
    station_dir: str
    ts: float
    method_values: dict[str, Any]
    control: ControlParams
    identity: dict[str, Any]
    flush_interval_s: float


@dataclass(frozen=True, slots=True)
class SlotResult:
    """The method's and the controller's figures of one slot (zeros/NaN outside a test)."""
    kt: int                     # the test's slot (the loop's slot outside a test)
    q: int = 0
    mask: int = 0
    ratio: float | None = None
    mu: float | None = None
    y: float = math.nan
    saturated: bool = False


class TestLifecycle:
    __test__ = False

    def __init__(self, setup: TestSetup, board: StatusBoard, health: Health, link: Stm32Drive,
                 meter: MeterPort, recorder_out: RecorderOutput) -> None:
        self.setup = setup
        self.board, self.health, self.link, self.meter = board, health, link, meter
        self.recorder_out = recorder_out
        self.session: TestSession | None = None
        self.starting: StartAttempt | None = None
        self.results: list[dict[str, Any]] = []
        #: starts that failed (§3a): {"sample_id", "reason", "source"}
        self.start_failures: list[dict[str, Any]] = []
        #: the speed command of the last slot, rpm
        self.speed_cmd = 0.0
        self.k = 0                      # the loop's current slot
        self.motor_off_k = 0            # loop slot of the last stop command to the take-up
        #: the §7a sources of a test's life prior (the records root's history: every station's)
        self.priors = PriorBook(setup.station_id, os.path.dirname(setup.station_dir) or ".")
        #: `test.restart_on_replace`: a replaced hook starts the next test at once
        self.restart_on_replace = False

    @property
    def monitor(self) -> StreamingMonitor | None:
        return self.session.monitor if self.session is not None else None

    @property
    def drives_motor(self) -> bool:
        """The take-up gets a speed command this slot (a test running, or a start spinning up)."""
        sess, att = self.session, self.starting
        mon = sess.monitor if sess is not None and not sess.ending else None
        return ((mon is not None and mon.stop_slot is None and not mon.finished)
                or (att is not None and att.motor_on))

    # ---------------------------------------------------------------- one slot
    def slot(self, k: int, present: bool, t1: float, t2: float) -> SlotResult:
        """The start sequence's or the test's computation of loop slot ``k`` (pure, no waiting)."""
        self.k = k
        if k == 0:                       # the station's first slot: the box's life history is read
            self.priors.refresh()        # off the loop (§7a), long before a test's slot 0
        y, sat = math.nan, False
        speed_act = self.link.speed_act
        if self.starting is not None:
            y, sat, self.speed_cmd = self.starting.slot(
                present, t1, t2, port_open=bool(self.meter.connected), speed_act=speed_act,
                speed_cmd=self.speed_cmd, off_for_s=(k - self.motor_off_k) * self.setup.ts)
        sess = self.session
        if sess is None:
            return SlotResult(kt=k, y=y, saturated=sat)
        if sess.k_start is None:
            sess.k_start = k
        kt = k - sess.k_start
        # asked BEFORE the method sees the slot: a recorder whose reserve is full (a disk outage
        # longer than it) refuses the slot, which the method then takes as LOST (rules.LOST) and the
        # recorder notes in lost_spans, so the offline analysis feeds it the same way
        out = sess.monitor.push(present, t1, t2, not sess.recorder.accepts())
        c = sess.controller.step((t1 + t2) / 2.0 if present else None,
                                 speed_act if math.isfinite(speed_act) else self.speed_cmd)
        self.speed_cmd = c.u
        self.board.method_events(sess, out, kt, self.setup.ts)
        return SlotResult(kt=kt, q=out.q, mask=out.mask, ratio=out.ratio, mu=out.mu, y=c.y,
                          saturated=c.saturated)

    def note_drive_stop(self) -> None:
        """A stop of the drive on its own the STM32 reported (its watchdog, a trip): the event
        at once, and the running test keeps it (the first) as why it ends."""
        ds = self.link.take_drive_stop()
        if ds is None:
            return
        self.board.drive_stopped(ds)
        sess = self.session
        if sess is not None and sess.drive_stop is None:
            sess.drive_stop = ds

    async def after_slot(self) -> None:
        """Lifecycle decisions after a slot: the start sequence's, protection stop, planned end."""
        self.note_drive_stop()
        att = self.starting
        if att is not None:
            step, reason = att.next_step()
            if step is StartStep.ENABLE_MOTOR:
                self._enable_motor(att)
            elif step is StartStep.SETTLED:
                refused = self._begin_test(att)
                if refused is not None:
                    await self.start_failed(refused)
            elif step is StartStep.FAILED:
                # a silent meter is named with its port and settings (drivers/meter/driver.py diagnosis)
                note = getattr(self.meter, "diagnosis", lambda: None)()
                await self.start_failed((reason or "start failed") + (f": {note}" if note else ""))
            return
        mon = self.monitor
        if mon is None:
            return
        if mon.stop_slot is not None:
            # the ports' state goes into the record before it closes: a stop caused by a vanished
            # port names the port (``port_lost``) in the test's own events, whenever the once-a-
            # second link check would have come (a loaded box can take the stop first)
            self.health.check_links()
            # §3: command the motor to stop at once, then close the test
            await self.end_test("protection stop")
        elif mon.finished:
            await self.end_test("completed")

    # ---------------------------------------------------------------- transitions
    def start_test(self, plan: TestPlan, source: str = "station") -> None:
        """Begin the start of a test (§3a); slot 0 comes once the tension has settled."""
        s = self.setup
        att = self.starting = StartAttempt.begin(plan, s.method_values, s.control, s.station_id,
                                                 source)
        self.priors.refresh()            # the history as it is now, read off the loop before slot 0
        self.board.test_starting(plan, zero_check=att.params.zero_check,
                                 start_timeout=att.params.start_timeout)
        if att.next_step()[0] is StartStep.ENABLE_MOTOR:     # no zero check: spin up at once
            self._enable_motor(att)

    async def stop_test(self, source: str, test_id: str | None = None) -> None:
        """A stop command: cancels a start in progress, else ends the running test (aborted). A
        stop naming ``test_id`` ends that test only (the desk refused it already otherwise)."""
        if test_id is not None:
            sess = self.session
            if sess is not None and sess.test_id == test_id:
                await self.end_test("stopped by command", source=source)
            return
        if self.starting is not None:
            await self.start_failed(f"start cancelled by command ({source})")
        else:
            await self.end_test("stopped by command", source=source)

    def _enable_motor(self, att: StartAttempt) -> None:
        att.motor_enabled = True
        self.link.enable_soon()

    def _begin_test(self, att: StartAttempt) -> str | None:
        """The tension has settled: the next slot is the test's slot 0 (log, method, t_life
        clock). A records folder that cannot be written refuses the start: the reason."""
        s = self.setup
        info = att.seq.sidecar()
        prior = self.priors.resolve(att.plan.grade, att.plan.t_set, s.method_values)
        try:
            sess = TestSession.begin(station_id=s.station_id, station_dir=s.station_dir,
                                     plan=att.plan, method_values=s.method_values,
                                     control=s.control, identity=s.identity,
                                     flush_interval_s=s.flush_interval_s,
                                     controller=att.controller, start_info=info, prior=prior)
        except OSError as e:        # EACCES, EROFS, ENOSPC, EMFILE: a state, never a crash
            why = e.strerror or str(e)
            log.error("%s: start of %s refused: %s cannot be written (%s)", s.station_id,
                      att.plan.sample_id, e.filename or s.station_dir, why)
            self.health.set_disk("records", False, {"reason": why})
            return f"records folder cannot be written: {why}"
        self.starting = None
        self.session = sess            # the test's slot 0 is the next slot the loop processes
        self.recorder_out.recorder = sess.recorder
        self.health.watch_recorder(sess.recorder)
        self.board.test_started(sess, att.source, info, prior)
        return None

    async def start_failed(self, reason: str) -> None:
        """The start is refused, timed out or cancelled (§3a): motor stopped, nothing recorded,
        ``start_failed`` with the reason, idle again."""
        att = self.starting
        if att is None:
            return
        self.starting = None
        self.speed_cmd = 0.0
        self.motor_off_k = self.k
        await self.link.stop(reason)         # a speed command not yet sent is withdrawn
        self.start_failures.append({"sample_id": att.plan.sample_id, "reason": reason,
                                    "source": att.source})
        self.board.start_failed(reason, **att.failure_data(self.setup.ts))

    async def end_test(self, reason: str, source: str = "station") -> dict[str, Any] | None:
        """End the running test (completed at t_end, or aborted) and write its result."""
        sess = self.session
        if sess is None or sess.ending:      # no test, or its end is already being carried out:
            return None                      # one test_ended, one result, whatever races
        sess.ending = True                   # claimed before the first await (issue 27)
        try:
            return await self._end(sess, reason, source)
        finally:
            sess.ended.set()

    async def _end(self, sess: TestSession, reason: str, source: str) -> dict[str, Any]:
        mon = sess.monitor
        self.motor_off_k = self.k
        self.speed_cmd = 0.0
        await self.link.stop(reason)         # a speed command not yet sent is withdrawn
        # the STOP's answer may be the first to tell that the drive had stopped on its own (a
        # stall of the gateway longer than the STM32's watchdog): the end says why
        self.note_drive_stop()
        if reason in ("completed", "protection stop"):
            res = mon.close()          # slots up to the planned end that never came: MISSING
        else:                          # ended on purpose (§3): end_slot into the sidecar
            res = sess.end_on_purpose()
        test_status = "completed" if reason == "completed" else "aborted"
        out = {"test_id": sess.test_id, "station": self.setup.station_id, "test_status": test_status,
               "end_reason": reason, "closed_utc": utc_iso(), "method": res.as_dict(),
               "sample_id": sess.plan.sample_id, "grade": sess.plan.grade, "t_set": sess.plan.t_set,
               "ts": sess.params.ts, "t_end": sess.params.t_end}
        ds = sess.drive_stop
        if ds is not None:
            out["why"], out["drive_stop"] = ds.words(), ds.as_data()
        self.board.test_ended(mon.k - 1, reason, source, test_status, res, ds)
        sess.recorder.close(out)
        self.results.append(out)
        self.priors.add_result(out)          # what §7a learns from (this station's and the box's)
        self.priors.refresh()
        if self.session is sess:
            self.session = None
            self.recorder_out.recorder = None
        self.speed_cmd = 0.0
        self.board.push()
        return out

    async def hook_replaced(self, source: str, sample_id: str | None, grade: str | None,
                            fallback: TestPlan | None, sample_id_max: int) -> dict[str, Any]:
        """The worn hook was replaced (issue 20): the running test ends (``hook_replaced``), its
        alarms close, one line goes to hooks.jsonl (what §7a's history and the planner read) and,
        with ``restart_on_replace``, the next test starts with the new hook."""
        st = self.board.state
        sess = self.session
        old_plan = sess.plan if sess is not None else (self.starting.plan if self.starting else None)
        if self.starting is not None:
            await self.start_failed(f"start cancelled: hook replaced ({source})")
        last = await self.end_test("hook_replaced", source=source) if sess is not None else None
        if sess is not None and last is None:    # another end of this test came first: its result
            await sess.ended.wait()
        old_sid = old_plan.sample_id if old_plan is not None else st.sample_id
        if last is None and self.results and self.results[-1].get("sample_id") == old_sid:
            last = self.results[-1]          # the old hook's last test (none: it never ran one)
        if sample_id == old_sid:        # a PLC's staged id is still the old hook's: not a new one
            sample_id = None
        new_sid = sample_id or next_sample_id(old_sid, sample_id_max)
        new_grade = grade or (old_plan.grade if old_plan is not None else st.grade)
        life = None
        if last is not None:
            m = last.get("method") or {}
            life = m.get("t_life") if m.get("t_life") is not None else (
                m.get("n_slots", 0) * self.setup.ts if m.get("n_slots") is not None else None)
        rec: dict[str, Any] = {
            "station": self.setup.station_id, "old_sample_id": old_sid, "new_sample_id": new_sid,
            "grade": new_grade, "by": source, "utc": utc_iso(),
            "test_id": last.get("test_id") if last is not None else None, "life_s": life,
            "life_kind": None}
        loop = asyncio.get_running_loop()
        if last is not None:     # §7a v3: an early failure is named as such (a scan: off the loop)
            rec["life_kind"] = await loop.run_in_executor(None, life_kind, last, self.priors.known())
        if self.board.alarms.highest() is not None:
            self.board.emit(EventType.ALARM_CLEARED, source=source, reason="hook_replaced")
        # written and synced by the disk thread (never on the slot loop: a flood of replacements
        # once cost 42 slots of 100), in order; the command's answer waits for it
        err = await loop.run_in_executor(disk_thread(), append_hook, self.setup.station_dir, rec)
        if err is not None:
            log.error("%s: hooks.jsonl cannot be written (%s); the replacement is in the event only",
                      self.setup.station_id, err)
            self.health.set_disk("records", False, {"reason": err})
        self.board.update(sample_id=new_sid, grade=new_grade)
        self.board.emit(EventType.HOOK_REPLACED, **rec, logged=err is None)
        base = old_plan or fallback
        if self.restart_on_replace and base is not None:
            self.start_test(TestPlan(sample_id=new_sid, grade=new_grade, t_set=base.t_set,
                                     t_end=base.t_end), source=source)
        self.board.push()
        return rec

    async def close(self, reason: str = "gateway shutdown") -> None:
        """A clean stop: the start in progress fails, the running test ends (aborted)."""
        try:
            if self.starting is not None:
                await self.start_failed(f"{reason} before slot 0")
            sess = self.session
            if sess is not None and await self.end_test(reason) is None:
                # its end is being carried out by a command: the result is written before the
                # ports close (bounded: the STM32's stop has its own timeout)
                await asyncio.wait_for(sess.ended.wait(), CLOSE_WAIT_S)
        finally:
            self.starting = None
            self.session = None
            self.recorder_out.recorder = None
