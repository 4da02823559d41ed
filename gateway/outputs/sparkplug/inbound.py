"""Everything a Sparkplug edge node receives, parsed within bounds. Pure: no I/O, no clock.

The node subscribes to the primary host's ``spBv1.0/STATE/<host_id>`` (JSON) and to its NCMD and
DCMD topics (Sparkplug protobuf). Anyone who may publish on the broker can put anything there, and
a **retained** STATE comes back at every reconnect, so nothing received may end the session or the
node's thread. Every payload is checked *before* it can cost anything:

- STATE: at most ``state_max_bytes`` bytes (checked on the bytes), nesting of ``[``/``{`` at most
  :data:`STATE_MAX_DEPTH` (a scan of the bytes before ``json.loads`` could recurse), number
  literals at most :data:`MAX_NUMBER_CHARS` characters, no NaN/Infinity, at most
  :data:`STATE_MAX_KEYS` keys, no duplicate key; ``online`` a JSON boolean, ``timestamp`` a JSON
  integer 0 ≤ t < 2⁶³ (ms since the epoch);
- NCMD / DCMD: at most ``max_payload_bytes`` bytes before the protobuf decoder sees them, at most
  ``max_metrics`` metrics, metric names and string values at most ``max_string_chars``
  characters.

A refused payload raises :class:`BadInput` (its kind and a short reason: never the payload itself
beyond a few characters); the node counts it and notes it in its :class:`BadInputs`, which the
caller takes for its log through :class:`gateway.plumbing.ratelog.RateLog` (one line per kind per minute,
with the count).
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

from ...core.command_intake import Refused, bounded_pairs, clip, nesting_depth, refuse_constant
from .sparkplug_b_pb2 import Payload

#: nesting of the STATE document: ``{"online": …, "timestamp": …}`` is depth 1
STATE_MAX_DEPTH = 2
STATE_MAX_KEYS = 8
MAX_KEY_CHARS = 32
MAX_NUMBER_CHARS = 32
#: a timestamp is a uint64 on the wire; JSON numbers beyond int64 are refused
MAX_TIMESTAMP = (1 << 63) - 1
#: bad inputs kept for the caller between two takes (the counters count them all)
BAD_MAX = 64


@dataclass(frozen=True)
class InboundLimits:
    """The bounds on what the node receives (the ``sparkplug:`` keys of the same names)."""
    max_payload_bytes: int = 16384
    max_metrics: int = 64
    max_string_chars: int = 256
    state_max_bytes: int = 1024


class BadInput(ValueError):
    """A received payload outside its bounds or malformed; ``kind`` names the door (state,
    ncmd, dcmd, topic)."""

    def __init__(self, kind: str, reason: str):
        super().__init__(f"{kind}: {reason}")
        self.kind = kind
        self.reason = reason


class BadInputs:
    """The bad inputs of a node: each counted (``bad_<kind>`` and ``ignored_commands`` in the
    node's counters) and noted (kind, reason) for the caller's rate-limited log, at most
    :data:`BAD_MAX` between two takes."""

    def __init__(self, counters: dict[str, int]) -> None:
        self.counters = counters
        self.notes: list[tuple[str, str]] = []

    def refused(self, e: BadInput) -> None:
        """A payload (or topic) refused: counted and noted."""
        self.counters[f"bad_{e.kind}"] = self.counters.get(f"bad_{e.kind}", 0) + 1
        self.counters["ignored_commands"] += 1
        self.note(e.kind, e.reason)

    def note(self, kind: str, reason: str) -> None:
        if len(self.notes) < BAD_MAX:
            self.notes.append((kind, reason))

    def take(self) -> list[tuple[str, str]]:
        """The bad inputs noted since the last call."""
        out, self.notes = self.notes, []
        return out


_Refused = Refused


def _num(s: str, conv: Any) -> Any:
    if len(s) > MAX_NUMBER_CHARS:
        raise _Refused(f"a number of {len(s)} characters; at most {MAX_NUMBER_CHARS}")
    v = conv(s)
    if isinstance(v, float) and not math.isfinite(v):
        raise _Refused(f"{clip(s)} is not a finite number")
    return v


_const = refuse_constant
_pairs = bounded_pairs(STATE_MAX_KEYS, MAX_KEY_CHARS)


def parse_state(payload: bytes, limits: InboundLimits) -> tuple[bool, int]:
    """``(online, timestamp_ms)`` of a Sparkplug 3.0 STATE payload, or :class:`BadInput`."""
    n = len(payload)
    if n > limits.state_max_bytes:
        raise BadInput("state", f"payload of {n} bytes; at most {limits.state_max_bytes}")
    raw = bytes(payload)
    d = nesting_depth(raw, STATE_MAX_DEPTH)
    if d > STATE_MAX_DEPTH:
        raise BadInput("state", f"nested deeper than {STATE_MAX_DEPTH} levels")
    try:
        text = raw.decode("utf-8")
        doc = json.loads(text, parse_int=lambda s: _num(s, int), parse_float=lambda s: _num(s, float),
                         parse_constant=_const, object_pairs_hook=_pairs)
    except _Refused as e:
        raise BadInput("state", str(e)) from None
    except (UnicodeDecodeError, ValueError, RecursionError) as e:
        raise BadInput("state", f"not UTF-8 JSON: {clip(str(e), 60)}") from None
    if not isinstance(doc, dict):
        raise BadInput("state", f"not a JSON object but {type(doc).__name__}")
    online = doc.get("online")
    ts = doc.get("timestamp")
    if not isinstance(online, bool):
        raise BadInput("state", f"online {clip(online)} is not a JSON boolean")
    if isinstance(ts, bool) or not isinstance(ts, int):
        raise BadInput("state", f"timestamp {clip(ts)} is not a JSON integer (ms since the epoch)")
    if not 0 <= ts <= MAX_TIMESTAMP:
        raise BadInput("state", f"timestamp {clip(ts)} is outside 0 … 2^63-1")
    return online, ts


def parse_payload(kind: str, payload: bytes, limits: InboundLimits) -> Payload:
    """A Sparkplug protobuf payload (NCMD, DCMD) within the limits, or :class:`BadInput`."""
    n = len(payload)
    if n > limits.max_payload_bytes:
        raise BadInput(kind, f"payload of {n} bytes; at most {limits.max_payload_bytes}")
    p = Payload()
    try:
        p.ParseFromString(bytes(payload))
    except Exception as e:  # noqa: BLE001 - DecodeError, and upb's RecursionError-like errors
        raise BadInput(kind, f"not a Sparkplug payload ({type(e).__name__})") from None
    if len(p.metrics) > limits.max_metrics:
        raise BadInput(kind, f"{len(p.metrics)} metrics; at most {limits.max_metrics}")
    cap = limits.max_string_chars
    for m in p.metrics:
        if len(m.name) > cap:
            raise BadInput(kind, f"a metric name of {len(m.name)} characters; at most {cap}")
        if m.WhichOneof("value") == "string_value" and len(m.string_value) > cap:
            raise BadInput(kind, f"{clip(m.name or m.alias)}: a string of {len(m.string_value)} characters; "
                           f"at most {cap}")
    return p
