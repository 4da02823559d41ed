"""A station's command desk: every door's commands, carried out once, one at a time.

The commands, their arguments, refusal codes and the one validation are pure and live in
:mod:`gateway.core.command_rules` (re-exported here). Every door makes a Command with the one bounded
intake (gateway/core/command_intake.py ``intake``) and hands it to its
:class:`gateway.core.ports.CommandSink` — ``submit(cmd)``, or ``refused(data)`` for a request the
intake refused. A station's sink is its :class:`CommandDesk` (a member of the Station): one
command at a time, a repeated ``request_id`` answered once for its whole 600 s
(:class:`RequestLedger`), a budget per source that every command taken costs (refused ones too),
validation once, every refusal through the bounded :class:`RefusalGate` — once per kind
(door, command, code) per minute with the ``count``, so a flood of refused commands is a few
events and log lines, not one each. A fleet's supervisor holds a worker's proxy as sink, which
hands the command to the worker's desk.
"""
from __future__ import annotations

import asyncio
import hashlib
import math
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from ..core.command_rules import (
    ALARM_COMMAND_EVENTS,
    CODE,
    COMMAND_KEYS,
    REJECT_CODES,
    RUNNING,
    SAMPLE_ID_MAX,
    T_END_MAX_S,
    Rejection,
    check_grade,
    check_sample_id,
    check_t_end,
    check_t_set,
    reject,
    validate,
)
from ..core.ports import StationLimits
from ..core.records import Command, CommandArgs, CommandKind, CommandReply, RefusalData
from ..plumbing.ratelog import RateBound, RefusalWindow, clip

__all__ = ["SAMPLE_ID_MAX", "T_END_MAX_S", "REJECT_CODES", "CODE", "COMMAND_KEYS", "RUNNING", "Rejection",
           "reject", "check_t_set", "check_sample_id", "check_grade", "check_t_end",
           "validate", "StationLimits", "ALARM_COMMAND_EVENTS", "RefusalGate", "RequestLedger",
           "CommandDesk", "REQUEST_ID_TTL_S", "REQUEST_ID_MAX_KEPT", "COMMANDS_PER_MIN",
           "COMMAND_BURST", "MAX_SOURCES", "REQUEST_ID_SOURCES", "budget_in"]

#: commands one source (``mqtt``, ``sparkplug``, ``console:<user>``, ``plc:<address>``, ``cli``)
#: may have a station take — carried out or refused by the validation alike: bursts of
#: COMMAND_BURST, COMMANDS_PER_MIN a minute on average (a token bucket)
COMMANDS_PER_MIN = 60
COMMAND_BURST = 20
#: sources whose rate is tracked at once (the one not seen the longest is forgotten)
MAX_SOURCES = 256
#: sources whose request_ids are remembered at once (the doors that send ids: ``mqtt``,
#: ``sparkplug``, ``cli``, each console user): one more is refused (14) until one's ids expire
REQUEST_ID_SOURCES = 64
#: a command's request_id is remembered (per station and source) this long: a repeat within it
#: gets the first answer and is not carried out again (docs/limits.md)
REQUEST_ID_TTL_S = 600.0


def budget_in(window_s: float, per_min: float = COMMANDS_PER_MIN, burst: float = COMMAND_BURST) -> int:
    """The most commands one source can have a station take within any ``window_s``: its whole
    burst at once, then the refill (a token bucket of ``burst`` refilled at ``per_min``)."""
    return int(burst) + int(math.floor(per_min * window_s / 60.0 + 1e-9))


#: the request_ids remembered per source: every command the budget lets one source have taken
#: within REQUEST_ID_TTL_S (20 + 600 = 620), so no id is forgotten before its 600 s — a flood can
#: only run into the budget (code 14), never push an id out of the memory
REQUEST_ID_MAX_KEPT = budget_in(REQUEST_ID_TTL_S)


# ----------------------------------------------------------------------------- bounded refusals
class RefusalGate:
    """The refusals of one station as bounded ``command_rejected`` events: per kind (door,
    command, code) the first refusal of a window (:data:`gateway.plumbing.ratelog.WINDOW_S`, 60 s) is an
    event at once with ``count: 1``, the others of the window are counted and become one event
    with their ``count`` when the window ends (the last one's reason and source). 3,000 refused
    PLC commands in a minute are two events (and two log lines), not 3,000; the sum of the counts
    is the number of refusals. Every request still gets its own answer.

    A member of the station's :class:`CommandDesk`, on the station's loop; ``emit`` makes one
    ``command_rejected`` event of its data."""

    def __init__(self, emit: Callable[[RefusalData], object], window_s: float | None = None):
        self._emit_event = emit
        self._w = RefusalWindow(window_s)
        self._timer: asyncio.TimerHandle | None = None
        self.refusals = 0           # every refusal counted here
        self.events = 0             # command_rejected events emitted for them

    @property
    def window_s(self) -> float:
        return self._w.window_s

    def refused(self, data: RefusalData) -> None:
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

    def _emit(self, data: RefusalData, n: int) -> None:
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
@dataclass(frozen=True, slots=True)
class _Answered:
    """One remembered answer, lean (a full memory is 64 sources × 620 answers): the command's
    arguments as a digest."""
    kind: CommandKind
    args: bytes
    ok: bool
    code: int
    reason: str
    at: float


def _args_key(args: CommandArgs) -> bytes:
    """The arguments of a command as 16 bytes (the same arguments, the same key; 1 and 1.0 are
    the same number)."""
    items = sorted((k, float(v) if isinstance(v, int) else v) for k, v in args.items())
    return hashlib.blake2b(repr(items).encode(), digest_size=16).digest()


class RequestLedger:
    """The answers of a station's recent commands by ``(source, request_id)`` (pure: every call
    takes the time). A command whose request_id this source already used within
    :data:`REQUEST_ID_TTL_S` is answered with the first one's reply and not carried out again;
    the same request_id naming another command (or other arguments) is refused (code 9). A
    command without a request_id is never remembered.

    Each source has its own memory of ``per_source`` answers (:data:`REQUEST_ID_MAX_KEPT`, what
    its budget lets it have taken within the TTL) and at most ``max_sources`` sources are
    remembered at once. Nothing is ever forgotten before its TTL: a command that would not fit
    (:meth:`room` says why) is refused by the desk instead, so no flood, of any source, can push
    an id out of the memory and replay it later."""

    def __init__(self, ttl_s: float = REQUEST_ID_TTL_S, per_source: int = REQUEST_ID_MAX_KEPT,
                 max_sources: int = REQUEST_ID_SOURCES):
        self.ttl_s, self.per_source, self.max_sources = float(ttl_s), int(per_source), int(max_sources)
        self._src: dict[str, OrderedDict[str, _Answered]] = {}

    def __len__(self) -> int:
        return sum(len(d) for d in self._src.values())

    def _expire(self, source: str, now: float) -> OrderedDict[str, _Answered] | None:
        """The source's memory without its answers older than the TTL (None: it has none left)."""
        d = self._src.get(source)
        if d is None:
            return None
        while d and now - next(iter(d.values())).at >= self.ttl_s:
            d.popitem(last=False)
        if not d:
            del self._src[source]
            return None
        return d

    def room(self, cmd: Command, now: float) -> tuple[str, float] | None:
        """None when the answer to ``cmd`` can be remembered for its whole TTL (or needs no
        memory); else why not and the seconds until it can."""
        if cmd.request_id is None:
            return None
        d = self._expire(cmd.source, now)
        if d is None:
            if len(self._src) < self.max_sources:
                return None
            for s in list(self._src):
                self._expire(s, now)
            if len(self._src) < self.max_sources:
                return None
            soonest = min(next(reversed(x.values())).at for x in self._src.values())   # one empties
            return (f"the station remembers the request_ids of {self.max_sources} sources of the "
                    f"last {self.ttl_s:.0f} s", max(0.0, soonest + self.ttl_s - now))
        if len(d) < self.per_source:
            return None
        oldest = next(iter(d.values())).at
        return (f"{clip(cmd.source)} had {len(d)} commands with a request_id taken in the last "
                f"{self.ttl_s:.0f} s, each remembered that long", max(0.0, oldest + self.ttl_s - now))

    def answer(self, cmd: Command, now: float) -> CommandReply | None:
        """The reply to a repeat of an earlier command (None: not a repeat)."""
        if cmd.request_id is None:
            return None
        d = self._expire(cmd.source, now)
        first = d.get(cmd.request_id) if d is not None else None
        if first is None:
            return None
        rid = clip(cmd.request_id)
        if first.kind != cmd.kind or first.args != _args_key(cmd.args):
            return reject(cmd, "BAD_REQUEST", f"request_id {rid} already named a {first.kind.value} "
                          f"command {now - first.at:.0f} s ago: a request_id names one command")
        said = "carried out" if first.ok else f"refused ({first.reason})"
        reason = f"duplicate of request_id {rid}: {said} once, {now - first.at:.0f} s ago, not again"
        if not first.ok:
            return Rejection(False, reason, cmd.request_id, first.code)
        return CommandReply(True, reason, cmd.request_id)

    def note(self, cmd: Command, reply: CommandReply, now: float) -> None:
        """Remember the answer to ``cmd`` (when it has a request_id), taken at ``now``. The caller
        asked :meth:`room` first: nothing younger than the TTL is ever dropped for it."""
        if cmd.request_id is None:
            return
        d = self._expire(cmd.source, now)
        if d is None:
            d = self._src[cmd.source] = OrderedDict()
        d[cmd.request_id] = _Answered(cmd.kind, _args_key(cmd.args), reply.ok, int(reply.code),
                                      reply.reason, now)
        d.move_to_end(cmd.request_id)


class CommandDesk:
    """A station's one place for commands, whichever door they came in by (every door's
    ``CommandSink.submit`` and ``refused`` end here, on the station's loop):

    - one command at a time (a lock): each is validated against the state the one before left
      (two stops at once: the second finds no test running);
    - a repeated request_id (:class:`RequestLedger`) is answered with the first answer, once, and
      costs nothing;
    - every other command costs its source one of its budget (:data:`COMMANDS_PER_MIN` a minute,
      bursts of :data:`COMMAND_BURST`; :class:`gateway.plumbing.ratelog.RateBound`) *before* it is
      validated — carried out or refused alike: over it, refused with code 14 RATE_LIMITED (not
      remembered: a retry later may pass). A flood of refused commands so runs into its own
      source's budget and can never push a request_id out of the ledger, whose memory per source
      is what that budget lets through in the ledger's TTL (a request the intake could not read
      never reaches the ledger and costs none);
    - validation once (``validate``), every refusal through the bounded :class:`RefusalGate`
      (counted ``command_rejected`` events);
    - then ``act`` carries it out (``gateway.station.dispatch.HANDLERS``)."""

    def __init__(self, validate: Callable[[Command], Rejection | None],
                 act: Callable[[Command], Awaitable[None]],
                 emit: Callable[[RefusalData], object], *, window_s: float | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self._validate, self._act, self.clock = validate, act, clock
        self.gate = RefusalGate(emit, window_s)
        self.ledger = RequestLedger()
        self.rate = RateBound(COMMANDS_PER_MIN, clock, max_keys=MAX_SOURCES, burst=COMMAND_BURST)
        self._lock: asyncio.Lock | None = None
        #: what the desk did: carried out, refused (any reason), of those over the rate, repeats
        self.counters = {"accepted": 0, "refused": 0, "rate_limited": 0, "duplicates": 0}

    def refused(self, data: RefusalData) -> None:
        """A door refused a request before it became a command (the intake, code 9 or 4)."""
        self.counters["refused"] += 1
        self.gate.refused(data)

    def _budget(self, cmd: Command, now: float) -> Rejection | None:
        """One of the source's budget taken for ``cmd``, or the code-14 refusal (nothing taken)."""
        full = self.ledger.room(cmd, now)
        if full is not None:
            why, wait = full
            return reject(cmd, "RATE_LIMITED", f"{cmd.kind.value}: {why}; try again in {wait:.1f} s")
        wait = self.rate.take(cmd.source)
        if wait > 0:
            return reject(cmd, "RATE_LIMITED", f"{cmd.kind.value}: more than {COMMAND_BURST} "
                          f"commands at once or {COMMANDS_PER_MIN} a minute from "
                          f"{clip(cmd.source)} (refused ones count); try again in {wait:.1f} s")
        return None

    async def submit(self, cmd: Command) -> CommandReply:
        if self._lock is None:
            self._lock = asyncio.Lock()
        async with self._lock:
            now = self.clock()
            again = self.ledger.answer(cmd, now)
            if again is not None:
                self.counters["duplicates"] += 1
                return again
            rej = self._budget(cmd, now)
            if rej is not None:
                self.counters["rate_limited"] += 1
            else:
                rej = self._validate(cmd)
            if rej is not None:
                self.refused({"command": cmd.kind.value, "source": cmd.source,
                              "reason": rej.reason, "code": int(rej.code)})
                if rej.code != CODE["RATE_LIMITED"]:        # a retry later may be carried out
                    self.ledger.note(cmd, rej, now)
                return rej
            await self._act(cmd)
            self.counters["accepted"] += 1
            reply = CommandReply(True, "", cmd.request_id)
            self.ledger.note(cmd, reply, now)
            return reply
