"""The one alarm store: the end-of-life alarm of a station, kept on disk across restarts.

The station changes it (end of life → active, ACK → acknowledged, a new test → none) and every
output reads it: the PLC through ``StationState.alarm``, MQTT through :attr:`AlarmStore.record`
(the retained ``alarm/end_of_life`` message). It is written to ``<station dir>/alarm.json``
atomically, so after a gateway restart the PLC and the MES see the same alarm until a new test
starts. The states are :class:`gateway.records.AlarmState` (one enum; an ISA-18.2 model would
replace this module and that enum).

Transitions are driven by the station's events (:meth:`AlarmStore.on_event`), so the store is
an ordinary listener placed first in the station's fan-out.
"""
from __future__ import annotations

import datetime as _dt
import json
import logging
import os
from dataclasses import asdict, dataclass, replace
from typing import Any

from ..records import AlarmState, Event, EventType

log = logging.getLogger("hookwatch.alarms")


def iso_ms(t: float) -> str:
    """UTC ISO 8601 with milliseconds and Z."""
    d = _dt.datetime.fromtimestamp(round(float(t), 3), tz=_dt.UTC)
    return d.strftime("%Y-%m-%dT%H:%M:%S.") + f"{d.microsecond // 1000:03d}Z"


@dataclass(frozen=True)
class AlarmRecord:
    """The end-of-life alarm as it stands (also after it was cleared: what it was about)."""
    state: AlarmState = AlarmState.NONE
    raised: bool = False                 # False: there never was an alarm (nothing to publish)
    acknowledged: bool = False
    test_id: str | None = None
    sample_id: str | None = None
    t_life: float | None = None
    k_life: int | None = None
    mu_ss: float | None = None
    mu_th: float | None = None
    raised_at: str | None = None
    acknowledged_at: str | None = None
    acknowledged_by: str | None = None
    cleared_at: str | None = None

    @property
    def active(self) -> bool:
        return self.state != AlarmState.NONE

    def as_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["alarm"] = d.pop("state").value          # the key alarm.json always had
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> AlarmRecord:
        state = AlarmState(d.get("alarm", "none"))
        names = {f for f in cls.__dataclass_fields__ if f != "state"}
        kw = {k: v for k, v in d.items() if k in names}
        kw.setdefault("raised", state != AlarmState.NONE)
        kw.setdefault("acknowledged", state == AlarmState.ACKNOWLEDGED)
        return cls(state=state, **kw)


class AlarmStore:
    """The persisted alarm of one station. ``path`` None: in memory only (an output on its own)."""

    def __init__(self, path: str | None, station_id: str = "") -> None:
        self.path = path
        self.station_id = station_id
        self.record = AlarmRecord()
        self.write_errors = 0

    @property
    def state(self) -> AlarmState:
        return self.record.state

    # -- persistence
    def restore(self) -> AlarmRecord:
        """Read the kept alarm (a missing or unreadable file: no alarm, one log line)."""
        if self.path is None:
            return self.record
        try:
            with open(self.path, encoding="utf-8") as f:
                self.record = AlarmRecord.from_json(json.load(f))
        except FileNotFoundError:
            pass
        except (OSError, ValueError, TypeError) as e:
            log.error("%s: alarm state %s unreadable (%s); starting with none", self.station_id,
                      self.path, e)
        if self.record.active:
            log.info("%s: end-of-life alarm of test %s restored: %s", self.station_id,
                     self.record.test_id, self.record.state.value)
        return self.record

    def _save(self) -> None:
        if self.path is None:
            return
        try:
            os.makedirs(os.path.dirname(self.path) or ".", exist_ok=True)
            tmp = self.path + ".tmp"
            with open(tmp, "w", encoding="utf-8") as f:
                json.dump(self.record.as_json(), f)
            os.replace(tmp, self.path)
        except OSError as e:
            self.write_errors += 1
            if self.write_errors == 1:
                log.error("%s: cannot keep the alarm state in %s: %s (the alarm stands in memory)",
                          self.station_id, self.path, e)

    def _set(self, rec: AlarmRecord) -> None:
        self.record = rec
        self._save()

    # -- transitions (driven by the station's events)
    def on_event(self, ev: Event) -> None:
        et, d, t = ev.type, ev.data, ev.wall_time
        if et == EventType.END_OF_LIFE:
            self._set(AlarmRecord(
                state=AlarmState.ACTIVE, raised=True, acknowledged=False, test_id=ev.test_id,
                sample_id=d.get("sample_id"), t_life=d.get("t_life"), k_life=d.get("k_life"),
                mu_ss=d.get("mu_ss"), mu_th=d.get("mu_th"), raised_at=iso_ms(t)))
        elif et == EventType.ALARM_ACK:
            self._set(replace(self.record, state=AlarmState.ACKNOWLEDGED, raised=True,
                              acknowledged=True, acknowledged_at=iso_ms(t),
                              acknowledged_by=d.get("source")))
        elif et == EventType.ALARM_CLEARED:
            self._set(replace(self.record, state=AlarmState.NONE, cleared_at=iso_ms(t)))
