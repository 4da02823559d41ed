"""docs/sparkplug.md, generated from the metric definition (metrics.py) and the conformance table
below: ``python -m gateway.outputs.sparkplug.docs > docs/sparkplug.md`` (a test checks it is
current)."""
from __future__ import annotations

import dataclasses

from ...config.sections import SparkplugConfig
from . import metrics as M

#: (statement ID of the Sparkplug 3.0 specification, what it asks, status, how / where / proof)
#: status: "yes" implemented and tested; "yes*" implemented, not covered by a test; "partial";
#: "no"; "n/a" (does not apply to this edge node)
CONFORMANCE: tuple[tuple[str, str, str, str], ...] = (
    ("tck-id-topic-structure, -namespace-a", "topic `spBv1.0/group/VERB/node[/device]`", "yes",
     "namespace.py `NodeTopics.topic`; e2e checks every topic"),
    ("tck-id-topic-structure-namespace-valid-group-id / -edge-node-id / -device-id",
     "IDs are UTF-8 without `+ / #`", "yes",
     "`namespace.valid_id` refuses them; the config's `ident` kind is stricter still"),
    ("tck-id-topic-structure-namespace-unique-device-id", "device IDs unique in the node", "yes",
     "device ID = station ID, unique in a fleet (loader)"),
    ("tck-id-topic-structure-namespace-unique-edge-node-descriptor",
     "group/edge node unique in the infrastructure", "partial",
     "derived from site/area/line; two gateway processes configured with the same hierarchy would "
     "clash — set `sparkplug.edge_node_id` per process"),
    ("tck-id-principles-persistence-clean-session-311", "Clean Session true (MQTT 3.1.1)", "yes",
     "node_session.py"),
    ("tck-id-message-flow-edge-node-birth-publish-will-message (-topic, -payload, -qos, -will-retained)",
     "NDEATH as the Will: its topic, Sparkplug payload, QoS 1, not retained", "yes",
     "node_session.py sets the Will before CONNECT; e2e: the broker's Will after kill -9 is QoS 1, "
     "not retained"),
    ("tck-id-message-flow-edge-node-birth-publish-will-message-payload-bdSeq, "
     "tck-id-topics-nbirth-bdseq-increment", "bdSeq Int64, +1 per CONNECT, from 0, wraps at 256",
     "yes", "persisted in the node's SQLite store before each CONNECT (WAL commit): e2e kill -9 → "
     "restart gives bdSeq + 1; unit test of the wrap"),
    ("tck-id-topics-nbirth-bdseq-matching, tck-id-payloads-ndeath-bdseq",
     "NBIRTH's bdSeq = the Will's", "yes", "e2e: NBIRTH, the Will after kill -9, the NDEATH of a "
     "clean stop and of STATE offline all carry the session's bdSeq"),
    ("tck-id-topics-ndeath-payload, tck-id-topics-ndeath-seq", "NDEATH: bdSeq only, no seq", "yes",
     "`payloads.Outgoing.ndeath`"),
    ("tck-id-operational-behavior-edge-node-intentional-disconnect-ndeath, "
     "tck-id-payloads-ndeath-will-message-publisher-disconnect-mqtt311",
     "NDEATH published before a deliberate DISCONNECT", "yes",
     "node_session.py waits for its PUBACK before DISCONNECT; e2e: clean stop gives DDEATH then NDEATH"),
    ("tck-id-message-flow-edge-node-ncmd-subscribe, tck-id-message-flow-device-dcmd-subscribe",
     "subscribe to NCMD and DCMD (QoS 1)", "yes", "`NodeTopics.subscriptions`"),
    ("tck-id-message-flow-edge-node-birth-publish-phid-wait (-id, -online, -timestamp), "
     "tck-id-operational-behavior-edge-node-birth-sequence-wait",
     "with a primary host: births only after its STATE online, newer-or-equal timestamp", "yes",
     "compared within one MQTT session (see STATE timestamps); unit tests (an older STATE is "
     "ignored, one from the future cannot lock the host out); e2e"),
    ("tck-id-operational-behavior-edge-node-termination-host-offline (-timestamp), "
     "tck-id-message-flow-edge-node-birth-publish-phid-offline",
     "STATE offline (not older): NDEATH, disconnect", "yes", "e2e: NDEATH, then nothing until online; "
     "an offline STATE older than the session's last STATE is ignored (unit test)"),
    ("tck-id-operational-behavior-edge-node-termination-host-offline-reconnect, "
     "tck-id-operational-behavior-primary-application-state-with-multiple-servers-walk",
     "then connect to the next MQTT server", "yes",
     "`sparkplug.servers` (the server set, §8.2; default `[host:port]`): STATE offline, "
     "`Node Control/Next Server` and a server that cannot be reached move the node to the next one; "
     "e2e over two Mosquittos (test_sparkplug_doors_e2e.py)"),
    ("tck-id-topics-nbirth-mqtt, -dbirth-mqtt, -ddata-mqtt, -ddeath-mqtt",
     "NBIRTH, DBIRTH, DDATA, DDEATH at QoS 0, not retained", "yes", "e2e checks qos/retain"),
    ("tck-id-topics-nbirth-seq-num, tck-id-payloads-sequence-num-incrementing, "
     "tck-id-payloads-dbirth-seq-inc / ddata-seq-inc / ddeath-seq-inc",
     "NBIRTH seq 0, then +1 per message, 255 → 0", "yes",
     "e2e checks every message of each session, a session with ≥ 1 wrap; unit test"),
    ("tck-id-topics-nbirth-timestamp, tck-id-payloads-*-timestamp, -timestamp-in-UTC",
     "payload timestamp (UTC ms) on every message", "yes", "ms since the epoch"),
    ("tck-id-payloads-name-birth-data-requirement", "a timestamp on every metric of births and data",
     "yes", "unit test"),
    ("tck-id-topics-nbirth-metric-reqs, tck-id-topics-dbirth-metric-reqs, "
     "tck-id-operational-behavior-data-publish-dbirth(-values)",
     "births carry every metric with name, datatype and current value (is_null when none or not finite)", "yes",
     "the tables below; e2e checks names, aliases, datatypes; unit test: DBIRTH = DEVICE_METRICS"),
    ("tck-id-topics-nbirth-rebirth-metric, tck-id-operational-behavior-data-commands-rebirth-*",
     "`Node Control/Rebirth` Boolean false, without alias", "yes", "unit test"),
    ("tck-id-payloads-alias-uniqueness, -alias-birth-requirement",
     "aliases unique in the node, births carry name and alias", "yes",
     "device aliases = CRC-32 of the device ID · 4096 + index, clashes moved (unit test); "
     "bdSeq and Rebirth carry no alias (the spec requires that for Rebirth)"),
    ("tck-id-payloads-alias-data-cmd-requirement, tck-id-payloads-metric-datatype-not-req",
     "DDATA by alias only, without name and datatype", "yes", "e2e and unit test"),
    ("tck-id-operational-behavior-data-commands-ncmd-rebirth-*, -rebirth-action-1/2/3",
     "on an NCMD Rebirth: NBIRTH (same bdSeq) and every DBIRTH, nothing in between", "yes",
     "e2e: NCMD → NBIRTH seq 0, same bdSeq, DBIRTH; at most one birth per "
     "`sparkplug.rebirth_min_interval_s`, later requests coalesced into one (e2e: 3,000 Rebirth "
     "NCMDs → a bounded number of births)"),
    ("tck-id-operational-behavior-data-commands-dcmd-*", "DCMD writes metrics of the DBIRTH", "yes",
     "by name or alias; start/stop/ack/hook replaced go through the station's one command path; "
     "e2e: a DCMD start starts a test, `Device Control/Last Result Code` 0"),
    ("tck-id-payloads-dbirth-order, tck-id-message-flow-device-birth-publish-nbirth-wait",
     "DBIRTHs right after the NBIRTH, before any data", "partial",
     "so at every (re)birth (the first CONNECT waits 0.5 s for the stations of a fleet starting "
     "together); a station that starts later in a running node gets its DBIRTH then "
     "(after data of others), as do stations whose stored history is replayed after a restart "
     "before they run again"),
    ("tck-id-operational-behavior-device-ddeath", "DDEATH when a device is lost", "yes",
     "when its station stops (e2e: clean stop); in a fleet when its worker process is down, "
     "DBIRTH when it is back (e2e: kill -9 of a worker)"),
    ("tck-id-operational-behavior-data-publish-dbirth-change, tck-id-principles-rbe-recommended",
     "DDATA only on change (report by exception)", "partial",
     "state, alarm and test metrics by exception; the measured values (tension, μ, speed) are "
     "interval aggregates sent every `data_interval_s`"),
    ("tck-id-operational-behavior-data-publish-dbirth-order",
     "chronological order of values in a payload", "yes", "one value per metric per payload"),
    ("store and forward (spec §5: `is_historical`)",
     "data held while no primary host is online, replayed flagged historical", "yes",
     "e2e: ≥ 270 held, replayed in order with is_historical, then live data"),
    ("tck-id-payloads-propertyset-*", "PropertySet keys/values of equal length", "yes",
     "`engUnit`, `description`, `writable`"),
    ("tck-id-principles-persistence-clean-session-50, -ndeath-will-message-publisher-disconnect-mqtt50",
     "MQTT 5 rules", "n/a", "the node speaks MQTT 3.1.1"),
    ("tck-id-payloads-template-*, tck-id-topics-nbirth-templates", "templates", "n/a",
     "no templates are used"),
    ("tck-id-topics-ndata-*", "NDATA", "n/a", "node metrics do not change during a session"),
    ("tck-id-case-sensitivity-metric-names", "no metric names equal in lower case", "yes",
     "unit-checked over the tables"),
)

HEAD = ("""# Sparkplug B 3.0

*Generated from `gateway/outputs/sparkplug/metrics.py` and `docs.py`:
`python -m gateway.outputs.sparkplug.docs > docs/sparkplug.md`.*

With a `sparkplug:` section (docs/configuration.md) a station is published as a **Sparkplug B
3.0 device** of an **edge node**, alongside or instead of the JSON tree of `mqtt:`
(docs/mqtt.md). The payloads follow the specification's protobuf definition
(`gateway/outputs/sparkplug/sparkplug_b.proto`; the generated `sparkplug_b_pb2.py` is committed
and needs only the `protobuf` runtime).

## Identity

| Sparkplug | from | default |
|---|---|---|
| group ID | `sparkplug.group_id` | `station.site` |
| edge node ID | `sparkplug.edge_node_id` | `<station.area>-<station.line>` |
| device ID | `sparkplug.device_id` | `station.id` (one device per station) |

Stations of one gateway with the same broker, group and edge node share **one** edge
node (one MQTT session, one bdSeq, one seq counter); each is a device of it. In a fleet
(`hookwatch run FLEET_DIR`) the nodes live in the supervisor, each station's device fed by its
worker process (docs/runtime.md "Sparkplug in a fleet").

## Session

1. Before each MQTT CONNECT the node takes the next **bdSeq** (0 … 255, +1 per CONNECT packet
   sent; a refused TCP connection sends none and uses none) and stores it (`sparkplug.store_path`,
   SQLite WAL: a `kill -9` does not lose it), then connects with the **NDEATH as the MQTT Will**
   (QoS 1, not retained, the bdSeq metric only) and Clean Session.
2. It subscribes to `spBv1.0/<group>/NCMD/<node>`, `spBv1.0/<group>/DCMD/<node>/+` and, with a
   primary host, `spBv1.0/STATE/<primary_host_id>`.
3. Without a primary host it publishes NBIRTH (seq 0, the same bdSeq) and a DBIRTH per station
   at once; with one it waits for the host's STATE `{"online": true, "timestamp": <ms>}` (a STATE
   whose timestamp is older than the last one seen in this session is ignored: STATE timestamps
   below).
4. Live data: DDATA by alias only, seq +1 per message (255 → 0), QoS 0.
5. STATE `online: false`: the node publishes its NDEATH, disconnects and connects to the **next
   server** of `sparkplug.servers` (the same one when only one is configured; next bdSeq), and
   waits for the host: from then on data is **held**.
6. A station that stops: DDEATH. The last station of the node: NDEATH (before DISCONNECT).
7. Any other end of a session (a lost connection, an error inside the node) closes the socket
   **without** DISCONNECT, so the broker publishes the Will: the host always gets an NDEATH. The
   node's thread is supervised: after an internal error it starts a new session after a back-off
   (0.5 s doubling up to the reconnect back-off's 10 s) and publishes on; stored data stays in the
   store.

## Server set (Sparkplug 3.0 §8.2)

`sparkplug.servers: [mqtt-a:1883, mqtt-b:1883]` lists the MQTT servers of the node (`host` alone
uses `sparkplug.port`; without the key the set is `[<host>:<port>]`, the old form). The node
connects to the first; it moves to the next (round robin) on `Node Control/Next Server`, when
the primary host's STATE on the current server goes offline, and when a server cannot be
reached. Each server carries its own retained STATE of the host: the node waits for
`online: true` on the server it is connected to.

## STATE timestamps

The rule (tck-id-message-flow-edge-node-birth-publish-phid-wait-timestamp,
tck-id-operational-behavior-edge-node-termination-host-offline-timestamp):

- A STATE is compared with the last STATE accepted **in the same MQTT session** only; at each
  CONNECT the comparison starts afresh (the retained STATE a server delivers after SUBSCRIBE is
  that server's current word). Nothing seen before a reconnect, or on another server, can lock
  the host out.
- Within a session, a STATE (online or offline) older than the last one accepted is ignored
  (counted `stale_state`): a stale offline STATE never ends the session.
- A timestamp more than `sparkplug.state_future_skew_s` (@state_future_skew_s@ s) ahead of the node's clock is
  accepted but remembered as the node's clock at receipt (counted `future_state`, logged), so a
  host whose clock once ran years ahead cannot make its later, correctly dated STATEs look stale:
  its `online: false` still ends the session, its `online: true` still brings the births.

## Inbound limits

Everything the node receives is parsed within bounds (`gateway/outputs/sparkplug/inbound.py`);
a payload outside them is **ignored and counted**, and logged at most once per kind (`state`,
`ncmd`, `dcmd`, `topic`) per minute with the count since the previous line. It never ends the
session or the node's thread — a hostile **retained** STATE that comes back at every reconnect
is ignored every time, and the node goes on waiting for a good one. The counts are on the metrics
endpoint of the process that runs the node (in a fleet, the supervisor):
`hookwatch_sparkplug_bad_payloads_total{group,node,kind}`, `hookwatch_sparkplug_connected` and
`hookwatch_sparkplug_events_total{event}` (births, rebirths, connect errors, crashes …;
docs/metrics.md).

| input | limit | key |
|---|---|---|
| STATE payload | @state_max_bytes@ bytes, checked before decoding | `sparkplug.state_max_bytes` |
| STATE JSON | nesting ≤ 2, numbers ≤ 32 characters, ≤ 8 keys of ≤ 32 characters (below) | fixed |
| NCMD / DCMD payload | @max_command_bytes@ bytes, checked before the protobuf decoder | `sparkplug.max_command_bytes` |
| metrics per NCMD / DCMD | @max_command_metrics@ | `sparkplug.max_command_metrics` |
| metric name, string value | @max_string_chars@ characters | `sparkplug.max_string_chars` |
| births | one per @rebirth_min_interval_s@ s, Rebirths coalesced | `sparkplug.rebirth_min_interval_s` |
| Reboot, Next Server | one per @rebirth_min_interval_s@ s, coalesced | `sparkplug.rebirth_min_interval_s` |
| STATE time ahead of the node | @state_future_skew_s@ s, then "now" | `sparkplug.state_future_skew_s` |

The STATE nesting is counted on the bytes before `json.loads` runs; NaN, Infinity and a key given
twice are refused; `online` must be a JSON boolean and `timestamp` a JSON integer 0 … 2⁶³−1.
The values a DCMD carries (sample ID, setpoint …) are then checked by the station's one command
path like every other command.

## Store and forward

While no primary host is online (or the broker is unreachable) DDATA payloads are stored in the
node's SQLite store (the outbox of `gateway/outputs/broker/outbox.py`), metrics flagged
`is_historical = true` with their original timestamps. When the host is online again the node
publishes NBIRTH and the DBIRTHs (current values), then the stored DDATA **in order** (seq given
at sending), then, once the store is empty, a live DDATA with the latest value of every metric
that changed during the replay, and live data after it. Measured values (tension, μ, speed)
beyond `sparkplug.history_budget_mb` are dropped oldest first (counted); state, test and alarm
changes are never dropped. A store that cannot be written (disk full) is a state: rows wait in
memory (bounded, measured values dropped first, counted, one log line) until the disk accepts
them again. Replayed data goes at QoS 0 like all Sparkplug data: a connection lost
during the replay loses the batch in flight (at most 50 payloads), not the rest of the store.

## Node controls (NCMD)

| metric | what the node does |
|---|---|
| `Node Control/Rebirth` = true | NBIRTH (seq 0, same bdSeq) and every DBIRTH again; no data in between |
"""
    # a Markdown table row is one line: these two are longer than the source's line length
    "| `Node Control/Next Server` = true | NDEATH, DISCONNECT, CONNECT to the next configured server (the same "
    "one when only one is configured), new bdSeq, births after the host's STATE |\n"
    "| `Node Control/Reboot` = true | restarts the Sparkplug session exactly like Next Server but on the same "
    "server. It does NOT reboot the box, restart the gateway or touch a station or its running test: a test rig "
    "is never stopped by a SCADA write |\n"
    "| rate of Reboot / Next Server | at most one session end per `sparkplug.rebirth_min_interval_s`, counted from "
    "the session's birth and from the last one: requests inside the interval are coalesced into one (Next Server "
    "over Reboot), carried out when it has passed (e2e: 300 Reboot NCMDs → a bounded number of NDEATH/NBIRTH "
    "pairs) |\n"
    """
## Alarms

Both alarms of a station (gateway/core/alarms.py, ISA-18.2) have the same metrics in their folder,
`Alarm/End Of Life/…` (priority 1) and `Alarm/Wear Warning/…` (the §5a early warning, priority
2): `State`, `Active`, `Priority` and `Shelved Until` (DateTime, null unless shelved), all in
the DBIRTH and as DDATA whenever they change — the same states the PLC reads in `alarm` /
`warning_alarm` and MQTT publishes on `alarm/end_of_life` / `alarm/warning`.

## Device commands (DCMD)

A DCMD names (or aliases) the writable metrics of the DBIRTH. `Device Control/Start Test`,
`Stop Test`, `Acknowledge Alarm`, `Hook Replaced`, `Alarms Out Of Service`, `Alarms In Service`,
`Shelve Alarm`, `Unshelve Alarm` set to true become the commands `start`, `stop`, `ack`,
`hook_replaced`, `out_of_service`, `in_service` (ISA-18.2, a needle being changed), `shelve`,
`unshelve` of the station's **one command path** (the same validation and rejection codes as MQTT,
the PLC and the CLI; `source` is `sparkplug`). `start` takes its arguments from
`Device Control/Sample ID`, `Grade`, `Setpoint` and `Planned End` in the same DCMD; `shelve` from
`Device Control/Alarm` (`end_of_life` or `wear_warning`) and `Device Control/Shelve Duration` (s),
`unshelve` from `Device Control/Alarm`. The outcome comes back as DDATA of `Device Control/Last Command` and
`Device Control/Last Result Code` (0 accepted, else the rejection code of docs/mqtt.md).
""")


def _metric_table(defs, alias) -> list[str]:
    out = ["| metric | datatype | unit | alias | writable | description |", "|---|---|---|---|---|---|"]
    for i, d in enumerate(defs):
        out.append(f"| `{d.name}` | {d.datatype.name} | {d.units or ''} | {alias(i, d)} | "
                   f"{'yes' if d.writable else ''} | {d.description} |")
    return out


def _with_defaults(text: str) -> str:
    """``@key@`` → the default of ``sparkplug.<key>`` (one definition: the schema)."""
    for f in dataclasses.fields(SparkplugConfig):
        if isinstance(f.default, (int, float)) and not isinstance(f.default, bool):
            text = text.replace(f"@{f.name}@", f"{f.default:g}")
    return text


def render() -> str:
    lines = [_with_defaults(HEAD).rstrip("\n"), "", "## Node metrics (NBIRTH)", ""]
    na = M.node_aliases()
    lines += _metric_table(M.NODE_METRICS, lambda i, d: str(na[d.name]) if d.name in na else "none")
    lines += ["", "## Device metrics (DBIRTH: every metric; DDATA: by alias)", "",
              "Aliases are `base + index` with `base = (CRC-32(device ID) + 1) · 4096` (stable "
              "across restarts; a clash between two stations moves one block up).", ""]
    lines += _metric_table(M.DEVICE_METRICS, lambda i, d: f"base + {i}")
    lines += ["", "## Conformance (Sparkplug 3.0 normative statements)", "",
              "yes = implemented and tested (tests/test_sparkplug_*.py); partial = see the note; "
              "n/a = does not apply.", "",
              "| statement | requirement | status | how / proof |", "|---|---|---|---|"]
    for sid, req, status, how in CONFORMANCE:
        lines.append(f"| {sid} | {req} | {status} | {how} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(render(), end="")
