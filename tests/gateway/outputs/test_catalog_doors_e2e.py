"""Issue 35 item 2 at the real doors: `hookwatch run` of a virtual station with a running test, its
MQTT output on Mosquitto (mosquitto_sub as the MES), its Modbus TCP server (mbpoll as the PLC), its
Sparkplug device (a primary host with its own decoder), its Prometheus endpoint (scraped over
HTTP) and its console (over HTTP). Each door publishes the catalog's values of the state
(gateway/core/catalog.py): the retained `state` exactly its keys, every row's PLC register readable
and holding the test's values, every row's Sparkplug metric in the DBIRTH at its alias and datatype,
every row's gauge, and the console's labels and a card's values; the same test, sample and
setpoint at every door. The encoders' exactness: tests/gateway/outputs/test_catalog.py."""
import json
import math
import urllib.request

from prometheus_client.parser import text_string_to_metric_families

from gateway.core import catalog
from gateway.outputs.console.feed import values_json
from gateway.outputs.mqtt import schema as S
from gateway.outputs.plc import registers as R
from gateway.outputs.sparkplug import metrics as SM
from kit.broker import Broker, Sub
from kit.e2e import run_gateway, station_yaml, virtual_station, wait_log
from kit.northbound import mbpoll
from kit.sparkplug_host import PrimaryHost, metric_value
from kit.tools import free_port, require_tool, wait_for


def _get(port: int, path: str):
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=5) as r:
        body = r.read().decode()
    return body if path == "/metrics" else json.loads(body)


def _register(port: int, name: str):
    r = R.IR[name]
    rc, v, err = mbpoll(port, "-t", "3", "-r", str(r.address), "-c", str(r.count), unit=3)
    assert rc == 0, err
    return R.decode_value(r, [v[a] & 0xFFFF for a in range(r.address, r.address + r.count)])


def test_every_door_publishes_the_catalog(tmp_path):
    require_tool("mbpoll")
    mport, pport, cport = free_port(), free_port(), free_port()
    with Broker(tmp_path) as b, virtual_station(tmp_path, "config/scenarios/quick.yaml") as (_sim, links):
        sub = Sub(b.port, "hookwatch/#")
        host = PrimaryHost(b.port, "unused", "lab", tmp_path)
        path = station_yaml(tmp_path, links, name="cat", mqtt={"enabled": True, "port": b.port},
                            modbus_tcp={"enabled": True, "port": mport, "unit_id": 3},
                            test={"t_end_s": 600},
                            extra={"sparkplug": {"enabled": True, "port": b.port, "group_id": "lab",
                                                 "edge_node_id": "hall", "data_interval_s": 0.5},
                                   "metrics": {"enabled": True, "port": pport},
                                   "console": {"enabled": True, "listen": [f"127.0.0.1:{cport}"]}})
        gw = run_gateway(tmp_path, path, "--start")
        try:
            wait_log(gw, "metrics for Prometheus on", timeout=30)
            # the MES: the retained state of the running test, exactly the catalog's keys
            msgs = sub.wait(lambda s: [m for m in s.messages("state") if m[2].get("test_id")], 60,
                            what="the state of the running test")
            state = msgs[-1][2]
            rows = [v for v in catalog.CATALOG if v.mqtt]
            assert list(state) == [f.name for f in S.ENVELOPE] + [v.name for v in rows]
            test_id, sample_id, t_set = state["test_id"], state["sample_id"], state["t_set"]
            assert sample_id == "S-1" and t_set == 0.5

            # the PLC: every row's register read by mbpoll; the test's figures as in the state
            plc = {v.plc.name: _register(mport, v.plc.name) for v in catalog.CATALOG if v.plc is not None}
            assert plc["run_test_id"].rstrip(b"\0").decode() == test_id
            assert plc["run_sample_id"].rstrip(b"\0").decode() == sample_id
            assert math.isclose(plc["t_set"], t_set, rel_tol=1e-6)
            assert catalog.TEST_STATES[plc["test_state"]] in ("baseline_search", "monitoring", "end_of_life")
            assert catalog.ALARM_STATES[plc["alarm"]] == "normal"

            # Sparkplug: the DBIRTH has every row's metric at the device's alias base + its index
            birth = host.wait(lambda: [m for m in host.all("DBIRTH") if m.device == "cat"], 30,
                              what="the DBIRTH")[-1]
            got = {m.name: m for m in birth.p.metrics}
            base = SM.device_alias_base("cat")
            for v in catalog.CATALOG:
                if v.sparkplug is not None:
                    m = got[v.sparkplug.name]
                    assert (m.alias, m.datatype) == (base + v.sparkplug.alias,
                                                     int(SM.DataType[v.sparkplug.datatype])), v.name
            by_alias = {m.alias: m.name for m in birth.p.metrics}
            seen = {m.name: metric_value(m) for m in birth.p.metrics}
            host.wait(lambda: any(by_alias.get(x.alias) == "Test/ID" and metric_value(x) == test_id
                                  for d in host.all("DDATA") for x in d.p.metrics)
                      or seen["Test/ID"] == test_id, 30, what="the test's ID")
            sp = dict(seen)
            for d in host.all("DDATA"):
                sp.update({by_alias[x.alias]: metric_value(x) for x in d.p.metrics if x.alias in by_alias})
            assert sp["Test/Sample ID"] == sample_id and math.isclose(sp["Test/Setpoint"], t_set, rel_tol=1e-6)

            # Prometheus: every row's gauge, with the station's label; the test running
            samples = wait_for(lambda: (x := {(s.name, tuple(sorted(s.labels.items()))): s.value
                                              for f in text_string_to_metric_families(_get(pport, "/metrics"))
                                              for s in f.samples}).get(
                ("hookwatch_test_running", (("station", "cat"),))) == 1 and x, 30, what="the test running")
            names = {n for n, _ in samples}
            for v in catalog.CATALOG:
                if v.prometheus is not None and v.prometheus.label:
                    assert {dict(k)[v.prometheus.label] for n, k in samples
                            if n == f"hookwatch_{v.prometheus.name}"} == set(v.choices), v.name
                elif v.prometheus is not None and v.base_type == "bool":
                    assert f"hookwatch_{v.prometheus.name}" in names, v.name
            assert samples[("hookwatch_alarm", (("alarm", "normal"), ("station", "cat")))] == 1

            # the console: the catalog's labels, and a card's values
            assert _get(cport, "/api/values")["values"] == values_json()
            values = _get(cport, "/api/station/cat")["summary"]["values"]
            assert set(values) == {v.name for v in catalog.CATALOG if v.label}
            assert (values["test_id"], values["sample_id"], values["t_set"]) == (test_id, sample_id, t_set)
        finally:
            gw.stop()
            sub.stop()
            host.close()
