#!/usr/bin/env python3
"""Issue 4 benchmark: the station runtime at 50 Hz.

wire   — `hookwatch sim` and `hookwatch run` as separate processes over pseudo-terminals, for
         DURATION seconds at a given meter baud: share of slots filled, slot lateness
         p50/p99/max, meter round-trip time, CPU and resident memory of the gateway process.
memory — a compressed 10-hour test (1.8 M slots at the paper's method defaults) through the real
         Station loop in one process, on a virtual clock, with the plant model behind in-memory
         ports: resident memory sampled along the way (must stay flat).

    bench/bench_station.py wire --baud 115200 --duration 600
    bench/bench_station.py wire --baud 19200 --duration 600
    bench/bench_station.py wire --duration 90 --revs main HEAD --rounds 3
    bench/bench_station.py memory [--hours 10]

``--revs`` runs the gateway of each git revision in turn (its tree exported to a temporary folder
and put first on PYTHONPATH; the simulator is always the working tree's), ``--rounds`` times,
alternating, and prints the median gateway CPU per revision: before/after in one run.
"""
from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

EXE = os.path.join(os.path.dirname(sys.executable), "hookwatch")
TICK = os.sysconf("SC_CLK_TCK")
PAGE = os.sysconf("SC_PAGE_SIZE")


def child_pids(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (read off /proc)."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                        out.append(int(d))
            except (OSError, IndexError, ValueError):
                pass
    return out


def proc_cpu_rss(pid: int) -> tuple[float, float]:
    """(CPU seconds, RSS MB) of a process from /proc."""
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    cpu = (int(parts[11]) + int(parts[12])) / TICK
    with open(f"/proc/{pid}/statm") as f:
        rss = int(f.read().split()[1]) * PAGE / 1e6
    return cpu, rss


def export_rev(rev: str) -> str:
    """The tree of git revision ``rev`` in a temporary folder (for PYTHONPATH)."""
    d = tempfile.mkdtemp(prefix=f"hw-rev-{rev.replace('/', '_')}-")
    arch = subprocess.run(["git", "-C", ROOT, "archive", rev, "gateway", "drivers", "config"],
                          capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", d], input=arch, check=True)
    return d


def wire(args, pythonpath: str | None = None) -> dict:
    import yaml

    work = tempfile.mkdtemp(prefix="hw-bench-station-")
    links = os.path.join(work, "links")
    os.makedirs(links)
    scen = os.path.join(ROOT, "config", "scenarios", "life-I-0.5.yaml")
    sim = subprocess.Popen([EXE, "sim", scen, "--link-dir", links, "--baud", str(args.baud)],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for _ in range(2):
        sim.stdout.readline()
    # the meter timeout follows the bus: a poll's wire time plus margin, within the slot
    timeout = 0.015 if args.baud >= 38400 else 0.018
    cfg = {
        "station": {"id": "bench", "site": "lab", "area": "bench", "line": "l1"},
        "meter": {"port": os.path.join(links, "meter"), "map": os.path.join(ROOT, "config", "meters", "zn-s.yaml"),
                  "baud": args.baud, "timeout_s": timeout},
        "stm32": {"port": os.path.join(links, "stm32")},
        "control": {"dead_band_n": 0.01},
        "test": {"sample_id": "B-1", "grade": "I", "t_set_n": 0.5, "t_end_s": 36000},
        "recorder": {"dir": os.path.join(work, "records")},
        "mqtt": {"enabled": False}, "modbus_tcp": {"enabled": False},
        **getattr(args, "extra_config", {}),     # sections another benchmark adds (bench_metrics)
    }
    st = os.path.join(work, "bench.yaml")
    with open(st, "w") as f:
        yaml.safe_dump(cfg, f)
    stats = os.path.join(work, "stats.json")
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    gw = subprocess.Popen([EXE, "run", st, "--start", "--duration", str(args.duration),
                           "--stats-json", stats, "--log-level", "warning"],
                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    # CPU is counted from the end of the warm-up (imports, ports, the §3a start sequence) on
    cpu0, _ = proc_cpu_rss(gw.pid)
    t_start = t0 = time.monotonic()
    rss = []
    warm = args.warmup <= 0
    while gw.poll() is None:
        time.sleep(1.0)
        try:
            c, r = proc_cpu_rss(gw.pid)
            if r <= 0:          # the process has exited (a zombie has no resident pages)
                break
            if not warm and time.monotonic() - t_start >= args.warmup:
                warm, cpu0, t0 = True, c, time.monotonic()
                continue
            cpu = c
            rss.append(r)
            wall = time.monotonic() - t0
        except (OSError, IndexError):
            break
    gw.wait()
    sim.send_signal(signal.SIGTERM)
    sim.wait(10)
    sim.stdout.close()
    with open(stats) as f:
        s = json.load(f)["bench"]
    out = {"rev": getattr(args, "rev", None), "load": os.getloadavg()[0],
           "baud": args.baud, "duration_s": args.duration, "slots": s["slots"],
           "filled_pct": 100.0 * s["filled_ratio"], "overrun_slots": s["overrun_slots"],
           "lateness_ms_p50": s["lateness_ms_p50"], "lateness_ms_p99": s["lateness_ms_p99"],
           "lateness_ms_max": s["lateness_ms_max"], "rtt_ms_median": s["rtt_ms_median"],
           "cpu_pct": 100.0 * (cpu - cpu0) / wall, "rss_mb_first": rss[2] if len(rss) > 2 else math.nan,
           "rss_mb_last": rss[-1] if rss else math.nan}
    print(f"{out['rev'] or 'worktree'}: load {out['load']:.2f}, "
          f"wire @ {args.baud} baud, {args.duration:.0f} s: {out['slots']} slots, filled "
          f"{out['filled_pct']:.3f} % (goal ≥ 99.9 %), overrun {out['overrun_slots']}, lateness "
          f"p50 {out['lateness_ms_p50']:.3f} / p99 {out['lateness_ms_p99']:.3f} / max "
          f"{out['lateness_ms_max']:.2f} ms (goal p99 ≤ 2 ms), meter RTT median "
          f"{out['rtt_ms_median']:.2f} ms, gateway CPU {out['cpu_pct']:.1f} % of one core, RSS "
          f"{out['rss_mb_first']:.0f} → {out['rss_mb_last']:.0f} MB", flush=True)
    return out


# ---------------------------------------------------------------------------------------------
class _Reading:
    __slots__ = ("ch1", "ch2", "rtt_s")

    def __init__(self, a, b):
        self.ch1, self.ch2, self.rtt_s = a, b, 0.0


class _Status:
    def __init__(self, rpm):
        self.actual_rpm = rpm


class PlantMeter:
    """An in-memory meter: the plant's readings at the virtual time of the slot."""
    connected = True

    def __init__(self, plant, vclock):
        self.plant, self.vclock, self.counters = plant, vclock, {}

    async def open(self):
        pass

    async def close(self):
        pass

    async def read(self):
        self.plant.advance_to(self.vclock.now)
        a, b = self.plant.tensions()
        return _Reading(a, b)


class PlantStm32:
    connected = True

    def __init__(self, plant):
        self.plant, self.counters = plant, {}

    async def open(self):
        pass

    async def close(self):
        pass

    async def enable(self):
        self.plant.enable(True)
        return _Status(self.plant.speed_rpm)

    async def set_speed(self, rpm):
        self.plant.set_command(rpm)
        return _Status(self.plant.speed_rpm)

    def post_speed(self, rpm):
        """As the real driver (drivers/stm32/driver.py): the command now, its reply with the next slot."""
        self.plant.set_command(rpm)
        self._posted = True
        return True

    def collect(self):
        if not getattr(self, "_posted", False):
            return None
        self._posted = False
        return _Status(self.plant.speed_rpm)

    async def stop(self, reason=""):
        self.plant.set_command(0.0)
        self.plant.enable(False)
        return _Status(self.plant.speed_rpm)

    async def read_status(self):
        return _Status(self.plant.speed_rpm)


class VirtualClock:
    """A slot clock whose time jumps to each deadline: the loop runs flat out."""

    def __init__(self, ts):
        self.ts = ts
        self.t0 = 0.0
        self.now = 0.0
        self.clock = lambda: self.now

    def deadline(self, k):
        return k * self.ts

    def slot_at(self, t):
        return int(math.floor(t / self.ts + 0.5))

    async def wait_for(self, k, spin_s=0.0):
        self.now = k * self.ts
        await asyncio.sleep(0)      # let the STM32 command of the previous slot go out
        return 0.0


def memory(args) -> dict:
    from drivers.sim.plant import Plant
    from drivers.sim.scenario import load_scenario
    from gateway.core.control import ControlParams
    from gateway.station import station as stmod

    sc = load_scenario(os.path.join(ROOT, "config", "scenarios", "life-I-0.5.yaml"))
    plant = Plant(sc.plant, seed=sc.seed)
    n_slots = int(args.hours * 3600 / 0.02)
    vclock = VirtualClock(0.02)
    work = tempfile.mkdtemp(prefix="hw-bench-mem-")
    st = stmod.Station(station_id="mem", method={}, control=ControlParams(dead_band_n=0.01),
                       meter=PlantMeter(plant, vclock), stm32=PlantStm32(plant), records_dir=work,
                       default_plan=stmod.TestPlan("M-1", "I", 0.5, args.hours * 3600.0),
                       autostart=True)
    st.clock_factory = lambda ts: vclock
    samples = []

    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(st.run(stop, max_slots=n_slots + 10))
        t0 = time.perf_counter()
        step = n_slots // 20
        while not task.done():
            await asyncio.sleep(0.5)
            k = st.stats.slots
            if not samples or k - samples[-1][0] >= step:
                _, rss = proc_cpu_rss(os.getpid())
                samples.append((k, rss, time.perf_counter() - t0))
                print(f"  slot {k:>9,}  ({k * 0.02 / 3600:5.2f} h)  RSS {rss:6.1f} MB", flush=True)
        await task

    t0 = time.perf_counter()
    asyncio.run(main())
    wall = time.perf_counter() - t0
    res = st.results[-1]["method"] if st.results else None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3
    rss_mid = [r for k, r, _ in samples if k > n_slots * 0.1]
    out = {"hours": args.hours, "slots": st.stats.slots, "wall_s": wall,
           "us_per_slot": wall / max(1, st.stats.slots) * 1e6,
           "rss_mb_at_10pct": rss_mid[0] if rss_mid else math.nan,
           "rss_mb_end": samples[-1][1] if samples else math.nan, "rss_mb_peak": peak,
           "status": res and res["status"], "t_life": res and res["t_life"],
           "stop_reasons": res and res["stop_reasons"], "stop_slot": res and res["stop_slot"]}
    print(f"memory: {out['slots']:,} slots ({args.hours} h) in {wall:.0f} s "
          f"({out['us_per_slot']:.0f} µs per slot incl. plant), RSS {out['rss_mb_at_10pct']:.1f} MB at 10 % → "
          f"{out['rss_mb_end']:.1f} MB at the end, peak {peak:.1f} MB (goal flat, ≤ 100 MB); "
          f"result {out['status']}, t_life {out['t_life']}, stop {out['stop_slot']} {out['stop_reasons']}", flush=True)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="mode", required=True)
    w = sub.add_parser("wire")
    w.add_argument("--baud", type=int, default=115200)
    w.add_argument("--duration", type=float, default=600.0)
    w.add_argument("--warmup", type=float, default=15.0,
                   help="seconds before the CPU is counted (start-up excluded; 0: from the start)")
    w.add_argument("--revs", nargs="*", default=None, help="git revisions of the gateway to compare")
    w.add_argument("--rounds", type=int, default=1)
    m = sub.add_parser("memory")
    m.add_argument("--hours", type=float, default=10.0)
    ap.add_argument("--json", help="append the figures to this JSON-lines file")
    args = ap.parse_args()
    if args.mode == "wire" and args.revs:
        import statistics
        paths = {rev: export_rev(rev) for rev in args.revs}
        cpu: dict[str, list[float]] = {rev: [] for rev in args.revs}
        outs = []
        for _ in range(args.rounds):
            for rev in args.revs:
                args.rev = rev
                o = wire(args, paths[rev])
                cpu[rev].append(o["cpu_pct"])
                outs.append(o)
        for rev, v in cpu.items():
            print(f"{rev}: gateway CPU median {statistics.median(v):.2f} % of a core "
                  f"(runs: {', '.join(f'{x:.2f}' for x in v)})", flush=True)
    else:
        outs = [wire(args) if args.mode == "wire" else memory(args)]
    if args.json:
        with open(args.json, "a") as f:
            for out in outs:
                f.write(json.dumps(out) + "\n")


if __name__ == "__main__":
    main()
