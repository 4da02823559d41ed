#!/usr/bin/env python3
"""Issues 6 and 16 benchmark: stations per box. N virtual stations (`hookwatch sim`, one process
each, 115200 baud) and ONE `hookwatch run FLEET_DIR` carrying all N stations, for DURATION seconds
each, in process-per-station mode (a supervisor and N workers, the default) and/or in one process
(`--in-process`); per N and mode: the worst station's share of slots filled and slot-lateness p99,
the gateway's CPU (supervisor + workers) per station, the simulators' CPU, the largest worker RSS.

    bench/bench_fleet.py [--counts 1 2 4 8] [--duration 60] [--modes process inprocess]
                         [--sim-exe OTHER/hookwatch --one-sim] [--realtime 20]
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

from bench_station import EXE, child_pids, proc_cpu_rss  # noqa: E402

#: the virtual twins' program (``--sim-exe``) and whether one process hosts them all (``--one-sim``)
SIM_EXE: str | None = None
WARMUP_S = 6.0
#: `hookwatch run --realtime PRIO` (the shipped systemd units use 20); None: normal scheduling
REALTIME: int | None = None
ONE_SIM = True


def _tree(pid: int) -> dict[int, tuple[float, float]]:
    """{pid: (CPU s, RSS MB)} of the gateway and its worker processes."""
    out = {}
    for p in [pid, *child_pids(pid)]:
        try:
            out[p] = proc_cpu_rss(p)
        except (OSError, IndexError):
            pass
    return out


def make_fleet(n: int, prefix: str, extra: dict | None = None, one_sim: bool = True,
               sim_exe: str | None = None) -> tuple[str, str, list]:
    """A fleet folder of n stations on n virtual stations (life-I-0.5, 115200 baud), started;
    returns (work folder, fleet folder, simulator processes). ``extra``: more fleet defaults;
    ``one_sim``: one `hookwatch sim --count N` process for all (else one sim per station);
    ``sim_exe``: the `hookwatch` whose `sim` plays the twins (default: this one)."""
    sim_exe = sim_exe or EXE
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
        p = subprocess.Popen([sim_exe, "sim", scen, "--count", str(n), "--seed", "1", "--link-dir",
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
            p = subprocess.Popen([sim_exe, "sim", scen, "--link-dir", links, "--seed", str(i + 1)],
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


def run_fleet(n: int, duration: float, mode: str = "process") -> dict:
    work, fleet, sims = make_fleet(n, f"hw-bench-fleet{n}-", one_sim=ONE_SIM, sim_exe=SIM_EXE)
    stats = os.path.join(work, "stats.json")
    extra = ["--in-process"] if mode == "inprocess" else []
    if REALTIME:
        extra += ["--realtime", str(REALTIME)]
    gw = subprocess.Popen([EXE, "run", fleet, "--duration", str(duration), "--stats-json", stats,
                           "--log-level", "warning", *extra], stdout=subprocess.DEVNULL,
                          stderr=subprocess.DEVNULL)
    time.sleep(WARMUP_S)                 # start-up (imports, the workers' start barrier) not counted
    first = _tree(gw.pid)
    c_sim0 = sum(proc_cpu_rss(p.pid)[0] for p in sims)
    t0 = time.monotonic()
    last = dict(first)
    rss_worker = rss_sup = 0.0
    c_sim = c_sim0
    wall = 1e-9
    while gw.poll() is None:
        time.sleep(0.5)
        tree = _tree(gw.pid)
        if gw.poll() is not None or gw.pid not in tree:
            break
        last.update(tree)
        for p, (_c, r) in tree.items():
            if p == gw.pid:
                rss_sup = max(rss_sup, r)
            else:
                rss_worker = max(rss_worker, r)
        c_sim = sum(proc_cpu_rss(p.pid)[0] for p in sims)
        wall = time.monotonic() - t0
    gw.wait()
    load = os.getloadavg()[0]
    c_gw = sum(c for p, (c, _r) in last.items()) - sum(c for p, (c, _r) in first.items() if p in last)
    c_sup = last.get(gw.pid, (0.0, 0.0))[0] - first.get(gw.pid, (0.0, 0.0))[0]
    for p in sims:
        p.send_signal(signal.SIGTERM)
    for p in sims:
        p.wait(10)
        p.stdout.close()
    with open(stats) as f:
        st = json.load(f)
    ok_st = [s for s in st.values() if s and "filled_ratio" in s]
    filled = [s["filled_ratio"] for s in ok_st] or [0.0]
    p99 = [s["lateness_ms_p99"] for s in ok_st] or [float("inf")]
    missing = sorted(((s.get("slots", 0) - s.get("filled", 0)), name) for name, s in st.items()
                     if s and "filled_ratio" in s)
    out = {"stations": n, "mode": mode, "duration_s": duration, "realtime": REALTIME,
           "worst_missing": missing[-1] if missing else None, "reported": len(ok_st),
           "worst_filled_pct": 100 * min(filled), "worst_lateness_ms_p99": max(p99),
           "gateway_cpu_pct": 100 * c_gw / wall, "gateway_cpu_pct_per_station": 100 * c_gw / wall / n,
           "sims_cpu_pct": 100 * (c_sim - c_sim0) / wall,
           "rss_mb_worker_max": rss_worker if mode == "process" else rss_sup,
           "rss_mb_supervisor": rss_sup, "loadavg_1min": load,
           "supervisor_cpu_pct": 100 * c_sup / wall if mode == "process" else None}
    ok = (out["reported"] == n and out["worst_filled_pct"] >= 99.9
          and out["worst_lateness_ms_p99"] <= 2.0)
    print(f"{n:2d} stations {mode:9s}: worst filled {out['worst_filled_pct']:.3f} %, worst p99 "
          f"lateness {out['worst_lateness_ms_p99']:.2f} ms, gateway CPU {out['gateway_cpu_pct']:.0f} % "
          f"({out['gateway_cpu_pct_per_station']:.1f} %/station), simulators CPU "
          f"{out['sims_cpu_pct']:.0f} % (of one core), RSS {out['rss_mb_worker_max']:.0f} MB/worker, "
          f"supervisor {out['rss_mb_supervisor']:.0f} MB"
          + (f" {out['supervisor_cpu_pct']:.1f} % CPU" if mode == "process" else "")
          + (f", SCHED_FIFO {REALTIME}" if REALTIME else "")
          + f", load {load:.1f}  {'OK' if ok else 'over goal'}", flush=True)
    out["ok"] = ok
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 2, 4, 8])
    ap.add_argument("--modes", nargs="+", default=["process", "inprocess"],
                    choices=["process", "inprocess"])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--json", help="append the figures to this JSON-lines file")
    ap.add_argument("--sim-exe", help="the `hookwatch` whose `sim` plays the twins (default: this one)")
    ap.add_argument("--realtime", type=int, metavar="PRIO",
                    help="run the gateway with --realtime PRIO (SCHED_FIFO slot loops; the systemd "
                         "units use 20)")
    ap.add_argument("--sim-per-station", action="store_true",
                    help="one `hookwatch sim` process per twin (default: one `sim --count N` for all)")
    args = ap.parse_args()
    global SIM_EXE, ONE_SIM
    SIM_EXE, ONE_SIM = args.sim_exe, not args.sim_per_station
    global REALTIME
    REALTIME = args.realtime
    best = {m: 0 for m in args.modes}
    for n in args.counts:
        for mode in args.modes:          # the two modes back to back: a ratio from one run
            out = run_fleet(n, args.duration, mode)
            if out["ok"]:
                best[mode] = max(best[mode], n)
            if args.json:
                with open(args.json, "a") as f:
                    f.write(json.dumps(out) + "\n")
    for mode in args.modes:
        print(f"{mode}: stations per box within the goals (≥ 99.9 % filled, p99 ≤ 2 ms): {best[mode]}")


if __name__ == "__main__":
    main()
