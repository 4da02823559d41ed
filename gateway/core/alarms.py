"""ISA-18.2 alarm states of a station's alarms, as a pure model: no I/O, no clock, no asyncio.

The ONE definition of the alarm states (ANSI/ISA-18.2-2016, the alarm state transition
diagram), used by the station's alarm store and shown the same way over MQTT, Sparkplug and the
PLC registers:

====================  =========  ============  ============================================
state                 condition  acknowledged  meaning for the operator
====================  =========  ============  ============================================
normal                no         yes           nothing to do
unacknowledged        yes        no            new alarm: look at it (annunciated)
acknowledged          yes        yes           known, still standing (e.g. the worn hook is
                                               still in the machine)
rtn_unacknowledged    no         no            returned to normal before anyone acknowledged
shelved               any        any           silenced by an operator until ``shelved_until``
out_of_service        any        any           taken out of service (a needle is being changed)
====================  =========  ============  ============================================

Transitions (each yields exactly one :class:`Transition`, the event record to publish/persist):
  normal → unacknowledged (``activate``), unacknowledged → acknowledged (``acknowledge``),
  unacknowledged → rtn_unacknowledged (``return_to_normal``), acknowledged → normal
  (``return_to_normal``), rtn_unacknowledged → normal (``acknowledge``), any annunciated state →
  shelved (``shelve``, with an expiry) → back by ``unshelve`` or at the expiry (``tick``), any →
  out_of_service (``remove_from_service``) → back (``return_to_service``), and any state but normal
  → normal by ``hook_replaced`` (the replaced hook's alarm is closed: condition gone and
  acknowledged by the replacement). Returning from shelved or out of service lands in
  unacknowledged when the condition still stands, else normal.

An end of life is a condition that does not go away by itself: the worn hook stays worn until it
is replaced. Its usual path is unacknowledged → acknowledged → (hook replaced) normal.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any

from .records import AlarmState

__all__ = ["AlarmState", "Priority", "AlarmDef", "ALARMS", "ANNUNCIATED", "SHELVE_MAX_S", "Alarm",
           "AlarmError", "Transition", "from_station"]


class Priority(enum.IntEnum):
    """ISA-18.2 priority (1 highest); also the value shown to the PLC and in Sparkplug."""
    CRITICAL = 1
    HIGH = 2
    MEDIUM = 3
    LOW = 4


@dataclass(frozen=True)
class AlarmDef:
    name: str
    priority: Priority
    doc: str


#: the station's alarms
ALARMS: dict[str, AlarmDef] = {
    "end_of_life": AlarmDef("end_of_life", Priority.CRITICAL,
                            "the hook reached the end of its life (t_life found, METHOD.md §6)"),
    "wear_warning": AlarmDef("wear_warning", Priority.HIGH,
                             "wear headroom below the early-warning level (METHOD.md §5a)"),
}

#: states in which the alarm is shown to the operator (annunciated)
ANNUNCIATED = (AlarmState.UNACKNOWLEDGED, AlarmState.ACKNOWLEDGED, AlarmState.RTN_UNACKNOWLEDGED)
#: longest shelving an operator may ask for, s (one shift of 12 h)
SHELVE_MAX_S = 12 * 3600.0


#: today's station alarm values (StationState.alarm) in ISA-18.2 terms, until the alarm store
#: keeps an :class:`Alarm` itself
FROM_STATION = {"none": AlarmState.NORMAL, "active": AlarmState.UNACKNOWLEDGED,
                "acknowledged": AlarmState.ACKNOWLEDGED}


def from_station(value: str) -> AlarmState:
    """An ISA-18.2 state from the station's alarm value (an ISA-18.2 name passes through)."""
    if value in FROM_STATION:
        return FROM_STATION[value]
    return AlarmState(value)


class AlarmError(ValueError):
    """A transition that the state does not allow (the reason names state and action)."""


@dataclass(frozen=True)
class Transition:
    """One event record: what changed, when, by whom."""
    alarm: str
    hook: str | None
    from_state: AlarmState
    to_state: AlarmState
    action: str
    time: float
    by: str | None = None
    priority: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {"alarm": self.alarm, "hook": self.hook, "from": self.from_state.value,
                "to": self.to_state.value, "action": self.action, "time": self.time, "by": self.by,
                "priority": self.priority}


@dataclass
class Alarm:
    """One alarm of one hook (a hook is named by the test/sample it is tested in)."""
    name: str
    hook: str | None = None
    state: AlarmState = AlarmState.NORMAL
    condition: bool = False              # the process condition (e.g. end of life found)
    acknowledged: bool = True
    shelved_until: float | None = None
    before_shelve: AlarmState | None = None
    raised_at: float | None = None
    acknowledged_at: float | None = None
    acknowledged_by: str | None = None
    cleared_at: float | None = None
    closed_by: str | None = None         # "hook_replaced" when the hook's replacement closed it
    data: dict[str, Any] = field(default_factory=dict)   # what the raise reported (t_life, μ …)

    def __post_init__(self) -> None:
        if self.name not in ALARMS:
            raise AlarmError(f"alarm {self.name!r} unknown; known: {', '.join(ALARMS)}")

    @property
    def priority(self) -> Priority:
        return ALARMS[self.name].priority

    # ------------------------------------------------------------------ helpers
    def _go(self, to: AlarmState, action: str, now: float, by: str | None) -> Transition:
        tr = Transition(self.name, self.hook, self.state, to, action, now, by, int(self.priority))
        self.state = to
        return tr

    def _refuse(self, action: str) -> AlarmError:
        return AlarmError(f"{self.name}: cannot {action} in state {self.state.value}")

    def _settled(self) -> AlarmState:
        """Where the alarm goes back to from shelved / out of service."""
        return AlarmState.UNACKNOWLEDGED if self.condition else AlarmState.NORMAL

    # ------------------------------------------------------------------ process condition
    def activate(self, now: float, hook: str | None = None, **data: Any) -> list[Transition]:
        """The condition came (end of life found). Shelved / out of service: remembered, silent."""
        if hook is not None:
            self.hook = hook
        self.condition = True
        self.raised_at = now
        self.cleared_at = None
        self.closed_by = None
        self.data = dict(data)
        if self.state in (AlarmState.SHELVED, AlarmState.OUT_OF_SERVICE):
            self.acknowledged = False
            return []
        if self.state in (AlarmState.UNACKNOWLEDGED, AlarmState.ACKNOWLEDGED):
            return []                    # already standing
        self.acknowledged = False
        self.acknowledged_at = self.acknowledged_by = None
        return [self._go(AlarmState.UNACKNOWLEDGED, "activate", now, None)]

    def return_to_normal(self, now: float) -> list[Transition]:
        """The condition went away by itself."""
        self.condition = False
        self.cleared_at = now
        if self.state == AlarmState.UNACKNOWLEDGED:
            return [self._go(AlarmState.RTN_UNACKNOWLEDGED, "return_to_normal", now, None)]
        if self.state == AlarmState.ACKNOWLEDGED:
            return [self._go(AlarmState.NORMAL, "return_to_normal", now, None)]
        return []

    # ------------------------------------------------------------------ operator actions
    def acknowledge(self, now: float, by: str | None = None) -> list[Transition]:
        if self.state == AlarmState.UNACKNOWLEDGED:
            to = AlarmState.ACKNOWLEDGED
        elif self.state == AlarmState.RTN_UNACKNOWLEDGED:
            to = AlarmState.NORMAL
        else:
            raise self._refuse("acknowledge")
        self.acknowledged = True
        self.acknowledged_at = now
        self.acknowledged_by = by
        return [self._go(to, "acknowledge", now, by)]

    def shelve(self, now: float, until: float, by: str | None = None) -> list[Transition]:
        if self.state not in ANNUNCIATED:
            raise self._refuse("shelve")
        if not (isinstance(until, (int, float)) and math.isfinite(until) and now < until <= now + SHELVE_MAX_S):
            raise AlarmError(f"{self.name}: shelve until {until!r}: must be later than now and at most "
                             f"{SHELVE_MAX_S:.0f} s ahead")
        self.shelved_until = float(until)
        self.before_shelve = self.state
        return [self._go(AlarmState.SHELVED, "shelve", now, by)]

    def unshelve(self, now: float, by: str | None = None, action: str = "unshelve") -> list[Transition]:
        if self.state != AlarmState.SHELVED:
            raise self._refuse("unshelve")
        self.shelved_until = None
        prev, self.before_shelve = self.before_shelve, None
        if self.condition:
            to = AlarmState.ACKNOWLEDGED if prev == AlarmState.ACKNOWLEDGED and self.acknowledged \
                else AlarmState.UNACKNOWLEDGED
        else:
            to = AlarmState.RTN_UNACKNOWLEDGED if not self.acknowledged else AlarmState.NORMAL
        return [self._go(to, action, now, by)]

    def tick(self, now: float) -> list[Transition]:
        """Time passes: a shelving expires."""
        if self.state == AlarmState.SHELVED and self.shelved_until is not None and now >= self.shelved_until:
            return self.unshelve(now, None, action="shelve_expired")
        return []

    def remove_from_service(self, now: float, by: str | None = None) -> list[Transition]:
        """Out of service while a needle is being changed (no annunciation meanwhile)."""
        if self.state == AlarmState.OUT_OF_SERVICE:
            raise self._refuse("remove from service")
        self.shelved_until = self.before_shelve = None
        return [self._go(AlarmState.OUT_OF_SERVICE, "remove_from_service", now, by)]

    def return_to_service(self, now: float, by: str | None = None) -> list[Transition]:
        if self.state != AlarmState.OUT_OF_SERVICE:
            raise self._refuse("return to service")
        to = self._settled()
        if to == AlarmState.NORMAL:
            self.acknowledged = True
        return [self._go(to, "return_to_service", now, by)]

    def hook_replaced(self, now: float, by: str | None = None) -> list[Transition]:
        """The hook this alarm is about was replaced: the alarm is closed (normal)."""
        if self.state == AlarmState.NORMAL:
            raise self._refuse("close (hook replaced)")
        self.condition = False
        self.acknowledged = True
        self.cleared_at = now
        self.shelved_until = self.before_shelve = None
        self.closed_by = "hook_replaced"
        return [self._go(AlarmState.NORMAL, "hook_replaced", now, by)]

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "hook": self.hook, "state": self.state.value, "condition": self.condition,
                "acknowledged": self.acknowledged, "shelved_until": self.shelved_until,
                "before_shelve": self.before_shelve.value if self.before_shelve else None,
                "raised_at": self.raised_at, "acknowledged_at": self.acknowledged_at,
                "acknowledged_by": self.acknowledged_by, "cleared_at": self.cleared_at,
                "closed_by": self.closed_by, "data": dict(self.data)}

    @classmethod
    def from_dict(cls, d: Any) -> Alarm:
        """Read back a persisted alarm; a damaged record raises AlarmError naming the field."""
        if not isinstance(d, dict):
            raise AlarmError(f"alarm record: expected an object, got {type(d).__name__}")
        try:
            state = AlarmState(d.get("state", "normal"))
            before = d.get("before_shelve")
            before = AlarmState(before) if before is not None else None
        except ValueError as e:
            raise AlarmError(f"alarm record: state: {e}") from None
        for k in ("shelved_until", "raised_at", "acknowledged_at", "cleared_at"):
            v = d.get(k)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
                raise AlarmError(f"alarm record: {k}: {v!r} is not a time")
        for k in ("condition", "acknowledged"):
            if not isinstance(d.get(k, False), bool):
                raise AlarmError(f"alarm record: {k}: {d.get(k)!r} is not a boolean")
        data = d.get("data") or {}
        if not isinstance(data, dict):
            raise AlarmError("alarm record: data: not an object")
        a = cls(name=str(d.get("name")), hook=d.get("hook"), state=state,
                condition=bool(d.get("condition", False)), acknowledged=bool(d.get("acknowledged", True)),
                shelved_until=d.get("shelved_until"), before_shelve=before, raised_at=d.get("raised_at"),
                acknowledged_at=d.get("acknowledged_at"), acknowledged_by=d.get("acknowledged_by"),
                cleared_at=d.get("cleared_at"), closed_by=d.get("closed_by"), data=dict(data))
        if state == AlarmState.SHELVED and a.shelved_until is None:
            raise AlarmError("alarm record: shelved without shelved_until")
        return a
