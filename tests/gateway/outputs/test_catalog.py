"""Issue 35 item 2: one catalog of published values (gateway/core/catalog.py).

Every door publishes exactly the catalog's rows among the values of the station's state — the
MQTT `state` (payload, fields, JSON schema, what makes a new retained state), the Sparkplug device
metrics (names, aliases, datatypes, units; DBIRTH decoded), the PLC input registers (block,
address, type, unit; the encoded image decoded), the Prometheus gauges and the console's "all
values" (labels, a card's values, a remote station's state) — found by changing every field of
the state and seeing what each door changes. And a value added as one row (with its source) shows
at every door: a new MQTT key, a Sparkplug metric on the next alias with every other alias kept,
a PLC register in its block's reserved space with every frozen address kept (the golden map), a
Prometheus gauge and a console label. The real doors (Mosquitto, mbpoll, the HTTP endpoint) in
tests/gateway/outputs/test_catalog_doors_e2e.py."""
from __future__ import annotations

import dataclasses
import json
import math
import os

import jsonschema
import pytest

from conftest import ROOT
from gateway.core import catalog
from gateway.core.records import StationState
from gateway.core.records import TestState as TState
from gateway.outputs.console.feed import VALUES, ConsoleOutput, StationFeed, values_json
from gateway.outputs.console.site import SiteView
from gateway.outputs.mqtt import messages as MM
from gateway.outputs.mqtt import schema as S
from gateway.outputs.mqtt import schema_gen as SG
from gateway.outputs.plc import registers as R
from gateway.outputs.plc.server import ModbusOutput, ModbusSettings
from gateway.outputs.prometheus import exposition as PE
from gateway.outputs.prometheus.figures import GAUGES, state_figures
from gateway.outputs.prometheus.outputs import MetricsOutput
from gateway.outputs.sparkplug import metrics as M
from gateway.outputs.sparkplug.node import EdgeNode
from gateway.outputs.sparkplug.output import metric_value, state_values, ticking_values
from gateway.outputs.sparkplug.sparkplug_b_pb2 import Payload

#: a state with every value set (and none at its default)
FULL = StationState(
    "st1", state=TState.MONITORING, test_id="20260301T060000Z-S-7-1", sample_id="S-7", grade="II",
    t_set=0.5, t_end=3600.0, mu_ss=0.21, mu_th=0.252, k_b=1500, t_life=1234.0, elapsed_s=1500.25,
    status="failure", end_reason="completed", alarm="acknowledged", warning_alarm="shelved",
    headroom=0.4, t_cross=2000.0, wear_warning=True, prior_mean=1800.0, prior_sd=300.0,
    prior_source="config", prior_n=12, prior_n_censored=3, prior_n_early=1, lead_s=600.0, p_due=0.1,
    end_p10=1600.0, end_p50=1800.0, end_p90=2100.0, p_end=0.35, due=True,
    warn_reasons=["headroom", "trend"], test_started_utc="2026-03-01T06:00:00.000Z", stopped=True,
    protection_stop=True, meter_ok=True, stm32_ok=True, mqtt_ok=True, saturation=True, disk_ok=False)
EMPTY = StationState("st1")
ENV = [f.name for f in S.ENVELOPE]


def _other(x):
    """Another value of ``x``'s type."""
    if isinstance(x, TState):
        return TState.COMPLETED
    if isinstance(x, bool):
        return not x
    if isinstance(x, (int, float)):
        return x + 7
    if isinstance(x, str):
        return x + "x"
    if isinstance(x, list):
        return x[:1]
    raise AssertionError(x)


def _variants():
    """(field, FULL with that field changed) for every field of the state but its station."""
    for f in dataclasses.fields(StationState):
        if f.name != "station":
            yield f.name, dataclasses.replace(FULL, **{f.name: _other(getattr(FULL, f.name))})


def _changed(view) -> set[str]:
    """The keys of ``view(state)`` that some change of the state changes."""
    base = view(FULL)
    out = set()
    for _, st in _variants():
        other = view(st)
        out |= {k for k in set(base) | set(other) if not _same(base.get(k, "∅"), other.get(k, "∅"))}
    return out


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


# ----------------------------------------------------------------------------- the catalog
def test_the_catalog_keeps_its_rules_and_reads_every_row_as_its_type():
    assert catalog.problems(catalog.CATALOG) == []
    twin = dataclasses.replace(catalog.BY_NAME["mu_ss"], name="mu_ss2")
    with pytest.raises(ValueError) as e:
        catalog.check(catalog.CATALOG + (twin,))
    for what in ("Sparkplug metric 'Method/mu_ss' twice", "Sparkplug alias 9 twice",
                 "PLC register 'mu_ss' twice", "Prometheus gauge 'mu_ss' twice"):
        assert what in str(e.value)
    types = {"str": str, "int": int, "float": float, "bool": bool, "list": list}
    for st in (FULL, EMPTY):
        for v in catalog.CATALOG:
            x = v.source(st)
            assert (x is None and ("null" in v.type or st is EMPTY and v.base_type == "float")) \
                or isinstance(x, types[v.base_type]), (v.name, x)
            if v.choices and x is not None:
                assert set(x if isinstance(x, list) else [x]) <= set(v.choices), v.name
    # a row of every door's own (the meter's channels, the counters) is not a value of the state
    assert {v.name for v in catalog.CATALOG} >= {f.name for f in S.STATE_FIELDS[len(ENV):]}


# ----------------------------------------------------------------------------- MQTT
def test_mqtt_state_is_exactly_the_catalog():
    rows = [v for v in catalog.CATALOG if v.mqtt]
    payload = S.state_payload(7, 0.0, FULL)
    assert list(payload) == ENV + [v.name for v in rows]
    assert [(f.name, f.type, f.doc) for f in S.STATE_FIELDS[len(ENV):]] == [(v.name, v.type, v.doc) for v in rows]
    assert all(payload[v.name] == v.source(FULL) for v in rows)
    # what the state changes in the payload: every row, nothing else
    assert _changed(lambda st: S.state_payload(7, 0.0, st)) == {v.name for v in rows}
    # the published JSON schema (docs/schemas) has exactly these keys and takes the payload
    with open(os.path.join(ROOT, "docs", "schemas", "state.json"), encoding="utf-8") as f:
        schema = json.load(f)
    assert set(schema["properties"]) == set(ENV) | {v.name for v in rows}
    jsonschema.validate(json.loads(S.encode(payload)), schema)
    jsonschema.validate(json.loads(S.encode(S.state_payload(8, 0.0, EMPTY))), schema)
    # a new retained state: when any row but the ticking ones (the elapsed time) changes
    key = MM.state_key(FULL)
    for name, st in _variants():
        moved = [v for v in rows if not _same(v.source(st), v.source(FULL))]
        assert (MM.state_key(st) != key) == any(not v.ticks for v in moved), name
    assert [v.name for v in rows if v.ticks] == ["elapsed_s"]


# ----------------------------------------------------------------------------- Sparkplug
def _golden_sparkplug() -> list[tuple[int, str, str, str]]:
    with open(os.path.join(ROOT, "tests", "golden", "sparkplug_device_metrics.txt"), encoding="utf-8") as f:
        return [(int(i), n, t, u) for i, n, t, u in
                (ln.rstrip("\n").split("\t") for ln in f if ln.strip() and not ln.startswith("#"))]


def _frozen(metrics) -> list[tuple[int, str, str, str]]:
    return [(i, m.name, m.datatype.name, m.units or "-") for i, m in enumerate(metrics)]


def _dbirth(values: dict) -> Payload:
    n = EdgeNode("plant-a", "hall-2", primary_host_id="scada", rebirth_min_interval_ms=0)
    n.connecting()
    n.device_up("loom-01", values, 1)
    n.connected_ok(2)
    n.host_state(json.dumps({"online": True, "timestamp": 10}).encode(), 3)
    birth = [o for o in n.rebirth(9) if "DBIRTH" in o.topic][0]
    p = Payload()
    p.ParseFromString(birth.payload)
    return p


def test_sparkplug_state_metrics_are_exactly_the_catalog():
    rows = [v for v in catalog.CATALOG if v.sparkplug is not None]
    # every alias as shipped (tests/golden/sparkplug_device_metrics.txt): none moved or reused
    # (a metric added since is appended: its line goes to the golden file once it ships)
    assert _frozen(M.DEVICE_METRICS)[:len(_golden_sparkplug())] == _golden_sparkplug()
    for v in rows:
        sp = v.sparkplug
        m = M.DEVICE_METRICS[sp.alias]
        assert (m.name, m.datatype.name, m.units, m.description, m.writable) == \
            (sp.name, sp.datatype, sp.units, sp.description, False)
    assert set(M.DEVICE_OWN).isdisjoint(v.sparkplug.alias for v in rows)
    # what the state changes: the catalog's metrics and the alarm folders (from its two alarm rows)
    view = lambda st: {**state_values(st), **ticking_values(st)}   # noqa: E731
    folders = {n for n in _changed(view) if n.startswith("Alarm/")}
    assert _changed(view) - folders == {v.sparkplug.name for v in rows}
    assert {f.split("/")[1] for f in folders} == {"End Of Life", "Wear Warning"}
    # DBIRTH: each at the device's alias base + its index, with its datatype and value
    b = _dbirth(view(FULL))
    base = M.device_alias_base("loom-01")
    got = {m.name: m for m in b.metrics}
    for v in rows:
        m = got[v.sparkplug.name]
        assert (m.alias, m.datatype) == (base + v.sparkplug.alias, int(M.DataType[v.sparkplug.datatype]))
        want = metric_value(v, v.source(FULL))
        which = m.WhichOneof("value")
        have = getattr(m, which)
        assert (math.isclose(have, want, rel_tol=1e-6) if isinstance(want, float) else have == want), v.name


# ----------------------------------------------------------------------------- PLC
#: the registers of the PLC door's own (not values of the state): versions, the liveness, the
#: status bits, the latest slot's live values and the test's counters (the slot records' rows of
#: the catalog: tests/gateway/outputs/test_catalog_slots.py), the elapsed time and the reason
#: counts of the test (from the slot records), the command status
PLC_OWN = {"heartbeat", "map_version", "sw_major", "sw_minor", "sw_patch", "status", "elapsed",
           "last_command", "last_result", "command_count", "map_minor",
           *(f"count_{n.lower()}" for _, n in R.REASONS),
           *(s.plc.name for s in catalog.SLOT_CATALOG if s.plc is not None)}


def _plc_image(st: StationState, regs=R.INPUT_REGS) -> dict:
    out = ModbusOutput(ModbusSettings("st1"))
    out.on_state(st)
    img = R.encode_table(regs, max(r.address + r.count for r in regs), out.values(now=0.0), "big")
    return {r.name: R.decode_value(r, img[r.address:r.address + r.count]) for r in regs}


def test_plc_registers_of_the_state_are_exactly_the_catalog():
    rows = [v for v in catalog.CATALOG if v.plc is not None]
    for v in rows:
        r = R.IR[v.plc.name]
        assert (r.block, r.type, r.unit, r.doc) == (v.plc.block, v.plc.type, v.plc.unit, v.plc.doc)
    assert set(R.IR) == PLC_OWN | {v.plc.name for v in rows}
    assert PLC_OWN.isdisjoint(v.plc.name for v in rows)
    # the image the server serves: each catalog register holds its row's value
    img = _plc_image(FULL)
    for v in rows:
        want = catalog.plc_number(v, FULL)
        if v.plc.type.startswith("string"):
            assert img[v.plc.name].rstrip(b"\0").decode() == want, v.name
        elif v.plc.type == "float32":
            assert math.isclose(img[v.plc.name], want, rel_tol=1e-6), v.name
        else:
            assert img[v.plc.name] == round(want), v.name
    # what the state changes: the catalog's registers, the status bits and the elapsed time
    assert _changed(_plc_image) == {v.plc.name for v in rows} | {"status", "elapsed"}


#: the status bits of the PLC door's own: composites of the state (a test running, the baseline
#: found, the end of life latched, the alarm unacknowledged, a start in progress), the MQTT link, the
#: last second's slots and the client's right to write
PLC_OWN_BITS = {"running", "baseline_found", "end_of_life", "alarm_unacknowledged", "mqtt_connected",
                "saturation", "writes_enabled", "starting"}


def _status_bits(st: StationState) -> dict[str, bool]:
    word = _plc_image(st)["status"]
    return {name: bool(word >> bit & 1) for bit, name, _ in R.STATUS_BITS}


def test_plc_status_bits_of_the_state_flags_are_exactly_the_catalog():
    flags = [v for v in catalog.CATALOG if v.plc_bit is not None]
    for v in flags:
        assert (v.plc_bit.bit, v.plc_bit.name, v.plc_bit.doc) in R.STATUS_BITS
        assert _status_bits(FULL)[v.plc_bit.name] == v.source(FULL) and v.base_type == "bool"
    assert {n for _, n, _ in R.STATUS_BITS} == PLC_OWN_BITS | {v.plc_bit.name for v in flags}
    # each flag of the state moves its own bit; what else the state moves is the door's composites
    for name, st in _variants():
        moved = {k for k, on in _status_bits(st).items() if on != _status_bits(FULL)[k]}
        assert moved - PLC_OWN_BITS == {v.plc_bit.name for v in flags
                                        if v.source(st) != v.source(FULL)}, name


# ----------------------------------------------------------------------------- Prometheus
def _samples(st: StationState, gauges=GAUGES) -> dict:
    out = MetricsOutput(_Station(), serve=False)
    out.on_state(st)
    snap = out.snapshot()
    snap.update(state_figures(st, gauges))
    fams = PE.families([snap]) + (PE.state_families(PE.PREFIX, [snap], gauges[len(GAUGES):]))
    return {(s.name, tuple(sorted(s.labels.items()))): s.value for f in fams for s in f.samples}


class _Station:
    id, ts = "st1", 0.02

    class _Port:
        connected, counters = True, {"reads": 1}

    meter = stm32 = _Port()


def test_prometheus_gauges_of_the_state_are_exactly_the_catalog():
    rows = [v for v in catalog.CATALOG if v.prometheus is not None]
    assert GAUGES == tuple(rows)
    full = _samples(FULL)
    for v in rows:
        name = f"{PE.PREFIX}_{v.prometheus.name}"
        x = v.source(FULL)
        if v.prometheus.label:
            label = v.prometheus.label
            assert {dict(k[1])[label]: val for k, val in full.items() if k[0] == name} == \
                {c: float(c == x) for c in v.choices}
        else:
            assert full[(name, (("station", "st1"),))] == float(x), v.name
    changed = {k[0] for k in _changed(_samples)}
    assert changed == {f"{PE.PREFIX}_{v.prometheus.name}" for v in rows}


# ----------------------------------------------------------------------------- console
def test_console_shows_exactly_the_catalog():
    labelled = [v for v in catalog.CATALOG if v.label]
    assert VALUES == tuple(labelled)
    assert values_json() == [{"name": v.name, "label": v.label, "unit": v.unit, "type": v.base_type}
                             for v in labelled]
    # every value of the MQTT state has a label: the page shows all of them
    assert {v.name for v in catalog.CATALOG if v.mqtt} <= {v.name for v in labelled}
    feed = StationFeed("st1")
    ConsoleOutput(feed).on_state(FULL)
    feed.drain()
    assert feed.snapshot()["summary"]["values"] == {v.name: v.source(FULL) for v in labelled}
    assert "values" not in feed.summary()          # a fleet card (polled every second) goes without
    # a station of another box: its retained state read by the rows' types, every row kept
    # (a running test without an end of life: the site view clears no projection)
    running = dataclasses.replace(FULL, t_life=None)
    site = SiteView(set())
    assert site.receive("hookwatch/plant/a/l/st1/state", S.encode(S.state_payload(1, 0.0, running)))
    (card,) = site.cards()
    assert card["state"] == "monitoring"
    for v in catalog.CATALOG:
        if v.mqtt and v.name != "test_state":
            assert card[v.name] == v.source(running), v.name


def test_a_new_flag_takes_a_free_status_bit():
    long_test = catalog.Value("long_test", "bool", "", "the test is planned longer than an hour",
                              lambda st: (st.t_end or 0.0) > 3600.0, mqtt=False,
                              plc_bit=catalog.PlcBit(15, "long_test", "the test is planned longer than an hour"))
    bits = R.status_bits(catalog.CATALOG + (long_test,))
    assert bits[:-1] == R.STATUS_BITS and bits[-1] == (15, "long_test", "the test is planned longer than an hour")
    with pytest.raises(ValueError, match="status bit taken twice"):
        R.status_bits(catalog.CATALOG + (dataclasses.replace(
            long_test, plc_bit=catalog.PlcBit(5, "long_test", "")),))


# ----------------------------------------------------------------------------- a new value
#: a value added as its source (here a function of the state's fields) and one row
REMAINING = catalog.Value(
    "t_remaining", "float|null", "s", "planned time left in the test, s",
    lambda st: None if st.t_end is None else max(0.0, st.t_end - float(st.elapsed_s)),
    sparkplug=catalog.SparkplugMetric("Test/Remaining", len(_golden_sparkplug()), "Double", "s",
                                      "planned time left in the test"),
    plc=catalog.PlcRegister("t_remaining", "more", "float32", "s", "planned time left in the test"),
    prometheus=catalog.PromGauge("test_remaining_seconds", "planned time left in the test"),
    label="time left")
EXTENDED = catalog.check(catalog.CATALOG + (REMAINING,))
LEFT = 3600.0 - 1500.25


def test_a_new_value_is_one_row_and_shows_at_every_door():
    # MQTT: the state's last key, in the fields (docs/mqtt.md), the JSON schema and the state key
    payload = S.state_payload(7, 0.0, FULL, EXTENDED)
    assert list(payload)[-1] == "t_remaining" and payload["t_remaining"] == LEFT
    fields = S.state_fields(EXTENDED)
    assert fields[:-1] == S.STATE_FIELDS and fields[-1] == S.Field("t_remaining", "float|null", REMAINING.doc)
    schema = SG.topic_schema(dataclasses.replace(S.TOPIC["state"], fields=fields))
    jsonschema.validate(json.loads(S.encode(payload)), schema)
    assert schema["properties"]["t_remaining"]["type"] == ["number", "null"]
    longer = dataclasses.replace(FULL, t_end=4000.0)
    assert MM.state_key(longer, EXTENDED) != MM.state_key(FULL, EXTENDED)

    # Sparkplug: a metric on the next alias, every shipped alias kept; in DBIRTH with its value
    metrics = M.device_metrics(EXTENDED)
    assert _frozen(metrics)[:-1] == _golden_sparkplug()
    assert _frozen(metrics)[-1] == (len(_golden_sparkplug()), "Test/Remaining", "Double", "s")
    sp_rows = tuple(v for v in EXTENDED if v.sparkplug is not None)
    assert state_values(FULL, values=sp_rows)["Test/Remaining"] == LEFT
    with pytest.raises(ValueError, match="is taken by Test/State"):
        M.device_metrics(catalog.CATALOG + (dataclasses.replace(
            REMAINING, sparkplug=dataclasses.replace(REMAINING.sparkplug, alias=0)),))

    # PLC: a register in block `more` (its reserved space); every frozen address kept
    regs = R.input_layout(EXTENDED)
    new = [r for r in regs if r.name == "t_remaining"]
    assert [(r.block, r.address, r.type) for r in new] == [("more", 200, "float32")]
    assert [r for r in regs if r.name != "t_remaining"] == list(R.INPUT_REGS)
    with open(os.path.join(ROOT, R.GOLDEN), encoding="utf-8") as f:
        golden = f.read()
    assert R.frozen_problems(golden) == []
    (problem,) = R.frozen_problems(golden, regs)
    assert "not frozen yet: input more 200 2 float32 s t_remaining" in problem     # then --freeze
    out = ModbusOutput(ModbusSettings("st1"))
    img = R.encode_table(regs, max(r.address + r.count for r in regs),
                         {**out.values(now=0.0), "t_remaining": catalog.plc_number(REMAINING, FULL)}, "big")
    assert math.isclose(R.decode_value(new[0], img[200:202]), LEFT, rel_tol=1e-6)
    # … a block without room refuses it at import, and so does an address taken
    with pytest.raises(ValueError, match="block wear needs"):
        R.input_layout(catalog.CATALOG + (dataclasses.replace(
            REMAINING, plc=dataclasses.replace(REMAINING.plc, block="wear")),))

    # Prometheus: its gauge with the value
    samples = _samples(FULL, GAUGES + (REMAINING,))
    assert samples[("hookwatch_test_remaining_seconds", (("station", "st1"),))] == LEFT

    # the console: its label, and its value in a card
    assert values_json(VALUES + (REMAINING,))[-1] == {"name": "t_remaining", "label": "time left",
                                                      "unit": "s", "type": "float"}
    assert catalog.read(VALUES + (REMAINING,), FULL)["t_remaining"] == LEFT
