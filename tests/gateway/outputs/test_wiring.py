"""outputs_for(cfg, station): the northbound outputs from a station file (gateway.config)."""
import logging

import yaml

from gateway.config import load_station
from gateway.outputs.mqtt.output import MqttOutput
from gateway.outputs.plc import registers as R
from gateway.outputs.plc.server import ModbusOutput
from gateway.outputs.wiring import outputs_for
from kit.northbound import make_station


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
def test_the_registry_rows_drive_the_worker_the_reload_key_and_the_probe(tmp_path):
    """Issue 35 item 1 (first step): what a fleet worker may leave to its supervisor, which of those
    need every slot record, the supervisor's reload key and the probe's doors and brokers all come
    from the rows of gateway/outputs/wiring.py OUTPUTS."""
    from gateway.commission import probe
    from gateway.outputs import wiring as W
    from gateway.supervisor import worker

    assert worker.SERVED == (*W.BOX_SERVED, "site") and worker.ROW_SERVED is W.ROW_SERVED
    assert set(W.BOX_SERVED) == {"modbus", "sparkplug", "console", "metrics"}
    assert W.ROW_SERVED == {"modbus", "sparkplug", "console"}
    cfg = _cfg(tmp_path, mqtt={"enabled": True}, modbus_tcp={"enabled": True, "port": 1502},
               metrics={"enabled": True, "port": 9108})
    assert W.reload_key(cfg) == (cfg.modbus_tcp, cfg.sparkplug, cfg.metrics)
    assert probe.listen_ports(cfg) == [("modbus_tcp", cfg.modbus_tcp.host, 1502),
                                       ("metrics", cfg.metrics.host, 9108)]
    assert W.broker_sections(cfg) == ["mqtt"]


def test_a_toy_output_in_one_row_is_probed_and_keyed(monkeypatch):
    """A new output is one row: its listening door is checked by the commissioning probe (a port
    held by another socket is reported in use), its section joins the supervisor's reload key."""
    import socket
    import types

    from gateway.commission import probe
    from gateway.outputs import wiring as W

    held = socket.socket()
    held.bind(("127.0.0.1", 0))
    held.listen(1)
    port = held.getsockname()[1]
    try:
        toy = W.OutputRow("toy", "toy", box=True, slot_rows=True, reload=True, broker=False,
                          doors=lambda cfg: [("toy.port", "127.0.0.1", int(cfg.toy.port))], metrics="none")
        monkeypatch.setattr(W, "OUTPUTS", (*W.OUTPUTS, toy))
        cfg = types.SimpleNamespace(toy=types.SimpleNamespace(enabled=True, port=port))
        assert probe.listen_ports(cfg) == [("toy.port", "127.0.0.1", port)]
        f = probe.probe_listen(*probe.listen_ports(cfg)[0])
        assert not f.ok and "toy.port" in f.text and "already in use" in f.text
        assert W.reload_key(cfg) == (None, None, None, cfg.toy)
    finally:
        held.close()


def test_a_row_without_a_field_fails_at_import():
    import pytest

    from gateway.outputs import wiring as W

    with pytest.raises(TypeError, match="metrics"):
        W.OutputRow("toy", "toy", box=True, slot_rows=True, reload=True, broker=False,    # type: ignore[call-arg]
                    doors=W._no_doors)
