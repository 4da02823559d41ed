"""The one definition of hookwatch's MQTT interface: topic tree, QoS/retain, payload fields.

The runtime (``gateway/outputs/mqtt/output.py``) builds every payload with the functions here and
``docs/mqtt.md`` is generated from the same tables (``python -m gateway.outputs.mqtt.schema >
docs/mqtt.md``; a test checks it is current). Bump :data:`SCHEMA_VERSION` when a field changes
meaning or disappears (adding a field is compatible).
"""
from __future__ import annotations

import datetime as _dt
import re
from dataclasses import dataclass
from typing import Any

from ...core import catalog
from ...core.command_rules import REJECT_CODES
from ...core.method.rules import REASON_NAMES
from ...core.records import AlarmState, CommandKind, Event, EventType, StationState, TestState
from ...plumbing import safeout
from ..plc.registers import MAP_VERSION

#: version of the topic tree and payloads (every payload carries it as "schema")
SCHEMA_VERSION = 3      # 3: ISA-18.2 alarm states (normal, unacknowledged, acknowledged,
                        # rtn_unacknowledged, shelved, out_of_service), alarm `condition` and
                        # `shelved_until`, events' `transitions`, cmd/shelve|unshelve|out_of_service|in_service
                        # 2: `status` carries its own `session` counter instead of a `seq`; state
                        # test_state `starting`; §5a headroom/t_cross; the alarm/warning alarms


@dataclass(frozen=True)
class Field:
    name: str
    type: str
    doc: str


@dataclass(frozen=True)
class Topic:
    key: str               # internal name
    path: str              # below the station's base topic
    direction: str         # "publish" (gateway → broker) or "subscribe" (broker → gateway)
    qos: int
    retain: bool
    durable: bool          # goes through the on-disk outbox
    doc: str
    fields: tuple[Field, ...] = ()


ENVELOPE = (
    Field("schema", "int", f"payload schema version ({SCHEMA_VERSION})"),
    Field("seq", "int", "per-station sequence number: one counter for every message of the station "
          "that goes through the outbox, strictly increasing across gateway restarts; consumers "
          "drop a message whose seq they have already processed (see Delivery, De-duplication). "
          "Every payload but `status` carries it"),
    Field("time", "str", "UTC time of what the message reports, ISO 8601 with milliseconds "
          "(`2026-03-01T08:00:00.020Z`)"),
    Field("station", "str", "station id"),
)

STATUS_FIELDS = (
    ENVELOPE[0],
    Field("session", "int", "the status's own counter, not an outbox `seq` (never compare the two): "
          "the number of the gateway's MQTT session for this station, +1 on every connect, persisted "
          "in the outbox so it keeps increasing across gateway restarts. `online` and the `offline` "
          "of the same session carry the same number; the highest number received is the current "
          "status"),
    ENVELOPE[2], ENVELOPE[3],
    Field("status", "str", "`online` (published on every connect) or `offline` (the Last Will, "
          "published by the broker when the gateway vanishes, or by the gateway on a clean stop). "
          "In the Last Will, `time` is the time the session **started** (the Will is handed to the "
          "broker with the CONNECT and cannot change afterwards), not the moment the gateway "
          "vanished; that moment is known only to the broker (it publishes the Will at once on a "
          "closed TCP connection, at the latest 1.5 × `keepalive_s` after the last packet): take "
          "your receive time. On a clean stop `time` is the stop time"),
    Field("software", "str", "gateway software version"),
    Field("map_version", "int", "version of the PLC register map served alongside"),
)

#: the §5b remaining-life figures (METHOD.md) of the station's state that `telemetry` carries too:
#: the forecast as found at the last forecast time (a window's end) of the running test; none
#: outside a test, none of the projection (end_p*, p_end, due) from the end-of-life detection on
TELEMETRY_FORECAST = ("end_p10", "end_p50", "end_p90", "p_end", "due")


def _field(v: catalog.Value) -> Field:
    return Field(v.name, v.type, v.doc)


FORECAST_FIELDS = tuple(_field(catalog.BY_NAME[n]) for n in TELEMETRY_FORECAST)


def _empty(f: Field) -> Any:
    return [] if f.type == "list" else False if f.type == "bool" else None


def forecast_fields(st: StationState | None) -> dict[str, Any]:
    """The forecast figures of ``st`` that `telemetry` carries (FORECAST_FIELDS; none without a state)."""
    if st is None:
        return {f.name: _empty(f) for f in FORECAST_FIELDS}
    return {n: catalog.BY_NAME[n].source(st) for n in TELEMETRY_FORECAST}


def state_fields(values: tuple[catalog.Value, ...] = catalog.CATALOG) -> tuple[Field, ...]:
    """The fields of the retained `state`: the envelope, then every catalog row with an MQTT key
    (gateway/core/catalog.py), in its order."""
    return ENVELOPE + tuple(_field(v) for v in values if v.mqtt)


STATE_FIELDS = state_fields()

def telemetry_fields(slots: tuple[catalog.SlotValue, ...] = catalog.SLOT_CATALOG) -> tuple[Field, ...]:
    """The fields of `telemetry`: the envelope, the test and the interval, every slot records' row
    of the catalog with a window source (gateway/core/catalog.py), in its order, then the §5a/§5b
    figures of the station's state."""
    return ENVELOPE + (
        Field("test_id", "str|null", "test running during this interval"),
        Field("interval_s", "float", "length of the interval the figures cover, s"),
        *(Field(s.name, s.type, s.doc) for s in slots if s.window is not None),
        Field("headroom", "float|null", "wear headroom of the last complete window (§5a), as in `state`"),
        Field("t_cross", "float|null", "projected crossing of μ_th, s from test start (§5a), as in `state`"),
        *FORECAST_FIELDS,
    )


TELEMETRY_FIELDS = telemetry_fields()

EVENT_FIELDS = ENVELOPE + (
    Field("type", "str", "event type (the last topic level)"),
    Field("test_id", "str|null", "test the event belongs to"),
    Field("k", "int|null", "slot of the test at which it happened"),
    Field("data", "object", "event-specific values, see the table of events"),
)

#: the lifecycle fields both alarms share (the alarm store's AlarmRecord)
_ALARM_STATE = (
    Field("state", "str", "ISA-18.2 state: `normal` → `unacknowledged` (raised) → `acknowledged` → "
          "`normal` (closed: the hook was replaced or a new test started); `rtn_unacknowledged`, "
          "`shelved` (until `shelved_until`), `out_of_service` (a needle is being changed)"),
    Field("active", "bool", "true while the alarm stands in any state but `normal`"),
    Field("condition", "bool", "true while the alarm's condition stands (the worn hook is in)"),
    Field("acknowledged", "bool", "true once someone acknowledged it"),
    Field("shelved_until", "str|null", "UTC time a shelving expires (state `shelved`)"),
)
_ALARM_TIMES = (
    Field("raised_at", "str|null", "UTC time the alarm was raised"),
    Field("acknowledged_at", "str|null", "UTC time of the acknowledgement"),
    Field("acknowledged_by", "str|null", "source of the acknowledgement (mqtt, plc:ADDR, cli)"),
    Field("cleared_at", "str|null", "UTC time the alarm was cleared"),
)

ALARM_FIELDS = ENVELOPE + (
    Field("alarm", "str", "`end_of_life`"),
    Field("priority", "int", "1: the most urgent (the wear warning is 2)"),
    *_ALARM_STATE,
    Field("test_id", "str|null", "the test that reached its end of life"),
    Field("sample_id", "str|null", "its sample"),
    Field("t_life", "float|null", "wear life, s from test start"),
    Field("k_life", "int|null", "slot of the end of life"),
    Field("mu_ss", "float|null", "baseline μ_ss"),
    Field("mu_th", "float|null", "threshold μ_th"),
    *_ALARM_TIMES,
)

WARNING_FIELDS = ENVELOPE + (
    Field("alarm", "str", "`warning`"),
    Field("priority", "int", "2: below the end of life (1)"),
    *_ALARM_STATE,
    Field("test_id", "str|null", "the test whose headroom fell"),
    Field("sample_id", "str|null", "its sample"),
    Field("warn_slot", "int|null", "last slot of the first due window (§5b)"),
    Field("t_warn", "float|null", "time of the warning, s from test start ((warn_slot + 1)·Ts)"),
    Field("headroom", "float|null", "the headroom of that window"),
    Field("t_cross", "float|null", "the projection at that window, s from test start (null: none)"),
    Field("reasons", "list|null", "why that window was due (§5b, sorted): headroom, prior, trend"),
    Field("end_p10", "float|null", "the forecast then: end quantile 10 %, s from slot 0"),
    Field("end_p50", "float|null", "end median, s from slot 0"),
    Field("end_p90", "float|null", "end quantile 90 %, s from slot 0"),
    Field("p_end", "float|null", "chance of the end within the lead then"),
    Field("lead_s", "float|null", "the lead, s"),
    Field("mu_ss", "float|null", "baseline μ_ss"),
    Field("mu_th", "float|null", "threshold μ_th"),
    *_ALARM_TIMES,
)

#: values of `result.status` (the method's verdict, METHOD.md) and what each means for the MES
RESULT_STATUS: tuple[tuple[str, str], ...] = (
    ("failure", "the hook reached its end of life: `t_life` is its wear life (s); replace the hook "
     "and count the life in the grade's statistics"),
    ("no_failure", "the test ran to its planned end `t_end` without an end of life: the life is "
     "longer than `t_end` (a censored observation, not a failure); the hook may stay in service"),
    ("no_baseline", "no steady baseline μ_ss was found, so no life can be judged: check the set-up "
     "(threading, tension, meter) and repeat the test"),
    ("aborted", "the test was stopped before a judgement (command, protection stop, gateway "
     "restart): no life; `end_reason` says why; repeat the test when needed"),
)

RESULT_FIELDS = ENVELOPE + (
    Field("test_id", "str|null", "the test"),
    Field("sample_id", "str|null", "its sample"),
    Field("grade", "str|null", "its grade"),
    Field("t_set", "float|null", "its setpoint, N"),
    Field("test_status", "str", "completed or aborted"),
    Field("end_reason", "str", "completed, protection stop, stopped by command, gateway restart, …"),
    Field("why", "str|null", "the cause in words when the drive stopped on its own during the test "
          "(`the drive stopped on its own (STM32 watchdog, 1.5 s without the gateway): the gateway "
          "stalled 2512 ms`: a protection stop follows); else null"),
    Field("result", "object|null", "the method's result (status, t_life, mu_ss, mu_th, k_b, "
          "stop_reasons — `[\"STOPPED\"]` for a test ended on purpose —, headroom, warn_slot, "
          "t_cross, … — the keys of `hookwatch analyze --json`); `result.status` is one of "
          + ", ".join(f"`{k}`" for k, _ in RESULT_STATUS) + " (see Results)"),
)

REPLY_FIELDS = ENVELOPE + (
    Field("command", "str", "the command answered (" + ", ".join(k.value for k in CommandKind)
          + ", or the unknown name)"),
    Field("request_id", "str|null", "the request_id of the command, if it had one"),
    Field("source", "str", "the door the command came in by: `mqtt` (`cmd/<command>`), or "
          "`mqtt:<door>` for a named door (`cmd/<door>/<command>`, `mqtt.command_doors`)"),
    Field("ok", "bool", "true: carried out; false: refused, nothing was done"),
    Field("code", "int", "0 when ok, else the rejection code (table below; the same codes a PLC reads)"),
    Field("reason", "str", "why it was refused (field, value, what is allowed); empty when ok"),
)

CMD_START_FIELDS = (
    Field("sample_id", "str", "required: 1–32 printable ASCII characters"),
    Field("grade", "str", "optional: one of the station's grades"),
    Field("t_set", "float", "required: tension setpoint, N, in (0, 0.98 · meter full scale)"),
    Field("t_end", "float", "optional: planned duration, s (default: the station's test.t_end_s)"),
    Field("request_id", "str", "optional: 1–64 printable ASCII characters, echoed in the reply"),
)
CMD_SIMPLE_FIELDS = (Field("request_id", "str", "optional: 1–64 printable ASCII characters, echoed in the reply"),)
CMD_STOP_FIELDS = (Field("test_id", "str", "optional: the test to stop (its `test_id`); a stop naming "
                         "a test that is not the running one is refused (15 WRONG_TEST, 2 "
                         "NOT_RUNNING) and stops nothing"), *CMD_SIMPLE_FIELDS)
CMD_HOOK_FIELDS = (Field("sample_id", "str", "optional: the NEW hook's sample id (1–64 printable "
                         "ASCII characters); without it `<old>-R<n>`"),
                   Field("grade", "str", "optional: the new hook's grade, one of the station's "
                         "grades (default: the old hook's)"),
                   *CMD_SIMPLE_FIELDS)
CMD_UNSHELVE_FIELDS = (Field("alarm", "str", "`end_of_life` or `wear_warning`"), *CMD_SIMPLE_FIELDS)
CMD_SHELVE_FIELDS = (*CMD_UNSHELVE_FIELDS[:1],
                     Field("duration_s", "float", "how long, s (at most 43200: one 12 h shift)"),
                     *CMD_SIMPLE_FIELDS)
CMD_SETPOINT_FIELDS = (
    Field("t_set", "float", "required: setpoint of the next test, N (refused while a test runs)"),
    Field("request_id", "str", "optional: 1–64 printable ASCII characters, echoed in the reply"),
)

LIVES_FIELDS = ENVELOPE + (
    Field("lives", "list", "the station's completed tests that give METHOD.md §7a's history a life, "
          "its newest 500 at most, oldest first; each `{test_id, grade, t_set, status, t_life, "
          "censored_s, n_slots, ts, k_b, stop_reasons, end_reason, t_end}`: a `failure` with "
          "`t_life` (s), or a right-censored life — a test that found its baseline (`k_b`) and "
          "ended on purpose (`aborted`, `stop_reasons` [\"STOPPED\"]) or at `t_end` "
          "(`no_failure`) — with `censored_s` = `n_slots` · `ts`; `t_end` the planned duration, "
          "`end_reason` the gateway's. The gateways of the site pool them into the life prior "
          "(`mqtt.share_lives`; gateway/outputs/mqtt/sitelives.py)"),
)

TOPICS: tuple[Topic, ...] = (
    Topic("status", "status", "publish", 1, True, False,
          "gateway connection status; `offline` is the Last Will", STATUS_FIELDS),
    Topic("state", "state", "publish", 1, True, True,
          "station and test state; on every change of the test state and at least every 10 s",
          STATE_FIELDS),
    Topic("telemetry", "telemetry", "publish", 1, False, True,
          "figures aggregated over `mqtt.telemetry_interval_s` (1 s by default)", TELEMETRY_FIELDS),
    Topic("event", "event/{type}", "publish", 1, False, True,
          "one message per event, each exactly once (types below)", EVENT_FIELDS),
    Topic("alarm", "alarm/end_of_life", "publish", 1, True, True,
          "the end-of-life alarm and its lifecycle", ALARM_FIELDS),
    Topic("alarm_warning", "alarm/warning", "publish", 1, True, True,
          "the wear-warning alarm (§5a, priority 2) and its lifecycle", WARNING_FIELDS),
    Topic("result", "result", "publish", 1, True, True,
          "the result of the last test that ended", RESULT_FIELDS),
    Topic("lives", "lives", "publish", 1, True, True,
          "the station's lives for its site's life history (METHOD.md §7a): one retained snapshot "
          "per station, published at the start, after every test, after every reconnect and in "
          "answer to a site's `<prefix>/<site>/lives_request` (at most once per 10 s); every "
          "gateway of the site subscribes to `<prefix>/<site>/+/+/+/lives` (`mqtt.share_lives`, "
          "on by default)", LIVES_FIELDS),
    Topic("reply", "reply", "publish", 1, False, True,
          "the answer to every command received on cmd/… (MQTT 5: on the request's Response Topic "
          "instead, when it names one below `mqtt.reply_prefix`)", REPLY_FIELDS),
    Topic("cmd_start", "cmd/start", "subscribe", 1, False, False,
          "start a test", CMD_START_FIELDS),
    Topic("cmd_stop", "cmd/stop", "subscribe", 1, False, False,
          "stop the running test (it ends as aborted)", CMD_STOP_FIELDS),
    Topic("cmd_ack", "cmd/ack", "subscribe", 1, False, False,
          "acknowledge the active alarms (end of life and wear warning)", CMD_SIMPLE_FIELDS),
    Topic("cmd_setpoint", "cmd/setpoint", "subscribe", 1, False, False,
          "set the tension setpoint of the next test", CMD_SETPOINT_FIELDS),
    Topic("cmd_hook_replaced", "cmd/hook_replaced", "subscribe", 1, False, False,
          "the worn hook was replaced: the running test ends (`end_reason` hook_replaced), its "
          "alarms close, one line goes to the station's hooks.jsonl (the history the life prior "
          "learns from, METHOD.md §7a) and, with `test.restart_on_replace`, the next test starts "
          "with the new hook. Refused (NO_ALARM) only when there is no alarm, no test and no "
          "`sample_id`", CMD_HOOK_FIELDS),
    Topic("cmd_shelve", "cmd/shelve", "subscribe", 1, False, False,
          "shelve one annunciated alarm until `duration_s` from now (ISA-18.2)", CMD_SHELVE_FIELDS),
    Topic("cmd_unshelve", "cmd/unshelve", "subscribe", 1, False, False,
          "end the shelving of one alarm", CMD_UNSHELVE_FIELDS),
    Topic("cmd_out_of_service", "cmd/out_of_service", "subscribe", 1, False, False,
          "take both alarms out of service (a needle is being changed)", CMD_SIMPLE_FIELDS),
    Topic("cmd_in_service", "cmd/in_service", "subscribe", 1, False, False,
          "return the alarms to service", CMD_SIMPLE_FIELDS),
)
TOPIC = {t.key: t for t in TOPICS}

#: data keys of each event type (the `data` object of event/… messages)
#: the data of a stop of the drive on its own (gateway/core/ports.py DriveStop.as_data)
_DRIVE_STOP: tuple[tuple[str, str], ...] = (
    ("reason", "the STM32's stop reason: WATCHDOG (no frame for its watchdog period), STALL, "
               "OVERSPEED (its trips)"),
    ("flags", "the STM32's status flags then (docs/protocols/stm32.md)"),
    ("watchdog_s", "the STM32's watchdog period, s"),
    ("silence_ms", "the longest time between two frames the gateway sent since the drive was "
                   "enabled, measured by the gateway's link (null: not measured)"),
    ("gateway_stalled", "that silence is longer than the keep-alive allows (half the watchdog): "
                        "the gateway's process stalled"),
    ("why", "in words: `the drive stopped on its own (STM32 watchdog, 1.5 s without the "
            "gateway): the gateway stalled 2512 ms`"),
)

EVENT_DATA: dict[EventType, tuple[tuple[str, str], ...]] = {
    EventType.TEST_STARTING: (("sample_id", "sample"), ("grade", "grade"), ("t_set", "setpoint, N"),
                              ("t_end", "planned duration, s"), ("zero_check", "a zero check runs first"),
                              ("start_timeout", "the start fails after this long, s")),
    EventType.START_FAILED: (("reason", "why (`zero check failed: T1 0.061 N …`, `no tension after "
                                        "30 s: T̄ 0.02 N …`, `channels swapped? …`, cancelled)"),
                             ("sample_id", "sample"), ("t_set", "setpoint, N"),
                             ("spin_up_s", "spin-up time before the failure, s"),
                             ("zero_offsets_n", "the offsets found {T1, T2}, N (after a zero check)")),
    EventType.TEST_STARTED: (("sample_id", "sample"), ("grade", "grade"), ("t_set", "setpoint, N"),
                             ("t_end", "planned duration, s"), ("source", "who started it"),
                             ("settle_s", "spin-up time until slot 0, s"),
                             ("zero_offsets_n", "zero offsets {T1, T2}, N (information only)"),
                             ("prior_mean", "the life prior's mean, s (§7a; null: none)"),
                             ("prior_sd", "its SD, s"), ("prior_source", "method, config, history:N"),
                             ("prior_n", "the count of wear-out failures it came from (or null)"),
                             ("prior_n_censored", "… of right-censored lives"),
                             ("prior_n_early", "… of early failures (§7a v3)")),
    EventType.BASELINE: (("mu_ss", "baseline μ_ss"), ("mu_th", "threshold μ_th"),
                         ("k_b", "slot of the baseline"), ("stable_first", "first slot of the stable segment")),
    EventType.END_OF_LIFE: (("k_life", "slot of the end of life"), ("t_life", "wear life, s"),
                            ("mu_ss", "baseline μ_ss"), ("mu_th", "threshold μ_th"),
                            ("sample_id", "sample")),
    EventType.WEAR_WARNING: (("warn_slot", "last slot of the warning run's last window"),
                             ("t_warn", "its time, s from test start"), ("headroom", "headroom then"),
                             ("t_cross", "projected crossing of μ_th, s (or null)"),
                             ("h_warn", "the headroom bound"), ("n_warn", "windows needed"),
                             ("mu_ss", "baseline μ_ss"), ("mu_th", "threshold μ_th"),
                             ("sample_id", "sample"),
                             ("reasons", "why the window is due (§5b, sorted): headroom, prior, trend"),
                             ("end_p10", "end quantile 10 %, s from slot 0 (null without a prior)"),
                             ("end_p50", "end median, s from slot 0"), ("end_p90", "end quantile 90 %, s"),
                             ("p_end", "chance of the end within the lead"), ("lead_s", "the lead, s")),
    EventType.HOOK_REPLACED: (("station", "station"), ("old_sample_id", "the replaced hook's sample"),
                              ("new_sample_id", "the new hook's sample"), ("grade", "its grade"),
                              ("by", "who (mqtt, plc:ADDR, sparkplug, console:user, cli)"),
                              ("utc", "when, ISO 8601"),
                              ("test_id", "the old hook's last test (or null)"),
                              ("life_s", "its t_life if it failed, else how long that test ran, s"),
                              ("life_kind", "that life in the §7a history when it was replaced: "
                               "wear_out (a wear-out failure), early (an early failure, §7a v3), "
                               "censored (replaced before its end of life), or null (no life)"),
                              ("logged", "the line reached hooks.jsonl (false: the disk refused it)")),
    EventType.PROTECTION_STOP: (("stop_reasons", "unsafe reasons of the run that stopped the test"),),
    EventType.DRIVE_STOPPED: _DRIVE_STOP,
    EventType.TEST_ENDED: (("reason", "why it ended"), ("test_status", "completed or aborted"),
                           ("source", "who ended it"), ("result", "the method's result"),
                           ("why", "the cause in words when the drive stopped on its own during "
                                   "the test (`the drive stopped on its own (STM32 watchdog, 1.5 s "
                                   "without the gateway): the gateway stalled 2512 ms`); else null"),
                           ("drive_stop", "that stop as the `drive_stopped` event gives it "
                                          "(reason, flags, watchdog_s, silence_ms, "
                                          "gateway_stalled, why); else null")),
    EventType.PORT_LOST: (("port", "meter or stm32"),),
    EventType.DISK_FULL: (("store", "records (the test's folder) or outbox (MQTT)"),
                          ("reason", "the operating system's error")),
    EventType.DISK_OK: (("store", "records or outbox"), ("reason", "the error it recovered from")),
    EventType.RECORDS_PRUNED: (("tests", "the test ids removed (whole test folders, oldest first)"),
                               ("bytes", "the bytes freed"),
                               ("rules", "the rule that selected each test (max_age_days, "
                                         "max_total_mb, min_free_percent), in the order of `tests`")),
    EventType.PORT_BACK: (("port", "meter or stm32"),),
    EventType.ALARM_ACK: (("source", "who acknowledged (mqtt, plc:ADDR, cli)"),),
    EventType.ALARM_CLEARED: (("reason", "why (new test started, hook_replaced)"),
                              ("source", "who closed it (hook_replaced: mqtt, sparkplug, cli …)")),
    EventType.ALARM_SHELVED: (("alarm", "end_of_life or wear_warning"), ("until", "expiry, epoch s"),
                              ("source", "who shelved it")),
    EventType.ALARM_UNSHELVED: (("alarm", "end_of_life or wear_warning"), ("source", "who (by command)"),
                                ("expired", "true: the shelving ran out")),
    EventType.ALARM_OUT_OF_SERVICE: (("source", "who took the alarms out of service"),),
    EventType.ALARM_IN_SERVICE: (("source", "who returned them to service"),),
    EventType.COMMAND_REJECTED: (("command", "the command"), ("source", "where it came from (the last "
                                 "of the window)"), ("reason", "why it was refused (the last of the "
                                 "window)"), ("code", "the rejection code"),
                                 ("count", "refusals of this kind (door, command, code) it stands for: "
                                  "1 for the first of a window, then the others of the window in one "
                                  "event when it ends"), ("window_s", "the window, s (60)")),
    EventType.CONFIG_RELOADED: (),
}

#: the events that change alarms carry the ISA-18.2 transitions they caused (the alarm store
#: writes them into the event): one item per alarm that changed
_TRANSITIONS = ("transitions", "ISA-18.2 alarm transitions it caused: [{alarm, hook, from, to, action, "
                "time, by, priority}] (absent when no alarm changed)")
for _et in (EventType.END_OF_LIFE, EventType.WEAR_WARNING, EventType.ALARM_ACK, EventType.ALARM_CLEARED,
            EventType.ALARM_SHELVED, EventType.ALARM_UNSHELVED, EventType.ALARM_OUT_OF_SERVICE,
            EventType.ALARM_IN_SERVICE):
    EVENT_DATA[_et] = (*EVENT_DATA[_et], _TRANSITIONS)

_LEVEL_BAD = re.compile(r"[+#/\x00]")


def topic_level(s: Any) -> str:
    """A string made safe as one MQTT topic level (no /, +, #, NUL; never empty)."""
    s = "" if s is None else str(s).strip()
    return _LEVEL_BAD.sub("_", s) or "_"


def base_topic(prefix: str, site: Any, area: Any, line: Any, station: str) -> str:
    """<prefix>/<site>/<area>/<line>/<station> — a missing level is written as `_`."""
    pre = "/".join(topic_level(p) for p in str(prefix or "hookwatch").strip("/").split("/"))
    return "/".join([pre, topic_level(site), topic_level(area), topic_level(line), topic_level(station)])


def topic_for(base: str, key: str, **kw: Any) -> str:
    return f"{base}/{TOPIC[key].path.format(**kw)}"


#: the command doors: the default door is ``<base>/cmd/<command>`` (the MES; a command's source
#: ``mqtt``); a station may listen on named doors too (``mqtt.command_doors``, at most
#: ``commandtypes.COMMAND_DOORS_MAX``, named as ``commandtypes.door_problem`` allows), each
#: ``<base>/cmd/<door>/<command>`` with its own source ``mqtt:<door>`` — and so its own command
#: budget (docs/limits.md) — for another writer (an operator's panel, a second MES) whom the
#: broker's ACL confines to that door (``hookwatch config acl``, docs/deploy.md)
COMMAND_SOURCE = "mqtt"


def command_source(door: str | None) -> str:
    """The source of a command received on ``door`` (None: the default door)."""
    return COMMAND_SOURCE if door is None else f"{COMMAND_SOURCE}:{door}"


def command_door_filter(base: str, door: str | None = None) -> str:
    """The subscription that receives every command of ``door`` (None: the default door)."""
    cmd = TOPIC["cmd_start"].path.rsplit("/", 1)[0]
    return f"{base}/{cmd}/+" if door is None else f"{base}/{cmd}/{door}/+"


def command_topic(base: str, name: str, door: str | None = None) -> str:
    """The topic of command ``name`` on ``door`` (None: the default door)."""
    return command_door_filter(base, door)[:-1] + name


def parse_command_topic(base: str, topic: str, doors: tuple[str, ...]) -> tuple[str, str | None] | None:
    """``(command name, door)`` of a topic below ``base``'s command doors (the default door: None),
    None when it is on none of them (another level, an unknown door)."""
    prefix = command_door_filter(base)[:-1]
    if not topic.startswith(prefix):
        return None
    rest = topic[len(prefix):].split("/")
    if len(rest) == 1:
        return rest[0], None
    if len(rest) == 2 and rest[0] in doors:
        return rest[1], rest[0]
    return None


#: the one topic of the site level (``<prefix>/<site>/lives_request``, not below a station): a
#: gateway's station that (re)connects asks there, not retained, for the lives of every station
#: of its site (payload: the asking station's id as text); every station of the site that hears
#: it publishes its ``lives`` again, at most once per ``sitelives.ANSWER_INTERVAL_S``
LIVES_REQUEST = "lives_request"


def lives_request_topic(base: str) -> str:
    """``<prefix>/<site>/lives_request`` of a station's base topic."""
    return "/".join(base.split("/")[:-3] + [LIVES_REQUEST])


#: the box level (issue 37): every box of a site publishes its configuration report, retained,
#: with a Will, on ``<prefix>/<site>/box/<box>/config`` (gateway/config/site/boxreport.py). Five
#: levels: never one of a station's topics (six and more), nor ``+/+/+/lives``
BOX_LEVEL = "box"
BOX_CONFIG = "config"
BOX_CONFIG_FIELDS = (
    Field("schema", "int", "payload schema version of the report (1)"),
    Field("box", "str", "the box's name (`boxes/<box>/` in the site repository)"),
    Field("site", "str", "the site (`site.yaml`)"),
    Field("online", "bool", "false: the Will (the box's supervisor vanished) or a clean stop"),
    Field("time", "str", "UTC time of the report, ISO 8601 with milliseconds"),
    Field("version", "str", "the Git commit the box's `current` tree comes from (null: none)"),
    Field("sha256", "str", "sha256 of the effective tree as staged (its files' paths and sha256)"),
    Field("verified", "str", "the last version that passed its health gate"),
    Field("applied_at", "str", "when the current version passed its health gate (null: not yet)"),
    Field("applying", "str", "a version being applied (switched to, its health gate running), or null"),
    Field("unverified", "dict", "`{version, why}`: the current version was applied while no "
          "supervisor ran: not yet verified; the supervisor's first start runs its health gate "
          "(passed: `verified`; failed: back to the last verified version), or null"),
    Field("supervisor", "dict", "`{pid, software, started}`: the box's supervisor process, the "
          "hookwatch version it runs and when it started (null: none has run)"),
    Field("deferred", "list", "stations still on an older version because a test runs: each "
          "applies when its test ends"),
    Field("pending", "list", "stations not yet on `version` (deferred ones included)"),
    Field("stations", "dict", "per station: `version` it runs, `pending` version, `in_test`, "
          "`running`, `refused` (why, or null)"),
    Field("last_rollback", "dict", "`{from, to, why, time}` of the last rollback (null: none)"),
    Field("last_interrupt", "dict", "`{by, version, stations, time}`: the last apply that "
                                    "interrupted running tests (`--interrupt-tests --by NAME`)"),
    Field("drift", "bool", "a file of the effective tree differs from what was staged (a hand edit)"),
    Field("drift_files", "list", "those files (at most 50)"),
)


def box_config_topic(prefix: str, site: Any, box: Any) -> str:
    """``<prefix>/<site>/box/<box>/config``: a box's retained configuration report."""
    pre = "/".join(topic_level(p) for p in str(prefix or "hookwatch").strip("/").split("/"))
    return "/".join([pre, topic_level(site), BOX_LEVEL, topic_level(box), BOX_CONFIG])


# ----------------------------------------------------------------------------- payloads
def iso_ms(t: float) -> str:
    """UTC ISO 8601 with milliseconds and Z."""
    d = _dt.datetime.fromtimestamp(round(float(t), 3), tz=_dt.UTC)
    return d.strftime("%Y-%m-%dT%H:%M:%S.") + f"{d.microsecond // 1000:03d}Z"


#: plain JSON values (non-finite numbers → null): the one definition, gateway.plumbing.safeout
json_safe = safeout.plain


def encode(payload: dict[str, Any]) -> bytes:
    """A payload as strict JSON (UTF-8): never NaN/Infinity (gateway.plumbing.safeout)."""
    return safeout.dumps(payload, ensure_ascii=False).encode("utf-8")


def _env(seq: int, t: float, station: str) -> dict[str, Any]:
    return {"schema": SCHEMA_VERSION, "seq": int(seq), "time": iso_ms(t), "station": station}


def status_payload(session: int, t: float, station: str, status: str, software: str,
                   map_version: int) -> dict[str, Any]:
    return {"schema": SCHEMA_VERSION, "session": int(session), "time": iso_ms(t), "station": station,
            "status": status, "software": software, "map_version": map_version}


def state_payload(seq: int, t: float, st: StationState,
                  values: tuple[catalog.Value, ...] = catalog.CATALOG) -> dict[str, Any]:
    """The retained `state`: the envelope and every catalog row with an MQTT key, as its source
    reads ``st``."""
    return {**_env(seq, t, st.station), **{v.name: v.source(st) for v in values if v.mqtt}}


def telemetry_payload(seq: int, t: float, station: str, agg: dict[str, Any],
                      fields: tuple[Field, ...] = TELEMETRY_FIELDS) -> dict[str, Any]:
    return {**_env(seq, t, station), **{f.name: agg.get(f.name) for f in fields[len(ENVELOPE):]}}


def event_payload(seq: int, ev: Event) -> dict[str, Any]:
    return {**_env(seq, ev.wall_time, ev.station), "type": ev.type.value, "test_id": ev.test_id,
            "k": ev.k, "data": dict(ev.data)}


def alarm_payload(seq: int, t: float, station: str, alarm: dict[str, Any]) -> dict[str, Any]:
    return {**_env(seq, t, station), "alarm": "end_of_life", "priority": 1,
            **{f.name: alarm.get(f.name) for f in ALARM_FIELDS[len(ENVELOPE) + 2:]}}


def warning_payload(seq: int, t: float, station: str, alarm: dict[str, Any]) -> dict[str, Any]:
    return {**_env(seq, t, station), "alarm": "warning", "priority": 2,
            **{f.name: alarm.get(f.name) for f in WARNING_FIELDS[len(ENVELOPE) + 2:]}}


def result_payload(seq: int, ev: Event, st: StationState | None) -> dict[str, Any]:
    d = ev.data
    own = st if st is not None and ev.test_id is not None and st.test_id == ev.test_id else None
    # a cut-off test closed at start-up is not the state's: its event carries its sidecar's figures
    return {**_env(seq, ev.wall_time, ev.station), "test_id": ev.test_id or d.get("test_dir"),
            "sample_id": own.sample_id if own else d.get("sample_id"),
            "grade": own.grade if own else d.get("grade"),
            "t_set": own.t_set if own else d.get("t_set"), "test_status": d.get("test_status", "aborted"),
            "end_reason": d.get("reason", ""), "why": d.get("why"), "result": d.get("result")}


def reply_payload(seq: int, t: float, station: str, command: str, request_id: str | None, ok: bool,
                  code: int, reason: str, source: str = "mqtt") -> dict[str, Any]:
    return {**_env(seq, t, station), "command": command, "request_id": request_id, "source": source,
            "ok": bool(ok), "code": int(code), "reason": reason}


def field_names(key: str) -> list[str]:
    return [f.name for f in TOPIC[key].fields]


# ----------------------------------------------------------------------------- docs
def _examples() -> dict[str, dict[str, Any]]:
    t = 1772352000.02     # 2026-03-01T08:00:00.020Z
    st = StationState(station="st1", state=TestState.END_OF_LIFE, test_id="20260301T060000Z-S-0042",
                      sample_id="S-0042", grade="I", t_set=0.5, t_end=36000.0, mu_ss=0.2213,
                      mu_th=0.2545, k_b=1500, t_life=6930.5, elapsed_s=7200.0, alarm="unacknowledged",
                      meter_ok=True, stm32_ok=True, wear_warning=True, warn_reasons=["prior"],
                      prior_mean=7800.0, prior_sd=900.0, prior_source="config", lead_s=3600.0,
                      p_due=0.1, test_started_utc="2026-03-01T06:00:00.000Z")
    ev = Event(EventType.END_OF_LIFE, "st1", t, st.test_id, 346525,
               {"k_life": 346525, "t_life": 6930.5, "mu_ss": 0.2213, "mu_th": 0.2545, "sample_id": "S-0042"})
    return {
        "status": status_payload(12, t, "st1", "online", "hookwatch 0.1.0", 1),
        "state": state_payload(1042, t, st),
        "telemetry": telemetry_payload(1043, t, "st1", {
            "test_id": st.test_id, "interval_s": 1.0, "slots": 50, "t1": 0.4313, "t2": 0.5712,
            "tension": {"mean": 0.5012, "min": 0.4981, "max": 0.5047}, "mu": 0.2561,
            "valid_ratio": 0.98, "counts": {n: (1 if n == "JUMP" else 0) for n in REASON_NAMES},
            "speed_cmd": 120.4, "speed_act": 120.1, "saturated_slots": 0, "saturation": False,
            "headroom": -0.42, "t_cross": None, "end_p10": None, "end_p50": None, "end_p90": None,
            "p_end": None, "due": False}),
        "event": event_payload(1044, ev),
        "alarm": alarm_payload(1045, t, "st1", {
            "state": "unacknowledged", "active": True, "condition": True, "acknowledged": False,
            "shelved_until": None, "test_id": st.test_id,
            "sample_id": "S-0042", "t_life": 6930.5, "k_life": 346525, "mu_ss": 0.2213,
            "mu_th": 0.2545, "raised_at": iso_ms(t)}),
        "alarm_warning": warning_payload(1040, t - 1380.0, "st1", {
            "state": "unacknowledged", "active": True, "condition": True, "acknowledged": False,
            "shelved_until": None, "test_id": st.test_id,
            "sample_id": "S-0042", "warn_slot": 275999, "t_warn": 5520.0, "headroom": 0.41,
            "t_cross": 7040.5, "reasons": ["prior"], "end_p10": 6620.4, "end_p50": 7905.2,
            "end_p90": 9080.7, "p_end": 0.12, "lead_s": 3600.0, "mu_ss": 0.2213, "mu_th": 0.2545,
            "raised_at": iso_ms(t - 1380.0)}),
        "result": {**_env(1046, t, "st1"), "test_id": st.test_id, "sample_id": "S-0042", "grade": "I",
                   "t_set": 0.5, "test_status": "completed", "end_reason": "completed", "why": None,
                   "result": {"status": "failure", "t_life": 6930.5, "mu_ss": 0.2213, "mu_th": 0.2545}},
        "lives": {**_env(1041, t, "st1"), "lives": [
            {"test_id": "20260228T080000Z-S-0040", "grade": "I", "t_set": 0.5, "status": "failure",
             "t_life": 7012.4, "censored_s": None, "n_slots": 350621, "ts": 0.02, "k_b": 180000,
             "stop_reasons": None, "end_reason": "completed", "t_end": 36000.0},
            {"test_id": "20260301T000000Z-S-0041", "grade": "I", "t_set": 0.5, "status": "aborted",
             "t_life": None, "censored_s": 5400.0, "n_slots": 270000, "ts": 0.02, "k_b": 180000,
             "stop_reasons": ["STOPPED"], "end_reason": "hook_replaced", "t_end": 36000.0}]},
        "reply": reply_payload(1047, t, "st1", "start", "r-17", False, 1,
                               "a test is already running; stop it first"),
        "cmd_start": {"sample_id": "S-0043", "grade": "I", "t_set": 0.5, "request_id": "r-17"},
        "cmd_stop": {"test_id": "20260301T080000.000Z-S-0043", "request_id": "r-18"},
        "cmd_ack": {"request_id": "r-19"},
        "cmd_setpoint": {"t_set": 0.6},
        "cmd_hook_replaced": {"sample_id": "S-0043", "request_id": "r-20"},
        "cmd_shelve": {"alarm": "end_of_life", "duration_s": 1800, "request_id": "r-21"},
        "cmd_unshelve": {"alarm": "end_of_life"},
        "cmd_out_of_service": {"request_id": "r-22"},
        "cmd_in_service": {"request_id": "r-23"},
    }


def render() -> str:

    ex = _examples()
    out = [
        "# MQTT interface",
        "",
        "Generated from `gateway/outputs/mqtt/schema.py` (`python -m gateway.outputs.mqtt.schema > "
        "docs/mqtt.md`); do not edit by hand.",
        "",
        f"Schema version **{SCHEMA_VERSION}** (every payload carries it as `schema`). "
        f"Register map version {MAP_VERSION} (see registers.md).",
        "",
        "## Topic tree",
        "",
        "Each station publishes under its base topic "
        "`<prefix>/<site>/<area>/<line>/<station>` built from its YAML (`mqtt.prefix`, "
        "`station.site`, `station.area`, `station.line`, `station.id`); a missing level is written "
        "`_`, and `/ + #` inside a name become `_`. Example: `hookwatch/plant1/knitting/l3/st1`.",
        "",
        "| topic (below the base) | direction | QoS | retained | through the outbox | content |",
        "|---|---|---|---|---|---|",
    ]
    for t in TOPICS:
        out.append(f"| `{t.path}` | {t.direction} | {t.qos} | {'yes' if t.retain else 'no'} | "
                   f"{'yes' if t.durable else 'no'} | {t.doc} |")
    out += [
        "",
        "Commands come in by *doors*: the default door `cmd/<command>` (the MES's) and, for each "
        "name in the station's `mqtt.command_doors`, `cmd/<door>/<command>` (an operator's panel, a "
        "second MES: each writer its own door, its own command budget; Commands, below).",
        "",
        "All payloads are UTF-8 JSON objects. Numbers that are not finite (NaN) are sent as `null`. "
        "Times are UTC, ISO 8601 with milliseconds.",
        "",
        "## Delivery",
        "",
        "- Every message marked *through the outbox* is first written to an on-disk SQLite outbox "
        "(WAL) and deleted only when the broker confirms it (PUBACK, paho `on_publish`). After a "
        "broker or network outage, and after a gateway restart, the outbox is delivered **in seq "
        "order** before anything newer, with a bounded number of messages in flight.",
        "- `seq` is one per-station counter over all outbox messages, persisted in the outbox, so "
        "it keeps increasing across restarts. A message is durable about 20 ms after it was "
        "produced (the outbox writer commits in batches).",
        "- A message confirmed by the broker is never sent again. A message that was *in flight* "
        "(sent, not yet confirmed) when the connection broke is sent again, with the MQTT DUP flag "
        "inside one gateway run and as a plain resend after a gateway restart; the broker may then "
        "forward it twice. It carries the same `seq` both times: **consumers drop a message whose "
        "`seq` (per station) they have already processed**. The same holds for the few "
        "milliseconds between a broker confirmation and its deletion from the outbox if the "
        "gateway is killed exactly then. The broker's own leg to the MES is at-least-once too: a "
        "message it had forwarded but whose PUBACK it had not read when it stopped is redelivered "
        "when the MES's persistent session resumes, and every (re)subscription replays the "
        "retained topics (retain flag set) — always with the original `seq`.",
        "- Telemetry is buffered too, within `mqtt.outbox.telemetry_budget_mb` on disk; when the "
        "budget is exceeded the oldest buffered telemetry is dropped first (visible as a gap in "
        "`seq`). Events, alarms, results and replies are never dropped.",
        "- `state` is retained and only its latest value matters: a buffered `state` that was "
        "superseded before it could be sent is dropped (a gap in `seq`).",
        "- `status` is not in the outbox and has no `seq`: `online` is published (retained) on "
        "every connect, `offline` is the retained Last Will, also published on a clean stop. It "
        "carries its own counter, `session` (+1 on every connect, across restarts too).",
        "",
        "### De-duplication",
        "",
        "The exact rule, per station: keep `H`, the highest `seq` you have processed (every "
        "message but `status` has one: `state`, `telemetry`, `event/…`, `alarm/…`, `result`, "
        "`reply`), stored with what you processed. A message with `seq ≤ H` is a duplicate: drop "
        "it. Otherwise process it and set `H = seq`. `status` has no `seq` and never takes part; "
        "for `status`, keep the highest `session` instead (a lower one is an old, replayed "
        "value). Gaps in `seq` are normal (dropped telemetry, "
        "superseded `state`): never wait for a missing number. Within one station outbox messages "
        "arrive in `seq` order, so `seq ≤ H` can only be a resend or a retained replay.",
        "",
        "Example of an outage: the MES has processed up to `seq` 1040 (`H = 1040`). The broker "
        "link drops; the station produces `event` 1041, `telemetry` 1042–1045 and `alarm` 1046, "
        "kept in the outbox. On reconnect the gateway publishes `status` `online` (`session` 8, no "
        "`seq`) **first**, then delivers 1041 … 1046 in order: 1041 … 1046 are processed and "
        "`H = 1046`. (Schema version 1 gave `status` a `seq`, the stream position — 1046 here — "
        "and a consumer moving `H` with it lost the whole backlog; version 2 has none.) If the "
        "gateway is then killed after sending 1046 but before the broker's PUBACK reached it, it "
        "sends 1046 again after its restart: `1046 ≤ H`, dropped. A resubscription replays the "
        "retained `state`/`alarm`/`result` with their original `seq` ≤ `H`: dropped too (the "
        "retained value is the one you already hold).",
        "",
        "Order a consumer can rely on (per station, on one subscription): messages with a `seq` "
        "arrive in `seq` order; `status` `online` of a session arrives **before** every message "
        "of that session, the backlog of an outage included (the gateway publishes it in the "
        "connect handler, before it sends anything from the outbox); `status` `offline` (the Will) "
        "arrives after everything the broker received from that session. So a consumer may treat "
        "`online` as \"a backlog may follow\", never as \"everything before it was delivered\".",
        "",
        "- Alarms follow ISA-18.2, the same states in MQTT (`alarm/…` `state`, `state` "
        "`alarm`/`warning_alarm`), Sparkplug and the PLC (enum registers `alarm`, `warning_alarm`: "
        + ", ".join(f"{i} `{a.value}`" for i, a in enumerate(AlarmState)) + "). The end of life: "
        "`normal` → `unacknowledged` (raised) → `acknowledged` (cmd/ack, a PLC write or the CLI) → "
        "`normal` (closed: cmd/hook_replaced, or a new test started; `closed_by` in the event's "
        "transition). An alarm whose condition went before an ack is `rtn_unacknowledged` (an ack "
        "makes it `normal`). cmd/shelve silences one annunciated alarm until `duration_s` from now "
        "(`shelved`, `shelved_until`; back at the expiry or by cmd/unshelve); cmd/out_of_service "
        "takes both alarms out of service while a needle is being changed (cmd/in_service or "
        "cmd/hook_replaced end it). Every one of these commands can come from the PLC as well "
        "(command codes 3, 5–9; shelve / unshelve with `alarm_select` and `shelve_duration`, "
        "docs/registers.md) and from a Sparkplug host (DCMD `Device Control/…`, docs/sparkplug.md), "
        "through the same validation. Every transition is in one event (`data.transitions`: `alarm`, "
        "`hook`, `from`, `to`, `action`, `time`, `by`, `priority`) and one retained message on "
        "`alarm/end_of_life` or `alarm/warning`, so a MES "
        "that connects late sees the current state. The wear warning (METHOD.md §5b: the first "
        "due window — the chance that the end comes within the lead reached `p_due` (`prior`), "
        "the headroom stayed under `h_warn` for `n_warn` windows (`headroom`) or the recent trend "
        "reaches μ_th within the lead (`trend`)) is a second alarm of lower "
        "priority (2; end of life is 1) with the same lifecycle on `alarm/warning`, raised at "
        "most once per test with the event `wear_warning` (its `reasons` and the forecast), never "
        "once the end of life was detected; one ack acknowledges both. It is informative: "
        "it never changes a test's status or t_life, and its projection `t_cross` assumes the "
        "recent trend goes on (the accelerated stage usually comes sooner). The forecast itself "
        "(`end_p10/50/90` in s from slot 0 — `test_started_utc` makes them wall times —, `p_end`, "
        "`due`) is in `state` and `telemetry` as found at the last forecast time, not an event "
        "stream of its own. Both alarms are kept "
        "in the station's alarm "
        "store (`alarm.json` in its records folder), which the PLC registers read as well: after a "
        "gateway restart the alarms stand until the next test start clears them.",
        "",
        "## The site's life history",
        "",
        "The life prior of a new test (METHOD.md §7a) comes from the lives of earlier hooks of "
        "its grade and T_set — on every box of the site, not only this one. Every gateway "
        "publishes, per station, the retained `<base>/lives`: the station's completed tests that "
        "give the history a life (failures, and tests that found their baseline and ended on "
        "purpose or at t_end: right-censored lives), its newest 500, at the start, after every "
        "test and after every (re)connect; and it subscribes to "
        "`<prefix>/<site>/+/+/+/lives` and pools what the other stations of its `station.site` "
        "share into the history, each test once (by test id). `mqtt.share_lives: false` turns "
        "both off. Why this design: *retained*, so a gateway that joins late (or restarts) on a "
        "single broker gets the whole site history from the broker at once; "
        "*one snapshot per station*, so the broker holds a bounded amount per station (one message "
        "of at most 256 KiB) and never a growing number of retained topics, and a new snapshot "
        "replaces the last whole; *published again on every connect*, so a broker that lost its "
        "retained store gets it back; *asked for on every (re)connect*, because a retained message "
        "is never relied on: a clustered broker keeps it on the node that received it (RabbitMQ "
        "3.10) and loses it with that node, so a gateway joining through another node would get "
        "nothing — each station of a gateway that (re)connects publishes one small non-retained "
        "request on the site's `<prefix>/<site>/lives_request` (QoS 1; payload: its station id "
        "as text, so that it ignores its own; gateway traffic, not for the MES: an MES "
        "subscribes to the station topics `<prefix>/<site>/+/+/+/#`, or skips this topic), "
        "and every station of the site that hears it "
        "publishes its `lives` snapshot again, retained as always: it reaches the asking gateway "
        "on any node through the cluster's routing, and gives the answering station's node its "
        "retained copy back. A station answers at most once per 10 s however many requests "
        "arrive (the requests within those 10 s share one answer at their end, or the next "
        "publication of its lives); a flood of requests is counted (`lives_requests`, "
        "`lives_requests_deferred`, `lives_answers` in the MQTT counters) and logged in one "
        "rate-limited line, and costs nothing else. A receiver keeps each station's newest "
        "snapshot, each test once by test id: a duplicate changes nothing; a test id that two "
        "stations claim with *different* lives is refused from both (it reaches no prior while "
        "they disagree; logged once per id in a rate-limited line, counted as `contested_ids`). "
        "The lives go on the wire as they are (a failure's t_life, a censored life's n_slots · ts, "
        "never a class): each gateway classes the early failures of its pooled history itself "
        "(METHOD.md §7a v3), so the same lives give every box the same prior. "
        "*Lives cost what they are worth*: a snapshot costs the station's MQTT thread one append "
        "to a bounded hand-over (the newest snapshot of a station replaces the one still waiting, "
        "which is dropped and counted: `lives_dropped`); one worker thread per station checks "
        "them one at a time — a station's newest once it has been quiet for 1 s (or 5 s after "
        "the first of a flood came), at most once per 5 s, and paced to at most a "
        "tenth of a core (`lives_checked`) —, gives the "
        "station's priors the site's lives at most once per 2 s and logs what changed in one "
        "rate-limited line, never a line per snapshot; commands, slots and state never wait "
        "behind lives (a flood of 400 changing snapshots: bench/README.md, issue 34). "
        "*Kept locally* (`site_lives.json` in the station's records "
        "folder, made when missing: a station that never ran a test keeps them too), so a "
        "gateway that restarts while the broker is down still has the site's lives; written by "
        "that worker at most once per 5 s (`lives_saves`, `lives_save_errors`), atomically: an "
        "exclusive temporary file beside it that is never a link followed (a link planted there "
        "is removed, its target never written), synced, renamed over the file. "
        "A retired station's lives are removed by clearing its retained topic (an empty retained "
        "message). What a gateway receives goes through the one bounded JSON reader (bytes, depth, "
        "numbers, keys, strings), then every record is checked (a test id, a grade, a plausible "
        "T_set and planned duration, a life > 0 and within the planned duration, a censored life "
        "that is `n_slots` · `ts` of a test with a baseline ended on purpose or at t_end, no NaN); "
        "a malformed message or an implausible record is refused with one counted, rate-limited "
        "log line and never reaches a prior. At most 500 lives per station, 256 stations and "
        "20,000 lives in all are kept. The sidecar of a test says where its prior came from "
        "(`prior_source: history`, `prior_n`, `prior_n_censored`, `prior_n_early`, `prior_stations` (how many), "
        "`prior_station_ids` (which: this station first, then by tests, at most 16), "
        "`prior_from`: `this station: N tests` or `the site: N tests from K stations (M of this "
        "station; a 30, b 12)`, the other stations named with their tests, at most 3 and "
        "`and J more`); the state's `prior_source` adds the same words to `history:N`, and the "
        "console's station page shows them.",
        "",
        "Only the box that runs a station may publish its lives; every box of the site reads them. "
        "The broker says so in its permissions, which `hookwatch config acl` writes from the "
        "station files (a Mosquitto `acl_file` or RabbitMQ topic permissions; docs/deploy.md, "
        "\"Broker permissions\"; the shipped deploy/mosquitto/ ACLs are made by it): one identity "
        "per box, which may write only its own stations' topics (`lives` among them) and the "
        "site's `lives_request`, and read the site's lives, state and status and its own "
        "stations' commands.",
        "",
        "What a box can and cannot forge under those permissions. It **cannot** publish lives, "
        "state, status, events, alarms or results for a station of another box, nor pose as a "
        "station that is not in its own station files, nor send a command to any station (only "
        "the commanders may, each on its own door): the broker refuses it (Mosquitto: PUBACK "
        "reason code 0x87 over MQTT 5, the message silently dropped over 3.1.1; RabbitMQ 3.10 "
        "closes the connection), and the message never reaches a subscriber. It **can** still lie "
        "about its *own* stations: a record that passes the checks is taken as true, so a "
        "compromised box can skew a prior within the plausible range with the lives of the "
        "stations it runs — and only those: `prior_from` counts the stations the lives came from, "
        "and each is one station of one box. A broker without these permissions (one shared user "
        "that may write `hookwatch/#`) lets one account pose as every station of the site (up to "
        "the 256 kept): then `prior_from`'s count of stations says nothing.",
        "",
        "## The console's site view",
        "",
        "The operator console of a box can show every station of its `station.site` in its due "
        "list and fleet cards (`console.site_view`, on by default; docs/console.md). It learns the "
        "other boxes' stations from the broker: the session of the first MQTT-enabled station of "
        "the console's process also subscribes to `<prefix>/<site>/+/+/+/state` and "
        "`<prefix>/<site>/+/+/+/status` (both retained: a console that starts late sees every "
        "station at once) — no second MQTT session. Those stations are read-only there: the "
        "console sends commands only to its own stations. A station is *silent* when its `status` "
        "is `offline` (its gateway's Last Will, or a clean stop) or its last `state` arrived more "
        "than 35 s ago (a state comes at least every 10 s: a box cut off with its edge broker "
        "leaves an `online` status behind); the console then shows it *silent since* the `time` of "
        "its last state. What arrives goes through the one bounded JSON reader (at most 8 KiB, "
        "depth 3), then every field the console keeps is type-checked and every string clipped "
        "to 64 printable ASCII characters; a malformed message is refused with one counted, "
        "rate-limited log line; at most 256 stations of other boxes are kept. The box's MQTT user "
        "needs read permission on `<prefix>/<site>/+/+/+/state` and `…/status` (the permissions "
        "`hookwatch config acl` writes give it to every box; above).",
        "",
        "## Payloads",
        "",
    ]
    for t in TOPICS:
        out += [f"### `{t.path}`", "", t.doc + ".", "", "| field | type | meaning |", "|---|---|---|"]
        for f in t.fields:
            out.append(f"| `{f.name}` | {f.type} | {f.doc} |")
        out += ["", "Example:", "", "```json", safeout.dumps(ex[t.key], compact=False, ensure_ascii=False),
                "```", ""]
    out += ["## Results", "", "`result.result.status`, the method's verdict on the test, and what "
            "it means for the MES:", "", "| status | meaning |", "|---|---|"]
    for k, d in RESULT_STATUS:
        out.append(f"| `{k}` | {d} |")
    out += ["", "`test_status` says how the test ended (`completed` at its planned end or at the "
            "end of life, `aborted` when stopped early); `end_reason` says why.", ""]
    out += ["## Events", "", "`event/<type>`; the `data` object holds:", "",
            "| type | data keys |", "|---|---|"]
    for et, keys in EVENT_DATA.items():
        ks = "; ".join(f"`{k}` ({d})" for k, d in keys) or "—"
        out.append(f"| `{et.value}` | {ks} |")
    out += [
        "",
        "## Commands",
        "",
        "A command is a JSON object published to `cmd/<name>` (an empty payload counts as `{}`). "
        "MQTT and PLC commands go through the same validation (`gateway/core/command_rules.py`) and "
        "the same station command path; every command is answered on `reply` — or, over MQTT 5, on "
        "the Response Topic the request names, with the request's Correlation Data (same payload, "
        "QoS 1, not retained, through the outbox). A Response Topic is obeyed only below "
        "`mqtt.reply_prefix` (default `<base>/reply`, i.e. `<base>/reply/<anything>`): a client "
        "allowed to publish on `cmd/…` cannot make the gateway publish on result, state, other "
        "stations' command or Sparkplug topics. One elsewhere, with a wildcard, starting with `$` "
        "or longer than 256 characters, or Correlation Data over 256 bytes, is not used: the answer "
        "goes to `reply` and the refusal is counted (`response_topic_refused`, logged once a "
        "minute with the count). A refused command is never acted on; refusals become "
        "`command_rejected` events once per kind (door, command, code) per minute with their "
        "`count`, so a flood of refusals is a few events, not one each. Every door (MQTT, PLC, "
        "console, Sparkplug, CLI) goes through one bounded intake (`gateway/core/command_intake.py`, "
        "docs/limits.md): payload ≤ 4096 bytes, nesting ≤ 4, strict types (`\"0.6\"` is not a "
        "number, `true` is not a number, only finite numbers), strings of printable ASCII ≤ 64 "
        "characters (`sample_id` ≤ 32, `request_id` ≤ 64); unknown keys, unknown commands and "
        "payloads that are not JSON objects are refused (code 9). Client text is never echoed "
        "longer than 40 characters, and always escaped.",
        "",
        "Every command acts once. A station carries out one command at a time, each checked "
        "against the state the one before left (two stops at once: one ends the test, the other "
        "is answered 2 NOT_RUNNING). A command sent again with the same `request_id` from the same "
        "source within 600 s is answered with the first answer (its `ok` and `code`; the reason "
        "says `duplicate of request_id …`) and not carried out again, whatever came in between: "
        "no id is forgotten before its 600 s. The same `request_id` naming another command or "
        "other arguments is refused (code 9). Give every command its own `request_id` and resend "
        "it unchanged when no reply came. Every command a station takes costs its source "
        "(`mqtt` and each `mqtt:<door>`, `sparkplug`, `console:<user>`, `plc:<address>`) one of "
        "its budget, carried out or refused alike: bursts of 20, 60 a minute; beyond it commands "
        "are refused with code 14 (not remembered: resend later) and counted. A repeat answered "
        "from memory costs nothing, and the memory per source holds what the budget lets through "
        "in 600 s (620 ids), so a flood of refused commands runs into its budget instead of "
        "pushing an id out. A `stop` may name the test it means (`test_id`, from `test_started` "
        "or `state`): it then ends that test only — a stop naming a test that already ended is "
        "refused (15 WRONG_TEST, or 2 NOT_RUNNING when no test runs) and never ends a newer test.",
        "",
        "MQTT does not tell a subscriber who published a message, so the MQTT budget is per "
        "*door*: the default door `cmd/<command>` (source `mqtt`, the MES's) and each named door "
        "`cmd/<door>/<command>` a station listens on (`mqtt.command_doors`, source `mqtt:<door>`: "
        "an operator's panel, a second MES) has its own, and the broker's permissions keep each "
        "writer to its own door (`hookwatch config acl`: commanders by door; docs/deploy.md). A "
        "writer flooding its door spends that door's budget only; the MES's commands on the "
        "default door are all carried out (tests/gateway/outputs/test_command_doors.py). The "
        "answer names the door in `source`. Without such permissions every client that may write "
        "a command topic shares its door's budget with the MES.",
        "",
        "| code | name | meaning |",
        "|---|---|---|",
    ]
    for code, name, doc in REJECT_CODES:
        out.append(f"| {code} | {name} | {doc} |")
    out += [
        "",
        "## Connection",
        "",
        "From the station YAML `mqtt:` section: `host`, `port`, `client_id` (default "
        "`hookwatch-<station>`), `keepalive_s`, `username`, the password from the environment "
        "variable named by `password_env` or the file named by `password_file` (never inline), "
        "`tls: {enabled, ca_file, cert_file, key_file}`, `telemetry_interval_s`, `outbox: {path, "
        "telemetry_budget_mb}`, `protocol` (`auto`: MQTT 5, falling back to 3.1.1 when the broker "
        "refuses it; `5`; `3.1.1`), `reply_prefix` (MQTT 5 Response Topics obeyed only below it; "
        "default `<base>/reply`), `servers` (a server list, below). One MQTT connection per "
        "station (its own Last Will). The client reconnects by itself (after 1 s, doubling up to "
        "10 s).",
        "",
        "### Clustered brokers",
        "",
        "`mqtt.servers: [\"mq1:1883\", \"mq2:1883\", \"mq3:1883\"]` lists the nodes of a clustered "
        "broker (EMQX, HiveMQ, RabbitMQ …; `host` alone uses `mqtt.port`; the single `host`/`port` "
        "form stays valid and is the list's default). The output connects to the first; a node that "
        "cannot be reached moves it to the next one at once, and only when every node failed in a "
        "row does it wait (the back-off above); a lost connection is tried again after 1 s, and if "
        "its node is gone the next one takes over: a node's loss costs a station about a second of "
        "link (measured: bench/README.md, site bench). Nothing is lost on the way: the outbox "
        "sends again, in `seq` order, whatever the broker had not confirmed (duplicates carry "
        "their `seq`: see De-duplication). With more than one server the client ID on server *i* "
        "is `<client_id>-<i>` (1-based): RabbitMQ keeps a session's queue on the node it was made "
        "on and refuses the same ID on another node while that one is down; one ID per server "
        "keeps each node's state its own (the `status` `session` counter says which session is "
        "current). The Sparkplug node's `sparkplug.servers` is the same session engine "
        "(`gateway/outputs/broker/paho_session.py`).",
        "",
        "A retained message is never left to one node: clustered brokers keep it on the node that "
        "received it (RabbitMQ 3.10) or lose it with a node's store. After every (re)connect the "
        "output publishes `status` `online` and then the latest confirmed message of every "
        "retained topic again (`state`, `alarm/end_of_life`, `alarm/warning`, the last `result`), "
        "with its original `seq` and the retain flag, before anything newer — a live subscriber "
        "receives it as a duplicate (`seq ≤ H`, drop it), a new one finds it retained on the node "
        "it subscribes on once its own gateway published there. Counted as "
        "`retained_republished`.",
        "",
        "### MQTT 3.1.1 brokers",
        "",
        "With `protocol: auto` the output asks for MQTT 5; a broker that refuses it (CONNACK "
        "*unacceptable protocol version*, or the connection closed before CONNACK twice in a row: "
        "RabbitMQ 3.10 drops an MQTT 5 CONNECT) is spoken to in MQTT 3.1.1 for the rest of the run, "
        "with one warning line: `refused MQTT 5 (…); using MQTT 3.1.1 from now on, which costs: …`. "
        "What 3.1.1 costs:",
        "",
        "- **no Response Topic / Correlation Data**: a command is answered on `<base>/reply` (QoS 1, "
        "through the outbox), matched to its request by the `request_id` the request carries — "
        "send one with every command you need to match;",
        "- **no user properties** (hookwatch sends none today: the payload carries everything);",
        "- **no message expiry** (hookwatch sets none: a late message is still a valid one, its "
        "`time` says when);",
        "- no reason codes on PUBACK: a broker that denies a publish (an ACL) either acknowledges "
        "and drops it or closes the connection (RabbitMQ), instead of saying why; set the ACL "
        "before the gateways connect (docs/deploy.md).",
        "",
        "## The box's configuration report",
        "",
        "A box run from a site repository (docs/deploy.md, \"A site of many boxes\") publishes, "
        "retained, QoS 1, `<prefix>/<site>/box/<box>/config`: which version of the site's "
        "configuration it runs, what is deferred, its last rollback and whether its tree was edited "
        "by hand (drift, seen within 10 s). Its Last Will is the same topic with `online: false`. "
        "It is published by the box's supervisor (`hookwatch run STATE/config/current`) on every "
        "change and every (re)connect; `hookwatch config status` prints the same report. The "
        "broker and prefix come from the site repository's `site.yaml` (`broker:`).",
        "",
        "| field | type | meaning |",
        "|---|---|---|",
        *[f"| `{f.name}` | {f.type} | {f.doc} |" for f in BOX_CONFIG_FIELDS],
        "",
    ]
    return "\n".join(out)


if __name__ == "__main__":
    print(render(), end="")
