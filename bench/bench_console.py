#!/usr/bin/env python3
"""Issue 14 benchmark: the operator console's cost to the slot loop, and how fast a long test draws.

1. ``slots``: 4 virtual stations (`hookwatch sim`, one process each) and ONE `hookwatch run` with the
   console on, for DURATION s, alternately without clients and with 10 browser-like clients (each an
   SSE stream of a station's live data, read as it comes, plus a fleet poll every second);
   per run: the worst station's slot-lateness p99 and share filled, the gateway's CPU and the console
   thread's CPU (from /proc/<pid>/task/*/stat, thread name "console"). Runs alternate so that a
   change of machine load hits both sides.
2. ``long``: a 10-hour test (1.8 M slots) fed through the console's hand-over into its series,
   then the time until a page shows its curve: the HTTP snapshot (GET /api/station/<id>) and, when
   Playwright and /usr/bin/chromium are there, a real browser from navigation to a drawn curve.

    bench/bench_console.py [--duration 60] [--runs 2] [--skip-slots] [--skip-long] [--realtime 20] [--in-process]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)

from bench_fleet import make_fleet, stop_sims_read  # noqa: E402
from bench_station import EXE, proc_cpu_rss  # noqa: E402

#: extra options of `hookwatch run` (--realtime PRIO, --in-process)
RUN_EXTRA: list[str] = []


def console_cpu(base: str) -> float:
    """CPU seconds of the console's thread (it reports its own ``time.thread_time()``)."""
    with urllib.request.urlopen(base + "/api/fleet", timeout=5) as r:
        return json.loads(r.read())["console"]["cpu_s"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class SseClient(threading.Thread):
    """A browser-like client: one live stream, read as it comes, and the fleet every second."""

    def __init__(self, base: str, station: str, stop: threading.Event):
        super().__init__(daemon=True)
        self.base, self.station, self.stop_ev = base, station, stop
        self.messages = 0
        self.bytes = 0

    def run(self):
        host, port = self.base.split("//")[1].split(":")
        s = socket.create_connection((host, int(port)))
        s.sendall(f"GET /api/station/{self.station}/stream HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
        s.settimeout(0.5)
        last_poll = 0.0
        while not self.stop_ev.is_set():
            try:
                b = s.recv(65536)
                if not b:
                    break
                self.bytes += len(b)
                self.messages += b.count(b"data: {")
            except TimeoutError:
                pass
            if time.monotonic() - last_poll >= 1.0:
                last_poll = time.monotonic()
                with urllib.request.urlopen(self.base + "/api/fleet", timeout=5) as r:
                    r.read()
        s.close()


def run_fleet(n: int, duration: float, clients: int) -> dict:
    port = free_port()
    work, fleet, sims = make_fleet(n, f"hw-bench-console{n}-",
                                   {"console": {"enabled": True, "listen": [f"127.0.0.1:{port}"]}})
    stats = os.path.join(work, "stats.json")
    gw = subprocess.Popen([EXE, "run", fleet, "--duration", str(duration), "--stats-json", stats,
                           "--log-level", "warning", *RUN_EXTRA], stdout=subprocess.DEVNULL,
                          stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}"
    t_end = time.monotonic() + 20
    while time.monotonic() < t_end:
        try:
            urllib.request.urlopen(base + "/api/fleet", timeout=1).read()
            break
        except OSError:
            time.sleep(0.2)
    stop = threading.Event()
    cl = [SseClient(base, f"s{i % n:02d}", stop) for i in range(clients)]
    for c in cl:
        c.start()
    time.sleep(1.0)
    c0, _ = proc_cpu_rss(gw.pid)
    k0 = console_cpu(base)
    t0 = time.monotonic()
    c1, k1, wall = c0, k0, 1e-9
    while gw.poll() is None:
        time.sleep(0.5)
        try:
            c, r = proc_cpu_rss(gw.pid)
            k = console_cpu(base)
            if r > 0:
                c1, k1, wall = c, k, time.monotonic() - t0
        except (OSError, IndexError, ValueError, KeyError):
            break
    stop.set()
    for c in cl:
        c.join(5)
    gw.wait()
    st = stop_sims_read(sims, stats)
    out = {"clients": clients, "duration_s": duration,
           "worst_filled_pct": 100 * min(s["filled_ratio"] for s in st.values()),
           "worst_lateness_ms_p99": max(s["lateness_ms_p99"] for s in st.values()),
           "gateway_cpu_pct": 100 * (c1 - c0) / wall, "console_cpu_pct": 100 * (k1 - k0) / wall,
           "messages": sum(c.messages for c in cl), "bytes": sum(c.bytes for c in cl)}
    print(f"{clients:2d} clients: worst p99 lateness {out['worst_lateness_ms_p99']:.2f} ms, worst filled "
          f"{out['worst_filled_pct']:.3f} %, gateway CPU {out['gateway_cpu_pct']:.1f} % "
          f"(the supervisor's, in process mode), console thread "
          f"{out['console_cpu_pct']:.1f} % of a core; clients got {out['messages']} messages "
          f"({out['bytes'] / 1e3:.0f} kB)", flush=True)
    return out


def long_test(hours: float = 10.0) -> dict:
    """A 10-hour test through the hand-over, then time to a drawn curve."""
    from gateway.core.records import Event, EventType, SlotRecord
    from gateway.outputs.console.app import ConsoleServer
    from gateway.outputs.console.feed import ConsoleOutput
    from gateway.outputs.console.settings import ConsoleSettings

    work = tempfile.mkdtemp(prefix="hw-bench-console-long-")
    srv = ConsoleServer(ConsoleSettings(listen=("127.0.0.1:0",), users_file=os.path.join(work, "u.json")),
                        {"long": os.path.join(work, "records", "long")})
    feed = srv.feeds["long"]
    out = ConsoleOutput(feed)
    n = int(hours * 3600 * 50)
    out.on_event(Event(EventType.TEST_STARTED, "long", time.time(), "T", 0, {"t_set": 0.5}))
    t0 = time.perf_counter()
    per_slot = []
    for k in range(n):
        mu = 0.35 + 0.05 * math.sin(k / 50000) + (0.2 if k == n // 3 else 0.0)
        out.on_record(SlotRecord(k=k, t=k * 0.02, present=True, t1=0.4, t2=0.6, q=1, mask=0, ratio=1.5,
                                 mu=mu, mean_filt=0.5, speed_cmd=100.0, speed_act=99.0, saturated=False))
        if len(feed.q) > 4000:
            t1 = time.perf_counter()
            m = len(feed.q)
            feed.drain()
            per_slot.append((time.perf_counter() - t1) / m)
    feed.drain()
    fill_s = time.perf_counter() - t0
    urls = srv.start()
    base = urls[0].rstrip("/")
    http_t = []
    size = 0
    for _ in range(7):
        t1 = time.perf_counter()
        with urllib.request.urlopen(base + "/api/station/long", timeout=10) as r:
            body = r.read()
        http_t.append(time.perf_counter() - t1)
        size = len(body)
    res = {"slots": n, "buckets": len(feed.series.buckets), "bucket_s": feed.series.width * 0.02,
           "drain_us_per_slot": statistics.median(per_slot) * 1e6, "fill_s": fill_s,
           "snapshot_bytes": size, "snapshot_http_ms_median": statistics.median(http_t) * 1e3}
    try:
        from playwright.sync_api import sync_playwright
        have_browser = os.path.exists("/usr/bin/chromium")
    except ImportError:
        have_browser = False
    if have_browser:
        args = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-component-update", "--disable-sync"]
        times = []
        with sync_playwright() as p:
            b = p.chromium.launch(executable_path="/usr/bin/chromium", args=args)
            ctx = b.new_context(bypass_csp=True)
            for _ in range(5):
                page = ctx.new_page()
                t1 = time.perf_counter()
                page.goto(base + "/#/station/long")
                page.wait_for_function("window.hw && window.hw.points > 1000", polling="raf", timeout=20000)
                times.append(time.perf_counter() - t1)
                page.close()
            b.close()
        res["browser_curve_s_median"] = statistics.median(times)
        res["browser_curve_s_all"] = [round(x, 3) for x in times]
    srv.stop()
    print(f"10-hour test: {n} slots → {res['buckets']} buckets of {res['bucket_s']:.1f} s; console-side "
          f"drain {res['drain_us_per_slot']:.2f} µs/slot; snapshot {size / 1e3:.0f} kB in "
          f"{res['snapshot_http_ms_median']:.1f} ms (HTTP, median of 7)"
          + (f"; browser from navigation to drawn curve: median {res['browser_curve_s_median']:.2f} s "
             f"({res['browser_curve_s_all']})" if "browser_curve_s_median" in res else ""), flush=True)
    return res


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stations", type=int, default=4)
    ap.add_argument("--clients", type=int, default=10)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--runs", type=int, default=2, help="pairs of runs (without / with clients)")
    ap.add_argument("--skip-slots", action="store_true")
    ap.add_argument("--skip-long", action="store_true")
    ap.add_argument("--json", help="append the figures to this JSON-lines file")
    ap.add_argument("--realtime", type=int, metavar="PRIO", help="hookwatch run --realtime PRIO")
    ap.add_argument("--in-process", action="store_true",
                    help="hookwatch run --in-process (default: a worker per station, the console "
                         "in the supervisor)")
    args = ap.parse_args()
    RUN_EXTRA.extend((["--realtime", str(args.realtime)] if args.realtime else [])
                     + (["--in-process"] if args.in_process else []))
    results = []
    if not args.skip_long:
        results.append({"long": long_test()})
    if not args.skip_slots:
        without, with_ = [], []
        for _ in range(args.runs):
            without.append(run_fleet(args.stations, args.duration, 0))
            with_.append(run_fleet(args.stations, args.duration, args.clients))
        p0 = statistics.median(r["worst_lateness_ms_p99"] for r in without)
        p1 = statistics.median(r["worst_lateness_ms_p99"] for r in with_)
        cpu = statistics.median(r["console_cpu_pct"] for r in with_)
        cpu0 = statistics.median(r["console_cpu_pct"] for r in without)
        print(f"median worst p99 lateness: {p0:.2f} ms without clients, {p1:.2f} ms with {args.clients} "
              f"(difference {p1 - p0:+.2f} ms; goal ≤ +0.5 ms); console thread {cpu0:.1f} % → {cpu:.1f} % "
              "of a core", flush=True)
        results.append({"without": without, "with": with_})
    if args.json:
        with open(args.json, "a") as f:
            for r in results:
                f.write(json.dumps(r) + "\n")


if __name__ == "__main__":
    main()
