"""JSON Schemas (2020-12) of the MQTT payloads: generated from gateway/outputs/mqtt/schema.py and
current in docs/schemas/; every message a real station publishes through a real Mosquitto (and
every documented example) validates against the schema of its topic, with `jsonschema`."""
import json
import os
import time

import jsonschema
import pytest

from conftest import ROOT
from gateway.core.records import EventType
from gateway.outputs.mqtt import schema as S
from gateway.outputs.mqtt import schema_gen
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker, Sub, pub
from kit.northbound import LoopThread, RunningStation, make_station
from kit.tools import wait_for

BASE = "hookwatch/lab/hall/l1/schemas"
SCHEMAS = {name[:-5]: json.loads(text) for name, text in schema_gen.render_all().items()}


def validator(key):
    return jsonschema.Draft202012Validator(SCHEMAS[key], format_checker=jsonschema.FormatChecker())


def key_of(topic: str) -> str:
    rest = topic[len(BASE) + 1:]
    if rest.startswith("event/"):
        return "event"
    if rest.startswith("alarm/"):
        return "alarm_warning" if rest == "alarm/warning" else "alarm"
    if rest.startswith("cmd/"):
        return "cmd_" + rest[4:]
    return rest


def test_schema_files_are_current():
    d = os.path.join(ROOT, "docs", "schemas")
    on_disk = sorted(f for f in os.listdir(d) if f.endswith(".json"))
    assert on_disk == sorted(schema_gen.render_all()), "regenerate: python -m gateway.outputs.mqtt.schema_gen"
    for name, text in schema_gen.render_all().items():
        with open(os.path.join(d, name), encoding="utf-8") as f:
            assert f.read() == text, f"regenerate: python -m gateway.outputs.mqtt.schema_gen ({name})"


@pytest.mark.parametrize("key", sorted(SCHEMAS))
def test_every_schema_is_valid_2020_12_and_the_documented_example_passes(key):
    jsonschema.Draft202012Validator.check_schema(SCHEMAS[key])
    validator(key).validate(json.loads(S.encode(S._examples()[key])))


def test_schemas_refuse_what_the_gateway_refuses():
    with pytest.raises(jsonschema.ValidationError):
        validator("cmd_start").validate({"sample_id": "S-1", "t_set": 0.5, "speed": 3})
    with pytest.raises(jsonschema.ValidationError):
        validator("cmd_start").validate({"sample_id": "S-1"})
    bad = json.loads(S.encode(S._examples()["state"]))
    bad["test_state"] = "running"
    with pytest.raises(jsonschema.ValidationError):
        validator("state").validate(bad)


def test_every_payload_a_station_publishes_validates(tmp_path):
    lt = LoopThread()
    with Broker(tmp_path) as b:
        sub = Sub(b.port, BASE + "/#")
        station = make_station(tmp_path, [], station_id="schemas")
        out = MqttOutput(MqttSettings(station_id="schemas", base_topic=BASE, port=b.port,
                                      outbox_path=str(tmp_path / "outbox.sqlite"),
                                      telemetry_interval_s=0.2, reconnect_min_s=0.2), station)
        station.outputs.append(out)
        run = RunningStation(lt, station)
        try:
            wait_for(lambda: out.connected, 20, what="connected")
            pub(b.port, f"{BASE}/cmd/start", '{"sample_id": "S-1", "t_set": 0.5, "request_id": "a"}')
            sub.wait(lambda s: s.messages("event/test_started"), 20)
            pub(b.port, f"{BASE}/cmd/start", '{"sample_id": "S-2", "t_set": 99}')     # refused
            pub(b.port, f"{BASE}/cmd/frobnicate", "{not json")                       # refused

            async def end_of_life():                 # what the method does at t_life
                station.board.emit(EventType.END_OF_LIFE, k=50, k_life=50, t_life=1.0, mu_ss=0.2,
                                    mu_th=0.23, sample_id="S-1")
            lt.call(end_of_life())
            pub(b.port, f"{BASE}/cmd/ack", "{}")
            sub.wait(lambda s: s.messages("event/alarm_acknowledged"), 20)
            pub(b.port, f"{BASE}/cmd/stop", '{"request_id": "z"}')
            sub.wait(lambda s: s.messages("result"), 20)
            pub(b.port, f"{BASE}/cmd/hook_replaced", "{}")
            sub.wait(lambda s: s.messages("event/alarm_cleared"), 20)
            time.sleep(0.5)
        finally:
            run.stop()
            lt.close()
            sub.stop()
    msgs = [m for m in sub.messages() if not m[1].split("/")[-2] == "cmd"]
    seen = set()
    for _r, topic, payload, _t in msgs:
        key = key_of(topic)
        if key.startswith("cmd_"):
            continue
        assert "_raw" not in payload, (topic, payload)
        validator(key).validate(payload)
        seen.add(key)
    assert seen >= {"status", "state", "telemetry", "event", "alarm", "result", "reply"}, seen
