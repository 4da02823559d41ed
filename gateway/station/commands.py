"""The one validation of commands, shared by every source (CLI, MQTT, PLC over Modbus TCP, the
console, Sparkplug); what a door received is first made a Command by the one bounded intake
(gateway/northbound/cmdparse.py ``intake``).

``validate(cmd, limits, state)`` returns ``None`` when the command may be carried out, else a
:class:`Rejection` (a :class:`CommandReply` with ``ok=False``, a human reason naming the field,
the value and what is allowed, and a numeric ``code`` for PLCs). The same bad request gets the
same reason and code whichever door it came through; ``Station.submit`` emits the same
``command_rejected`` event for all of them.

Every door hands its commands over with :func:`submit` (and reports a request its intake refused
with :func:`refused`) to its :class:`gateway.ports.CommandSink`: a station's
:class:`CommandDesk` (one command at a time, a repeated ``request_id`` answered once, validation
once, a rate per source, every refusal through the bounded :class:`RefusalGate` — once per kind
(door, command, code) per minute with the ``count``, so a flood of refused commands is a few
events and log lines, not one each), or a fleet worker's proxy, which hands it to its worker's.

The limits are a :class:`gateway.ports.StationLimits`, built once from the station's configuration
(full scale, saturation ratio, grades). Value rules (``check_t_set``, ``check_sample_id``,
``check_grade``, ``check_t_end``) are also used on their own by the Modbus TCP server to refuse an
out-of-range register write with exception 03 before anything changes.
"""
from __future__ import annotations

import asyncio
import math
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from ..alarms import ALARMS, ANNUNCIATED, SHELVE_MAX_S
from ..ports import SAMPLE_ID_MAX, T_END_MAX_S, CommandSink, StationLimits
from ..ratelog import RateBound, RefusalWindow, clip
from ..records import AlarmState, Command, CommandKind, CommandReply, EventType, StationState, TestState

__all__ = ["SAMPLE_ID_MAX", "T_END_MAX_S", "REJECT_CODES", "CODE", "COMMAND_KEYS", "Rejection",
           "reject", "check_t_set", "check_sample_id", "check_grade", "check_t_end",
           "validate", "StationLimits", "ALARM_COMMAND_EVENTS", "RefusalGate", "RequestLedger",
           "CommandDesk", "submit", "refused", "REQUEST_ID_TTL_S", "REQUEST_ID_MAX_KEPT",
           "COMMANDS_PER_MIN", "COMMAND_BURST"]

#: test states in which a test is running (or starting: a stop cancels the start, §3a)
RUNNING = frozenset({TestState.STARTING, TestState.BASELINE_SEARCH, TestState.MONITORING,
                     TestState.END_OF_LIFE})

#: a command's request_id is remembered (per station and source) this long and this many at most:
#: a repeat within both bounds gets the first answer and is not carried out again (docs/limits.md)
REQUEST_ID_TTL_S = 600.0
REQUEST_ID_MAX_KEPT = 1024
#: commands one source (``mqtt``, ``sparkplug``, ``console:<user>``, ``plc:<address>``, ``cli``)
#: may have a station carry out: bursts of COMMAND_BURST, COMMANDS_PER_MIN a minute on average
COMMANDS_PER_MIN = 60
COMMAND_BURST = 20
#: sources whose rate is tracked at once (the one not seen the longest is forgotten)
MAX_SOURCES = 256

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
    (14, "RATE_LIMITED", "too many commands from this source (door); try again in a few seconds"),
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


# ----------------------------------------------------------------------------- bounded refusals
class RefusalGate:
    """The refusals of one station as bounded ``command_rejected`` events: per kind (door,
    command, code) the first refusal of a window (:data:`gateway.ratelog.WINDOW_S`, 60 s) is an
    event at once with ``count: 1``, the others of the window are counted and become one event
    with their ``count`` when the window ends (the last one's reason and source). 3,000 refused
    PLC commands in a minute are two events (and two log lines), not 3,000; the sum of the counts
    is the number of refusals. Every request still gets its own answer.

    A member of the station's :class:`CommandDesk`, on the station's loop; ``emit`` makes one
    ``command_rejected`` event of its data."""

    def __init__(self, emit: Callable[[dict[str, Any]], object], window_s: float | None = None):
        self._emit_event = emit
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

    def _emit(self, data: dict[str, Any], n: int) -> None:
        self.events += 1
        self._emit_event({**data, "count": n, "window_s": self._w.window_s})

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


# ----------------------------------------------------------------------------- once, and not too often
@dataclass(frozen=True)
class _Answered:
    kind: CommandKind
    args: tuple[tuple[str, Any], ...]
    reply: CommandReply
    at: float


def _args_key(args: dict[str, Any]) -> tuple[tuple[str, Any], ...]:
    return tuple(sorted(args.items()))


class RequestLedger:
    """The answers of a station's recent commands by ``(source, request_id)`` (pure: every call
    takes the time). A command whose request_id this source already used within
    :data:`REQUEST_ID_TTL_S` (and among the last :data:`REQUEST_ID_MAX_KEPT`) is answered with the
    first one's reply and not carried out again; the same request_id naming another command (or
    other arguments) is refused (code 9). A command without a request_id is never remembered."""

    def __init__(self, ttl_s: float = REQUEST_ID_TTL_S, max_kept: int = REQUEST_ID_MAX_KEPT):
        self.ttl_s, self.max_kept = float(ttl_s), int(max_kept)
        self._d: OrderedDict[tuple[str, str], _Answered] = OrderedDict()

    def __len__(self) -> int:
        return len(self._d)

    def _expire(self, now: float) -> None:
        while self._d:
            key, first = next(iter(self._d.items()))
            if now - first.at < self.ttl_s and len(self._d) <= self.max_kept:
                return
            del self._d[key]

    def answer(self, cmd: Command, now: float) -> CommandReply | None:
        """The reply to a repeat of an earlier command (None: not a repeat)."""
        if cmd.request_id is None:
            return None
        self._expire(now)
        first = self._d.get((cmd.source, cmd.request_id))
        if first is None:
            return None
        rid = clip(cmd.request_id)
        if first.kind != cmd.kind or first.args != _args_key(cmd.args):
            return reject(cmd, "BAD_REQUEST", f"request_id {rid} already named a {first.kind.value} "
                          f"command {now - first.at:.0f} s ago: a request_id names one command")
        r = first.reply
        said = "carried out" if r.ok else f"refused ({r.reason})"
        reason = f"duplicate of request_id {rid}: {said} once, {now - first.at:.0f} s ago, not again"
        if isinstance(r, Rejection):
            return Rejection(False, reason, cmd.request_id, r.code)
        return CommandReply(r.ok, reason, cmd.request_id)

    def note(self, cmd: Command, reply: CommandReply, now: float) -> None:
        """Remember the answer to ``cmd`` (when it has a request_id)."""
        if cmd.request_id is None:
            return
        key = (cmd.source, cmd.request_id)
        self._d[key] = _Answered(cmd.kind, _args_key(cmd.args), reply, now)
        self._d.move_to_end(key)
        self._expire(now)


class CommandDesk:
    """A station's one place for commands, whichever door they came in by (every door's
    ``CommandSink.submit`` and ``refused`` end here, on the station's loop):

    - one command at a time (a lock): each is validated against the state the one before left
      (two stops at once: the second finds no test running);
    - a repeated request_id (:class:`RequestLedger`) is answered with the first answer, once;
    - validation once (``validate``), then a rate per source (:data:`COMMANDS_PER_MIN` a minute,
      bursts of :data:`COMMAND_BURST`; :class:`gateway.ratelog.RateBound`) for the commands that
      would be carried out: over it, refused with code 14 RATE_LIMITED (a refused or repeated
      command costs none of it, so a flood of bad requests cannot lock a door's good ones out);
    - every refusal through the bounded :class:`RefusalGate` (counted ``command_rejected`` events);
    - then ``act`` carries it out (``gateway.station.dispatch.HANDLERS``)."""

    def __init__(self, validate: Callable[[Command], Rejection | None],
                 act: Callable[[Command], Awaitable[None]],
                 emit: Callable[[dict[str, Any]], object], *, window_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._validate, self._act, self.clock = validate, act, clock
        self.gate = RefusalGate(emit, window_s)
        self.ledger = RequestLedger()
        self.rate = RateBound(COMMANDS_PER_MIN, clock, max_keys=MAX_SOURCES, burst=COMMAND_BURST)
        self._lock: asyncio.Lock | None = None
        #: what the desk did: carried out, refused (any reason), of those over the rate, repeats
        self.counters = {"accepted": 0, "refused": 0, "rate_limited": 0, "duplicates": 0}

    def refused(self, data: dict[str, Any]) -> None:
        """A door refused a request before it became a command (the intake, code 9 or 4)."""
        self.counters["refused"] += 1
        self.gate.refused(data)

    async def submit(self, cmd: Command) -> CommandReply:
        if self._lock is None:
            self._lock = asyncio.Lock()
        async with self._lock:
            now = self.clock()
            again = self.ledger.answer(cmd, now)
            if again is not None:
                self.counters["duplicates"] += 1
                return again
            rej = self._validate(cmd)
            if rej is None:
                wait = self.rate.take(cmd.source)
                if wait > 0:
                    self.counters["rate_limited"] += 1
                    rej = reject(cmd, "RATE_LIMITED", f"{cmd.kind.value}: more than {COMMAND_BURST} "
                                 f"commands at once or {COMMANDS_PER_MIN} a minute from "
                                 f"{clip(cmd.source)}; try again in {wait:.1f} s")
            if rej is not None:
                self.refused({"command": cmd.kind.value, "source": cmd.source,
                              "reason": rej.reason, "code": int(rej.code)})
                if rej.code != CODE["RATE_LIMITED"]:        # a retry later may be carried out
                    self.ledger.note(cmd, rej, now)
                return rej
            await self._act(cmd)
            self.counters["accepted"] += 1
            reply = CommandReply(True, "", cmd.request_id)
            self.ledger.note(cmd, reply, self.clock())
            return reply


async def submit(sink: CommandSink, cmd: Command) -> CommandReply:
    """Every door's hand-over of a command (on the sink's loop): the sink's one command path
    (a station's :class:`CommandDesk`, or a fleet worker's proxy that hands it to the worker's)."""
    return await sink.submit(cmd)


def refused(sink: CommandSink, data: dict[str, Any]) -> None:
    """A door refused a request before it became a command (the intake, code 9 or 4): one more
    refusal for the sink's bounded ``command_rejected`` events. On the sink's loop."""
    sink.refused(data)
