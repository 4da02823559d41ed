"""Metrics scraped by Debian's real Prometheus server while `hookwatch run` runs against
`hookwatch sim` (processes talking over pseudo-terminals; everything on loopback)."""
import os
import subprocess
import time

import yaml

from conftest import ROOT
from kit.e2e import run_gateway, station_yaml, virtual_station, wait_log
from kit.prometheus import RULES, prometheus, query, series, wait_for  # noqa: F401 (prometheus: a fixture)
from kit.tools import free_port, require_tool


def test_prometheus_scrapes_a_running_gateway(tmp_path, prometheus):  # noqa: F811 (the fixture)
    mport = free_port()
    with virtual_station(tmp_path, "config/scenarios/quick.yaml") as (_sim, links):
        path = station_yaml(tmp_path, links, name="loom-m", method={"w_ss": 5, "w_hold": 20, "tau": 5})
        with open(path) as f:
            cfg = yaml.safe_load(f)
        cfg["metrics"] = {"enabled": True, "host": "127.0.0.1", "port": mport}
        with open(path, "w") as f:
            yaml.safe_dump(cfg, f)
        gw = run_gateway(tmp_path, path, "--start", "--duration", "120")
        try:
            wait_log(gw, "metrics for Prometheus on", timeout=30)
            api = prometheus(f"127.0.0.1:{mport}")
            plog = lambda: (tmp_path / "prometheus.log").read_text()[-3000:] + "\n" + gw.log()  # noqa: E731

            # the target is up
            up = wait_for(lambda: [r for r in query(api, 'up{job="hookwatch"}') if r["value"][1] == "1"],
                          60, "target up", plog)
            assert up[0]["metric"]["instance"] == f"127.0.0.1:{mport}"

            # the station's series are there, its links up, a test running
            names = wait_for(lambda: {s["__name__"] for s in series(api, '{station="loom-m"}')} >= {
                "hookwatch_slots_total", "hookwatch_slots_filled_total",
                "hookwatch_slot_lateness_seconds_bucket", "hookwatch_meter_rtt_seconds_bucket",
                "hookwatch_link_up", "hookwatch_station_state"} and
                {s["__name__"] for s in series(api, '{station="loom-m"}')}, 30, "station series", plog)
            assert "hookwatch_test_running" in names
            def links():
                return {r["metric"]["link"]: r["value"][1]
                        for r in query(api, 'hookwatch_link_up{station="loom-m"}')}

            wait_for(lambda: links() == {"meter": "1", "stm32": "1"}, 20, "links up", plog)
            # the test runs from slot 0 on, after the start (METHOD.md §3a: zero check, spin-up),
            # during which the station is `starting` and hookwatch_test_running still 0
            wait_for(lambda: [r for r in query(api, 'hookwatch_test_running{station="loom-m"}')
                              if r["value"][1] == "1"], 60, "test running", plog)
            state = query(api, 'hookwatch_station_state{station="loom-m"} == 1')
            assert [r["metric"]["state"] for r in state] in (
                ["baseline_search"], ["monitoring"], ["end_of_life"]), state

            # and moving: slots counted between two queries (50 per second)
            def slots():
                r = query(api, 'hookwatch_slots_total{station="loom-m"}')
                return float(r[0]["value"][1]) if r else None

            first = wait_for(slots, 20, "slots series", plog)
            second = wait_for(lambda: (v := slots()) is not None and v >= first + 100 and v, 20,
                              "slots moving", plog)
            assert second - first >= 100
            # a counter across 5 s of scrapes: it never goes back and it grows (its rate, 50 per
            # second, is a bench/ figure: bench/bench_metrics.py; on a loaded test machine the
            # scrapes' spacing is whatever the machine gives)
            time.sleep(5)
            window = query(api, 'hookwatch_slots_total{station="loom-m"}[6s]')[0]["values"]
            assert len(window) >= 3, window
            vals = [float(v) for _, v in window]
            assert all(a <= b for a, b in zip(vals, vals[1:])) and vals[-1] > vals[0], window
            filled = query(api, 'hookwatch_slots_filled_total{station="loom-m"}')
            assert float(filled[0]["value"][1]) > 0
            # the lateness histogram is a histogram: cumulative buckets, the +Inf one equal to its
            # count (its p99 is a bench/ figure: bench_station.py)
            buckets = {r["metric"]["le"]: float(r["value"][1]) for r in query(
                api, 'hookwatch_slot_lateness_seconds_bucket{station="loom-m"} @ ' + str(window[-1][0]))}
            count = query(api, 'hookwatch_slot_lateness_seconds_count{station="loom-m"} @ '
                          + str(window[-1][0]))
            ordered = [buckets[k] for k in sorted(buckets, key=float)]
            assert all(a <= b for a, b in zip(ordered, ordered[1:])), buckets
            assert count and buckets["+Inf"] == float(count[0]["value"][1]) > 0, (buckets, count)
            # the shipped recording rules evaluate on the live series
            ratio = wait_for(lambda: query(api, 'hookwatch:slots_filled:ratio1m{station="loom-m"}'), 20,
                             "recording rule", plog)
            assert 0.0 <= float(ratio[0]["value"][1]) <= 1.0
        finally:
            gw.stop()


def test_shipped_prometheus_config_and_rules_are_valid():
    promtool = require_tool("promtool")
    for args in (["check", "config", os.path.join(ROOT, "deploy", "prometheus", "prometheus.yml")],
                 ["check", "rules", RULES]):
        p = subprocess.run([promtool, *args], capture_output=True, text=True, timeout=60)
        assert p.returncode == 0, p.stdout + p.stderr
        assert "SUCCESS" in p.stdout + p.stderr
