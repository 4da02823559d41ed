"""The one validation of commands, shared by every source (CLI, MQTT, PLC over Modbus TCP, the
console, Sparkplug); what a door received is first made a Command by the one bounded intake
(gateway/northbound/cmdparse.py ``intake``).

``validate(cmd, limits, state)`` returns ``None`` when the command may be carried out, else a
:class:`Rejection` (a :class:`CommandReply` with ``ok=False``, a human reason naming the field,
the value and what is allowed, and a numeric ``code`` for PLCs). The same bad request gets the
same reason and code whichever door it came through; ``Station.submit`` emits the same
``command_rejected`` event for all of them.

Every door hands its commands over with :func:`submit` (and reports a request its intake refused
with :func:`refused`): the station's :class:`RefusalGate` turns refusals into bounded
``command_rejected`` events — once per kind (door, command, code) per minute, with the ``count``
— so a flood of refused commands is a few events and log lines, not one each
(``Station.submit`` is unchanged and still validates every command it gets).

The limits are a :class:`gateway.ports.StationLimits`, built once from the station's configuration
(full scale, saturation ratio, grades). Value rules (``check_t_set``, ``check_sample_id``,
``check_grade``, ``check_t_end``) are also used on their own by the Modbus TCP server to refuse an
out-of-range register write with exception 03 before anything changes.
"""
from __future__ import annotations

import asyncio
import math
import time
import weakref
from dataclasses import dataclass
from typing import Any

from ..alarms import ALARMS, ANNUNCIATED, SHELVE_MAX_S
from ..ports import SAMPLE_ID_MAX, T_END_MAX_S, StationLimits
from ..ratelog import RefusalWindow, clip
from ..records import AlarmState, Command, CommandKind, CommandReply, EventType, StationState, TestState

__all__ = ["SAMPLE_ID_MAX", "T_END_MAX_S", "REJECT_CODES", "CODE", "COMMAND_KEYS", "Rejection",
           "reject", "check_t_set", "check_sample_id", "check_grade", "check_t_end",
           "validate", "StationLimits", "ALARM_COMMAND_EVENTS", "RefusalGate", "gate_of", "submit",
           "refused"]

#: test states in which a test is running (or starting: a stop cancels the start, §3a)
RUNNING = frozenset({TestState.STARTING, TestState.BASELINE_SEARCH, TestState.MONITORING,
                     TestState.END_OF_LIFE})

#: rejection codes (served to PLCs in the "last command result" input register)
REJECT_CODES: tuple[tuple[int, str, str], ...] = (
    (0, "OK", "accepted"),
    (1, "BUSY", "a test is already running; stop it first"),
    (2, "NOT_RUNNING", "no test is running"),
    (3, "NO_ALARM", "no unacknowledged alarm (end of life or wear warning)"),
    (4, "SAMPLE_ID", f"sample_id missing, too long (> {SAMPLE_ID_MAX}) or not printable ASCII"),
    (5, "T_SET", "t_set not a number or out of range"),
    (6, "GRADE", "grade not one of the station's grades"),
    (7, "T_END", f"t_end not a number or out of range (0, {T_END_MAX_S}] s"),
    (8, "SETPOINT_LOCKED", "the setpoint of a running test cannot change"),
    (9, "BAD_REQUEST", "malformed request (unknown command, unknown key, not JSON)"),
    (10, "NO_STATION", "the station did not answer (not running or busy)"),
    (11, "ALARM", f"alarm not one of {', '.join(ALARMS)}"),
    (12, "DURATION", f"duration_s not a number in (0, {SHELVE_MAX_S:.0f}] s"),
    (13, "ALARM_STATE", "the alarm's ISA-18.2 state does not allow this command"),
)
CODE = {name: code for code, name, _ in REJECT_CODES}

#: keys each command accepts (MQTT JSON payloads; the PLC fills them from holding registers)
COMMAND_KEYS: dict[CommandKind, tuple[str, ...]] = {
    CommandKind.START: ("sample_id", "grade", "t_set", "t_end"),
    CommandKind.STOP: (),
    CommandKind.ACK: (),
    CommandKind.SETPOINT: ("t_set",),
    CommandKind.HOOK_REPLACED: ("sample_id", "grade"),
    CommandKind.SHELVE: ("alarm", "duration_s"),
    CommandKind.UNSHELVE: ("alarm",),
    CommandKind.OUT_OF_SERVICE: (),
    CommandKind.IN_SERVICE: (),
}

#: the ISA-18.2 alarm commands and the station event each becomes (the alarm store applies it)
ALARM_COMMAND_EVENTS: dict[CommandKind, EventType] = {
    CommandKind.SHELVE: EventType.ALARM_SHELVED,
    CommandKind.UNSHELVE: EventType.ALARM_UNSHELVED,
    CommandKind.OUT_OF_SERVICE: EventType.ALARM_OUT_OF_SERVICE,
    CommandKind.IN_SERVICE: EventType.ALARM_IN_SERVICE,
}
_ACKABLE = (AlarmState.UNACKNOWLEDGED.value, AlarmState.RTN_UNACKNOWLEDGED.value)


def _alarm_states(state: StationState) -> dict[str, str]:
    """The station's alarms by their ISA-18.2 name (gateway.alarms.ALARMS)."""
    return {"end_of_life": state.alarm, "wear_warning": state.warning_alarm}


def _check_alarm_command(cmd: Command, state: StationState) -> Rejection | None:
    """shelve / unshelve / out_of_service / in_service against the alarms' ISA-18.2 states."""
    a = cmd.args
    states = _alarm_states(state)
    if cmd.kind in (CommandKind.SHELVE, CommandKind.UNSHELVE):
        name = a.get("alarm")
        if name not in ALARMS:
            return reject(cmd, "ALARM", f"alarm {clip(name)}: not one of {', '.join(ALARMS)}")
        d = a.get("duration_s")
        if cmd.kind == CommandKind.SHELVE:
            if isinstance(d, bool) or not isinstance(d, (int, float)) or not 0 < d <= SHELVE_MAX_S:
                return reject(cmd, "DURATION", f"duration_s {clip(d)}: a number in (0, {SHELVE_MAX_S:.0f}] s")
            if states[name] not in {s.value for s in ANNUNCIATED}:
                return reject(cmd, "ALARM_STATE", f"{name} is {states[name]}: only an annunciated "
                              "alarm (unacknowledged, acknowledged, rtn_unacknowledged) can be shelved")
        elif states[name] != AlarmState.SHELVED.value:
            return reject(cmd, "ALARM_STATE", f"{name} is {states[name]}, not shelved")
    elif cmd.kind == CommandKind.OUT_OF_SERVICE:
        if all(v == AlarmState.OUT_OF_SERVICE.value for v in states.values()):
            return reject(cmd, "ALARM_STATE", "the alarms are already out of service")
    elif AlarmState.OUT_OF_SERVICE.value not in states.values():
        return reject(cmd, "ALARM_STATE", "no alarm is out of service")
    return None


@dataclass
class Rejection(CommandReply):
    """A refused command: ``reason`` for people, ``code`` (see REJECT_CODES) for PLCs."""
    code: int = 0


def reject(cmd: Command | None, name: str, reason: str) -> Rejection:
    return Rejection(False, reason, cmd.request_id if cmd is not None else None, CODE[name])


# ----------------------------------------------------------------------------- value rules
def check_t_set(value: Any, limits: StationLimits) -> str | None:
    lo, hi = limits.t_set_range
    try:
        v = float(value)
    except (TypeError, ValueError):
        return f"t_set: {clip(value)} is not a number (N); allowed: ({lo:g}, {hi:g}) N"
    if isinstance(value, bool) or not math.isfinite(v) or not lo < v < hi:
        return f"t_set: {clip(value)} N out of range; allowed: ({lo:g}, {hi:g}) N"
    return None


def check_sample_id(value: Any, limit: int = SAMPLE_ID_MAX) -> str | None:
    if value is None or not isinstance(value, str) or not value.strip():
        return f"sample_id: {clip(value)}: required, 1 to {SAMPLE_ID_MAX} printable ASCII characters"
    if len(value) > limit:
        return f"sample_id: {clip(value)} has {len(value)} characters; at most {limit}"
    if not all(0x20 <= ord(c) <= 0x7E for c in value):
        return f"sample_id: {clip(value)}: only printable ASCII characters (0x20–0x7E) are allowed"
    return None


def check_grade(value: Any, grades: tuple[str, ...]) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str) or value not in tuple(grades):
        return f"grade: {clip(value)} unknown; allowed: {', '.join(grades)}"
    return None


def check_t_end(value: Any, t_end_max: int = T_END_MAX_S) -> str | None:
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        return f"t_end: {clip(value)} is not a number (s); allowed: (0, {t_end_max}] s"
    if isinstance(value, bool) or not math.isfinite(v) or not 0 < v <= t_end_max:
        return f"t_end: {clip(value)} s out of range; allowed: (0, {t_end_max}] s"
    return None


def validate(cmd: Command, limits: StationLimits, state: StationState) -> Rejection | None:
    """Can a station with these ``limits``, now in ``state``, carry out ``cmd``? None if yes, else
    the reason (and code)."""
    running = state.state in RUNNING
    a = cmd.args or {}
    if cmd.kind == CommandKind.START:
        if running:
            return reject(cmd, "BUSY", "a test is already running; stop it first")
        err = check_sample_id(a.get("sample_id"), limits.sample_id_max)
        if err:
            return reject(cmd, "SAMPLE_ID", err)
        err = check_t_set(a.get("t_set"), limits)
        if err:
            return reject(cmd, "T_SET", err)
        err = check_grade(a.get("grade"), limits.grades)
        if err:
            return reject(cmd, "GRADE", err)
        err = check_t_end(a.get("t_end"), limits.t_end_max_s)
        if err:
            return reject(cmd, "T_END", err)
    elif cmd.kind == CommandKind.STOP:
        if not running:
            return reject(cmd, "NOT_RUNNING", "no test is running")
    elif cmd.kind == CommandKind.ACK:
        if state.alarm not in _ACKABLE and state.warning_alarm not in _ACKABLE:
            return reject(cmd, "NO_ALARM", "no unacknowledged alarm (end of life or wear warning)")
    elif cmd.kind == CommandKind.SETPOINT:
        if running:
            return reject(cmd, "SETPOINT_LOCKED",
                          "the setpoint of a running test cannot change (it is in its sidecar)")
        err = check_t_set(a.get("t_set"), limits)
        if err:
            return reject(cmd, "T_SET", err)
    elif cmd.kind == CommandKind.HOOK_REPLACED:
        # the new hook's sample id (optional: `<old>-R<n>`) and grade, checked as a start's are
        if a.get("sample_id") is not None:
            err = check_sample_id(a.get("sample_id"), limits.sample_id_max)
            if err:
                return reject(cmd, "SAMPLE_ID", err)
        err = check_grade(a.get("grade"), limits.grades)
        if err:
            return reject(cmd, "GRADE", err)
        if (state.alarm == AlarmState.NORMAL.value and state.warning_alarm == AlarmState.NORMAL.value
                and not running and a.get("sample_id") is None):
            return reject(cmd, "NO_ALARM", "no alarm, no test and no new sample_id: nothing to "
                          "record (name the new hook's sample_id)")
    elif cmd.kind in ALARM_COMMAND_EVENTS:
        return _check_alarm_command(cmd, state)
    else:  # pragma: no cover - CommandKind is closed
        return reject(cmd, "BAD_REQUEST", f"command {cmd.kind!r} unknown")
    return None


# ----------------------------------------------------------------------------- bounded refusals
class RefusalGate:
    """The refusals of one station as bounded ``command_rejected`` events: per kind (door,
    command, code) the first refusal of a window (:data:`gateway.ratelog.WINDOW_S`, 60 s) is an
    event at once with ``count: 1``, the others of the window are counted and become one event
    with their ``count`` when the window ends (the last one's reason and source). 3,000 refused
    PLC commands in a minute are two events (and two log lines), not 3,000; the sum of the counts
    is the number of refusals. Every request still gets its own answer.

    Used on the station's loop by every door (:func:`submit`, :func:`refused`): a command the
    station's validation refuses never reaches ``Station.submit`` (which would report it alone);
    a command it accepts is submitted as before. ``Station`` itself is not changed."""

    def __init__(self, station: Any, window_s: float | None = None):
        self.station = station
        self._w = RefusalWindow(window_s)
        self._timer: asyncio.TimerHandle | None = None
        self.refusals = 0           # every refusal counted here
        self.events = 0             # command_rejected events emitted for them

    @property
    def window_s(self) -> float:
        return self._w.window_s

    def refused(self, data: dict[str, Any]) -> None:
        """One refusal (``data``: command, source, reason, code), on the station's loop."""
        self.refusals += 1
        now = time.monotonic()
        door = str(data.get("source", "")).split(":", 1)[0]
        key = (door, str(data.get("command", "")), int(data.get("code", 0) or 0))
        self._flush(now)
        if self._w.add(key, now, data):
            self._emit(data, 1)
        else:
            self._arm(now)

    async def submit(self, cmd: Command) -> CommandReply:
        check = getattr(self.station, "validate", None)
        rej = check(cmd) if check is not None else None
        if rej is None:
            return await self.station.submit(cmd)
        self.refused({"command": cmd.kind.value, "source": cmd.source, "reason": rej.reason,
                      "code": int(rej.code)})
        return rej

    def _emit(self, data: dict[str, Any], n: int) -> None:
        emit = getattr(self.station, "intake_rejected", None)
        if emit is not None:
            self.events += 1
            emit({**data, "count": n, "window_s": self._w.window_s})

    def _flush(self, now: float) -> None:
        for _key, n, (data,) in self._w.due(now):
            self._emit(data, n)

    def _arm(self, now: float) -> None:
        at = self._w.next_due()
        if self._timer is not None or at is None:
            return
        self._timer = asyncio.get_running_loop().call_later(max(0.0, at - now) + 0.01, self._fire)

    def _fire(self) -> None:
        self._timer = None
        now = time.monotonic()
        self._flush(now)
        self._arm(now)


_GATES: weakref.WeakKeyDictionary[Any, RefusalGate] = weakref.WeakKeyDictionary()


def gate_of(station: Any) -> RefusalGate:
    """The one refusal gate of ``station`` (made on first use), shared by all its doors."""
    g = _GATES.get(station)
    if g is None:
        g = _GATES[station] = RefusalGate(station)
    return g


async def submit(station: Any, cmd: Command) -> CommandReply:
    """Every door's hand-over of a command to a station (on the station's loop): validated, and a
    refusal reported through the station's bounded gate. A sink that is not a Station (no
    ``validate``/``intake_rejected``: a remote proxy) gets ``submit`` as it is."""
    if not hasattr(station, "validate") or not hasattr(station, "intake_rejected"):
        return await station.submit(cmd)
    return await gate_of(station).submit(cmd)


def refused(station: Any, data: dict[str, Any]) -> None:
    """A door refused a request before it became a command (the intake, code 9 or 4): one more
    refusal for the station's bounded ``command_rejected`` events. On the station's loop."""
    if hasattr(station, "intake_rejected"):
        gate_of(station).refused(data)
