"""The test kit's own check (tests/kit/broker.py): every JSON message a Sub receives on hookwatch's
tree is validated against its topic's schema, and a violation fails the test naming the topic, the
payload and the schema path — shown here with a real Mosquitto and a payload that is wrong on
purpose (a station never publishes one: every other test's messages pass the same check)."""
import json

import pytest

from gateway.outputs.mqtt import schema as S
from kit.broker import Broker, SchemaViolation, Sub, check_message, pub, schema_key

BASE = "hookwatch/lab/hall/l1/kit"


def test_topics_map_to_their_schema():
    assert schema_key(f"{BASE}/state") == "state"
    assert schema_key(f"{BASE}/alarm/warning") == "alarm_warning"
    assert schema_key(f"{BASE}/alarm/end_of_life") == "alarm"
    assert schema_key(f"{BASE}/event/test_started") == "event"
    assert schema_key(f"{BASE}/cmd/start") == ""              # commands: the tests' own, not checked
    assert schema_key("spBv1.0/lab/DDATA/n/d") == ""          # Sparkplug: protobuf
    assert schema_key(f"{BASE}/probe") is None


def test_a_violation_names_topic_payload_and_schema_path():
    good = json.loads(S.encode(S._examples()["state"]))
    assert check_message(f"{BASE}/state", json.dumps(good)) is None
    bad = dict(good, test_state="running")
    msg = check_message(f"{BASE}/state", json.dumps(bad))
    assert f"{BASE}/state" in msg and "docs/schemas/state.json" in msg and "test_state" in msg
    assert '"running"' in msg                                   # the payload is shown
    assert "not JSON" in check_message(f"{BASE}/telemetry", "{oops")
    # an envelope on a topic without a schema is a violation; a test's own probe is not
    assert "without a JSON Schema" in check_message(f"{BASE}/surprise", json.dumps(good))
    assert check_message(f"{BASE}/probe", "{}") is None


def test_a_bad_message_through_mosquitto_fails_the_receiving_test(tmp_path):
    with Broker(tmp_path) as b:
        sub = Sub(b.port, BASE + "/#")
        try:
            bad = dict(json.loads(S.encode(S._examples()["alarm_warning"])), priority="high")
            # retained (as the gateway's alarm/warning is): it arrives whenever the Sub subscribed
            pub(b.port, f"{BASE}/alarm/warning", json.dumps(bad), retain=True)
            with pytest.raises(SchemaViolation, match=r"alarm/warning.*alarm_warning\.json at priority"):
                sub.wait(lambda s: s.messages("alarm/warning"), 20)
        finally:
            sub.stop()            # reported once: stop() does not raise it again
