"""Bounded command intake: raw bytes of a command request → a :class:`Command` or a
:class:`Rejection` with its code. Pure: no I/O, no clock (the limiter takes the time as an argument).

Used by MQTT (``cmd/<name>`` payloads) and meant for every later text door (the web console).
Every input is bounded *before* it can cost anything:

- the payload is at most :data:`MAX_PAYLOAD_BYTES` (checked on the bytes);
- nesting of ``[``/``{`` is at most :data:`MAX_DEPTH` (counted by a scan of the bytes, outside
  strings, before ``json.loads`` could recurse);
- a number literal has at most :data:`MAX_NUMBER_CHARS` characters (``json.loads`` hooks: a
  400-digit ``t_set`` is refused, it never reaches ``float()``); NaN/Infinity are refused;
- a string has at most :data:`MAX_STRING_CHARS` characters, an object at most :data:`MAX_KEYS`
  keys of at most :data:`MAX_KEY_CHARS` characters; duplicate keys are refused;
- numeric fields (``t_set``, ``t_end``) must be JSON numbers: the string ``"0.6"`` is refused;
  text fields (``sample_id``, ``grade``, ``request_id``) must be strings.

Nothing the client sent is echoed back longer than :data:`ECHO_CHARS` characters (:func:`clip`):
replies, ``command_rejected`` events and log lines stay small whatever comes in (no amplification).
Every refusal here has code 9 (BAD_REQUEST); :func:`rejected_event_data` gives the data of the
``command_rejected`` event (docs/mqtt.md) and :class:`RejectionLimiter` bounds how many such events
a flood of bad requests can produce (each request still gets its reply).
"""
from __future__ import annotations

import json
from typing import Any

from ..records import Command, CommandKind
from ..station.commands import CODE, COMMAND_KEYS, Rejection

MAX_PAYLOAD_BYTES = 4096
MAX_DEPTH = 4
MAX_NUMBER_CHARS = 32
MAX_STRING_CHARS = 64
MAX_KEYS = 16
MAX_KEY_CHARS = 32
MAX_NAME_CHARS = 32
#: longest piece of client input quoted in a reason
ECHO_CHARS = 40

NUMERIC_FIELDS = frozenset({"t_set", "t_end"})
TEXT_FIELDS = frozenset({"sample_id", "grade", "request_id"})


class _Refused(ValueError):
    pass


def clip(value: Any, n: int = ECHO_CHARS) -> str:
    """``repr`` of client input, cut to about ``n`` characters (with the full length named)."""
    r = repr(value)
    if len(r) <= n:
        return r
    size = len(value) if isinstance(value, (str, bytes)) else len(r)
    return f"{r[:n]}… ({size} chars)"


def nesting_depth(data: bytes, limit: int) -> int:
    """Deepest ``[``/``{`` nesting outside JSON strings; stops counting past ``limit``."""
    depth = deepest = 0
    in_str = esc = False
    for b in data:
        if in_str:
            if esc:
                esc = False
            elif b == 0x5C:        # backslash
                esc = True
            elif b == 0x22:        # quote
                in_str = False
        elif b == 0x22:
            in_str = True
        elif b in (0x5B, 0x7B):    # [ {
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > limit:
                    return deepest
        elif b in (0x5D, 0x7D):
            depth -= 1
    return deepest


def _num(s: str, conv):
    if len(s) > MAX_NUMBER_CHARS:
        raise _Refused(f"a number of {len(s)} characters; at most {MAX_NUMBER_CHARS}")
    return conv(s)


def _const(s: str):
    raise _Refused(f"{s} is not allowed")


def _pairs(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    if len(pairs) > MAX_KEYS:
        raise _Refused(f"an object with {len(pairs)} keys; at most {MAX_KEYS}")
    out: dict[str, Any] = {}
    for k, v in pairs:
        if len(k) > MAX_KEY_CHARS:
            raise _Refused(f"key {clip(k)} too long; at most {MAX_KEY_CHARS} characters")
        if k in out:
            raise _Refused(f"key {clip(k)} given twice")
        if isinstance(v, str) and len(v) > MAX_STRING_CHARS:
            raise _Refused(f"{k}: a string of {len(v)} characters; at most {MAX_STRING_CHARS}")
        out[k] = v
    return out


def bad(name: str, reason: str, request_id: str | None = None) -> Rejection:
    return Rejection(False, f"{name}: {reason}", request_id, CODE["BAD_REQUEST"])


def parse_command(name: str, payload: bytes, source: str = "mqtt") -> Command | Rejection:
    """The command ``name`` (the last topic level) with its request ``payload`` (JSON object
    bytes; empty means ``{}``) → a Command for the station's validation, or a code-9 Rejection."""
    if not isinstance(name, str) or len(name) > MAX_NAME_CHARS:
        name = clip(name, MAX_NAME_CHARS)
    try:
        kind = CommandKind(name)
    except ValueError:
        kinds = ", ".join(k.value for k in CommandKind)
        return bad("command", f"{clip(name)} unknown; allowed: {kinds}")
    name = kind.value
    if len(payload) > MAX_PAYLOAD_BYTES:
        return bad(name, f"payload of {len(payload)} bytes; at most {MAX_PAYLOAD_BYTES}")
    try:
        text = bytes(payload).decode("utf-8").strip()
    except UnicodeDecodeError:
        return bad(name, "payload is not UTF-8 JSON")
    if not text:
        obj: Any = {}
    else:
        d = nesting_depth(text.encode(), MAX_DEPTH)
        if d > MAX_DEPTH:
            return bad(name, f"payload nested deeper than {MAX_DEPTH} levels")
        try:
            obj = json.loads(text, parse_int=lambda s: _num(s, int), parse_float=lambda s: _num(s, float),
                             parse_constant=_const, object_pairs_hook=_pairs)
        except _Refused as e:
            return bad(name, str(e))
        except (json.JSONDecodeError, RecursionError, ValueError) as e:
            return bad(name, f"payload is not JSON: {clip(str(e), 80)}")
        if isinstance(obj, str) and len(obj) > MAX_STRING_CHARS:
            return bad(name, f"payload must be a JSON object, got a string of {len(obj)} characters")
    if not isinstance(obj, dict):
        return bad(name, f"payload must be a JSON object, got {type(obj).__name__}")
    rid = obj.get("request_id")
    if rid is not None and not isinstance(rid, str):
        rid = clip(rid, MAX_STRING_CHARS)
    allowed = COMMAND_KEYS[kind]
    unknown = sorted(k for k in obj if k not in allowed and k != "request_id")
    if unknown:
        return bad(name, f"unknown key(s) {', '.join(clip(k) for k in unknown[:4])}; allowed: "
                   f"{', '.join(allowed + ('request_id',))}", rid)
    for k in allowed:
        if k not in obj or obj[k] is None:
            continue
        v = obj[k]
        if k in NUMERIC_FIELDS and (isinstance(v, bool) or not isinstance(v, (int, float))):
            return bad(name, f"{k}: {clip(v)} must be a JSON number", rid)
        if k in TEXT_FIELDS and not isinstance(v, str):
            return bad(name, f"{k}: {clip(v)} must be a JSON string", rid)
    args = {k: obj[k] for k in allowed if k in obj}
    return Command(kind, source, args, rid)


def rejected_event_data(command: str, rejection: Rejection, source: str) -> dict[str, Any]:
    """Data of the ``command_rejected`` event for an intake refusal (docs/mqtt.md, Events)."""
    return {"command": clip(command, MAX_NAME_CHARS).strip("'"), "source": source,
            "reason": rejection.reason, "code": int(rejection.code)}


class RejectionLimiter:
    """Token bucket over ``command_rejected`` events of intake refusals: at most ``burst`` at
    once, ``rate`` per second after; the refusals not reported are counted (``suppressed``) and
    the count goes into the next event that passes."""

    def __init__(self, rate: float = 2.0, burst: int = 10):
        self.rate, self.burst = float(rate), float(burst)
        self._tokens = float(burst)
        self._t: float | None = None
        self.suppressed = 0

    def allow(self, now: float) -> int | None:
        """None: suppress this event; else the number suppressed since the last one passed."""
        if self._t is not None:
            self._tokens = min(self.burst, self._tokens + (now - self._t) * self.rate)
        self._t = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            n, self.suppressed = self.suppressed, 0
            return n
        self.suppressed += 1
        return None
