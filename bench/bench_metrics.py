#!/usr/bin/env python3
"""Issue 16 (4) benchmark: what the metrics cost.

slot   — ``MetricsOutput.on_record`` per slot (the only metrics work on the 50 Hz path), net of
         the loop and of a do-nothing output's call, on a realistic mix of records (filled slots
         with RTT, a silent meter, an overrun); median of RUNS runs of N slots each.
scrape — one scrape at the HTTP endpoint's cost (snapshots of S stations with their drivers'
         counters, rendering, text exposition), for 1, 8 and 16 stations: median of RUNS.
wire   — (--wire ROUNDS) `hookwatch run` against `hookwatch sim` over pseudo-terminals
         (bench_station.py's wire run), alternately without metrics and with metrics scraped
         every --scrape-s seconds: slots filled and lateness of each run.

    bench/bench_metrics.py [--runs 7] [--slots 200000] [--wire 2 --duration 60 --scrape-s 1]
"""
from __future__ import annotations

import argparse
import math
import os
import socket
import statistics
import sys
import time
from types import SimpleNamespace

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)

from prometheus_client import CollectorRegistry  # noqa: E402
from prometheus_client.exposition import generate_latest  # noqa: E402

from gateway.core.records import SlotRecord  # noqa: E402
from gateway.outputs import prometheus as M  # noqa: E402


def records() -> list[SlotRecord]:
    out = []
    for k in range(50):
        present = k % 25 != 7                        # a silent meter now and then
        lateness = 0.030 if k == 40 else 0.0002 + (k % 9) * 0.0003
        out.append(SlotRecord(k=k, t=k * 0.02, present=present, t1=0.4 if present else math.nan,
                              t2=0.7 if present else math.nan, q=1 if present else 0, mask=0,
                              ratio=1.75 if present else None, mu=0.3 if present else None,
                              mean_filt=0.5, speed_cmd=120.0, speed_act=119.0, saturated=False,
                              lateness_s=lateness, rtt_s=0.0055 + (k % 5) * 0.001 if present else math.nan))
    return out


def station(name: str):
    return SimpleNamespace(
        id=name, ts=0.02,
        meter=SimpleNamespace(connected=True, counters={k: 3 for k in (
            "reads", "reads_ok", "timeouts", "crc_errors", "garbage", "modbus_exceptions",
            "decode_errors", "stale_replies", "port_lost", "reopened", "not_connected",
            "late_bytes", "errors")}),
        stm32=SimpleNamespace(connected=True, counters={k: 2 for k in (
            "sent", "acked", "naks", "timeouts", "crc_errors", "retries", "port_lost", "reopened",
            "stale", "bad_replies", "keepalives", "failed")}))


class Nothing:
    def on_record(self, rec) -> None:
        pass


def per_slot_ns(out, recs, n: int) -> float:
    on_record = out.on_record
    m = len(recs)
    t0 = time.perf_counter_ns()
    for i in range(n):
        on_record(recs[i % m])
    return (time.perf_counter_ns() - t0) / n


def bench_slot(runs: int, n: int) -> None:
    recs = records()
    out = M.MetricsOutput(station("bench-slot"), "127.0.0.1", 0)
    base, full = [], []
    for _ in range(runs):
        base.append(per_slot_ns(Nothing(), recs, n))
        full.append(per_slot_ns(out, recs, n))
    net = [f - b for f, b in zip(full, base)]
    print(f"slot: on_record {statistics.median(full):.0f} ns per slot (median of {runs} × {n}), "
          f"a do-nothing output {statistics.median(base):.0f} ns, net {statistics.median(net):.0f} ns "
          f"(min {min(net):.0f}, max {max(net):.0f}) = {statistics.median(net) / 20e6 * 100:.4f} % "
          f"of a core at 50 Hz")


def bench_scrape(runs: int) -> None:
    recs = records()
    for n_st in (1, 8, 16):
        outs = [M.MetricsOutput(station(f"bench-{n_st}-{i}"), "127.0.0.1", 0) for i in range(n_st)]
        for o in outs:
            for r in recs * 20:
                o.on_record(r)
        reg = CollectorRegistry(auto_describe=False)
        reg.register(M.SnapshotCollector(lambda outs=outs: [o.snapshot for o in outs]))
        times, size = [], 0
        for _ in range(runs):
            t0 = time.perf_counter()
            size = len(generate_latest(reg))
            times.append(time.perf_counter() - t0)
        print(f"scrape: {n_st:2d} station(s): {statistics.median(times) * 1e3:.2f} ms "
              f"(min {min(times) * 1e3:.2f}), {size / 1024:.1f} KiB of text")


def bench_wire(rounds: int, duration: float, scrape_s: float) -> None:
    import threading
    import urllib.request

    import bench_station

    res: dict[bool, list[dict]] = {False: [], True: []}
    for _ in range(rounds):
        for on in (False, True):
            with socket.socket() as sk:
                sk.bind(("127.0.0.1", 0))
                port = sk.getsockname()[1]
            args = argparse.Namespace(baud=115200, duration=duration, extra_config={
                "metrics": {"enabled": on, "host": "127.0.0.1", "port": port}})
            stop = threading.Event()
            scrapes = [0]

            def scraper(port=port, stop=stop, scrapes=scrapes):
                while not stop.wait(scrape_s):
                    try:
                        with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
                            r.read()
                        scrapes[0] += 1
                    except OSError:
                        pass
            th = threading.Thread(target=scraper, daemon=True)
            if on:
                th.start()
            print(f"metrics {'on' if on else 'off'}: ", end="", flush=True)
            out = bench_station.wire(args)
            stop.set()
            out["scrapes"] = scrapes[0]
            res[on].append(out)
    for on in (False, True):
        rs = res[on]
        print(f"wire, metrics {f'on, scraped every {scrape_s:g} s' if on else 'off'}: {len(rs)} runs of "
              f"{duration:.0f} s: filled median {statistics.median(r['filled_pct'] for r in rs):.3f} %, "
              f"lateness p99 median {statistics.median(r['lateness_ms_p99'] for r in rs):.3f} ms "
              f"(runs {', '.join(format(r['lateness_ms_p99'], '.2f') for r in rs)}), gateway CPU median "
              f"{statistics.median(r['cpu_pct'] for r in rs):.1f} % of a core"
              + (f", scrapes {[r['scrapes'] for r in rs]}" if on else ""))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--slots", type=int, default=200_000)
    ap.add_argument("--wire", type=int, default=0, metavar="ROUNDS")
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--scrape-s", type=float, default=1.0)
    a = ap.parse_args()
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}")
    if a.wire:
        bench_wire(a.wire, a.duration, a.scrape_s)
        return
    bench_slot(a.runs, a.slots)
    bench_scrape(a.runs)


if __name__ == "__main__":
    main()
