"""Issue 12, disk state north: the records and the MQTT outbox on a real tmpfs filled during a
test, then freed. The station's `disk_ok` reaches the PLC (status bit, read by mbpoll), the MQTT
state and a `disk_full`/`disk_ok` event per store and transition (through Mosquitto), and
Prometheus' `hookwatch_disk_ok`; the station runs on throughout."""
import os
import time
import urllib.request
from pathlib import Path

from prometheus_client.parser import text_string_to_metric_families

from gateway.outputs import prometheus as M
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from gateway.outputs.plc import registers as R
from gateway.outputs.plc.server import ModbusOutput, ModbusSettings
from kit.broker import Broker, Sub
from kit.northbound import LoopThread, RunningStation, make_station, mbpoll
from kit.smallfs import fill, small_tmpfs
from kit.tools import free_port, require_tool, wait_for

BASE = "hw/disk/st1"
IR = R.IR


def disk_metric(ep) -> float:
    assert ep.listening.wait(5), ep.error
    host, port = ep.address
    with urllib.request.urlopen(f"http://{host}:{port}/metrics", timeout=5) as r:
        text = r.read().decode()
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            if s.name == "hookwatch_disk_ok" and s.labels.get("station") == "st1":
                return s.value
    raise AssertionError(f"no hookwatch_disk_ok in {text[:2000]}")


def plc_disk_bit(port: int) -> int:
    rc, v, err = mbpoll(port, "-t", "3", "-r", str(IR["status"].address), unit=3)
    assert rc == 0, err
    return (v[IR["status"].address] >> R.STATUS_BIT["disk_ok"]) & 1


def disk_events(sub, etype):
    return [m[2] for m in sub.messages(f"event/{etype}") if not m[0]]


def test_full_disk_reaches_plc_mqtt_and_metrics_once_per_transition(tmp_path):
    require_tool("mbpoll")
    mport = free_port()
    with Broker(tmp_path) as b, small_tmpfs(tmp_path / "fs", "2m") as fs:
        sub = Sub(b.port, BASE + "/#")
        lt = LoopThread()
        run = None
        try:
            st = make_station(Path(fs), [], autostart=True, flush_interval_s=0.2)
            mqtt = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, port=b.port,
                                           outbox_path=os.path.join(fs, "outbox.sqlite"),
                                           reconnect_min_s=0.2, reconnect_max_s=1.0,
                                           telemetry_interval_s=0.2), station=st)
            plc = ModbusOutput(ModbusSettings(station_id="st1", port=mport, unit_id=3), station=st)
            met = M.MetricsOutput(st, "127.0.0.1", 0, mqtt=mqtt, modbus=plc)
            st.outputs.extend([mqtt, plc, met])
            run = RunningStation(lt, st)
            wait_for(lambda: st.session is not None, 30, what="the test's slot 0")
            wait_for(lambda: sub.messages("telemetry"), 30, what="telemetry")
            assert plc_disk_bit(mport) == 1 and disk_metric(met.endpoint) == 1.0
            slots0 = st.stats.slots

            filler = fill(fs)
            full = wait_for(lambda: len(disk_events(sub, "disk_full")) >= 2 and disk_events(sub, "disk_full"),
                            90, what="disk_full of the records and the outbox")
            assert sorted(e["data"]["store"] for e in full) == ["outbox", "records"], full
            assert all(e["data"]["reason"] for e in full), full
            assert full[0]["test_id"] == st.test_id
            # each door shows it as it next refreshes (a loaded machine may take a moment)
            wait_for(lambda: plc_disk_bit(mport) == 0, 30, what="the PLC's disk_ok bit cleared")
            wait_for(lambda: disk_metric(met.endpoint) == 0.0, 30, what="the metric's disk_ok 0")
            wait_for(lambda: sub.messages("state")[-1][2]["disk_ok"] is False, 30, what="state disk_ok false")
            time.sleep(3)          # still full: no further event, the station runs on
            assert len(disk_events(sub, "disk_full")) == 2
            assert st.stats.slots > slots0 + 100 and st.session is not None

            os.unlink(filler)
            ok = wait_for(lambda: len(disk_events(sub, "disk_ok")) >= 2 and disk_events(sub, "disk_ok"),
                          90, what="disk_ok of the records and the outbox")
            assert sorted(e["data"]["store"] for e in ok) == ["outbox", "records"], ok
            wait_for(lambda: plc_disk_bit(mport) == 1, 30, what="the PLC's disk_ok bit back")
            wait_for(lambda: disk_metric(met.endpoint) == 1.0, 30, what="the metric's disk_ok 1")
            wait_for(lambda: sub.messages("state")[-1][2]["disk_ok"] is True, 30, what="state disk_ok")
            time.sleep(2)
            assert len(disk_events(sub, "disk_full")) == 2 and len(disk_events(sub, "disk_ok")) == 2
        finally:
            if run is not None:
                run.stop()
            lt.close()
            sub.stop()
            M.shutdown_all()
