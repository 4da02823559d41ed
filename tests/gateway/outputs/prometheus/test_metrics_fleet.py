"""A fleet in one process shares one metrics endpoint; a SIGHUP reload rebuilds the stations
without resetting their slot counters (real `hookwatch run FLEET` against two `hookwatch sim`)."""
import contextlib
import signal
import urllib.request

import yaml
from prometheus_client.parser import text_string_to_metric_families

from kit.e2e import fleet_dir, run_gateway, virtual_station, wait_log
from kit.tools import free_port, wait_for

STATIONS = ("fm-a", "fm-b")


def slots(port: int) -> dict[str, float]:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
        text = r.read().decode()
    return {s.labels["station"]: s.value for f in text_string_to_metric_families(text)
            for s in f.samples if s.name == "hookwatch_slots_total"}


def test_fleet_shares_the_endpoint_and_a_reload_keeps_counting(tmp_path):
    mport = free_port()
    fleet = fleet_dir(tmp_path, metrics={"enabled": True, "port": mport})
    with contextlib.ExitStack() as stack:
        for name in STATIONS:
            sub = tmp_path / name
            sub.mkdir()
            _p, links = stack.enter_context(virtual_station(sub, "config/scenarios/quick.yaml"))
            (fleet / "stations" / f"{name}.yaml").write_text(yaml.safe_dump({
                "station": {"id": name}, "meter": {"port": links["meter"]},
                "stm32": {"port": links["stm32"]}}))
        # a fleet in ONE process (per process: tests/test_supervisor_shared_e2e.py)
        gw = run_gateway(tmp_path, str(fleet), "--in-process")
        try:
            wait_log(gw, "metrics for Prometheus on", timeout=30)
            before = wait_for(lambda: (s := slots(mport)).keys() == set(STATIONS)
                              and min(s.values()) >= 100 and s, 30, what="both stations counting")
            gw.p.send_signal(signal.SIGHUP)
            wait_log(gw, "configuration reloaded; station restarts", timeout=30)
            after = wait_for(lambda: (s := slots(mport)).keys() == set(STATIONS)
                             and all(s[n] >= before[n] + 100 for n in STATIONS) and s, 30,
                             what="counting on after the reload")
            assert all(after[n] > before[n] for n in STATIONS)
            assert gw.log_all().count("metrics for Prometheus on") == 1     # one endpoint, never reopened
        finally:
            gw.stop()
