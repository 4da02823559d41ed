"""The commands a station takes and the one validation of them, for every door (CLI, MQTT,
Sparkplug, the console, the PLC over Modbus TCP): pure — no I/O, no clock, no asyncio — and
checked with ``mypy --strict``. What a door received is first made a :class:`Command` by the one
bounded intake (gateway/core/command_intake.py ``intake``); the station's command desk
(gateway/station/command_desk.py ``CommandDesk``) then calls :func:`validate` once per command.

- :data:`REJECT_CODES` / :data:`CODE` — the refusal codes (MQTT ``reply``, Sparkplug's Last
  Result Code, the PLC's ``last_result``); :data:`COMMAND_KEYS` — the arguments each command
  takes (its payload); :data:`ALARM_COMMAND_EVENTS` — the ISA-18.2 commands and their events.
- ``validate(cmd, limits, state)`` returns ``None`` when the command may be carried out, else a
  :class:`Rejection` (a :class:`CommandReply` with ``ok=False``, a human reason naming the field,
  the value and what is allowed, and its ``code``). The same bad request gets the same reason and
  code whichever door it came through.
- Value rules (``check_t_set``, ``check_sample_id``, ``check_grade``, ``check_t_end``) are also
  used on their own by the Modbus TCP server to refuse an out-of-range register write with
  exception 03 before anything changes.

The limits are a :class:`gateway.core.ports.StationLimits`, built once from the station's configuration
(full scale, saturation ratio, grades).
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass

from ..plumbing.ratelog import clip
from .alarms import ALARMS, ANNUNCIATED, SHELVE_MAX_S
from .ports import SAMPLE_ID_MAX, T_END_MAX_S, StationLimits
from .records import (
    AlarmState,
    ArgValue,
    Command,
    CommandArgs,
    CommandKind,
    CommandReply,
    EventType,
    StationState,
    TestState,
)

__all__ = ["SAMPLE_ID_MAX", "T_END_MAX_S", "REJECT_CODES", "CODE", "COMMAND_KEYS", "RUNNING",
           "ALARM_COMMAND_EVENTS", "NUMERIC_FIELDS", "TEXT_FIELDS", "Rejection", "reject", "check_t_set",
           "check_sample_id", "check_grade", "check_t_end", "validate", "StationLimits", "ArgValue",
           "CommandArgs", "text_arg", "reply_code", "COMMAND_DOORS_MAX", "door_problem"]

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
    (14, "RATE_LIMITED", "too many commands from this source (door), refused ones included; try "
     "again in a few seconds"),
    (15, "WRONG_TEST", "the stop names a test that is not the one running (it ended): nothing stopped"),
)
CODE = {name: code for code, name, _ in REJECT_CODES}

#: named command doors (MQTT ``<base>/cmd/<door>/<command>``, ``mqtt.command_doors``) a station
#: listens on at most besides the default door; each door is a source with its own command budget
COMMAND_DOORS_MAX = 8
_DOOR_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$")


def door_problem(door: object) -> str | None:
    """Why ``door`` cannot name a command door (None: it can): 1–32 letters, digits, '-' and '_'
    (one topic level; no '.', which RabbitMQ's MQTT plugin reads as a level separator), starting
    with a letter or digit, and not a command's name."""
    if not isinstance(door, str) or not _DOOR_RE.match(door):
        return "a door is named by 1–32 letters, digits, '-' and '_', starting with a letter or digit"
    if door in {k.value for k in CommandKind}:
        return f"{door!r} is a command's name; name the door otherwise"
    return None

#: keys each command accepts (MQTT JSON payloads; the PLC fills them from holding registers)
COMMAND_KEYS: dict[CommandKind, tuple[str, ...]] = {
    CommandKind.START: ("sample_id", "grade", "t_set", "t_end"),
    CommandKind.STOP: ("test_id",),
    CommandKind.ACK: (),
    CommandKind.SETPOINT: ("t_set",),
    CommandKind.HOOK_REPLACED: ("sample_id", "grade"),
    CommandKind.SHELVE: ("alarm", "duration_s"),
    CommandKind.UNSHELVE: ("alarm",),
    CommandKind.OUT_OF_SERVICE: (),
    CommandKind.IN_SERVICE: (),
}

#: the payload's types: the arguments that are numbers (finite, not booleans) and those that are
#: text (printable ASCII); the one intake holds every door to them (gateway/core/command_intake.py)
NUMERIC_FIELDS = frozenset({"t_set", "t_end", "duration_s"})
TEXT_FIELDS = frozenset({"sample_id", "grade", "alarm", "request_id", "test_id"})

#: the ISA-18.2 alarm commands and the station event each becomes (the alarm store applies it)
ALARM_COMMAND_EVENTS: dict[CommandKind, EventType] = {
    CommandKind.SHELVE: EventType.ALARM_SHELVED,
    CommandKind.UNSHELVE: EventType.ALARM_UNSHELVED,
    CommandKind.OUT_OF_SERVICE: EventType.ALARM_OUT_OF_SERVICE,
    CommandKind.IN_SERVICE: EventType.ALARM_IN_SERVICE,
}
_ACKABLE = (AlarmState.UNACKNOWLEDGED.value, AlarmState.RTN_UNACKNOWLEDGED.value)


def _alarm_states(state: StationState) -> dict[str, str]:
    """The station's alarms by their ISA-18.2 name (gateway.core.alarms.ALARMS)."""
    return {"end_of_life": state.alarm, "wear_warning": state.warning_alarm}


def _check_alarm_command(cmd: Command, state: StationState) -> Rejection | None:
    """shelve / unshelve / out_of_service / in_service against the alarms' ISA-18.2 states."""
    a = cmd.args
    states = _alarm_states(state)
    if cmd.kind in (CommandKind.SHELVE, CommandKind.UNSHELVE):
        name = a.get("alarm")
        if not isinstance(name, str) or name not in ALARMS:
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


def reply_code(r: CommandReply) -> int:
    """The code every door answers: 0 accepted, else the refusal's code (9 if it has none)."""
    return 0 if r.ok else (r.code or CODE["BAD_REQUEST"])


def text_arg(args: CommandArgs, key: str) -> str | None:
    """A text argument (``sample_id``, ``grade``, ``alarm``) as the intake let it through."""
    v = args.get(key)
    return v if isinstance(v, str) else None


def reject(cmd: Command | None, name: str, reason: str) -> Rejection:
    return Rejection(False, reason, cmd.request_id if cmd is not None else None, CODE[name])


# ----------------------------------------------------------------------------- value rules
def _as_float(value: object) -> float | None:
    """``float(value)`` for a number or numeric text; None for anything else."""
    if isinstance(value, (int, float, str)):
        try:
            return float(value)
        except ValueError:
            return None
    return None


def check_t_set(value: object, limits: StationLimits) -> str | None:
    lo, hi = limits.t_set_range
    v = _as_float(value)
    if v is None:
        return f"t_set: {clip(value)} is not a number (N); allowed: ({lo:g}, {hi:g}) N"
    if isinstance(value, bool) or not math.isfinite(v) or not lo < v < hi:
        return f"t_set: {clip(value)} N out of range; allowed: ({lo:g}, {hi:g}) N"
    return None


def check_sample_id(value: object, limit: int = SAMPLE_ID_MAX) -> str | None:
    if value is None or not isinstance(value, str) or not value.strip():
        return f"sample_id: {clip(value)}: required, 1 to {SAMPLE_ID_MAX} printable ASCII characters"
    if len(value) > limit:
        return f"sample_id: {clip(value)} has {len(value)} characters; at most {limit}"
    if not all(0x20 <= ord(c) <= 0x7E for c in value):
        return f"sample_id: {clip(value)}: only printable ASCII characters (0x20–0x7E) are allowed"
    return None


def check_grade(value: object, grades: tuple[str, ...]) -> str | None:
    if value is None:
        return None
    if not isinstance(value, str) or value not in tuple(grades):
        return f"grade: {clip(value)} unknown; allowed: {', '.join(grades)}"
    return None


def check_t_end(value: object, t_end_max: int = T_END_MAX_S) -> str | None:
    if value is None:
        return None
    v = _as_float(value)
    if v is None:
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
        named = a.get("test_id")
        if not running:
            return reject(cmd, "NOT_RUNNING", "no test is running" + (
                f" (test {clip(named)} ended)" if named is not None else ""))
        if named is not None and named != state.test_id:
            now = (f"test {clip(state.test_id)} is running" if state.test_id
                   else "a new test is starting")
            return reject(cmd, "WRONG_TEST", f"stop names test {clip(named)}, but {now}: not "
                          "stopped (a stop naming a test ends only that test)")
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
        # idle, no alarm: only a new hook's sample_id makes a replacement (a PLC writing the
        # command again with the id still staged names the hook the station already has)
        if (state.alarm == AlarmState.NORMAL.value and state.warning_alarm == AlarmState.NORMAL.value
                and not running and a.get("sample_id") in (None, state.sample_id)):
            return reject(cmd, "NO_ALARM", "no alarm, no test and no new sample_id: nothing to "
                          "record (name the new hook's sample_id)")
    elif cmd.kind in ALARM_COMMAND_EVENTS:
        return _check_alarm_command(cmd, state)
    else:  # pragma: no cover - CommandKind is closed
        return reject(cmd, "BAD_REQUEST", f"command {cmd.kind!r} unknown")
    return None
