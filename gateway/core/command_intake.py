"""The one bounded command intake: a raw command from ANY door → a :class:`Command` for the
station's validation, or a :class:`Rejection` with its code. Pure: no I/O, no clock.

:func:`intake` is the single entry point, used by every source of commands:

- MQTT: ``cmd/<name>`` topics, the payload as bytes (JSON object);
- the web console: ``POST /api/station/<id>/command``, the body as bytes (JSON object with the
  command name under ``command``);
- Sparkplug B: the DCMD metrics of a command, as a mapping of argument names to values (their
  Sparkplug types are kept: a String metric is a ``str``, a Double a ``float``);
- the PLC: the arguments decoded from the holding registers, as a mapping;
- the CLI and the supervisor's command channel: a mapping.

Every input is bounded *before* it can cost anything:

- a payload is at most :data:`MAX_PAYLOAD_BYTES` (checked on the bytes);
- nesting of ``[``/``{`` is at most :data:`MAX_DEPTH` (counted by a scan of the bytes, outside
  strings, before ``json.loads`` could recurse);
- a number literal has at most :data:`MAX_NUMBER_CHARS` characters (``json.loads`` hooks: a
  400-digit ``t_set`` is refused, it never reaches ``float()``); NaN/Infinity are refused;
- a string has at most :data:`MAX_STRING_CHARS` characters, an object at most :data:`MAX_KEYS`
  keys of at most :data:`MAX_KEY_CHARS` characters; duplicate keys are refused;
- types are strict, whatever the door: numeric fields (``t_set``, ``t_end``, ``duration_s``) must
  be numbers — not the string ``"0.6"``, not a boolean — and finite; text fields (``sample_id``,
  ``grade``, ``alarm``, ``request_id``, ``test_id``) must be strings of printable ASCII (0x20–0x7E);
  ``sample_id`` at most :data:`SAMPLE_ID_MAX` characters (code 4, as the station says it),
  ``request_id`` at most :data:`REQUEST_ID_MAX`;
- a value that is a list or an object is refused; unknown keys are refused.

Nothing the client sent is echoed back longer than :data:`ECHO_CHARS` characters
(:func:`gateway.plumbing.ratelog.clip`, one line, control characters escaped): replies,
``command_rejected`` events, Sparkplug metrics and log lines stay small whatever comes in.
Refusals here have code 9 (BAD_REQUEST), or 4 (SAMPLE_ID) for a sample ID that is not one;
:func:`rejected_event_data` gives the data of the ``command_rejected`` event (docs/mqtt.md), and
the station's refusal gate (gateway/station/command_desk.py) bounds how many such events a flood
produces.
"""
from __future__ import annotations

import json
import math
import re
from collections.abc import Callable, Mapping
from typing import Any

from ..plumbing.ratelog import ECHO_CHARS, clip, safe
from .command_rules import CODE, COMMAND_KEYS, NUMERIC_FIELDS, SAMPLE_ID_MAX, TEXT_FIELDS, Rejection, check_sample_id
from .records import Command, CommandKind, RefusalData

__all__ = ["intake", "parse_command", "read_bounded_json", "Refused", "bounded_pairs",
           "rejected_event_data", "clip", "safe", "nesting_depth", "bad",
           "ECHO_CHARS", "MAX_PAYLOAD_BYTES", "MAX_DEPTH", "MAX_NUMBER_CHARS", "MAX_STRING_CHARS",
           "MAX_KEYS", "MAX_KEY_CHARS", "MAX_NAME_CHARS", "REQUEST_ID_MAX", "SAMPLE_ID_MAX",
           "NUMERIC_FIELDS", "TEXT_FIELDS", "COMMAND_KEY"]

MAX_PAYLOAD_BYTES = 4096
MAX_DEPTH = 4
MAX_NUMBER_CHARS = 32
MAX_STRING_CHARS = 64
MAX_KEYS = 16
MAX_KEY_CHARS = 32
MAX_NAME_CHARS = 32
REQUEST_ID_MAX = 64
#: an integer argument larger than this (in magnitude) is refused (a float of it is not exact)
MAX_INT = 2 ** 53
#: the key that names the command in a body that carries it (the web console)
COMMAND_KEY = "command"



class Refused(ValueError):
    """Raised inside ``json.loads`` hooks for input over a bound (every bounded JSON reader)."""


_Refused = Refused


#: a JSON string (an unterminated one runs to the end), for :func:`nesting_depth`
_JSON_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"?', re.S)
#: every byte but the brackets (``bytes.translate`` deletes them)
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")


def nesting_depth(data: bytes | bytearray | memoryview, limit: int) -> int:
    """Deepest ``[``/``{`` nesting outside JSON strings; stops counting past ``limit``. The strings
    and every other byte go first at C speed (a 256 KiB message costs about a millisecond, not a
    Python loop over every byte); only the brackets are walked."""
    raw = bytes(data)
    # without a backslash, every other quote ends a string: the pieces between them are outside
    outside = b"".join(raw.split(b'"')[::2]) if b"\\" not in raw else _JSON_STRING.sub(b"", raw)
    brackets = outside.translate(None, _NOT_BRACKETS)
    depth = deepest = 0
    for b in brackets:
        if b in (0x5B, 0x7B):      # [ {
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > limit:
                    return deepest
        else:
            depth -= 1
    return deepest


def _num(s: str, conv):
    if len(s) > MAX_NUMBER_CHARS:
        raise _Refused(f"a number of {len(s)} characters; at most {MAX_NUMBER_CHARS}")
    return conv(s)


def refuse_constant(s: str) -> Any:
    """``parse_constant`` of a bounded JSON read: NaN, Infinity and -Infinity are refused."""
    raise Refused(f"{s} is not allowed")


def bounded_pairs(max_keys: int, max_key_chars: int,
                  max_string_chars: int | None = None) -> Callable[[list[tuple[str, Any]]], dict[str, Any]]:
    """``object_pairs_hook`` of a bounded JSON read: at most ``max_keys`` keys of at most
    ``max_key_chars`` characters, none twice, string values of at most ``max_string_chars``."""

    def pairs(items: list[tuple[str, Any]]) -> dict[str, Any]:
        if len(items) > max_keys:
            raise Refused(f"an object with {len(items)} keys; at most {max_keys}")
        out: dict[str, Any] = {}
        for k, v in items:
            if len(k) > max_key_chars:
                raise Refused(f"key {clip(k)} too long; at most {max_key_chars} characters")
            if k in out:
                raise Refused(f"key {clip(k)} given twice")
            if max_string_chars is not None and isinstance(v, str) and len(v) > max_string_chars:
                raise Refused(f"{safe(k)}: a string of {len(v)} characters; at most {max_string_chars}")
            out[k] = v
        return out

    return pairs


_const = refuse_constant
_pairs = bounded_pairs(MAX_KEYS, MAX_KEY_CHARS, MAX_STRING_CHARS)


def bad(name: str, reason: str, request_id: str | None = None, code: str = "BAD_REQUEST") -> Rejection:
    return Rejection(False, f"{name}: {reason}", request_id, CODE[code])


def _printable(s: str) -> bool:
    return all(0x20 <= ord(c) <= 0x7E for c in s)


def _kind(name: Any) -> CommandKind | Rejection:
    if isinstance(name, str) and len(name) <= MAX_NAME_CHARS:
        try:
            return CommandKind(name)
        except ValueError:
            pass
    kinds = ", ".join(k.value for k in CommandKind)
    return bad("command", f"{clip(name, MAX_NAME_CHARS)} unknown; allowed: {kinds}")


def read_bounded_json(payload: bytes | bytearray | memoryview, *, max_bytes: int = MAX_PAYLOAD_BYTES,
                      max_depth: int = MAX_DEPTH,
                      pairs: Callable[[list[tuple[str, Any]]], dict[str, Any]] = _pairs) -> Any:
    """THE bounded JSON reader: ``payload`` → a JSON value (None when it is empty), or
    :class:`Refused` with the reason. Bounded before it costs anything: the bytes, the nesting
    depth (a scan, before ``json.loads`` could recurse), every number's characters (NaN/Infinity
    refused), every object's keys and string values (``pairs``, :func:`bounded_pairs`)."""
    if len(payload) > max_bytes:
        raise Refused(f"payload of {len(payload)} bytes; at most {max_bytes}")
    try:
        text = bytes(payload).decode("utf-8").strip()
    except UnicodeDecodeError:
        raise Refused("payload is not UTF-8 JSON") from None
    if not text:
        return None
    if nesting_depth(text.encode(), max_depth) > max_depth:
        raise Refused(f"payload nested deeper than {max_depth} levels")
    try:
        return json.loads(text, parse_int=lambda s: _num(s, int), parse_float=lambda s: _num(s, float),
                          parse_constant=_const, object_pairs_hook=pairs)
    except _Refused:
        raise
    except (json.JSONDecodeError, RecursionError, ValueError) as e:
        raise Refused(f"payload is not JSON: {clip(str(e), 80)}") from None


def _decode(name: str, payload: bytes | bytearray | memoryview) -> dict[str, Any] | Rejection:
    """Bounded JSON: bytes → a dict of scalars' parents, or a code-9 Rejection."""
    try:
        obj = read_bounded_json(payload)
    except _Refused as e:
        return bad(name, str(e))
    if obj is None:
        return {}
    if isinstance(obj, str):
        return bad(name, f"payload must be a JSON object, got a string of {len(obj)} characters")
    if not isinstance(obj, dict):
        return bad(name, f"payload must be a JSON object, got {type(obj).__name__}")
    return obj


def _request_id(obj: Mapping[Any, Any]) -> str | None | Rejection:
    rid = obj.get("request_id")
    if rid is None:
        return None
    if not isinstance(rid, str) or not 0 < len(rid) <= REQUEST_ID_MAX or not _printable(rid):
        return bad("request_id", f"{clip(rid)}: a string of 1 to {REQUEST_ID_MAX} printable ASCII characters")
    return rid


def _check_value(name: str, k: str, v: Any, rid: str | None) -> Rejection | None:
    """Strict types, whatever the door: the same value is refused the same way everywhere."""
    if isinstance(v, (list, tuple, dict, set, bytes, bytearray)):
        return bad(name, f"{k}: a {type(v).__name__} is not allowed here", rid)
    if k in NUMERIC_FIELDS:
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return bad(name, f"{k}: {clip(v)} must be a number (not text, not true/false)", rid)
        if isinstance(v, int) and abs(v) > MAX_INT:
            return bad(name, f"{k}: an integer of {len(str(abs(v)))} digits is not allowed", rid)
        if not math.isfinite(v):
            return bad(name, f"{k}: {clip(v)} must be a finite number", rid)
    elif k in TEXT_FIELDS:
        if not isinstance(v, str):
            return bad(name, f"{k}: {clip(v)} must be a string", rid)
        if len(v) > MAX_STRING_CHARS:
            return bad(name, f"{k}: a string of {len(v)} characters; at most {MAX_STRING_CHARS}", rid)
        if k == "sample_id":
            err = check_sample_id(v)
            if err:
                return Rejection(False, f"{name}: {err}", rid, CODE["SAMPLE_ID"])
        elif not _printable(v):
            return bad(name, f"{k}: {clip(v)}: only printable ASCII characters (0x20–0x7E) are allowed", rid)
    return None


def intake(name: Any, raw: bytes | bytearray | memoryview | Mapping[Any, Any] | None,
           source: str) -> Command | Rejection:
    """THE intake of every door: the command ``name`` with its raw arguments ``raw`` → a Command
    for the station's validation (``Station.submit``), or a Rejection (code 9, or 4 for a sample ID
    that is not one). ``raw`` is the JSON object as bytes (MQTT, console; empty means ``{}``) or a
    mapping of argument names to values (Sparkplug, PLC, CLI). ``name=None``: the name is the
    object's ``command`` key (the console's body)."""
    if name is not None:
        kind = _kind(name)
        if isinstance(kind, Rejection):
            return kind
        label = kind.value
    else:
        label = "command"
    if raw is None:
        obj: Any = {}
    elif isinstance(raw, (bytes, bytearray, memoryview)):
        obj = _decode(label, raw)
        if isinstance(obj, Rejection):
            return obj
    elif isinstance(raw, Mapping):
        if len(raw) > MAX_KEYS:
            return bad(label, f"{len(raw)} arguments; at most {MAX_KEYS}")
        obj = raw
    else:
        return bad(label, f"arguments must be an object, got {type(raw).__name__}")
    for k in obj:
        if not isinstance(k, str) or len(k) > MAX_KEY_CHARS:
            return bad(label, f"key {clip(k)}: a name of at most {MAX_KEY_CHARS} characters")
    if name is None:
        kind = _kind(obj.get(COMMAND_KEY))
        if isinstance(kind, Rejection):
            return kind
        obj = {k: v for k, v in obj.items() if k != COMMAND_KEY}
    assert isinstance(kind, CommandKind)
    name = kind.value
    rid = _request_id(obj)
    if isinstance(rid, Rejection):
        return bad(name, rid.reason)
    allowed = COMMAND_KEYS[kind]
    unknown = sorted(k for k in obj if k not in allowed and k != "request_id")
    if unknown:
        return bad(name, f"unknown key(s) {', '.join(clip(k) for k in unknown[:4])}; allowed: "
                   f"{', '.join(allowed + ('request_id',))}", rid)
    args: dict[str, Any] = {}
    for k in allowed:
        v = obj.get(k)
        if v is None:
            continue
        err = _check_value(name, k, v, rid)
        if err is not None:
            return err
        args[k] = v
    return Command(kind, source, args, rid)


def parse_command(name: str, payload: bytes, source: str = "mqtt") -> Command | Rejection:
    """The MQTT door's call of :func:`intake`: ``cmd/<name>`` with its payload bytes."""
    return intake(name, payload, source)


def rejected_event_data(command: object, rejection: Rejection, source: str) -> RefusalData:
    """Data of the ``command_rejected`` event for an intake refusal (docs/mqtt.md, Events)."""
    return {"command": safe(command, MAX_NAME_CHARS), "source": safe(source, 80),
            "reason": rejection.reason, "code": int(rejection.code)}
