"""One test on a station: its plan, method monitor, controller and recorder, from start to end.

The station's slot loop owns at most one :class:`TestSession` at a time; the session's recorder
is fed through :class:`RecorderOutput`, an ordinary output placed first in the station's fan-out.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from .. import __version__
from ..control import Controller, ControlParams
from ..method.core import StreamingMonitor
from ..method.params import MethodParams, build_params
from ..records import Event, SlotRecord, StationState
from .recorder import TestRecorder, new_test_dir, utc_iso


@dataclass
class TestPlan:
    __test__ = False  # not a pytest test class
    sample_id: str
    grade: str | None
    t_set: float
    t_end: float



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

    @classmethod
    def begin(cls, *, station_id: str, station_dir: str, plan: TestPlan,
              method_values: dict[str, Any], control: ControlParams, identity: dict[str, Any],
              flush_interval_s: float, start_wall: float | None = None) -> TestSession:
        """Build the method and controller of ``plan`` and open its test folder."""
        values = dict(method_values)
        values["t_set"] = plan.t_set
        values["t_end"] = plan.t_end
        p = build_params(values, f"station {station_id}")
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
        rec = TestRecorder(test_dir, meta, flush_interval_s)
        return cls(test_id=test_id, plan=plan, params=p, monitor=StreamingMonitor(p),
                   controller=Controller(control, plan.t_set), recorder=rec)


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
