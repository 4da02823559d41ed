#!/usr/bin/env python3
"""Issue 16: a virtual fleet that fits on the box. ``hookwatch sim --count N`` (one process, N
virtual stations: plant, meter, STM32) polled like N gateways would: every 20 ms one 4-register
read from each meter and one STM32 frame (READ_STATUS) on each STM32 link; station i polls at
i·20 ms/N into the slot, as a fleet gateway spreads its stations' deadlines (``--same-instant``:
all at the slot start, the worst case: every reply due at about the same moment).

Prints per N: the simulator's CPU (utime + stime from /proc over the window) per station, the
meters' own reply lateness (write time − due time, from the sim's stop events: p50 / p99 / max over
all replies) and the share of replies later than 0.3 ms, and the poller-side reply time median vs.
the arithmetic wire time.

    python bench/bench_sim.py --counts 1 4 8 16 --duration 30 [--runs 3]
"""
import argparse
import json
import os
import selectors
import signal
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

import serial  # noqa: E402

from drivers.meter.meter_map import DEFAULT_MAP_PATH, load_map, with_crc  # noqa: E402
from drivers.stm32 import protocol as sp  # noqa: E402

REQ = with_crc(bytes([1, 3, 0, 0, 0, 4]))
REPLY_LEN = 13


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def run_one(n: int, duration: float, baud: int, same_instant: bool = False) -> dict:
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    with tempfile.TemporaryDirectory(prefix="bench-sim-") as tmp:
        ev = os.path.join(tmp, "events.jsonl")
        p = subprocess.Popen([exe, "sim", "--count", str(n), "--baud", str(baud), "--link-dir",
                              os.path.join(tmp, "links"), "--events", ev],
                             stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        names = []
        while True:
            line = p.stdout.readline()
            if not line or line.startswith("ready:"):
                break
            if line.startswith("meter "):
                names.append(line.split()[1].rstrip(":"))
        meters = {nm: serial.Serial(os.path.join(tmp, "links", nm, "meter"), baud, timeout=0)
                  for nm in names}
        stms = {nm: serial.Serial(os.path.join(tmp, "links", nm, "stm32"), 115200, timeout=0)
                for nm in names}
        sel = selectors.DefaultSelector()
        for nm, s in meters.items():
            sel.register(s.fileno(), selectors.EVENT_READ, ("m", nm))
        for nm, s in stms.items():
            sel.register(s.fileno(), selectors.EVENT_READ, ("s", nm))
        rtimes: list[float] = []
        seq = 0
        time.sleep(0.5)
        c0, w0 = cpu_s(p.pid), time.monotonic()
        t_slot = time.monotonic()
        end = t_slot + duration
        # station i polls at offset i·Ts/N in the slot (as a fleet gateway spreads its stations'
        # deadlines), or all at the slot start with --same-instant
        offs = [0.0 if same_instant else 0.02 * i / len(names) for i in range(len(names))]
        t0: dict[str, float] = {}
        bufs: dict[str, bytes] = {}
        pending: set[str] = set()

        def collect(until: float) -> None:
            while True:
                rem = until - time.monotonic()
                if rem <= 0:
                    return
                for key, _ in sel.select(rem):
                    kind, nm = key.data
                    data = os.read(key.fd, 256)
                    if kind == "m" and nm in pending:
                        bufs[nm] += data
                        if len(bufs[nm]) >= REPLY_LEN:
                            rtimes.append(time.perf_counter() - t0[nm])
                            pending.discard(nm)

        while t_slot < end:
            seq = (seq + 1) & 0xFF
            for i, nm in enumerate(names):
                collect(t_slot + offs[i])
                pending.discard(nm)                    # a reply that missed its slot is dropped
                meters[nm].reset_input_buffer()
                bufs[nm] = b""
                pending.add(nm)
                t0[nm] = time.perf_counter()
                os.write(meters[nm].fileno(), REQ)
                os.write(stms[nm].fileno(), sp.req_read_status(seq))
            t_slot += 0.02
        collect(t_slot + 0.02)
        c1, w1 = cpu_s(p.pid), time.monotonic()
        sel.close()
        for s in list(meters.values()) + list(stms.values()):
            s.close()
        p.send_signal(signal.SIGTERM)
        p.wait(30)
        lat: list[float] = []
        p99: list[float] = []
        late = replies = 0
        with open(ev) as f:
            for line in f:
                e = json.loads(line)
                if e.get("event") == "stop":
                    c = e["counters"]["meter"]
                    replies += c["replies"]
                    late += c["late_replies"]
                    lt = e.get("meter_reply_lateness_ms") or {}
                    if lt:
                        lat.append(lt["p50"])
                        p99.append(lt["p99"])
    expected = load_map(DEFAULT_MAP_PATH).with_overrides(baud=baud).poll_time_s()
    return {"n": n, "cpu_per_station_pct": (c1 - c0) / (w1 - w0) * 100 / n,
            "cpu_total_pct": (c1 - c0) / (w1 - w0) * 100,
            "meter_lateness_p50_ms": statistics.median(lat) if lat else float("nan"),
            "meter_lateness_worst_p99_ms": max(p99) if p99 else float("nan"),
            "late_share_pct": 100.0 * late / max(1, replies), "replies": replies,
            "poll_reply_ms": statistics.median(rtimes) * 1e3 if rtimes else float("nan"),
            "expected_ms": expected * 1e3}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 4, 8, 16])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--baud", type=int, default=115200)
    ap.add_argument("--same-instant", action="store_true",
                    help="poll every station at the slot start (worst case) instead of spread")
    a = ap.parse_args()
    print(f"load average before: {os.getloadavg()[0]:.2f}")
    for n in a.counts:
        rs = [run_one(n, a.duration, a.baud, a.same_instant) for _ in range(a.runs)]
        med = {k: statistics.median(r[k] for r in rs) for k in rs[0]}
        print(f"N={n:2d}: sim CPU {med['cpu_per_station_pct']:.2f} % of a core per station "
              f"({med['cpu_total_pct']:.1f} % total) [goal ≤ 2 %]; meter reply lateness p50 "
              f"{med['meter_lateness_p50_ms'] * 1e3:.0f} µs, worst station p99 "
              f"{med['meter_lateness_worst_p99_ms'] * 1e3:.0f} µs, replies > 0.3 ms late "
              f"{med['late_share_pct']:.2f} % of {int(med['replies'])}; poller-side reply time "
              f"{med['poll_reply_ms']:.2f} ms (wire time {med['expected_ms']:.2f} ms)  "
              f"[{a.runs} run(s), load {os.getloadavg()[0]:.2f}]", flush=True)


if __name__ == "__main__":
    main()
