"""One broker-settings base for the JSON tree's pump and the Sparkplug edge node (issue 15): the
keys users write in `mqtt:` and `sparkplug:` are what they were, and the same keys give the same
broker connection in both (host, port, client ID, keep-alive, user, password, TLS)."""
import dataclasses
import textwrap

import pytest

from gateway.config import load_station
from gateway.config.sections import BrokerConfig, MqttConfig, SparkplugConfig
from gateway.outputs.broker.settings import BrokerSettings, SecretError
from gateway.outputs.mqtt.settings import MqttSettings
from gateway.outputs.registry import mqtt_settings
from gateway.outputs.sparkplug.node_settings import SparkplugSettings
from gateway.outputs.sparkplug.output import settings_from_config

BASE = """\
station: {id: loom-01, site: plant-a, area: hall-2, line: line-3}
meter: {port: /dev/a-meter}
stm32: {port: /dev/a-stm32}
recorder: {dir: REC}
"""
#: the configuration keys of each section before the shared base (they must not change)
MQTT_KEYS = {"enabled", "host", "port", "prefix", "client_id", "keepalive_s", "protocol", "username",
             "password_env", "password_file", "tls", "telemetry_interval_s", "outbox",
             "reply_prefix",                                  # issue 21: MQTT 5 response topics
             "share_lives", "servers",                        # issue 29: site lives, clustered brokers
             "command_doors"}                                 # issue 34: a command budget per door
SPARKPLUG_KEYS = {"enabled", "host", "port", "group_id", "edge_node_id", "device_id", "primary_host_id",
                  "client_id", "username", "password_env", "keepalive_s", "tls", "data_interval_s",
                  "store_path", "history_budget_mb",
                  # issue 21: server sets, inbound bounds, rebirth rate, STATE rule
                  "servers", "max_command_bytes", "max_command_metrics", "max_string_chars",
                  "rebirth_min_interval_s", "state_max_bytes", "state_future_skew_s"}


def names(cls):
    return {f.name for f in dataclasses.fields(cls)}


def test_the_configuration_keys_are_unchanged_and_the_connection_keys_shared():
    assert names(MqttConfig) == MQTT_KEYS
    assert names(SparkplugConfig) == SPARKPLUG_KEYS
    assert issubclass(MqttConfig, BrokerConfig) and issubclass(SparkplugConfig, BrokerConfig)
    assert issubclass(MqttSettings, BrokerSettings) and issubclass(SparkplugSettings, BrokerSettings)


def test_the_same_keys_give_the_same_connection_in_both_sections(tmp_path, monkeypatch):
    pw = tmp_path / "pw"
    pw.write_text("s3cret\n")
    ca, crt, key = (tmp_path / n for n in ("ca.crt", "c.crt", "c.key"))
    conn = textwrap.dedent(f"""\
        {{enabled: true, host: broker.plant, port: 8883, keepalive_s: 45, username: gw,
          password_env: HW_TEST_PW, tls: {{enabled: true, ca_file: {ca}, cert_file: {crt}, key_file: {key}}}}}
        """).strip()
    p = tmp_path / "s.yaml"
    p.write_text(BASE.replace("REC", str(tmp_path / "rec")) + f"mqtt: {conn}\nsparkplug: {conn}\n")
    cfg = load_station(str(p))
    m, s = mqtt_settings(cfg), settings_from_config(cfg)
    shared = [f.name for f in dataclasses.fields(BrokerSettings)]
    assert {k: getattr(m, k) for k in shared if k != "client_id"} == \
        {k: getattr(s, k) for k in shared if k != "client_id"}
    assert (m.host, m.port, m.keepalive_s, m.tls_enabled, m.ca_file) == ("broker.plant", 8883, 45, True, str(ca))
    assert s.servers == [("broker.plant", 8883)]
    monkeypatch.setenv("HW_TEST_PW", "pw-from-env")
    assert m.password() == s.password() == "pw-from-env"
    monkeypatch.delenv("HW_TEST_PW")
    with pytest.raises(SecretError, match=r"^mqtt\.password_env"):
        m.password()
    with pytest.raises(SecretError, match=r"^sparkplug\.password_env"):     # names its own section
        s.password()
    assert MqttSettings("s", "b", password_file=str(pw)).password() == "s3cret"
