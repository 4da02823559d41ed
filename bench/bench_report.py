#!/usr/bin/env python3
"""Issue 7 benchmark: `hookwatch report` over a campaign of 18 ten-hour logs (1.8 M slots each,
.csv.gz, the same row format as bench/gen_long_log.py), with 1 and with 2 worker processes
(`--jobs`). The campaign is generated once into bench/data/campaign10h/ (gitignored) and reused.
Prints the median wall time over several runs, the CPU time, and the speed-up from one process to
two.

    python bench/bench_report.py [--runs 3] [--jobs 1 2] [--no-figures]
"""
import argparse
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import gen_campaign as G  # noqa: E402

DATA = os.path.join(HERE, "data", "campaign10h")
MARK = os.path.join(DATA, ".complete")


def ensure_campaign() -> None:
    if os.path.exists(MARK):
        return
    t0 = time.perf_counter()
    print(f"generating 18 ten-hour logs into {DATA} (once) …", flush=True)
    shutil.rmtree(DATA, ignore_errors=True)
    G.make_campaign(DATA, compress=1, hours=10.0)
    with open(MARK, "w") as f:
        f.write("ok\n")
    print(f"  done in {time.perf_counter() - t0:.0f} s", flush=True)


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def run_once(jobs: int, figures: bool) -> tuple[float, float, str]:
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    with tempfile.TemporaryDirectory() as out:
        args = [exe, "report", DATA, "--out", out, "--jobs", str(jobs), "--quiet"]
        if not figures:
            args.append("--no-figures")
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        p = subprocess.run(args, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        assert p.returncode == 0, p.stderr
        # the workers are children of multiprocessing's fork server, not of this process: take
        # the report's own figure for them, plus what the hookwatch process itself used
        own = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
        line = p.stdout.splitlines()[0]
        worker = float(line.rsplit("analysis CPU", 1)[1].split()[0])
        cpu = own + (worker if jobs > 1 else 0.0)
        return wall, cpu, line


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--jobs", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--no-figures", action="store_true")
    a = ap.parse_args()
    ensure_campaign()
    size = sum(os.path.getsize(os.path.join(d, f)) for d, _, fs in os.walk(DATA) for f in fs)
    print(f"machine: {os.cpu_count()} cores (nproc), {cpu_model()}; load average "
          f"{os.getloadavg()[0]:.2f} at start; campaign {size / 1e6:.0f} MB on disk")
    med = {}
    for jobs in a.jobs:
        walls, cpus = [], []
        for _ in range(a.runs):
            w, c, summary = run_once(jobs, not a.no_figures)
            walls.append(w)
            cpus.append(c)
        med[jobs] = statistics.median(walls)
        print(f"--jobs {jobs}: median {med[jobs]:.1f} s wall (min {min(walls):.1f}, max {max(walls):.1f}) "
              f"over {a.runs} runs; CPU {statistics.median(cpus):.1f} s; {summary}", flush=True)
    if 1 in med and 2 in med:
        print(f"speed-up 1 → 2 processes: {med[1] / med[2]:.2f}×  [goal: report ≤ 20 s on 2 cores]")
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
