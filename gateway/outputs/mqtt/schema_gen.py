"""JSON Schemas (draft 2020-12) of every MQTT payload and command, generated from the one
definition in :mod:`gateway.outputs.mqtt.schema` (topics, fields, types) plus the enumerations that
live in code (test states, rejection codes, method statuses).

    python -m gateway.outputs.mqtt.schema_gen docs/schemas     # writes docs/schemas/*.json

A test checks the committed files are current, and validates payloads the gateway publishes.
"""
from __future__ import annotations

import json
import os
import sys
from typing import Any

from ...core import catalog
from ...core.command_intake import MAX_STRING_CHARS, REQUEST_ID_MAX, SAMPLE_ID_MAX
from ...core.command_rules import REJECT_CODES
from ...core.method.rules import REASON_NAMES
from ...core.records import AlarmState
from . import schema as S

DIALECT = "https://json-schema.org/draft/2020-12/schema"
ID_BASE = "https://hookwatch.invalid/schemas/"     # a name, not a place to fetch from

_TYPES = {"str": "string", "int": "integer", "float": "number", "bool": "boolean", "object": "object",
          "null": "null", "list": "array"}

TIME = {"type": "string", "pattern": r"^\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}\.\d{3}Z$"}
TIME_OR_NULL = {"anyOf": [TIME, {"type": "null"}]}

#: fields whose values are a closed set, per topic key (None: every topic)
ENUMS: dict[tuple[str | None, str], list[Any]] = {
    ("status", "status"): ["online", "offline"],
    # the state's enumerations: the catalog's rows with their choices (gateway/core/catalog.py)
    **{("state", v.name): list(v.choices) for v in catalog.CATALOG if v.mqtt and v.choices and v.type == "str"},
    ("alarm", "alarm"): ["end_of_life"],
    ("alarm", "state"): [a.value for a in AlarmState],
    ("alarm_warning", "state"): [a.value for a in AlarmState],
    ("result", "test_status"): ["completed", "aborted"],
    ("reply", "code"): [c for c, _n, _d in REJECT_CODES],
    ("event", "type"): [e.value for e in S.EVENT_DATA],
}

NESTED: dict[tuple[str, str], dict[str, Any]] = {
    ("telemetry", "tension"): {
        "type": "object", "additionalProperties": False, "required": ["mean", "min", "max"],
        "properties": {k: {"type": ["number", "null"]} for k in ("mean", "min", "max")}},
    ("telemetry", "counts"): {
        "type": "object", "additionalProperties": False, "required": list(REASON_NAMES),
        "properties": {k: {"type": "integer", "minimum": 0} for k in REASON_NAMES}},
    ("result", "result"): {
        "type": ["object", "null"],
        "properties": {"status": {"enum": [s for s, _ in S.RESULT_STATUS],
                                  "description": "; ".join(f"{s}: {d}" for s, d in S.RESULT_STATUS)},
                       "t_life": {"type": ["number", "null"]}, "mu_ss": {"type": ["number", "null"]},
                       "mu_th": {"type": ["number", "null"]}}},
}

_NUM_OR_NULL = {"type": ["number", "null"]}
NESTED[("lives", "lives")] = {
    "type": "array", "maxItems": 500,
    "items": {"type": "object", "additionalProperties": False,
              "required": ["test_id", "grade", "t_set", "status", "t_life", "censored_s", "n_slots",
                           "ts", "k_b", "stop_reasons", "end_reason", "t_end"],
              "properties": {
                  "test_id": {"type": "string"}, "grade": {"type": "string"},
                  "t_set": {"type": "number"}, "status": {"enum": ["failure", "no_failure", "aborted"]},
                  "t_life": _NUM_OR_NULL, "censored_s": _NUM_OR_NULL,
                  "n_slots": {"type": "integer", "minimum": 1}, "ts": {"type": "number"},
                  "k_b": {"type": ["integer", "null"]},
                  "stop_reasons": {"type": ["array", "null"], "items": {"type": "string"}},
                  "end_reason": {"type": ["string", "null"]}, "t_end": {"type": "number"}}}}

#: command fields that must be present
REQUIRED_CMD = {"cmd_start": ("sample_id", "t_set"), "cmd_setpoint": ("t_set",)}


def _type(spec: str) -> dict[str, Any]:
    parts = spec.split("|")
    ts = [_TYPES[p] for p in parts]
    return {"type": ts[0] if len(ts) == 1 else ts}


def field_schema(topic: S.Topic, f: S.Field) -> dict[str, Any]:
    if (topic.key, f.name) in NESTED:
        out = dict(NESTED[(topic.key, f.name)])
    elif f.name == "time" or f.name.endswith("_at"):
        out = dict(TIME if f.type == "str" else TIME_OR_NULL)
    else:
        out = _type(f.type)
    enum = ENUMS.get((topic.key, f.name))
    if enum is not None:
        out["enum"] = enum + ([None] if "null" in f.type else [])
    if f.name == "schema":
        out = {"const": S.SCHEMA_VERSION}
    if f.name in ("seq", "session"):
        out["minimum"] = 0
    if t_is_command(topic) and f.type == "str":
        # the intake's bounds (gateway/core/command_intake.py): printable ASCII, bounded length
        out["minLength"] = 1 if f.name in ("sample_id", "request_id", "test_id") else 0
        out["maxLength"] = {"sample_id": SAMPLE_ID_MAX, "request_id": REQUEST_ID_MAX}.get(f.name, MAX_STRING_CHARS)
        out["pattern"] = "^[ -~]*$"
    out["description"] = f.doc
    return out


def t_is_command(t: S.Topic) -> bool:
    return t.direction == "subscribe"


def topic_schema(t: S.Topic) -> dict[str, Any]:
    props = {f.name: field_schema(t, f) for f in t.fields}
    if t.direction == "publish":
        required = [f.name for f in t.fields]
    else:
        required = list(REQUIRED_CMD.get(t.key, ()))
    return {
        "$schema": DIALECT, "$id": f"{ID_BASE}{t.key}.json",
        "title": f"hookwatch MQTT `{t.path}` ({'published' if t.direction == 'publish' else 'command'})",
        "description": f"{t.doc}. QoS {t.qos}, retained: {'yes' if t.retain else 'no'}. "
                       f"Schema version {S.SCHEMA_VERSION}; generated from gateway/outputs/mqtt/schema.py.",
        "type": "object", "additionalProperties": False, "required": required, "properties": props,
    }


def render_all() -> dict[str, str]:
    """File name → JSON text of every schema."""
    return {f"{t.key}.json": json.dumps(topic_schema(t), indent=2, ensure_ascii=False) + "\n"
            for t in S.TOPICS}


def main(argv: list[str]) -> int:
    out_dir = argv[0] if argv else os.path.join("docs", "schemas")
    os.makedirs(out_dir, exist_ok=True)
    for name, text in render_all().items():
        with open(os.path.join(out_dir, name), "w", encoding="utf-8") as f:
            f.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
