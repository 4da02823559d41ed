"""Metrics of the northbound links from real parts: `hookwatch run` against `hookwatch sim`, MQTT
through a real Mosquitto (stopped to make a backlog), the PLC played by mbpoll; the endpoint
scraped over HTTP and parsed with prometheus_client's parser."""
import urllib.request

import yaml
from prometheus_client.parser import text_string_to_metric_families

from kit.broker import Broker
from kit.e2e import run_gateway, station_yaml, virtual_station, wait_log
from kit.northbound import mbpoll
from kit.tools import free_port, require_tool, wait_for


def scrape(port: int) -> dict:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
        text = r.read().decode()
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for f in text_string_to_metric_families(text) for s in f.samples}


def test_mqtt_outbox_and_plc_figures(tmp_path):
    require_tool("mbpoll")
    mport, pport = free_port(), free_port()
    lab = (("station", "nbm"),)
    with Broker(tmp_path) as b, virtual_station(tmp_path, "config/scenarios/quick.yaml") as (_sim, links):
        path = station_yaml(tmp_path, links, name="nbm", mqtt={"enabled": True, "port": b.port},
                            modbus_tcp={"enabled": True, "port": pport, "unit_id": 3})
        with open(path) as f:
            cfg = yaml.safe_load(f)
        cfg["metrics"] = {"enabled": True, "port": mport}
        with open(path, "w") as f:
            yaml.safe_dump(cfg, f)
        gw = run_gateway(tmp_path, path)
        try:
            wait_log(gw, "metrics for Prometheus on", timeout=30)
            m = wait_for(lambda: (x := scrape(mport)).get(("hookwatch_link_up", (("link", "mqtt"), *lab))) == 1
                         and x, 30, what="MQTT link up")
            assert m[("hookwatch_link_operations_total", (("kind", "connects"), ("link", "mqtt"), *lab))] >= 1
            assert ("hookwatch_outbox_messages", lab) in m
            # the PLC reads: served requests counted on the server's listen address
            wait_for(lambda: scrape(mport).get(("hookwatch_plc_listening", (("listen", f"127.0.0.1:{pport}"),)))
                     == 1, 30, what="PLC server listening")
            for _ in range(3):
                rc, _v, err = mbpoll(pport, "-t", "3", "-r", "0", "-c", "4", unit=3)
                assert rc == 0, err
            m = scrape(mport)
            reads = m[("hookwatch_plc_requests_total", (("listen", f"127.0.0.1:{pport}"), ("result", "reads")))]
            assert reads >= 3
            # a write without permission is refused and counted
            mbpoll(pport, "-t", "4", "-r", "0", unit=3, values=(1,))
            m = wait_for(lambda: (x := scrape(mport)).get(
                ("hookwatch_plc_requests_total", (("listen", f"127.0.0.1:{pport}"), ("result", "refused"))), 0) >= 1
                and x, 10, what="refused write counted")
            # the broker goes away: the link is down, messages pile up in the outbox and age
            b.stop()
            m = wait_for(lambda: (x := scrape(mport)).get(("hookwatch_outbox_messages", lab), 0) >= 2
                         and x.get(("hookwatch_link_up", (("link", "mqtt"), *lab))) == 0 and x,
                         30, what="outbox backlog")
            m = wait_for(lambda: (x := scrape(mport))[("hookwatch_outbox_oldest_age_seconds", lab)] >= 1.5
                         and x, 15, what="oldest message ages")
            assert m[("hookwatch_link_errors_total", (("kind", "disconnects"), ("link", "mqtt"), *lab))] >= 1
            # the broker is back: the outbox drains
            b.start()
            wait_for(lambda: scrape(mport).get(("hookwatch_link_up", (("link", "mqtt"), *lab))) == 1, 60,
                     what="MQTT back")
            wait_for(lambda: scrape(mport)[("hookwatch_outbox_messages", lab)] <= 1, 60, what="outbox drained")
        finally:
            gw.stop()
