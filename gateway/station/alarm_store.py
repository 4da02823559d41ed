"""The one alarm store: the alarms of a station as ISA-18.2 knows them, kept on disk across restarts.

Two alarms of the same model (:mod:`gateway.core.alarms`): ``end_of_life`` (priority 1, the most
urgent: t_life was found) and ``warning`` (priority 2: the §5a early warning — informative, it
never changes the test's result). States (:class:`gateway.core.records.AlarmState`, the one enum the
PLC register, MQTT and Sparkplug show): normal → unacknowledged (raised) → acknowledged → normal
(closed: the hook was replaced / a new test started), unacknowledged → rtn_unacknowledged, shelved
with an expiry, out_of_service while a needle is being changed.

Transitions are driven by the station's events (:meth:`AlarmStore.on_event`): the store is the
first listener of the station's fan-out, applies the event to the model and writes the
transitions it caused into the event itself (``ev.data["transitions"]``, each ``{alarm, hook,
from, to, action, time, by, priority}``), so every transition travels in one station event. The
store is written to ``<station dir>/alarm.json`` atomically; a file of the old form
(``alarm``: none/active/acknowledged) still loads (none → normal, active → unacknowledged).
"""
from __future__ import annotations

import datetime as _dt
import json
import logging
import os
from dataclasses import replace
from typing import Any

from ..core.alarms import Alarm, AlarmError, Transition
from ..core.records import ALARM_END_OF_LIFE, ALARM_PRIORITY, ALARM_WARNING, AlarmRecord, AlarmState, Event, EventType
from ..plumbing import safeout

log = logging.getLogger("hookwatch.alarms")

END_OF_LIFE = ALARM_END_OF_LIFE
WARNING = ALARM_WARNING
#: the store's alarm kinds → the model's alarm names (gateway.core.alarms.ALARMS)
MODEL_NAME = {END_OF_LIFE: "end_of_life", WARNING: "wear_warning"}
KIND_OF = {v: k for k, v in MODEL_NAME.items()}
PRIORITY = ALARM_PRIORITY


def iso_ms(t: float) -> str:
    """UTC ISO 8601 with milliseconds and Z."""
    d = _dt.datetime.fromtimestamp(round(float(t), 3), tz=_dt.UTC)
    return d.strftime("%Y-%m-%dT%H:%M:%S.") + f"{d.microsecond // 1000:03d}Z"


class AlarmStore:
    """The persisted alarms of one station. ``path`` None: in memory only (an output on its own)."""

    def __init__(self, path: str | None, station_id: str = "") -> None:
        self.path = path
        self.station_id = station_id
        self.record = AlarmRecord()                                  # the end of life
        self.warning = AlarmRecord(kind=WARNING, priority=PRIORITY[WARNING])   # the wear warning
        self.models: dict[str, Alarm] = {k: Alarm(MODEL_NAME[k]) for k in (END_OF_LIFE, WARNING)}
        self.write_errors = 0

    @property
    def state(self) -> AlarmState:
        """The end-of-life alarm's state."""
        return self.record.state

    def records(self) -> list[AlarmRecord]:
        """Both alarms, the most urgent first."""
        return [self.record, self.warning]

    def by_kind(self, kind: str) -> AlarmRecord:
        return self.record if kind == END_OF_LIFE else self.warning

    def highest(self) -> AlarmRecord | None:
        """The most urgent alarm that stands (any state but normal), or None."""
        return next((r for r in self.records() if r.active), None)

    def shelved_until(self, name: str) -> float | None:
        """When the shelving of alarm ``name`` (a model name, gateway.core.alarms.ALARMS) expires, s since
        the epoch; None unless it is shelved."""
        a = self.models.get(KIND_OF.get(name, name))
        return a.shelved_until if a is not None and a.state == AlarmState.SHELVED else None

    def expired(self, now: float) -> list[str]:
        """The model names of the alarms whose shelving has expired at ``now``."""
        return [a.name for a in self.models.values()
                if a.state == AlarmState.SHELVED and a.shelved_until is not None and now >= a.shelved_until]

    # -- persistence
    def restore(self) -> AlarmRecord:
        """Read the kept alarms (a missing or unreadable file: none, one log line). The old form
        (before ISA-18.2: ``alarm`` none/active/acknowledged, no ``isa``) is migrated."""
        if self.path is None:
            return self.record
        try:
            with open(self.path, encoding="utf-8") as f:
                d = json.load(f)
            rec = AlarmRecord.from_json(d)
            warn = AlarmRecord.from_json(d[WARNING], WARNING) if isinstance(d.get(WARNING), dict) \
                else self.warning
            models = {}
            for kind, r, src in ((END_OF_LIFE, rec, d), (WARNING, warn, d.get(WARNING) or {})):
                isa = src.get("isa") if isinstance(src, dict) else None
                models[kind] = Alarm.from_dict(isa) if isinstance(isa, dict) else self._migrate(kind, r)
            self.record, self.warning, self.models = rec, warn, models
        except FileNotFoundError:
            pass
        except (OSError, ValueError, TypeError, AttributeError, KeyError) as e:
            log.error("%s: alarm state %s unreadable (%s); starting with none", self.station_id,
                      self.path, e)
        if self.record.active:
            log.info("%s: end-of-life alarm of test %s restored: %s", self.station_id,
                     self.record.test_id, self.record.state.value)
        return self.record

    @staticmethod
    def _migrate(kind: str, r: AlarmRecord) -> Alarm:
        """The model of an alarm kept in the old form."""
        return Alarm(MODEL_NAME[kind], hook=r.test_id, state=r.state, condition=r.condition,
                     acknowledged=r.acknowledged or r.state == AlarmState.NORMAL)

    def _save(self) -> None:
        if self.path is None:
            return
        try:
            os.makedirs(os.path.dirname(self.path) or ".", exist_ok=True)
            tmp = self.path + ".tmp"
            with open(tmp, "w", encoding="utf-8") as f:
                safeout.dump({**self.record.as_json(), "isa": self.models[END_OF_LIFE].to_dict(),
                              WARNING: {**self.warning.as_json(), "isa": self.models[WARNING].to_dict()}}, f)
            os.replace(tmp, self.path)
        except OSError as e:
            self.write_errors += 1
            if self.write_errors == 1:
                log.error("%s: cannot keep the alarm state in %s: %s (the alarm stands in memory)",
                          self.station_id, self.path, e)

    def _sync(self, kind: str, tr: list[Transition], **changes: Any) -> list[Transition]:
        """Copy the model's state into the record of ``kind`` (plus ``changes``)."""
        a = self.models[kind]
        rec = replace(self.by_kind(kind), state=a.state, condition=a.condition,
                      acknowledged=a.acknowledged,
                      shelved_until=iso_ms(a.shelved_until) if a.shelved_until is not None else None,
                      **changes)
        if kind == END_OF_LIFE:
            self.record = rec
        else:
            self.warning = rec
        return tr

    # -- transitions (driven by the station's events)
    def _raise(self, kind: str, ev: Event, **figures: Any) -> list[Transition]:
        a = self.models[kind]
        if a.state == AlarmState.NORMAL:       # a new alarm: the old one's figures go
            base = AlarmRecord(kind=kind, priority=PRIORITY[kind])
            if kind == END_OF_LIFE:
                self.record = base
            else:
                self.warning = base
        tr = a.activate(ev.wall_time, hook=ev.test_id)
        if not a.acknowledged:                 # raised anew (not: still standing, acknowledged)
            figures.update(acknowledged_at=None, acknowledged_by=None)
        return self._sync(kind, tr, raised=True, test_id=ev.test_id, raised_at=iso_ms(ev.wall_time),
                          cleared_at=None, **figures)

    def _each(self, names: Any, fn: Any) -> list[Transition]:
        """Apply ``fn(model) -> transitions`` to the alarms named (all when None) that allow it."""
        out: list[Transition] = []
        for kind, a in self.models.items():
            if names is not None and a.name not in names and kind not in names:
                continue
            try:
                tr = fn(a)
            except AlarmError:
                continue
            t = tr[-1].time if tr else 0.0
            extra: dict[str, Any] = {}
            if tr and tr[-1].action == "acknowledge":
                extra = {"acknowledged_at": iso_ms(t), "acknowledged_by": tr[-1].by}
            elif tr and tr[-1].to_state == AlarmState.NORMAL and tr[-1].action != "acknowledge":
                extra = {"cleared_at": iso_ms(t)}
            out += self._sync(kind, tr, **extra)
        return out

    def on_event(self, ev: Event) -> list[Transition]:
        """Apply one station event; its transitions are returned and written into
        ``ev.data["transitions"]`` (an event that changed no alarm gets none)."""
        et, d, t = ev.type, ev.data, ev.wall_time
        src = d.get("source")
        only = [d["alarm"]] if isinstance(d.get("alarm"), str) else None
        tr: list[Transition] = []
        if et == EventType.END_OF_LIFE:
            tr = self._raise(END_OF_LIFE, ev, sample_id=d.get("sample_id"), t_life=d.get("t_life"),
                             k_life=d.get("k_life"), mu_ss=d.get("mu_ss"), mu_th=d.get("mu_th"))
        elif et == EventType.WEAR_WARNING:
            tr = self._raise(WARNING, ev, sample_id=d.get("sample_id"), warn_slot=d.get("warn_slot"),
                             t_warn=d.get("t_warn"), headroom=d.get("headroom"),
                             t_cross=d.get("t_cross"), mu_ss=d.get("mu_ss"), mu_th=d.get("mu_th"),
                             reasons=d.get("reasons"), end_p10=d.get("end_p10"),
                             end_p50=d.get("end_p50"), end_p90=d.get("end_p90"),
                             p_end=d.get("p_end"), lead_s=d.get("lead_s"))
        elif et == EventType.ALARM_ACK:        # one ACK acknowledges every unacknowledged alarm
            tr = self._each(only, lambda a: a.acknowledge(t, src))
        elif et == EventType.ALARM_CLEARED:    # a new test / the hook was replaced: closed
            tr = self._each(only, lambda a: a.hook_replaced(t, src or d.get("reason")))
        elif et == EventType.ALARM_SHELVED:
            until = d.get("until")
            tr = self._each(only, lambda a: a.shelve(t, float(until) if until is not None else t, src))
        elif et == EventType.ALARM_UNSHELVED:
            tr = self._each(only, lambda a: a.tick(t) if d.get("expired") else a.unshelve(t, src))
        elif et == EventType.ALARM_OUT_OF_SERVICE:
            tr = self._each(only, lambda a: a.remove_from_service(t, src))
        elif et == EventType.ALARM_IN_SERVICE:
            tr = self._each(only, lambda a: a.return_to_service(t, src))
        else:
            return []
        if tr:
            self._save()
            ev.data["transitions"] = [x.as_dict() for x in tr]
        return tr
