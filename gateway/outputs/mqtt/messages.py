"""MQTT messages of a station, built purely: station data in, (topic, payload, QoS, retain) out.

No I/O, no clock, no threads: each function turns a slot record summary, an event, the station's
state, the alarm store's record or a command reply into :class:`Message` objects. The payload is
a function of the stream's sequence number, which the pump stamps when it queues the message
(``gateway/outputs/mqtt/pump.py``). The topic tree and payload fields are defined once in
``schema.py``.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ... import __version__
from ...core import catalog
from ...core.command_rules import reply_code
from ...core.records import CommandReply, Event, EventType, StationState
from ...core.slotwindow import SlotWindow
from ...station.alarm_store import AlarmRecord
from ..plc.registers import MAP_VERSION
from . import schema as mqtt_schema

SOFTWARE = f"hookwatch {__version__}"


@dataclass(frozen=True)
class Message:
    """One MQTT message: what to publish where. ``payload(seq)`` is its JSON object."""
    kind: str                                   # telemetry, event, alarm, result, state, reply, status
    topic: str
    payload: Callable[[int], dict[str, Any]]
    qos: int = 1
    retain: bool = False
    correlation: bytes | None = None            # MQTT 5 Correlation Data (a reply to a request)

    def encode(self, seq: int) -> bytes:
        return mqtt_schema.encode(self.payload(seq))


def _r(x: float) -> float:
    return round(x, 6)


def telemetry_summary(w: SlotWindow, now: float, test_id: str | None, headroom: float | None = None,
                      t_cross: float | None = None,
                      slots: tuple[catalog.SlotValue, ...] = catalog.SLOT_CATALOG) -> dict[str, Any]:
    """A telemetry interval's figures from its window of slots (``gateway/core/slotwindow.py``, opened
    at ``w.t0`` on the output's monotonic clock): the slot records' rows of the catalog
    (gateway/core/catalog.py); ``headroom`` and ``t_cross`` are the §5a figures of the last
    complete window of the running test (the station's state)."""
    return {
        "test_id": test_id, "interval_s": round(now - w.t0, 3),
        **catalog.read_window(slots, w, bool(test_id)),
        "headroom": headroom if test_id else None, "t_cross": t_cross if test_id else None,
        # §5b: the forecast of the last forecast time (the MQTT output fills it from the state)
        **mqtt_schema.forecast_fields(None),
    }


def alarm_fields(rec: AlarmRecord) -> dict[str, Any]:
    """The alarm store's record as the fields of the ``alarm/end_of_life`` (or, for the wear
    warning, ``alarm/warning``) message."""
    return {"state": rec.state.value, "active": rec.active, "condition": rec.condition,
            "acknowledged": rec.acknowledged, "shelved_until": rec.shelved_until, "test_id": rec.test_id,
            "sample_id": rec.sample_id, "t_life": rec.t_life, "k_life": rec.k_life,
            "warn_slot": rec.warn_slot, "t_warn": rec.t_warn, "headroom": rec.headroom,
            "t_cross": rec.t_cross, "reasons": None if rec.reasons is None else list(rec.reasons),
            "end_p10": rec.end_p10, "end_p50": rec.end_p50, "end_p90": rec.end_p90,
            "p_end": rec.p_end, "lead_s": rec.lead_s,
            "mu_ss": rec.mu_ss, "mu_th": rec.mu_th, "raised_at": rec.raised_at,
            "acknowledged_at": rec.acknowledged_at, "acknowledged_by": rec.acknowledged_by,
            "cleared_at": rec.cleared_at}


def _message(key: str, base: str, payload: Callable[[int], dict[str, Any]], **path: str) -> Message:
    """A message on topic ``key`` of the tree; QoS and retain as ``mqtt_schema.TOPICS`` defines them."""
    t = mqtt_schema.TOPIC[key]
    return Message(key, mqtt_schema.topic_for(base, key, **path), payload, t.qos, t.retain)


def telemetry_message(base: str, station: str, t: float, summary: dict[str, Any]) -> Message:
    return _message("telemetry", base, lambda seq: mqtt_schema.telemetry_payload(seq, t, station, summary))


def alarm_message(base: str, station: str, t: float, rec: AlarmRecord) -> Message:
    fields = alarm_fields(rec)
    return _message("alarm", base, lambda seq: mqtt_schema.alarm_payload(seq, t, station, fields))


def warning_message(base: str, station: str, t: float, rec: AlarmRecord) -> Message:
    fields = alarm_fields(rec)
    return _message("alarm_warning", base, lambda seq: mqtt_schema.warning_payload(seq, t, station, fields))


#: the events that change alarms (by command or by time)
ALARM_EVENTS = (EventType.ALARM_ACK, EventType.ALARM_CLEARED, EventType.ALARM_SHELVED,
                EventType.ALARM_UNSHELVED, EventType.ALARM_OUT_OF_SERVICE, EventType.ALARM_IN_SERVICE)


def event_messages(base: str, ev: Event, last_state: StationState | None,
                   alarm: AlarmRecord, warning: AlarmRecord | None = None) -> list[Message]:
    """The messages of one event: the event itself, then the alarms (alarm events, as the alarm
    store now has them: the wear warning only once it was ever raised) or the retained result
    (end of a test)."""
    out = [_message("event", base, lambda seq: mqtt_schema.event_payload(seq, ev), type=ev.type.value)]
    changed = {tr.get("alarm") for tr in ev.data.get("transitions") or ()}
    if ev.type == EventType.END_OF_LIFE or (ev.type in ALARM_EVENTS and (
            "end_of_life" in changed or "transitions" not in ev.data)):
        out.append(alarm_message(base, ev.station, ev.wall_time, alarm))
    if warning is not None and (warning.raised or "wear_warning" in changed) and (
            ev.type == EventType.WEAR_WARNING or (ev.type in ALARM_EVENTS and (
                "wear_warning" in changed or "transitions" not in ev.data))):
        out.append(warning_message(base, ev.station, ev.wall_time, warning))
    elif ev.type == EventType.TEST_ENDED:
        out.append(_message("result", base, lambda seq: mqtt_schema.result_payload(seq, ev, last_state)))
    return out


def state_key(st: StationState,
              values: tuple[catalog.Value, ...] = catalog.CATALOG) -> tuple[catalog.Reading | tuple[str, ...], ...]:
    """What makes a new retained ``state`` message worth sending: every value of the `state`
    (gateway/core/catalog.py) but those that change with time alone (the elapsed time)."""
    return tuple(tuple(x) if isinstance(x, list) else x
                 for x in (v.source(st) for v in values if v.mqtt and not v.ticks))


def state_message(base: str, t: float, st: StationState) -> Message:
    return _message("state", base, lambda seq: mqtt_schema.state_payload(seq, t, st))


def status_message(base: str, station: str, t: float, online: bool) -> Message:
    """The retained ``status`` (also the Last Will): published directly, not through the outbox;
    ``payload(n)``/``encode(n)`` take its own counter, the session number, not an outbox seq."""
    status = "online" if online else "offline"
    return _message("status", base,
                    lambda session: mqtt_schema.status_payload(session, t, station, status, SOFTWARE, MAP_VERSION))


def reply_message(base: str, station: str, t: float, command: str, request_id: str | None,
                  r: CommandReply, response: tuple[str, bytes | None] | None = None,
                  source: str = mqtt_schema.COMMAND_SOURCE) -> Message:
    """The answer to a command of ``source`` (its door: ``mqtt``, ``mqtt:<door>``): on ``reply``,
    or (MQTT 5) on the request's Response Topic with its Correlation Data, ``response = (topic,
    correlation)``."""
    code = reply_code(r)
    rid = request_id if request_id is not None else r.request_id
    msg = _message("reply", base, lambda seq: mqtt_schema.reply_payload(seq, t, station, command, rid, r.ok,
                                                                        code, r.reason, source))
    if response is None:
        return msg
    return Message(msg.kind, response[0], msg.payload, msg.qos, False, response[1])


def command_filter(base: str) -> str:
    """The subscription that receives every command topic of the station's default door."""
    return mqtt_schema.command_door_filter(base)
