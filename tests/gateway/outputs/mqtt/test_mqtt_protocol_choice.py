"""The MQTT 5 / 3.1.1 choice of the pump's session (gateway/outputs/mqtt/protocol_choice.py), without a
broker: when ``auto`` falls back to 3.1.1, and when it never does. The same choice against real
Mosquitto brokers (one that refuses MQTT 5 at CONNACK, one that closes the connection) is
tests/gateway/outputs/mqtt/test_mqtt5.py."""
import collections
import logging

from gateway.outputs.mqtt.protocol_choice import V311_COSTS, ProtocolChoice
from gateway.outputs.mqtt.settings import MqttSettings

SERVER = ("127.0.0.1", 1883)


def _choice(protocol: str) -> ProtocolChoice:
    return ProtocolChoice(MqttSettings(station_id="st1", base_topic="b", protocol=protocol),
                          collections.Counter())


def test_auto_falls_back_once_on_a_version_refused_at_connack(caplog):
    caplog.set_level(logging.WARNING, "hookwatch.mqtt")
    p = _choice("auto")
    assert p.v5 and p.version_refused(True, 132) and p.version_refused(True, 1)
    assert not p.version_refused(True, 135) and not p.version_refused(False, 0)   # not authorized, success
    assert p.fall_back("132", SERVER) and not p.v5
    assert not p.version_refused(True, 132)          # 3.1.1 now: nothing left to refuse
    assert not p.fall_back("again", SERVER) and p.counters["mqtt311_fallbacks"] == 1
    lines = [r.getMessage() for r in caplog.records if "refused MQTT 5" in r.getMessage()]
    assert len(lines) == 1 and V311_COSTS in lines[0]


def test_auto_falls_back_on_the_second_close_before_connack_in_a_row():
    p = _choice("auto")
    p.connecting()
    assert p.closed("reset") is None                  # once may be a broker going down
    p.connecting()
    p.connack()                                       # a CONNACK came: the row starts again
    assert p.closed("reset") is None
    p.connecting()
    assert p.closed("reset") is None
    p.connecting()
    why = p.closed("reset")
    assert why is not None and "twice" in why and p.fall_back(why, SERVER) and not p.v5


def test_mqtt_5_once_accepted_or_configured_is_never_left():
    accepted = _choice("auto")
    accepted.connecting()
    accepted.connack()
    accepted.accepted()
    assert not accepted.fall_back("closed before CONNACK twice", SERVER) and accepted.v5
    fixed = _choice("5")
    assert fixed.v5 and not fixed.fall_back("132", SERVER) and fixed.v5
    old = _choice("3.1.1")
    old.connecting()
    assert not old.v5 and old.closed("reset") is None and old.closed("reset") is None
    assert sum(p.counters["mqtt311_fallbacks"] for p in (accepted, fixed, old)) == 0
