"""The one alarm store: the alarms of a station, kept on disk across restarts.

Two alarms, one lifecycle: ``end_of_life`` (priority 1, the most urgent: t_life was found) and
``warning`` (priority 2: the §5a early warning — the headroom stayed under h_warn for n_warn
windows; informative, it never changes the test's result). Each is raised by its event, both are
acknowledged by one ACK and cleared when a new test starts.

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

END_OF_LIFE = "end_of_life"
WARNING = "warning"
#: the alarm kinds and their priority (1 = most urgent; ISA-18.2 style): end of life outranks
#: the wear warning
PRIORITY = {END_OF_LIFE: 1, WARNING: 2}


def iso_ms(t: float) -> str:
    """UTC ISO 8601 with milliseconds and Z."""
    d = _dt.datetime.fromtimestamp(round(float(t), 3), tz=_dt.UTC)
    return d.strftime("%Y-%m-%dT%H:%M:%S.") + f"{d.microsecond // 1000:03d}Z"


@dataclass(frozen=True)
class AlarmRecord:
    """One alarm as it stands (also after it was cleared: what it was about)."""
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
    kind: str = END_OF_LIFE              # END_OF_LIFE or WARNING
    priority: int = PRIORITY[END_OF_LIFE]
    # the wear warning's figures (§5a); None for the end of life
    warn_slot: int | None = None
    t_warn: float | None = None
    headroom: float | None = None
    t_cross: float | None = None

    @property
    def active(self) -> bool:
        return self.state != AlarmState.NONE

    def as_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["alarm"] = d.pop("state").value          # the key alarm.json always had
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any], kind: str = END_OF_LIFE) -> AlarmRecord:
        state = AlarmState(d.get("alarm", "none"))
        names = {f for f in cls.__dataclass_fields__ if f not in ("state", "kind", "priority")}
        kw = {k: v for k, v in d.items() if k in names}
        kw.setdefault("raised", state != AlarmState.NONE)
        kw.setdefault("acknowledged", state == AlarmState.ACKNOWLEDGED)
        return cls(state=state, kind=kind, priority=PRIORITY[kind], **kw)


class AlarmStore:
    """The persisted alarm of one station. ``path`` None: in memory only (an output on its own)."""

    def __init__(self, path: str | None, station_id: str = "") -> None:
        self.path = path
        self.station_id = station_id
        self.record = AlarmRecord()                                  # the end of life
        self.warning = AlarmRecord(kind=WARNING, priority=PRIORITY[WARNING])   # the wear warning
        self.write_errors = 0

    @property
    def state(self) -> AlarmState:
        """The end-of-life alarm's state."""
        return self.record.state

    def records(self) -> list[AlarmRecord]:
        """Both alarms, the most urgent first."""
        return [self.record, self.warning]

    def highest(self) -> AlarmRecord | None:
        """The most urgent alarm that stands (active or acknowledged), or None."""
        return next((r for r in self.records() if r.active), None)

    # -- persistence
    def restore(self) -> AlarmRecord:
        """Read the kept alarm (a missing or unreadable file: no alarm, one log line)."""
        if self.path is None:
            return self.record
        try:
            with open(self.path, encoding="utf-8") as f:
                d = json.load(f)
            self.record = AlarmRecord.from_json(d)
            if isinstance(d.get(WARNING), dict):
                self.warning = AlarmRecord.from_json(d[WARNING], WARNING)
        except FileNotFoundError:
            pass
        except (OSError, ValueError, TypeError, AttributeError, KeyError) as e:
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
                json.dump({**self.record.as_json(), WARNING: self.warning.as_json()}, f)
            os.replace(tmp, self.path)
        except OSError as e:
            self.write_errors += 1
            if self.write_errors == 1:
                log.error("%s: cannot keep the alarm state in %s: %s (the alarm stands in memory)",
                          self.station_id, self.path, e)

    def _set(self, rec: AlarmRecord | None = None, warning: AlarmRecord | None = None) -> None:
        if rec is not None:
            self.record = rec
        if warning is not None:
            self.warning = warning
        self._save()

    @staticmethod
    def _ack(rec: AlarmRecord, t: float, source: Any) -> AlarmRecord:
        if rec.state != AlarmState.ACTIVE:
            return rec
        return replace(rec, state=AlarmState.ACKNOWLEDGED, raised=True, acknowledged=True,
                       acknowledged_at=iso_ms(t), acknowledged_by=source)

    @staticmethod
    def _clear(rec: AlarmRecord, t: float) -> AlarmRecord:
        return replace(rec, state=AlarmState.NONE, cleared_at=iso_ms(t)) if rec.active else rec

    # -- transitions (driven by the station's events)
    def on_event(self, ev: Event) -> None:
        et, d, t = ev.type, ev.data, ev.wall_time
        if et == EventType.END_OF_LIFE:
            self._set(AlarmRecord(
                state=AlarmState.ACTIVE, raised=True, acknowledged=False, test_id=ev.test_id,
                sample_id=d.get("sample_id"), t_life=d.get("t_life"), k_life=d.get("k_life"),
                mu_ss=d.get("mu_ss"), mu_th=d.get("mu_th"), raised_at=iso_ms(t)))
        elif et == EventType.WEAR_WARNING:
            self._set(warning=AlarmRecord(
                state=AlarmState.ACTIVE, raised=True, acknowledged=False, test_id=ev.test_id,
                sample_id=d.get("sample_id"), raised_at=iso_ms(t), kind=WARNING,
                priority=PRIORITY[WARNING], warn_slot=d.get("warn_slot"), t_warn=d.get("t_warn"),
                headroom=d.get("headroom"), t_cross=d.get("t_cross"),
                mu_ss=d.get("mu_ss"), mu_th=d.get("mu_th")))
        elif et == EventType.ALARM_ACK:        # one ACK acknowledges every active alarm
            src = d.get("source")
            self._set(self._ack(self.record, t, src), self._ack(self.warning, t, src))
        elif et == EventType.ALARM_CLEARED:    # a new test: every alarm is cleared
            self._set(self._clear(self.record, t), self._clear(self.warning, t))
