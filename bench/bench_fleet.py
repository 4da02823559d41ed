#!/usr/bin/env python3
"""Issue 6 benchmark: stations per box. N virtual stations (one `hookwatch sim --count N`
process, or with --sim-per-station one process each; 115200 baud) and ONE `hookwatch run FLEET_DIR`
carrying all N stations, for DURATION seconds each;
per N: the worst station's share of slots filled and slot-lateness p99, the gateway's CPU and the
simulators' CPU (they count against the same two cores).

    bench/bench_fleet.py [--counts 1 2 4 6 8] [--duration 60]
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

from bench_station import EXE, proc_cpu_rss  # noqa: E402


def make_fleet(n: int, prefix: str, extra: dict | None = None, one_sim: bool = True) -> tuple[str, str, list]:
    """A fleet folder of n stations on n virtual stations (life-I-0.5, 115200 baud), started;
    returns (work folder, fleet folder, simulator processes). ``extra``: more fleet defaults;
    ``one_sim``: one `hookwatch sim --count N` process for all (else one sim per station)."""
    import yaml

    work = tempfile.mkdtemp(prefix=prefix)
    fleet = os.path.join(work, "fleet")
    os.makedirs(os.path.join(fleet, "stations"))
    scen = os.path.join(ROOT, "config", "scenarios", "life-I-0.5.yaml")
    with open(os.path.join(fleet, "fleet.yaml"), "w") as f:
        yaml.safe_dump({"defaults": {
            "station": {"site": "lab", "area": "bench", "line": "l1"},
            "meter": {"map": os.path.join(ROOT, "config", "meters", "zn-s.yaml")},
            "control": {"dead_band_n": 0.01},
            "test": {"t_set_n": 0.5, "t_end_s": 36000, "autostart": True},
            "recorder": {"dir": os.path.join(work, "records")},
            "mqtt": {"enabled": False}, "modbus_tcp": {"enabled": False},
            "logging": {"level": "warning"}, **(extra or {})}}, f)
    sims = []
    if one_sim:
        # one `hookwatch sim --count N` process hosts all N virtual stations (issue 16)
        links_root = os.path.join(work, "links")
        p = subprocess.Popen([EXE, "sim", scen, "--count", str(n), "--seed", "1", "--link-dir",
                              links_root], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        while True:
            line = p.stdout.readline()
            if not line or line.startswith("ready:"):
                break
        sims.append(p)
    for i in range(n):
        if one_sim:
            links = os.path.join(work, "links", f"sim{i + 1:02d}")
        else:
            links = os.path.join(work, f"links{i}")
            os.makedirs(links)
            p = subprocess.Popen([EXE, "sim", scen, "--link-dir", links, "--seed", str(i + 1)],
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
            p.stdout.readline()
            p.stdout.readline()
            sims.append(p)
        with open(os.path.join(fleet, "stations", f"s{i:02d}.yaml"), "w") as f:
            yaml.safe_dump({"station": {"id": f"s{i:02d}"},
                            "meter": {"port": os.path.join(links, "meter")},
                            "stm32": {"port": os.path.join(links, "stm32")},
                            "test": {"sample_id": f"F-{i}"}}, f)
    return work, fleet, sims


def stop_sims_read(sims: list, stats: str) -> dict:
    """Stop the simulators; the gateway's --stats-json figures."""
    for p in sims:
        p.send_signal(signal.SIGTERM)
    for p in sims:
        p.wait(10)
        p.stdout.close()
    with open(stats) as f:
        return json.load(f)


def run_fleet(n: int, duration: float, one_sim: bool = True) -> dict:
    work, fleet, sims = make_fleet(n, f"hw-bench-fleet{n}-", one_sim=one_sim)
    stats = os.path.join(work, "stats.json")
    gw = subprocess.Popen([EXE, "run", fleet, "--duration", str(duration), "--stats-json", stats,
                           "--log-level", "warning"], stdout=subprocess.DEVNULL,
                          stderr=subprocess.DEVNULL)
    time.sleep(2.0)
    c_gw0, _ = proc_cpu_rss(gw.pid)
    c_sim0 = sum(proc_cpu_rss(p.pid)[0] for p in sims)
    t0 = time.monotonic()
    c_gw = c_gw0
    while gw.poll() is None:
        time.sleep(0.5)
        try:
            c, r = proc_cpu_rss(gw.pid)
            if r > 0:
                c_gw = c
                c_sim = sum(proc_cpu_rss(p.pid)[0] for p in sims)
                wall = time.monotonic() - t0
        except (OSError, IndexError):
            break
    gw.wait()
    st = stop_sims_read(sims, stats)
    filled = [s["filled_ratio"] for s in st.values()]
    p99 = [s["lateness_ms_p99"] for s in st.values()]
    out = {"stations": n, "duration_s": duration, "worst_filled_pct": 100 * min(filled),
           "worst_lateness_ms_p99": max(p99), "gateway_cpu_pct": 100 * (c_gw - c_gw0) / wall,
           "sims_cpu_pct": 100 * (c_sim - c_sim0) / wall}
    ok = out["worst_filled_pct"] >= 99.9 and out["worst_lateness_ms_p99"] <= 2.0
    print(f"{n:2d} stations: worst filled {out['worst_filled_pct']:.3f} %, worst p99 lateness "
          f"{out['worst_lateness_ms_p99']:.2f} ms, gateway CPU {out['gateway_cpu_pct']:.0f} %, "
          f"simulators CPU {out['sims_cpu_pct']:.0f} % (of one core)  {'OK' if ok else 'over goal'}",
          flush=True)
    out["ok"] = ok
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 2, 4, 6, 8])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--json", help="append the figures to this JSON-lines file")
    ap.add_argument("--sim-per-station", action="store_true",
                    help="one `hookwatch sim` process per station (before issue 16) instead of one "
                         "`hookwatch sim --count N` for all")
    args = ap.parse_args()
    best = 0
    for n in args.counts:
        out = run_fleet(n, args.duration, not args.sim_per_station)
        if out["ok"]:
            best = max(best, n)
        if args.json:
            with open(args.json, "a") as f:
                f.write(json.dumps(out) + "\n")
    print(f"stations per box within the goals (≥ 99.9 % filled, p99 ≤ 2 ms): {best}")


if __name__ == "__main__":
    main()
