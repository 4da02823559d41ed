"""Issue 35 item 2: the slot records' values in the one catalog (gateway/core/catalog.py SLOT_CATALOG).

Every door publishes exactly the catalog's slot rows among its figures of the slot records — MQTT
telemetry (payload, fields, JSON schema), the Sparkplug data interval (metrics, aliases,
datatypes, values), the PLC live registers (block, type, unit, doc; the encoded image decoded) —
found by changing every field of a slot record and seeing what each door changes. And a value
added as one row shows at every door with no alias or address moved: a derived value (T2 − T1)
and a third meter channel (a new record field and one :func:`catalog.channel` row: the window
keeps its mean, no door changed)."""
from __future__ import annotations

import dataclasses
import json
import math
import os

import jsonschema
import pytest

from conftest import ROOT
from gateway.core import catalog
from gateway.core.records import Event, EventType, SlotRecord
from gateway.core.slotwindow import SlotWindow
from gateway.outputs.console.feed import SLOT_VALUES, VALUES, ConsoleOutput, StationFeed, values_json
from gateway.outputs.mqtt import messages as MM
from gateway.outputs.mqtt import schema as S
from gateway.outputs.mqtt import schema_gen as SG
from gateway.outputs.plc import registers as R
from gateway.outputs.plc.server import ModbusOutput, ModbusSettings
from gateway.outputs.prometheus import docs as PD
from gateway.outputs.prometheus import exposition as PE
from gateway.outputs.prometheus.figures import GAUGES, SLOT_GAUGES
from gateway.outputs.prometheus.outputs import MetricsOutput
from gateway.outputs.sparkplug import metrics as M
from gateway.outputs.sparkplug.output import window_values

ENV = [f.name for f in S.ENVELOPE]
#: telemetry's keys that are not figures of the slot records: the test, the interval, the §5a/§5b
#: figures of the station's state
TELEMETRY_OWN = ["test_id", "interval_s", "headroom", "t_cross", *S.TELEMETRY_FORECAST]


def _rec(k: int, **kw) -> SlotRecord:
    d = dict(k=k, t=k * 0.02, present=True, t1=0.40 + 0.001 * k, t2=0.52 + 0.002 * k, q=1, mask=0,
             ratio=1.3, mu=0.21 + 0.0005 * k, mean_filt=0.46, speed_cmd=120.0 + k, speed_act=119.0 + k,
             saturated=False, lateness_s=0.0, rtt_s=0.004)
    d.update(kw)
    return SlotRecord(**d)


#: slot records with a reason bit, a slot without reading (and no clamped slot: a variant clamps one)
RECS = [_rec(0), _rec(1, mask=1, q=0, mu=None), _rec(2),
        _rec(3, present=False, t1=math.nan, t2=math.nan, q=0, mu=None), _rec(4)]


def _window(recs, means=catalog.MEANS) -> SlotWindow:
    w = SlotWindow(0.0, means)
    for r in recs:
        w.add(r)
    return w


def _other(x):
    if isinstance(x, bool):
        return not x
    if x is None:
        return 0.33
    if isinstance(x, (int, float)):
        return 0.0 if x != x else x + 1
    raise AssertionError(x)


def _variants(recs):
    """Records with one field of the last record changed (but k, t), and one record more."""
    last = recs[-1]
    for f in dataclasses.fields(SlotRecord):
        if f.name not in ("k", "t"):
            yield recs[:-1] + [dataclasses.replace(last, **{f.name: _other(getattr(last, f.name))})]
    yield recs + [_rec(len(recs))]


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def _changed(view, recs=RECS) -> set[str]:
    base = view(recs)
    out = set()
    for other_recs in _variants(recs):
        other = view(other_recs)
        out |= {k for k in set(base) | set(other) if not _same(base.get(k, "∅"), other.get(k, "∅"))}
    return out


# ----------------------------------------------------------------------------- the rows
def test_the_slot_rows_keep_the_catalog_rules_with_the_state_rows():
    assert catalog.problems(catalog.CATALOG, catalog.SLOT_CATALOG) == []
    # a slot row may not take a state row's alias or register, nor another slot row's
    twin = dataclasses.replace(catalog.SLOT_BY_NAME["t1"], name="t1b", sparkplug=dataclasses.replace(
        catalog.SLOT_BY_NAME["t1"].sparkplug, alias=9))
    with pytest.raises(ValueError) as e:
        catalog.check(catalog.CATALOG, catalog.SLOT_CATALOG + (twin,))
    for what in ("Sparkplug metric 'Tension/T1' twice", "Sparkplug alias 9 twice", "PLC register 't1' twice"):
        assert what in str(e.value)
    # every window figure as its type (an object: the tension's and the reasons' figures)
    types = {"int": int, "float": float, "bool": bool, "object": dict}
    for recs in (RECS, []):
        w = _window(recs)
        for s in catalog.SLOT_CATALOG:
            if s.window is not None:
                x = s.window(w)
                assert (x is None and "null" in s.type) or isinstance(x, types[s.base_type]), (s.name, x)


# ----------------------------------------------------------------------------- MQTT telemetry
def _telemetry(recs, slots=catalog.SLOT_CATALOG) -> dict:
    w = _window(recs, catalog.means(slots))
    return S.telemetry_payload(5, 0.0, "st1", MM.telemetry_summary(w, 1.0, "T-1", 0.4, 900.0, slots),
                               S.telemetry_fields(slots))


def test_mqtt_telemetry_is_exactly_the_slot_rows():
    rows = [s for s in catalog.SLOT_CATALOG if s.window is not None]
    payload = _telemetry(RECS)
    assert [k for k in payload if k not in ENV and k not in TELEMETRY_OWN] == [s.name for s in rows]
    w = _window(RECS)
    assert all(_same(payload[s.name], s.window(w)) for s in rows)
    fields = [(f.name, f.type, f.doc) for f in S.TELEMETRY_FIELDS if f.name in {s.name for s in rows}]
    assert fields == [(s.name, s.type, s.doc) for s in rows]
    # outside a test, the rows that are null there
    out_of_test = MM.telemetry_summary(w, 1.0, None)
    assert {s.name for s in rows if out_of_test[s.name] is None and s.window(w) is not None} == \
        {s.name for s in rows if s.in_test}
    # what the slot records change in the payload: every row, nothing else
    assert _changed(_telemetry) == {s.name for s in rows}
    # the published JSON schema (docs/schemas) has exactly these keys and takes the payload
    with open(os.path.join(ROOT, "docs", "schemas", "telemetry.json"), encoding="utf-8") as f:
        schema = json.load(f)
    assert set(schema["properties"]) == set(ENV) | set(TELEMETRY_OWN) | {s.name for s in rows}
    jsonschema.validate(json.loads(S.encode(payload)), schema)
    jsonschema.validate(json.loads(S.encode(_telemetry([]))), schema)


# ----------------------------------------------------------------------------- Sparkplug
def _sparkplug(recs, slots=catalog.SLOT_CATALOG) -> dict:
    return window_values(_window(recs, catalog.means(slots)), slots)


def test_sparkplug_data_interval_is_exactly_the_slot_rows():
    rows = [s for s in catalog.SLOT_CATALOG if s.sparkplug is not None]
    for s in rows:
        sp = s.sparkplug
        m = M.DEVICE_METRICS[sp.alias]
        assert (m.name, m.datatype.name, m.units, m.description, m.writable, m.telemetry) == \
            (sp.name, sp.datatype, sp.units, sp.description, False, True)
    assert set(M.DEVICE_OWN).isdisjoint(s.sparkplug.alias for s in rows)
    got = _sparkplug(RECS)
    assert list(got) == [s.sparkplug.name for s in rows]
    w = _window(RECS)
    for s in rows:
        want = (s.sparkplug_window or s.window)(w)
        assert _same(got[s.sparkplug.name], want), s.name
    # the telemetry metrics of a device are exactly these rows
    assert {m.name for m in M.DEVICE_METRICS if m.telemetry} == {s.sparkplug.name for s in rows}
    assert _changed(_sparkplug) == {s.sparkplug.name for s in rows}


# ----------------------------------------------------------------------------- PLC
def _plc(recs, slot_regs=R.SLOT_REGS, regs=R.INPUT_REGS) -> dict:
    out = ModbusOutput(ModbusSettings("st1"))
    out.slot_regs = slot_regs
    out.on_event(Event(EventType.TEST_STARTED, "st1", 0.0, "T-1", 0))
    for r in recs:
        out.on_record(r)
    img = R.encode_table(regs, max(r.address + r.count for r in regs), out.values(now=0.0), "big")
    return {r.name: R.decode_value(r, img[r.address:r.address + r.count]) for r in regs}


def _f32(x: float) -> float:
    return R.decode_value(R.IR["t1"], R.encode_table((R.IR["t1"],), R.IR["t1"].address + 2, {"t1": x},
                                                     "big")[R.IR["t1"].address:])


def test_plc_live_registers_are_exactly_the_slot_rows():
    rows = [s for s in catalog.SLOT_CATALOG if s.plc is not None]
    for s in rows:
        r = R.IR[s.plc.name]
        assert (r.block, r.type, r.unit, r.doc) == (s.plc.block, s.plc.type, s.plc.unit, s.plc.doc)
    assert R.SLOT_REGS == {s.plc.name: s for s in rows}
    # the image: the latest slot's reading, or the test window's, each as its register holds it
    img = _plc(RECS)
    w = _window(RECS)
    for s in rows:
        if s.latest is None and s.plc_test is None:
            continue            # the output's own reading (μ of the latest valid slot within 1 s)
        want = s.latest(RECS[-1]) if s.latest is not None else s.plc_test(w)
        if s.plc.type == "float32":
            assert _same(img[s.plc.name], _f32(want)), s.name
        else:
            assert img[s.plc.name] == want, s.name
    assert {s.name for s in rows if s.latest is None and s.plc_test is None} == {"mu"}
    # what the slot records change: the rows' registers, the reason counts, the saturation bit
    # (status) and the elapsed time, nothing else
    own = {"status", "elapsed", *(f"count_{n.lower()}" for _, n in R.REASONS)}
    assert _changed(_plc) - own == {s.plc.name for s in rows}


# ----------------------------------------------------------------------------- Prometheus, console
class _Station:
    id, ts = "st-slots", 0.02

    class _Port:
        connected, counters = True, {"reads": 1}

    meter = stm32 = _Port()


def test_prometheus_and_console_show_exactly_the_slot_rows_with_a_gauge_or_a_label():
    # none today: the Prometheus slot counters and the console's live series are the doors' own
    assert SLOT_GAUGES == tuple(s for s in catalog.SLOT_CATALOG if s.prometheus is not None) == ()
    assert SLOT_VALUES == tuple(s for s in catalog.SLOT_CATALOG if s.label) == ()
    assert values_json() == values_json(VALUES, ())
    assert PD.table() == PD.table(GAUGES)


# ----------------------------------------------------------------------------- a new value
@dataclasses.dataclass(slots=True)
class T3Record(SlotRecord):
    """A slot record with a third meter channel (the new record field)."""
    t3: float = math.nan


def _t3(rec: SlotRecord) -> float:
    return rec.t3 if isinstance(rec, T3Record) and rec.present else math.nan


NEXT = len(M.DEVICE_METRICS)      # the next free Sparkplug alias index
#: a derived value: T2 − T1 (its window's figure, the latest slot's on the PLC)
DIFF = catalog.SlotValue(
    "t_diff", "float|null", "N", "mean T2 − T1 over slots with a reading, N",
    lambda w: None if w.n_read == 0 else round((w.s2 - w.s1) / w.n_read, 6),
    sparkplug=catalog.SparkplugMetric("Tension/Difference", NEXT, "Float", "N", "T2 − T1, interval mean"),
    plc=catalog.PlcRegister("t_diff", "more", "float32", "N", "T2 − T1 of the latest slot"),
    latest=lambda rec: rec.t2 - rec.t1 if rec.present else math.nan,
    prometheus=catalog.PromGauge("tension_difference_newtons", "T2 − T1 of the latest slot"),
    label="T2 − T1")
#: a third meter channel: its record field (T3Record.t3) and one row
T3 = catalog.channel("t3", "N", "mean T3 (third channel), N, over slots with a reading", _t3,
                     catalog.SparkplugMetric("Tension/T3", NEXT + 1, "Float", "N", "third channel, interval mean"),
                     catalog.PlcRegister("t3", "more", "float32", "N", "third channel T3 of the latest slot"),
                     catalog.PromGauge("tension_t3_newtons", "third channel T3 of the latest slot"), "T3")
EXTENDED = catalog.SLOT_CATALOG + (DIFF, T3)
T3RECS = [T3Record(**{f.name: getattr(r, f.name) for f in dataclasses.fields(SlotRecord)},
                   t3=0.9 + 0.01 * r.k) for r in RECS]


def test_a_new_slot_value_is_one_row_and_shows_at_every_door():
    catalog.check(catalog.CATALOG, EXTENDED)
    diff = sum(r.t2 - r.t1 for r in RECS if r.present) / sum(r.present for r in RECS)
    t3 = sum(r.t3 for r in T3RECS if r.present) / sum(r.present for r in T3RECS)

    # MQTT telemetry: two new keys (after the slot rows), in the fields and the JSON schema
    payload = _telemetry(T3RECS, EXTENDED)
    assert math.isclose(payload["t_diff"], diff, rel_tol=1e-6) and math.isclose(payload["t3"], t3, rel_tol=1e-6)
    fields = S.telemetry_fields(EXTENDED)
    assert [f for f in fields if f.name not in ("t_diff", "t3")] == list(S.TELEMETRY_FIELDS)
    schema = SG.topic_schema(dataclasses.replace(S.TOPIC["telemetry"], fields=fields))
    jsonschema.validate(json.loads(S.encode(payload)), schema)
    assert schema["properties"]["t3"]["type"] == ["number", "null"]
    # … the existing keys and values unchanged
    assert {k: v for k, v in payload.items() if k not in ("t_diff", "t3")} == _telemetry(RECS)

    # Sparkplug: two metrics on the next aliases, every other alias kept
    metrics = M.device_metrics(catalog.CATALOG, EXTENDED)
    assert metrics[:NEXT] == M.DEVICE_METRICS
    assert [(m.name, m.datatype.name, m.units, m.telemetry) for m in metrics[NEXT:]] == \
        [("Tension/Difference", "Float", "N", True), ("Tension/T3", "Float", "N", True)]
    vals = _sparkplug(T3RECS, EXTENDED)
    assert math.isclose(vals["Tension/Difference"], diff, rel_tol=1e-6)
    assert math.isclose(vals["Tension/T3"], t3, rel_tol=1e-9)
    with pytest.raises(ValueError, match="is taken by Tension/T1"):
        M.device_metrics(catalog.CATALOG, catalog.SLOT_CATALOG + (dataclasses.replace(
            DIFF, sparkplug=dataclasses.replace(DIFF.sparkplug, alias=18)),))

    # PLC: two registers in block `more` (its reserved space); every frozen address kept
    regs = R.input_layout(catalog.CATALOG, EXTENDED)
    new = [r for r in regs if r.name in ("t_diff", "t3")]
    assert [(r.name, r.block, r.address, r.type) for r in new] == \
        [("t_diff", "more", 200, "float32"), ("t3", "more", 202, "float32")]
    assert [r for r in regs if r not in new] == list(R.INPUT_REGS)
    with open(os.path.join(ROOT, R.GOLDEN), encoding="utf-8") as f:
        golden = f.read()
    assert R.frozen_problems(golden) == []
    (problem,) = R.frozen_problems(golden, regs)
    assert "not frozen yet: input more 200 2 float32 N t_diff" in problem      # then --freeze
    slot_regs = {s.plc.name: s for s in EXTENDED if s.plc is not None}
    img = _plc(T3RECS, slot_regs, regs)
    last = T3RECS[-1]
    assert img["t_diff"] == _f32(last.t2 - last.t1) and img["t3"] == _f32(last.t3)
    # … the existing registers hold what they held
    before = _plc(RECS)
    assert all(_same(v, before[k]) for k, v in img.items() if k not in ("t_diff", "t3"))
    assert set(img) - set(before) == {"t_diff", "t3"}

    # Prometheus: a gauge each, of the latest slot; in docs/metrics.md's table
    gauges = tuple(s for s in EXTENDED if s.prometheus is not None)
    got = {}
    out = MetricsOutput(_Station(), serve=False)
    for r in T3RECS:
        out.on_record(r)
    snap = {**out.snapshot(), **catalog.read_latest(gauges, out.f.latest)}
    for fam in PE.state_families(PE.PREFIX, [snap], gauges):
        (sample,) = fam.samples
        got[fam.name] = sample.value
    assert got == {"hookwatch_tension_difference_newtons": last.t2 - last.t1, "hookwatch_tension_t3_newtons": last.t3}
    rows = PD.table(GAUGES + gauges)
    assert rows[:-2] == PD.table() and "`hookwatch_tension_t3_newtons` | gauge | station | N |" in rows[-1]

    # the console: its label under "all values", the latest slot's reading in the station's values
    assert values_json(VALUES, (DIFF, T3))[-2:] == [
        {"name": "t_diff", "label": "T2 − T1", "unit": "N", "type": "float"},
        {"name": "t3", "label": "T3", "unit": "N", "type": "float"}]
    feed = StationFeed("st1")
    feed.slot_values = (DIFF, T3)
    console = ConsoleOutput(feed)
    for r in T3RECS:
        console.on_record(r)
    feed.drain()
    values = feed.snapshot()["summary"]["values"]
    assert values == {"t_diff": last.t2 - last.t1, "t3": last.t3}
