"""One test on a station: its plan, method monitor, controller and recorder, from start to end.

Before slot 0 a :class:`~.starting.StartAttempt` runs METHOD.md §3a (zero check with the motor off, spin-up
with the loop closed); it records nothing. Once the tension has settled, its controller goes on
into the :class:`TestSession` (the loop stays closed) and its settle time and zero offsets go into
the sidecar (``start:``, information only).

The station's slot loop owns at most one :class:`TestSession` at a time; the session's recorder
is fed through :class:`RecorderOutput`, an ordinary output placed first in the station's fan-out.
"""
from __future__ import annotations

import asyncio
import shutil
import time
from dataclasses import dataclass, field
from typing import Any

from .. import __version__
from ..core.control import Controller, ControlParams
from ..core.method.core import StreamingMonitor
from ..core.method.params import MethodParams, build_params
from ..core.method.prior import Prior
from ..core.ports import DriveStop
from ..core.records import Event, SlotRecord, StationState
from .recorder import TestRecorder, new_test_dir, utc_iso


@dataclass
class TestPlan:
    __test__ = False  # not a pytest test class
    sample_id: str
    grade: str | None
    t_set: float
    t_end: float


def plan_params(plan: TestPlan, method_values: dict[str, Any], station_id: str) -> MethodParams:
    """The method parameters of ``plan`` (the station's values with the plan's t_set and t_end)."""
    values = dict(method_values)
    values["t_set"] = plan.t_set
    values["t_end"] = plan.t_end
    return build_params(values, f"station {station_id}")


@dataclass
class TestSession:
    """A running test: what the slot loop needs between its start and its end."""
    __test__ = False
    test_id: str
    plan: TestPlan
    params: MethodParams
    monitor: StreamingMonitor
    controller: Controller
    recorder: TestRecorder
    k_start: int | None = None        # the loop's slot that is the test's slot 0
    #: the test's end is claimed (:meth:`~.lifecycle.TestLifecycle.end_test`, synchronously,
    #: before its first await): whoever comes second (a stop, the planned end, a protection stop,
    #: a replaced hook, the shutdown) finds it taken and ends nothing
    ending: bool = False
    #: set once the test's result is written (what a second ender waits for)
    ended: asyncio.Event = field(default_factory=asyncio.Event)
    #: the STM32 stopped the drive on its own during the test (the first time): why it ended
    drive_stop: DriveStop | None = None

    @classmethod
    def begin(cls, *, station_id: str, station_dir: str, plan: TestPlan,
              method_values: dict[str, Any], control: ControlParams, identity: dict[str, Any],
              flush_interval_s: float, start_wall: float | None = None,
              controller: Controller | None = None,
              start_info: dict[str, Any] | None = None,
              prior: Prior | None = None) -> TestSession:
        """Build the method of ``plan`` and open its test folder; ``controller`` is the one that ran
        the spin-up (a new one without), ``start_info`` the §3a figures for the sidecar, ``prior``
        the test's life prior (§7a): its mean and SD go into the method (and so into the sidecar's
        ``method:`` section, for `hookwatch analyze` to give the same forecast), its source and
        counts beside it (``prior_source``, ``prior_n``, ``prior_n_censored``, ``prior_n_early``)."""
        values = dict(method_values)
        if prior is not None and prior.mean is not None and prior.sd is not None:
            values["prior_mean"], values["prior_sd"] = prior.mean, prior.sd
        p = plan_params(plan, values, station_id)
        start_wall = time.time() if start_wall is None else start_wall
        # a folder of its own, created exclusively (two starts within one millisecond cannot share one)
        test_id, test_dir = new_test_dir(station_dir, plan.sample_id, start_wall)
        meta = {
            "station": station_id, **{k: v for k, v in identity.items() if k != "id"},
            "test_id": test_id, "sample_id": plan.sample_id, "grade": plan.grade,
            "t_set": plan.t_set, "start_time": utc_iso(start_wall),
            "software": f"hookwatch {__version__}",
            "method": dict(p.as_dict()),
            "control": control.as_dict(),
        }
        if start_info is not None:
            meta["start"] = dict(start_info)
        if prior is not None:
            side = prior.sidecar()
            for k in ("prior_source", "prior_n", "prior_n_censored", "prior_n_early", "prior_stations",
                      "prior_from", "prior_station_ids"):
                if k in side:
                    meta[k] = side[k]
        try:
            rec = TestRecorder(test_dir, meta, flush_interval_s)
        except OSError:       # the log cannot be opened: the new folder of a test that never began goes
            shutil.rmtree(test_dir, ignore_errors=True)
            raise
        return cls(test_id=test_id, plan=plan, params=p, monitor=StreamingMonitor(p),
                   controller=controller or Controller(control, plan.t_set), recorder=rec)

    def end_on_purpose(self):
        """§3: the test is ended before its planned end by a command or a clean shutdown. The
        monitor ends after the slots pushed so far and ``end_slot`` goes into the sidecar's
        ``method:`` section, so that `hookwatch analyze` of the log gives the same result."""
        mon = self.monitor
        if mon.finished:                  # a protection stop or the planned end came first
            return mon.close()
        end_slot = mon.k
        res = mon.stop(end_slot)
        self.recorder.update_meta(["method", "end_slot"], end_slot)
        return res


class RecorderOutput:
    """The recorder as an ordinary output: it writes the current session's records and events."""

    def __init__(self) -> None:
        self.recorder: TestRecorder | None = None

    async def start(self) -> None:
        pass

    async def stop(self) -> None:
        pass

    def on_record(self, rec: SlotRecord) -> None:
        if self.recorder is not None:
            self.recorder.on_record(rec)

    def on_event(self, ev: Event) -> None:
        if self.recorder is not None:
            self.recorder.on_event(ev)

    def on_state(self, st: StationState) -> None:
        pass
