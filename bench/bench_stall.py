#!/usr/bin/env python3
"""Issue 27 item 1: hiccups never end a test. A life beside what makes a box stall.

Each round runs a one-minute life (`hookwatch sim config/scenarios/quick.yaml` and
`hookwatch run --start --realtime 20` over pseudo-terminals, the method's own protection stop of
1 s, the console on) and, some seconds into the test, starts at once beside it:

- Chromium (headless /usr/bin/chromium on the station's console page, its own profile),
- `hookwatch report` on a campaign (bench/gen_campaign.py, made once),
- a `pip install pyyaml` into a fresh venv (from the local wheel cache / find-links),

then prints per round and in sum: aborted tests (must be 0), drive stops by the STM32 twin's
watchdog, the worst slot lateness of the station (its ``--stats-json``), and the garbage
collector's pauses inside the gateway process (a probe wraps ``hookwatch run``: gc.callbacks).

    python bench/bench_stall.py [--rounds 3] [--quiet] [--watchdog 0.2] [--no-freeze]

``--quiet``: the life alone (no Chromium, report, pip). ``--watchdog 0.2``: the gateway sets the
old 0.2 s watchdog (before issue 27). ``--no-freeze``: the gateway without its heap freeze
(gc.freeze after the station is built) — the before/after of the GC pauses in one run.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

EXE = os.path.join(os.path.dirname(sys.executable), "hookwatch")
CHROMIUM = "/usr/bin/chromium"

#: runs ``hookwatch run`` with the garbage collector's pauses recorded (bench only)
GC_PROBE = r"""
import atexit, gc, json, os, sys, time
_t = [0.0]
_built = []          # set when the station is built (the product calls gc.freeze then)
pauses = []
def _cb(phase, info):
    if phase == "start":
        _t[0] = time.perf_counter()
    else:
        pauses.append((info["generation"], (time.perf_counter() - _t[0]) * 1e3, bool(_built)))
gc.callbacks.append(_cb)
_freeze = gc.freeze
def _mark():
    _built.append(1)
    if not os.environ.get("BENCH_NO_FREEZE"):
        _freeze()
gc.freeze = _mark
def _dump():
    with open(os.environ["BENCH_GC_OUT"], "w") as f:
        json.dump(pauses, f)
atexit.register(_dump)
from gateway.cli import main
sys.exit(main(sys.argv[1:]))
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def campaign(work: str) -> str:
    d = os.path.join(work, "campaign")
    subprocess.run([sys.executable, os.path.join(HERE, "gen_campaign.py"), d, "--compress", "100"],
                   check=True, stdout=subprocess.DEVNULL)
    return d


def disturbances(work: str, url: str, camp: str, k: int) -> list[tuple[str, subprocess.Popen]]:
    """Chromium on the console, `hookwatch report`, a pip install: all started at once."""
    out = []
    if os.path.exists(CHROMIUM):
        prof = os.path.join(work, f"chromium-{k}")
        out.append(("chromium", subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--no-first-run", f"--user-data-dir={prof}", url],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)))
    out.append(("report", subprocess.Popen(
        [EXE, "report", camp, "--out", os.path.join(work, f"report-{k}")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)))
    venv = os.path.join(work, f"venv-{k}")
    out.append(("pip", subprocess.Popen(
        ["sh", "-c", f"python3 -m venv {venv} && {venv}/bin/pip install -q pyyaml"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)))
    return out


def one_round(args, work: str, camp: str | None, k: int) -> dict:
    import yaml

    rd = os.path.join(work, f"round-{k}")
    links = os.path.join(rd, "links")
    os.makedirs(links)
    with open(os.path.join(ROOT, "config", "scenarios", "quick.yaml")) as f:
        sc = yaml.safe_load(f)
    sc["meter"]["map"] = os.path.join(ROOT, "config", "meters", "zn-s.yaml")
    scp = os.path.join(rd, "quick.yaml")
    with open(scp, "w") as f:
        yaml.safe_dump(sc, f)
    sim_events = os.path.join(rd, "sim-events.jsonl")
    sim_log = open(os.path.join(rd, "sim.log"), "w")
    nice = ["nice", "-n", str(args.nice)] if args.nice else []
    sim = subprocess.Popen([*nice, EXE, "sim", scp, "--link-dir", links, "--events", sim_events,
                            *([] if args.sim_normal else ["--realtime", "10"])],
                           stdout=subprocess.PIPE, stderr=sim_log, text=True)
    for _ in range(2):
        sim.stdout.readline()
    port = free_port()
    m = sc["method"]
    cfg = {
        "station": {"id": "stall", "site": "lab", "area": "bench", "line": "l1"},
        "meter": {"port": os.path.join(links, "meter"), "map": sc["meter"]["map"]},
        "stm32": {"port": os.path.join(links, "stm32"),
                  **({"watchdog_s": args.watchdog} if args.watchdog else {})},
        "method": {"w_ss": m["w_ss"], "w_hold": m["w_hold"], "tau": m["tau"]},  # stop_after 1 s
        "control": {"dead_band_n": 0.01},
        "test": {"sample_id": f"B-{k}", "grade": "I", "t_set_n": 0.5, "t_end_s": m["t_end"]},
        "recorder": {"dir": os.path.join(rd, "records")},
        "mqtt": {"enabled": False}, "modbus_tcp": {"enabled": False},
        "console": {"enabled": True, "listen": [f"127.0.0.1:{port}"]},
    }
    st = os.path.join(rd, "stall.yaml")
    with open(st, "w") as f:
        yaml.safe_dump(cfg, f)
    stats, gc_out = os.path.join(rd, "stats.json"), os.path.join(rd, "gc.json")
    env = {**os.environ, "BENCH_GC_OUT": gc_out, "PYTHONPATH": ROOT}
    if args.no_freeze:
        env["BENCH_NO_FREEZE"] = "1"
    gw_log = open(os.path.join(rd, "gw.log"), "w")
    gw = subprocess.Popen([*nice, sys.executable, "-c", GC_PROBE, "run", st, "--start", "--realtime", "20",
                           "--duration", str(m["t_end"] + 30), "--exit-when-done",
                           "--stats-json", stats, "--log-level", "warning"],
                          stdout=subprocess.DEVNULL, stderr=gw_log, env=env)
    rec = os.path.join(rd, "records", "stall")
    t_wait = time.monotonic() + 60
    while time.monotonic() < t_wait and not (os.path.isdir(rec) and os.listdir(rec)):
        time.sleep(0.2)
    time.sleep(args.after)
    extra = [] if args.quiet or camp is None else disturbances(
        rd, f"http://127.0.0.1:{port}/#/station/stall", camp, k)
    t_kill = time.monotonic() + 25
    while gw.poll() is None:
        if extra and time.monotonic() > t_kill:
            for _name, p in extra:
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
        time.sleep(0.5)
    for _name, p in extra:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
        try:
            p.wait(20)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    sim.send_signal(signal.SIGTERM)
    sim.wait(10)
    sim.stdout.close()
    sim_log.close()
    gw_log.close()
    results = []
    for dp, _dirs, files in os.walk(rec):
        if "result.json" in files:
            with open(os.path.join(dp, "result.json")) as f:
                results.append(json.load(f))
    with open(stats) as f:
        s = json.load(f)["stall"]
    with open(gc_out) as f:
        pauses = json.load(f)
    stops = []
    if os.path.exists(sim_events):
        with open(sim_events) as f:
            stops = [e for e in map(json.loads, filter(str.strip, f))
                     if e.get("event") == "drive" and not e["enabled"] and e["reason"] == "WATCHDOG"]
    # the passes once the station is built (its slot loop runs): those are the stalls that count
    pauses = [(g, d) for g, d, live in pauses if live]
    gc2 = [d for g, d in pauses if g == 2]
    # the station's own words on late slot starts (a slot passed over late: the process stalled)
    with open(os.path.join(rd, "gw.log")) as f:
        glog = f.read()
    late = [int(a or b) for a, b in re.findall(r"started (\d+) ms late|the worst (\d+) ms late", glog)]
    return {"tests": len(results),
            "aborted": sum(r["test_status"] != "completed" for r in results),
            "end": [r.get("end_reason") for r in results],
            "watchdog_stops": len(stops), "lateness_ms_max": s["lateness_ms_max"],
            "late_start_ms_max": max(late, default=0), "missing": sum(
                r["method"]["reasons"].get("MISSING", 0) for r in results),
            "n_slots": sum(r["method"]["n_slots"] for r in results),
            "status": [r["method"]["status"] for r in results],
            "lateness_ms_p99": s["lateness_ms_p99"], "filled_pct": 100 * s["filled_ratio"],
            "gc_n": len(pauses), "gc_max_ms": max((d for _g, d in pauses), default=0.0),
            "gc2_n": len(gc2), "gc2_max_ms": max(gc2, default=0.0),
            "gc_over_10ms": sum(d > 10 for _g, d in pauses)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--quiet", action="store_true", help="the life alone, nothing started beside it")
    ap.add_argument("--after", type=float, default=8.0, metavar="S",
                    help="start the disturbances this long after the test folder appears")
    ap.add_argument("--watchdog", type=float, default=None, metavar="S",
                    help="stm32.watchdog_s of the station (default: null, stop_after + 0.5 s)")
    ap.add_argument("--no-freeze", action="store_true", help="the gateway without gc.freeze")
    ap.add_argument("--nice", type=int, default=-5, help="niceness of the gateway and the simulator "
                    "(default -5, as the units' Nice=-5; 0: as an ordinary process)")
    ap.add_argument("--sim-normal", action="store_true", help="the simulator at normal priority "
                    "(default: hookwatch sim --realtime 10, as the demo starts it)")
    ap.add_argument("--keep", action="store_true", help="keep the work folder")
    args = ap.parse_args()
    work = tempfile.mkdtemp(prefix="hw-bench-stall-")
    try:
        camp = None if args.quiet else campaign(work)
        rows = []
        for k in range(args.rounds):
            r = one_round(args, work, camp, k)
            rows.append(r)
            print(f"round {k + 1}: load {os.getloadavg()[0]:.1f}; tests {r['tests']}, aborted "
                  f"{r['aborted']} ({', '.join(map(str, r['end']))}); watchdog stops "
                  f"{r['watchdog_stops']}; method status {', '.join(r['status'])}, MISSING "
                  f"{r['missing']} of {r['n_slots']} slots; worst late slot start "
                  f"{r['late_start_ms_max']} ms; lateness of the polled slots max "
                  f"{r['lateness_ms_max']:.1f} ms (p99 {r['lateness_ms_p99']:.2f}), filled "
                  f"{r['filled_pct']:.2f} %; GC "
                  f"{r['gc_n']} passes, max {r['gc_max_ms']:.1f} ms, gen-2 {r['gc2_n']} "
                  f"(max {r['gc2_max_ms']:.1f} ms), {r['gc_over_10ms']} over 10 ms", flush=True)
        wd = (f", watchdog {args.watchdog:g} s" if args.watchdog else "") + f", nice {args.nice}"
        print(f"sum: {len(rows)} rounds ({'quiet' if args.quiet else 'beside chromium, report, pip'}"
              f"{wd}"
              f"{', no gc.freeze' if args.no_freeze else ''}): aborted tests "
              f"{sum(r['aborted'] for r in rows)} (must be 0), watchdog stops "
              f"{sum(r['watchdog_stops'] for r in rows)}, worst late slot start (stall) "
              f"{max(r['late_start_ms_max'] for r in rows)} ms, worst lateness of a polled slot "
              f"{max(r['lateness_ms_max'] for r in rows):.1f} ms, worst GC pause "
              f"{max(r['gc_max_ms'] for r in rows):.1f} ms")
        return 1 if any(r["aborted"] for r in rows) else 0
    finally:
        if args.keep:
            print(f"work folder: {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    raise SystemExit(main())
