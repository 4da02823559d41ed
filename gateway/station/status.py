"""The one place a station's state changes: its :class:`~gateway.core.records.StationState`, its events
and their hand-over to the outputs.

A :class:`StatusBoard` owns the state. Every change goes through :meth:`StatusBoard.update` (the
only writer of its fields) or one of the named transitions built on it (a test starting, started,
ended, a start failed, the method's events of a slot); :meth:`StatusBoard.emit` sends an event
to the alarm store first (the outputs read it) and then to every output; :meth:`StatusBoard.push`
hands a copy of the state to every output. The slot loop decides *when*; this module says *what*
each change writes.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import fields, replace
from typing import Any

from ..core.method.core import SlotOut
from ..core.method.prior import Prior
from ..core.ports import DriveStop
from ..core.records import Event, EventType, StationState, TestState
from .alarm_store import AlarmStore
from .fanout import Fanout
from .session import TestPlan, TestSession

__all__ = ["StatusBoard"]

log = logging.getLogger("hookwatch.station")

_FIELDS = frozenset(f.name for f in fields(StationState))
#: the §5a/§5b projections, cleared outside a test and from the end-of-life detection on
NO_PROJECTION: dict[str, Any] = {"end_p10": None, "end_p50": None, "end_p90": None, "p_end": None,
                                 "t_cross": None, "due": False}
#: … and the rest of the §5b/§7a figures, none outside a test (the contract of issue 20)
NO_FORECAST: dict[str, Any] = {"prior_mean": None, "prior_sd": None, "prior_source": None,
                               "prior_n": None, "prior_n_censored": None, "prior_n_early": None,
                               "lead_s": None, "p_due": None, "warn_reasons": [],
                               "test_started_utc": None}


class StatusBoard:
    """A station's state, events and their fan-out (see the module doc). ``test_id`` gives the
    running test's id (events belong to it unless told otherwise)."""

    def __init__(self, station_id: str, alarms: AlarmStore, fanout: Fanout,
                 test_id: Callable[[], str | None]) -> None:
        self.id = station_id
        self.alarms = alarms
        self.fanout = fanout
        self._test_id = test_id
        self.state = StationState(station=station_id)
        #: when the state last went to the outputs (time.monotonic())
        self.last_push = 0.0

    # ---------------------------------------------------------------- the primitives
    def update(self, push: bool = False, **values: Any) -> None:
        """The one writer of the state's fields; ``push``: hand the new state to the outputs."""
        unknown = set(values) - _FIELDS
        if unknown:
            raise AttributeError(f"StationState has no field(s) {', '.join(sorted(unknown))}")
        st = self.state
        for name, v in values.items():
            setattr(st, name, v)
        if push:
            self.push()

    def push(self) -> None:
        self.last_push = time.monotonic()
        self.fanout.state(replace(self.state))

    def emit(self, etype: EventType, k: int | None = None, *, of_test: str | None = None,
             **data: Any) -> Event:
        """One event to the alarm store and every output; ``of_test``: the test it belongs to
        when that is not the running one (a cut-off test closed at start-up)."""
        return self.emit_data(etype, data, k, of_test=of_test)

    def emit_data(self, etype: EventType, data: Mapping[str, object], k: int | None = None, *,
                  of_test: str | None = None) -> Event:
        """:meth:`emit` with the event's data as one mapping (a command's refusal, an alarm
        command's arguments)."""
        data = dict(data)
        ev = Event(type=etype, station=self.id, wall_time=time.time(),
                   test_id=of_test if of_test is not None else self._test_id(), k=k, data=data)
        log.info("%s: %s %s", self.id, etype.value, data or "")
        self.alarms.on_event(ev)              # the alarm store first: outputs read it
        self.update(alarm=self.alarms.state.value, warning_alarm=self.alarms.warning.state.value)
        self.fanout.event(ev)
        return ev

    def restore_alarm(self) -> None:
        """The alarms as the store kept them across a restart (an open end of life: its test)."""
        rec = self.alarms.restore()
        self.update(alarm=rec.state.value, warning_alarm=self.alarms.warning.state.value)
        if rec.active:
            self.update(test_id=rec.test_id, sample_id=rec.sample_id, t_life=rec.t_life)

    # ---------------------------------------------------------------- the test's transitions
    def test_starting(self, plan: TestPlan, **data: Any) -> None:
        """A start (§3a) begins: STARTING; a raised alarm is closed (a new test: a new hook)."""
        if self.alarms.highest() is not None:
            self.emit(EventType.ALARM_CLEARED, reason="new test started")
        self.update(state=TestState.STARTING, test_id=None, sample_id=plan.sample_id,
                    grade=plan.grade, t_set=plan.t_set, t_end=plan.t_end, status=None,
                    end_reason=None)
        self.emit(EventType.TEST_STARTING, sample_id=plan.sample_id, grade=plan.grade,
                  t_set=plan.t_set, t_end=plan.t_end, **data)
        self.push()

    def test_started(self, sess: TestSession, source: str, info: dict[str, Any],
                     prior: Prior | None = None) -> None:
        """Slot 0 comes next: BASELINE_SEARCH with the figures of the last test cleared, the test's
        life prior (§7a) and the §5b parameters in the state."""
        plan, p = sess.plan, sess.params
        src = (prior.label or prior.source) if prior is not None and p.prior_mean is not None else None
        # how many lives it came from (§7a v3: wear-out failures, censored lives, early failures)
        counts = ({"prior_n": prior.n, "prior_n_censored": prior.n_censored,
                   "prior_n_early": prior.n_early} if prior is not None and src is not None
                  else {"prior_n": None, "prior_n_censored": None, "prior_n_early": None})
        self.update(state=TestState.BASELINE_SEARCH, test_id=sess.test_id, sample_id=plan.sample_id,
                    grade=plan.grade, t_set=plan.t_set, t_end=plan.t_end, mu_ss=None, mu_th=None,
                    t_life=None, k_b=None, status=None, end_reason=None, protection_stop=False,
                    stopped=False, wear_warning=False, elapsed_s=0.0,
                    prior_mean=p.prior_mean, prior_sd=p.prior_sd, prior_source=src, **counts,
                    lead_s=p.lead, p_due=p.p_due, warn_reasons=[],
                    test_started_utc=sess.recorder.meta.get("start_time"), headroom=None,
                    **NO_PROJECTION)
        self.emit(EventType.TEST_STARTED, k=0, sample_id=plan.sample_id, grade=plan.grade,
                  t_set=plan.t_set, t_end=plan.t_end, source=source, prior_mean=p.prior_mean,
                  prior_sd=p.prior_sd, prior_source=src, **counts, **info)
        self.push()

    def start_failed(self, reason: str, **data: Any) -> None:
        """The start was refused, timed out or cancelled: IDLE again, ``start_failed``."""
        self.update(state=TestState.IDLE, status=None, end_reason=reason)
        self.emit(EventType.START_FAILED, reason=reason, **data)
        self.push()

    def test_ended(self, k: int, reason: str, source: str, test_status: str, result: Any,
                   drive_stop: DriveStop | None = None) -> None:
        """The test is closed (completed or aborted) with the method's ``result``; ``drive_stop``:
        the drive stopped on its own during it (its sentence is the end's ``why``)."""
        self.update(state=TestState.COMPLETED if test_status == "completed" else TestState.ABORTED,
                    status=result.status, end_reason=reason,
                    stopped=result.stop_reasons == ["STOPPED"], **NO_PROJECTION, **NO_FORECAST)
        self.emit(EventType.TEST_ENDED, k=k, reason=reason, source=source, test_status=test_status,
                  result=result.as_dict(), why=drive_stop.words() if drive_stop is not None else None,
                  drive_stop=drive_stop.as_data() if drive_stop is not None else None)

    def drive_stopped(self, ds: DriveStop) -> None:
        """The STM32 stopped the drive on its own (its watchdog, a trip): ``drive_stopped``, the
        sentence in ``why`` (and in the station's log with the event)."""
        self.emit_data(EventType.DRIVE_STOPPED, ds.as_data())

    def method_events(self, sess: TestSession, out: SlotOut, kt: int, ts: float) -> None:
        """The method's events of test slot ``kt`` (baseline, end of life, a §5a window, the wear
        warning, a protection stop) into the state and out as station events."""
        mon = sess.monitor
        self.update(elapsed_s=(kt + 1) * ts)
        for e in out.events:
            if e == "baseline":
                self.update(state=TestState.MONITORING, mu_ss=mon.mu_ss, mu_th=mon.mu_th, k_b=mon.k_b)
                self.emit(EventType.BASELINE, k=kt, mu_ss=mon.mu_ss, mu_th=mon.mu_th, k_b=mon.k_b,
                          stable_first=mon.stable_first)
                self.push()
            elif e == "end_of_life" and mon.k_life is not None:
                # from the detection on the end-of-life alarm speaks, not the forecast (§5b)
                self.update(state=TestState.END_OF_LIFE, t_life=mon.k_life * ts, **NO_PROJECTION)
                self.emit(EventType.END_OF_LIFE, k=kt, k_life=mon.k_life, t_life=self.state.t_life,
                          mu_ss=mon.mu_ss, mu_th=mon.mu_th, sample_id=sess.plan.sample_id)
                self.push()
            elif e == "window" and out.window is not None:
                # §5a, informative: every window's headroom and projection reach the outputs (the
                # projection only before the end of life was detected)
                w = out.window
                if w.headroom is not None:
                    self.update(headroom=w.headroom)
                    if mon.k_life is None:
                        self.update(t_cross=w.t_cross)
                if out.forecast is None:
                    self.push()
            elif e == "forecast" and (fc := out.forecast) is not None:
                # §5b: every forecast time's e_p and P as found (state only, no event stream)
                self.update(end_p10=fc.e10, end_p50=fc.e50, end_p90=fc.e90, p_end=fc.p_end,
                            due=fc.due)
                self.push()
            elif e == "wear_warning" and (fc := out.forecast) is not None and fc.warning:
                # the first due window (§5b): at most once per test, never at or after k_det
                self.update(wear_warning=True, warn_reasons=list(fc.reasons))
                self.emit(EventType.WEAR_WARNING, k=kt, warn_slot=fc.last_slot, t_warn=fc.t,
                          reasons=list(fc.reasons), end_p10=fc.e10, end_p50=fc.e50, end_p90=fc.e90,
                          p_end=fc.p_end, lead_s=sess.params.lead, headroom=fc.headroom,
                          t_cross=fc.t_cross, h_warn=sess.params.h_warn, n_warn=sess.params.n_warn,
                          mu_ss=mon.mu_ss, mu_th=mon.mu_th, sample_id=sess.plan.sample_id)
                self.push()
            elif e == "protection_stop":
                self.update(protection_stop=True)
                self.emit(EventType.PROTECTION_STOP, k=kt, stop_reasons=mon.result().stop_reasons)
