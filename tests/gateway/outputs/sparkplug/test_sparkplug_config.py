"""The `sparkplug:` section: defaults, IDs from the plant hierarchy, bad IDs refused with file:line."""
import textwrap

import pytest

from gateway.compose import station_outputs
from gateway.config import ConfigError, load_station
from gateway.outputs.registry import Host
from gateway.outputs.sparkplug.output import settings_from_config

BASE = """\
station: {id: loom-01, site: plant-a, area: hall-2, line: line-3}
meter: {port: /dev/a-meter}
stm32: {port: /dev/a-stm32}
recorder: {dir: REC}
"""


def outputs_for(cfg, station):
    return station_outputs(cfg, station, [], Host(None, True))


def station(tmp_path, extra=""):
    p = tmp_path / "s.yaml"
    p.write_text(BASE.replace("REC", str(tmp_path / "rec")) + textwrap.dedent(extra))
    return load_station(str(p))


def test_defaults_and_ids_from_the_plant_hierarchy(tmp_path):
    cfg = station(tmp_path)
    assert cfg.sparkplug.enabled is False and cfg.sparkplug.primary_host_id is None
    assert outputs_for(cfg, None) == []
    cfg = station(tmp_path, "sparkplug: {enabled: true, primary_host_id: scada-1}\n")
    s = settings_from_config(cfg)
    assert (s.group_id, s.edge_node_id, s.device_id) == ("plant-a", "hall-2-line-3", "loom-01")
    assert s.primary_host_id == "scada-1" and s.servers == [("127.0.0.1", 1883)]
    assert s.store_path == str(tmp_path / "rec" / "sparkplug-plant-a-hall-2-line-3.sqlite")
    outs = outputs_for(cfg, None)
    assert [type(o).__name__ for o in outs] == ["SparkplugOutput"]


@pytest.mark.parametrize("bad", ["group_id: 'a/b'", "edge_node_id: 'x+y'", "device_id: '#'",
                                 "primary_host_id: ''", "port: 0", "data_interval_s: 0.01"])
def test_bad_values_are_refused_with_the_line(tmp_path, bad):
    with pytest.raises(ConfigError) as e:
        station(tmp_path, f"sparkplug:\n  enabled: true\n  {bad}\n")
    assert "sparkplug." in str(e.value) and "s.yaml:" in str(e.value)


def test_server_set_and_the_new_limits(tmp_path):
    cfg = station(tmp_path, "sparkplug: {enabled: true, host: mqtt-a, port: 1884}\n")
    assert settings_from_config(cfg).servers == [("mqtt-a", 1884)]          # the old form
    cfg = station(tmp_path, """\
        sparkplug:
          enabled: true
          port: 1884
          servers: [mqtt-a:1883, mqtt-b, "[fd00::7]:8883"]
          rebirth_min_interval_s: 5
          max_command_bytes: 4096
          max_command_metrics: 16
          max_string_chars: 64
          state_max_bytes: 512
          state_future_skew_s: 60
        """)
    s = settings_from_config(cfg)
    assert s.servers == [("mqtt-a", 1883), ("mqtt-b", 1884), ("fd00::7", 8883)]
    assert (s.rebirth_min_interval_s, s.max_command_bytes, s.max_command_metrics, s.max_string_chars,
            s.state_max_bytes, s.state_future_skew_s) == (5.0, 4096, 16, 64, 512, 60.0)
    from gateway.outputs.sparkplug.runtime import NodeRuntime
    rt = NodeRuntime(s)
    try:
        assert rt.node.limits.max_payload_bytes == 4096 and rt.node.pacing.interval_ms == 5000
        assert rt.node.host.future_skew_ms == 60_000 and rt.node.limits.state_max_bytes == 512
    finally:
        rt.stop()
        if rt.store.outbox is not None:
            rt.store.outbox.close()


@pytest.mark.parametrize("bad", ["servers: []", "servers: ['a:0']", "servers: ['a:b']", "servers: ['::1']",
                                 "servers: ['a:1883', 'a']", "max_command_metrics: 0",
                                 "state_max_bytes: 10", "rebirth_min_interval_s: -1"])
def test_bad_server_sets_and_limits_are_refused(tmp_path, bad):
    with pytest.raises(ConfigError) as e:
        station(tmp_path, f"sparkplug:\n  enabled: true\n  {bad}\n")
    assert "sparkplug." in str(e.value) and "s.yaml:" in str(e.value)
