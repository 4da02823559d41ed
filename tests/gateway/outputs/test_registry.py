"""The output registry (gateway/outputs/registry.py): a station's outputs from its file, the rows
that drive the fleet's worker and supervisor, the probe and the loader, and a plug-in's row."""
import logging
import socket
from dataclasses import dataclass

import pytest
import yaml

from gateway.commission import probe
from gateway.compose import station_outputs
from gateway.config import ConfigError, load_fleet, load_station
from gateway.config import plugins as P
from gateway.config.sections import key
from gateway.outputs import registry as W
from gateway.outputs.mqtt.output import MqttOutput
from gateway.outputs.plc import registers as R
from gateway.outputs.plc.server import ModbusOutput
from gateway.supervisor import worker
from kit.northbound import make_station


def outputs_for(cfg, station):
    """The station's outputs of the registry in one process (``hookwatch run STATION.yaml``)."""
    return station_outputs(cfg, station, [], W.Host(None, True))


def _cfg(tmp_path, **sections):
    cfg = {"station": {"id": "loom-7", "site": "plant a", "area": "hall/2", "line": ""},
           "meter": {"port": "/dev/ttyUSB0"}, "stm32": {"port": "/dev/ttyUSB1"},
           "recorder": {"dir": str(tmp_path / "rec")}, "grades": ["I", "II", "III"], **sections}
    p = tmp_path / "loom-7.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return load_station(str(p))


def test_nothing_unless_enabled(tmp_path):
    assert outputs_for(_cfg(tmp_path), make_station(tmp_path, [])) == []


def test_mqtt_and_modbus_from_the_station_file(tmp_path):
    cfg = _cfg(tmp_path, mqtt={"enabled": True, "prefix": "acme/hw", "port": 1884, "username": "u",
                               "password_env": "HW_SECRET", "telemetry_interval_s": 2.0,
                               "outbox": {"telemetry_budget_mb": 1.5}},
               modbus_tcp={"enabled": True, "port": 1502, "unit_id": 9, "word_order": "little",
                           "writes": {"enabled": True, "allowed_clients": ["10.1.2.3"]}})
    st = make_station(tmp_path, [], station_id="loom-7")
    outs = outputs_for(cfg, st)
    try:
        assert [type(o) for o in outs] == [MqttOutput, ModbusOutput]
        m, mb = outs
        assert m.s.base_topic == "acme/hw/plant a/hall_2/_/loom-7"
        assert (m.s.port, m.s.username, m.s.password_env, m.s.telemetry_interval_s) == (1884, "u", "HW_SECRET", 2.0)
        assert m.s.outbox_path == str(tmp_path / "rec" / "loom-7" / "outbox.sqlite")
        assert m.s.telemetry_budget_bytes == int(1.5 * 1024 * 1024)
        assert (mb.s.port, mb.s.unit_id, mb.word_order) == (1502, 9, "little")
        assert mb.writes_enabled and mb.allowed_clients == frozenset({"10.1.2.3"})
        assert mb.station is st and m.station is st
        # the MQTT link reaches the PLC through the station's state, not through the MQTT output
        assert not hasattr(mb, "mqtt_connected") and st.state.mqtt_ok is False
        assert not mb.values()["status"] & (1 << R.STATUS_BIT["mqtt_connected"])
        st.outputs.extend(outs)
        st.set_uplink("mqtt", True)
        assert mb.values()["status"] & (1 << R.STATUS_BIT["mqtt_connected"])
    finally:
        for o in outs:
            if isinstance(o, MqttOutput):
                o.outbox.close()


def test_an_outbox_that_cannot_be_opened_is_reported_and_the_station_runs_on(tmp_path, caplog):
    blocker = tmp_path / "file"
    blocker.write_text("")
    cfg = _cfg(tmp_path, mqtt={"enabled": True, "outbox": {"path": str(blocker / "sub" / "o.sqlite")}})
    with caplog.at_level(logging.ERROR, logger="hookwatch.northbound"):
        outs = outputs_for(cfg, make_station(tmp_path, []))
    assert outs == []
    assert "mqtt.outbox.path" in caplog.text and "loom-7" in caplog.text


# ----------------------------------------------------------------------------- the output registry
def test_a_station_gets_its_outputs_in_the_registry_order_in_one_process_and_as_a_worker(tmp_path):
    """``build_station`` builds from the rows: the retention first, then MQTT, Modbus TCP,
    Sparkplug, the metrics last (they read the others); as a fleet's worker whose supervisor
    serves the PLC unit, the Sparkplug device and the metrics, only MQTT and the metrics' feed
    (counting, no endpoint of its own) are built there."""
    from gateway.compose import build_station

    cfg = _cfg(tmp_path, mqtt={"enabled": True}, modbus_tcp={"enabled": True}, sparkplug={"enabled": True},
               metrics={"enabled": True})
    for served, names in ((frozenset(), ["RetentionOutput", "MqttOutput", "ModbusOutput", "SparkplugOutput",
                                         "MetricsOutput"]),
                          (frozenset({"modbus", "sparkplug", "metrics"}),
                           ["RetentionOutput", "MqttOutput", "MetricsOutput"])):
        st = build_station(cfg, served_by_supervisor=served)
        try:
            assert [type(o).__name__ for o in st.outputs] == names
            assert st.outputs[-1].serve is not bool(served)
        finally:
            for o in st.outputs:
                if isinstance(o, MqttOutput):
                    o.outbox.close()


def test_the_docs_table_of_the_outputs_is_the_registry():
    """docs/architecture.md's table of the outputs says what each row says (its docs entry)."""
    import os

    from conftest import ROOT

    with open(os.path.join(ROOT, "docs", "architecture.md"), encoding="utf-8") as f:
        text = f.read().split("## Adding an output", 1)[1].split("\n## ", 1)[0]
    yn = {"yes": True, "no": False}
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in text.splitlines()
            if line.startswith("| `")]
    assert [(r[0].strip("`"), r[1].strip("`"), yn[r[2]], yn[r[3]], yn[r[4]], yn[r[5]], r[6]) for r in rows] == [
        (r.name, r.section, r.box, r.slot_rows, r.reload, r.northbound, r.metrics) for r in W.BUILTIN]


def test_the_registry_rows_drive_the_worker_the_reload_key_and_the_probe(tmp_path):
    """What a fleet worker may leave to its supervisor, which of those need every slot record,
    the supervisor's reload key and the probe's doors and brokers all come from the rows."""
    assert worker.served_words() == (*W.box_served(), "site")
    assert set(W.box_served()) == {"modbus", "sparkplug", "console", "metrics"}
    assert W.row_served() == {"modbus", "sparkplug", "console"}
    cfg = _cfg(tmp_path, mqtt={"enabled": True}, modbus_tcp={"enabled": True, "port": 1502},
               metrics={"enabled": True, "port": 9108})
    assert W.reload_key(cfg) == (cfg.modbus_tcp, cfg.sparkplug, cfg.metrics)
    assert probe.listen_ports(cfg) == [("modbus_tcp", cfg.modbus_tcp.host, 1502),
                                       ("metrics", cfg.metrics.host, 9108)]
    assert W.brokers(cfg) == [("mqtt", cfg.mqtt)]
    assert W.served_by_box(cfg, W.Host(None, True)) == {"modbus", "metrics"}
    assert W.served_by_box(cfg, W.Host(None, False)) == {"metrics"}      # --no-northbound


@dataclass(frozen=True, kw_only=True)
class ToyConfig:
    enabled: bool = key(False, "on", kind="bool")
    host: str = key("127.0.0.1", "address", kind="str")
    port: int = key(7777, "port", kind="int", lo=1, hi=65535)


def _toy_doors(cfg):
    t = P.plugin_config(cfg, "toy", ToyConfig)
    return [("toy.port", t.host, t.port)] if t.enabled else []


def _toy_row(*, box: bool):
    return W.plugin_row("toy", ToyConfig, northbound=False, box=box, slot_rows=True, reload=True,
                        build=lambda b: [], feed=None, serve=(lambda b: []) if box else None,
                        broker=W.no_broker, doors=_toy_doors, metrics="none")


@pytest.fixture
def clean_registry(monkeypatch):
    """A registry and a set of plug-in sections of this test's own (the process's come back)."""
    monkeypatch.setattr(W, "_PLUGINS", [])
    monkeypatch.setattr(P, "_SECTIONS", {})
    monkeypatch.setattr(P, "_LOADED", set())


def test_a_plugin_row_brings_its_section_its_door_to_the_probe_and_its_reload_key(tmp_path, clean_registry):
    """A new output is one row: its section is accepted and checked by the loader, its listening
    door is checked by the commissioning probe (a port held by another socket is reported in use),
    its section joins the supervisor's reload key, the worker may leave it to the supervisor and
    streams it every slot record."""
    with pytest.raises(ConfigError, match="toy: unknown key"):
        _cfg(tmp_path, toy={"enabled": True})
    W.register(_toy_row(box=True))
    held = socket.socket()
    held.bind(("127.0.0.1", 0))
    held.listen(1)
    port = held.getsockname()[1]
    try:
        cfg = _cfg(tmp_path, toy={"enabled": True, "port": port})
        assert cfg.plugins == {"toy": ToyConfig(enabled=True, port=port)}
        assert probe.listen_ports(cfg) == [("toy.port", "127.0.0.1", port)]
        f = probe.probe_listen(*probe.listen_ports(cfg)[0])
        assert not f.ok and "toy.port" in f.text and "already in use" in f.text
        assert W.reload_key(cfg) == (cfg.modbus_tcp, cfg.sparkplug, cfg.plugins["toy"], cfg.metrics)
        assert "toy" in worker.served_words() and "toy" in W.row_served()
        assert W.served_by_box(cfg, W.Host(None, True)) == {"toy"}
    finally:
        held.close()
    assert _cfg(tmp_path).plugins == {"toy": ToyConfig()}        # off unless switched on
    with pytest.raises(ConfigError, match=r"loom-7.yaml:\d+: toy.port: 0 is out of range"):
        _cfg(tmp_path, toy={"port": 0})
    with pytest.raises(ConfigError, match="toy.prot: unknown key; did you mean 'port'"):
        _cfg(tmp_path, toy={"prot": 1})


def test_a_per_station_plugin_door_clashes_between_stations(tmp_path, clean_registry):
    """The loader's clash checks read the rows: a plug-in output that listens per station (not
    served by the box) may not share its door with another station of the box. Its section is a
    fleet default like any other (deep-merged), and only there."""
    W.register(_toy_row(box=False))
    fleet = tmp_path / "fleet"
    (fleet / "stations").mkdir(parents=True)
    (fleet / "fleet.yaml").write_text(yaml.safe_dump({"defaults": {"toy": {"enabled": True, "port": 7100}}}))
    for i in range(2):
        (fleet / "stations" / f"s{i}.yaml").write_text(yaml.safe_dump({
            "station": {"id": f"s{i}"}, "meter": {"port": f"/dev/m{i}"}, "stm32": {"port": f"/dev/s{i}"},
            "recorder": {"dir": str(tmp_path / "rec")}}))
    with pytest.raises(ConfigError, match=r"fleet.yaml:\d+: toy.port: 127.0.0.1:7100 is also the toy.port "
                       r"of station s0 .*; toy listens on a port of its own per station"):
        load_fleet(str(fleet))
    (fleet / "stations" / "s1.yaml").write_text((fleet / "stations" / "s1.yaml").read_text() + "toy: {port: 7101}\n")
    assert [c.plugins["toy"] for c in load_fleet(str(fleet))] == [ToyConfig(enabled=True, port=7100),
                                                                 ToyConfig(enabled=True, port=7101)]
    (fleet / "fleet.yaml").write_text(yaml.safe_dump({"toy": {"enabled": True}}))
    with pytest.raises(ConfigError, match="station settings in fleet.yaml go under `defaults:`"):
        load_fleet(str(fleet))


def test_a_row_missing_a_field_or_a_factory_fails_at_import(clean_registry):
    with pytest.raises(TypeError, match="metrics"):
        W.OutputRow("toy", "toy", schema=None, config=lambda c: c.mqtt, wanted=lambda c, h: True,  # type: ignore[call-arg]
                    northbound=False, box=True, slot_rows=True, reload=True, build=None, feed=None,
                    serve=None, broker=W.no_broker, doors=W.no_doors)
    with pytest.raises(TypeError, match="no `serve` factory"):
        W.OutputRow("toy", "toy", schema=None, config=lambda c: c.mqtt, wanted=lambda c, h: True,
                    northbound=False, box=True, slot_rows=True, reload=True, build=lambda b: [],
                    feed=None, serve=None, broker=W.no_broker, doors=W.no_doors, metrics="none")
    with pytest.raises(TypeError, match="no `build` factory"):
        W.OutputRow("toy", "toy", schema=None, config=lambda c: c.mqtt, wanted=lambda c, h: True,
                    northbound=False, box=False, slot_rows=False, reload=False, build=None,
                    feed=None, serve=lambda b: [], broker=W.no_broker, doors=W.no_doors, metrics="none")


def test_a_plugin_takes_no_name_or_section_already_taken(monkeypatch, clean_registry):
    W.register(_toy_row(box=True))
    assert [r.name for r in W.rows()].count("toy") == 1
    with pytest.raises(ValueError, match="registered already"):
        W.register(W.plugin_row("toy", ToyConfig, northbound=False, box=False, slot_rows=False,
                                reload=False, build=lambda b: [], feed=None, serve=None,
                                broker=W.no_broker, doors=W.no_doors, metrics="none"))
    with pytest.raises(ValueError, match="registered already"):
        W.register(W.plugin_row("metrics", ToyConfig, northbound=False, box=False, slot_rows=False,
                                reload=False, build=lambda b: [], feed=None, serve=None,
                                broker=W.no_broker, doors=W.no_doors, metrics="none"))
    with pytest.raises(ValueError, match="a section of every station file"):
        W.register(W.plugin_row("logging", ToyConfig, northbound=False, box=False, slot_rows=False,
                                reload=False, build=lambda b: [], feed=None, serve=None,
                                broker=W.no_broker, doors=W.no_doors, metrics="none"))
    monkeypatch.setenv(P.PLUGINS_ENV, "kit.no_such_plugin")
    with pytest.raises(ModuleNotFoundError):
        P.load_plugins()
    monkeypatch.setenv(P.PLUGINS_ENV, "kit.crashy:outputs")
    with pytest.raises(ValueError, match="not a module name"):
        P.load_plugins()


def test_an_output_shipped_in_tree_is_its_module_and_one_line(tmp_path, monkeypatch, clean_registry):
    """A new output of the product (an OPC UA server, say) is three places: its module (the
    output, its section's schema and its row: here the toy's), ONE line of ``plugins.IN_TREE``
    and its docs entry. Nothing else names it: without ``$HOOKWATCH_OUTPUTS`` the loader accepts
    its section, the registry builds it, the supervisor serves it, the probe checks its door."""
    import sys
    monkeypatch.delenv(P.PLUGINS_ENV, raising=False)
    monkeypatch.delitem(sys.modules, "kit.toy_output", raising=False)
    assert "toy" not in {r.name for r in W.rows()}
    monkeypatch.setattr(P, "IN_TREE", (*P.IN_TREE, "kit.toy_output"))      # the one line
    P.load_plugins()
    toy = next(r for r in W.rows() if r.name == "toy")
    assert toy.box and toy.slot_rows and toy.reload
    assert "toy" in worker.served_words() and "toy" in W.row_served()
    assert "toy" in {s.spec.name for s in P.sections()}
    cfg = _cfg(tmp_path, toy={"enabled": True, "port": 7101})
    assert W.wanted(cfg, toy, W.Host(None, True)) and probe.listen_ports(cfg) == [("toy.port", "127.0.0.1", 7101)]
