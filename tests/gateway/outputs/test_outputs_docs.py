"""One definition → runtime, docs and `hookwatch regmap`: docs current, payloads match the schema,
register encoding round-trips, the CLI prints the map of a station."""
import csv
import io
import json
import math
import os
import re
import subprocess

import pytest

from conftest import ROOT, hookwatch_cmd
from gateway.core.records import Event, EventType, StationState
from gateway.core.records import TestState as TState
from gateway.outputs.mqtt import schema as S
from gateway.outputs.plc import registers as R

GENERATED = [("gateway.outputs.mqtt.schema", "docs/mqtt.md"),
             ("gateway.outputs.plc.registers", "docs/registers.md")]


@pytest.mark.parametrize("module,path", GENERATED)
def test_generated_doc_is_current(module, path):
    import importlib

    mod = importlib.import_module(module)
    with open(os.path.join(ROOT, path), encoding="utf-8") as f:
        assert f.read() == mod.render(), f"regenerate: python -m {module} > {path}"


def test_docs_name_every_topic_field_and_register():
    md = S.render()
    for t in S.TOPICS:
        assert f"### `{t.path}`" in md
        for f in t.fields:
            assert f"| `{f.name}` |" in md
    for et in EventType:
        assert f"| `{et.value}` |" in md
    rm = R.render()
    for r in R.INPUT_REGS + R.HOLDING_REGS:
        assert f"| `{r.name}` |" in rm


def test_payload_builders_match_the_documented_fields():
    ex = S._examples()
    for key in ("status", "state", "telemetry", "event", "alarm", "result", "reply"):
        assert list(ex[key]) == S.field_names(key), key
        assert ex[key]["schema"] == S.SCHEMA_VERSION
        json.loads(S.encode(ex[key]))
    for key in ("cmd_start", "cmd_stop", "cmd_ack", "cmd_setpoint"):
        assert set(ex[key]) <= set(S.field_names(key))


def test_payloads_are_plain_json_with_utc_ms_times():
    import numpy as np

    st = StationState(station="s", state=TState.MONITORING, mu_ss=float("nan"), t_set=np.float64(0.5))
    p = json.loads(S.encode(S.state_payload(7, 1772352000.0205, st)))
    assert p["mu_ss"] is None and p["t_set"] == 0.5 and p["test_state"] == "monitoring"
    assert p["time"] == "2026-03-01T08:00:00.021Z" or p["time"] == "2026-03-01T08:00:00.020Z"
    ev = Event(EventType.PROTECTION_STOP, "s", 1772352000.0, "T", 5, {"stop_reasons": ("MISSING",),
                                                                      "x": np.int64(3)})
    p = json.loads(S.encode(S.event_payload(8, ev)))
    assert p["data"] == {"stop_reasons": ["MISSING"], "x": 3} and p["seq"] == 8
    assert S.iso_ms(0) == "1970-01-01T00:00:00.000Z"


def test_topic_tree_from_the_plant_hierarchy():
    assert S.base_topic("hookwatch", "plant1", "knit", "l3", "st1") == "hookwatch/plant1/knit/l3/st1"
    assert S.base_topic("acme/hw/", "", None, "a/b", "s+#") == "acme/hw/_/_/a_b/s__"
    assert S.topic_for("p/s/a/l/x", "event", type="end_of_life") == "p/s/a/l/x/event/end_of_life"
    assert S.topic_for("p/s/a/l/x", "alarm") == "p/s/a/l/x/alarm/end_of_life"


@pytest.mark.parametrize("order", ["big", "little"])
def test_register_values_round_trip(order):
    for r in R.INPUT_REGS + R.HOLDING_REGS:
        if r.type == "float32":
            regs = R.encode_value(r, 0.2345, order)
            assert abs(R.decode_value(r, regs, order) - 0.2345) < 1e-7
            assert math.isnan(R.decode_value(r, R.encode_value(r, None, order), order))
            assert math.isnan(R.decode_value(r, R.encode_value(r, 1e300, order), order))
        elif r.type == "uint32":
            assert R.decode_value(r, R.encode_value(r, 123456.4, order), order) == 123456
            assert R.decode_value(r, R.encode_value(r, -5, order), order) == 0
        elif r.type in ("string", "string80"):
            raw = R.decode_value(r, R.encode_value(r, "S-0042", order), order)
            assert R.decode_sample_id(raw) == "S-0042"
            long_id = "20260105T080700.123Z-" + "s" * 48 + "-9999"
            raw = R.decode_value(r, R.encode_value(r, long_id, order), order)
            assert R.decode_sample_id(raw) == long_id[:2 * r.count]
        else:
            assert R.decode_value(r, R.encode_value(r, 70000, order), order) == 0xFFFF
    # big: high word first
    assert R.encode_value(R.IR["t1"], 1.0, "big") == [0x3F80, 0x0000]
    assert R.encode_value(R.IR["t1"], 1.0, "little") == [0x0000, 0x3F80]
    assert R.decode_sample_id(b"AB\0C" + b"\0" * 28) is None


def test_refusals_answer_the_modbus_exception_the_specification_means():
    from gateway.station.command_desk import CODE, REJECT_CODES

    assert R.refusal_exception(CODE["BUSY"]) == 6               # server device busy: retry later
    assert R.refusal_exception(CODE["SETPOINT_LOCKED"]) == 6
    assert R.refusal_exception(CODE["RATE_LIMITED"]) == 6       # too many commands: retry later
    assert R.refusal_exception(CODE["NO_STATION"]) == 4         # the only real failure
    assert R.refusal_exception(999) == 4
    for code, name, _ in REJECT_CODES:
        if code and name not in ("BUSY", "SETPOINT_LOCKED", "RATE_LIMITED", "NO_STATION"):
            assert R.refusal_exception(code) == 3, name         # a refused value / state
    # the map only grew: the added input registers come after every earlier one
    assert R.IR["run_sample_id"].address == R.IR["command_count"].address + 1
    assert R.IR["run_test_id"].address == R.IR["run_sample_id"].address + R.IR["run_sample_id"].count


def _station_yaml(tmp_path, **mb):
    import yaml

    cfg = {"station": {"id": "loom-9", "site": "p", "area": "a", "line": "l"},
           "meter": {"port": "/dev/ttyUSB0"}, "stm32": {"port": "/dev/ttyUSB1"},
           "recorder": {"dir": str(tmp_path / "rec")},
           "modbus_tcp": {"enabled": True, "port": 1502, "unit_id": 7, "word_order": "little", **mb}}
    p = tmp_path / "loom-9.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return str(p)


def test_regmap_cli_for_a_station(tmp_path):
    path = _station_yaml(tmp_path, writes={"enabled": True, "allowed_clients": ["10.0.0.5"]})
    r = subprocess.run(hookwatch_cmd() + ["regmap", path], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "Station **loom-9**" in r.stdout and "unit ID **7**" in r.stdout
    assert "little-endian word order" in r.stdout and "10.0.0.5" in r.stdout
    assert "| `heartbeat` |" in r.stdout
    # the blocks, their reserved space and the versioning rule (issue 35 item 3)
    assert "## Blocks" in r.stdout and "| input | `reasons_more` | 128–191 | 0 | 64 |" in r.stdout
    assert "## Versioning: addresses never move" in r.stdout
    r = subprocess.run(hookwatch_cmd() + ["regmap", path, "--format", "csv"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(io.StringIO(r.stdout)))
    names = [x["name"] for x in rows if x["table"] in ("input", "holding")]
    assert names == [x.name for x in R.INPUT_REGS + R.HOLDING_REGS]
    assert {x["unit_id"] for x in rows} == {"7"}
    t1 = next(x for x in rows if x["name"] == "t1")
    assert (t1["address"], t1["reference"], t1["type"], t1["block"]) == (str(R.IR["t1"].address), "30009",
                                                                         "float32", "live")


def test_regmap_cli_errors(tmp_path):
    r = subprocess.run(hookwatch_cmd() + ["regmap", str(tmp_path / "nope.yaml")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode != 0 and "nope.yaml" in r.stderr and "Traceback" not in r.stderr
    bad = tmp_path / "bad.yaml"
    bad.write_text("station: {id: x}\nmodbus_tcp: {word_order: middle}\n")
    r = subprocess.run(hookwatch_cmd() + ["regmap", str(bad)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "word_order" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(hookwatch_cmd() + ["regmap"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and r.stdout == R.render()


def test_regmap_shows_the_configurations_strings_as_text(tmp_path):
    """Grades from the station file go into the generated Markdown as text: a newline starts no
    heading, a tag is no tag (issue 27, item 4); the CSV has no cell a spreadsheet runs."""
    import yaml

    path = _station_yaml(tmp_path)
    with open(path, encoding="utf-8") as f:
        cfg = yaml.safe_load(f)
    cfg["grades"] = ["I\n# injected", "<img src=x onerror=alert(1)>", "x;=1+1"]
    with open(path, "w", encoding="utf-8") as f:
        yaml.safe_dump(cfg, f)
    r = subprocess.run(hookwatch_cmd() + ["regmap", path], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert not [ln for ln in r.stdout.splitlines() if ln.startswith("# injected")]
    assert not re.search(r"(?<!\\)<img", r.stdout) and "\\<img src=x onerror=alert(1)\\>" in r.stdout
    assert "1 I # injected, 2 \\<img" in r.stdout
