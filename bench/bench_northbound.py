#!/usr/bin/env python3
"""Issue 5 benchmark: the northbound under load, with `hookwatch sim` + `hookwatch run` as
separate processes (real pseudo-terminals, real Mosquitto).

plc     — N PLC clients (default 10) poll M input registers (default 20) as fast as they can
          (one request outstanding per connection, raw Modbus TCP) for DURATION s while the station
          runs a test at 50 Hz; the same gateway is run once without the PLC load. Reports
          requests/s served [goal ≥ 2000] and the station's slot lateness p99 with and without
          the load [goal: unchanged within 1 ms].
latency — a compressed life (end of life after ~1 min) with MQTT: time from the end-of-life
          detection (the alarm's raised_at) to its arrival at mosquitto_sub [goal ≤ 100 ms];
          the other events of the life are reported too.

    bench/bench_northbound.py plc [--duration 60] [--clients 10] [--regs 20] [--rounds 3]
    bench/bench_northbound.py latency [--lives 1]
    bench/bench_northbound.py all
"""
from __future__ import annotations

import argparse
import asyncio
import datetime as dt
import json
import os
import shutil
import signal
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

EXE = os.path.join(os.path.dirname(sys.executable), "hookwatch")
MOSQUITTO = shutil.which("mosquitto") or "/usr/sbin/mosquitto"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout: float = 30.0) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"nothing listens on 127.0.0.1:{port}")


class Bench:
    def __init__(self, work: str):
        self.work = work
        self.procs: list[subprocess.Popen] = []

    def spawn(self, argv, **kw) -> subprocess.Popen:
        p = subprocess.Popen(argv, **kw)
        self.procs.append(p)
        return p

    def sim(self, scenario: str, name: str) -> dict:
        links = os.path.join(self.work, f"links-{name}")
        os.makedirs(links, exist_ok=True)
        p = self.spawn([EXE, "sim", scenario, "--link-dir", links], stdout=subprocess.PIPE,
                       stderr=subprocess.DEVNULL, text=True)
        for _ in range(2):
            p.stdout.readline()
        return {"meter": os.path.join(links, "meter"), "stm32": os.path.join(links, "stm32"), "proc": p}

    def station(self, name: str, links: dict, **sections) -> str:
        import yaml

        cfg = {"station": {"id": name, "site": "lab", "area": "bench", "line": "l1"},
               "meter": {"port": links["meter"], "map": os.path.join(ROOT, "config", "meters", "zn-s.yaml")},
               "stm32": {"port": links["stm32"]}, "control": {"dead_band_n": 0.01},
               "recorder": {"dir": os.path.join(self.work, "records")}, **sections}
        path = os.path.join(self.work, f"{name}.yaml")
        with open(path, "w") as f:
            yaml.safe_dump(cfg, f)
        return path

    def broker(self) -> int:
        import getpass

        port = free_port()
        conf = os.path.join(self.work, f"mosquitto-{port}.conf")
        with open(conf, "w") as f:
            f.write(f"user {getpass.getuser()}\nlistener {port} 127.0.0.1\nallow_anonymous true\n"
                    "persistence false\nlog_type error\n")
        self.spawn([MOSQUITTO, "-c", conf], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wait_port(port)
        return port

    def close(self) -> None:
        for p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
            for s in (p.stdout, p.stderr):
                if s:
                    s.close()


# ------------------------------------------------------------------ PLC load
async def _client(port: int, unit: int, regs: int, t_end: float, counts: list, idx: int) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    tid = 0
    pdu = struct.pack(">BHH", 4, 0, regs)
    n = err = 0
    try:
        while time.monotonic() < t_end:
            tid = (tid + 1) & 0xFFFF
            writer.write(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)
            head = await reader.readexactly(7)
            _tid, _proto, length, _unit = struct.unpack(">HHHB", head)
            body = await reader.readexactly(length - 1)
            if body[0] == 4 and _tid == tid:
                n += 1
            else:
                err += 1
    finally:
        writer.close()
        try:
            await writer.wait_closed()
        except Exception:
            pass
        counts[idx] = (n, err)


def plc_load(port: int, unit: int, clients: int, regs: int, duration: float) -> dict:
    counts = [(0, 0)] * clients

    async def main():
        t_end = time.monotonic() + duration
        await asyncio.gather(*(_client(port, unit, regs, t_end, counts, i) for i in range(clients)))

    t0 = time.monotonic()
    asyncio.run(main())
    el = time.monotonic() - t0
    ok = sum(c[0] for c in counts)
    return {"requests": ok, "errors": sum(c[1] for c in counts), "seconds": round(el, 2),
            "requests_per_s": round(ok / el, 1), "per_client": [c[0] for c in counts]}


def proc_cpu(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")


def _phase(b: Bench, args, broker: int, phase: str, n: int) -> dict:
    scen = os.path.join(ROOT, "config", "scenarios", "life-I-0.5.yaml")
    name = f"bench-{phase}-{n}"
    links = b.sim(scen, name)
    mport = free_port()
    st = b.station(name, links, test={"sample_id": "B-1", "grade": "I", "t_set_n": 0.5, "t_end_s": 36000},
                   mqtt={"enabled": True, "port": broker},
                   modbus_tcp={"enabled": True, "port": mport, "unit_id": 1})
    stats = os.path.join(b.work, f"stats-{name}.json")
    warm = 8.0
    gw = b.spawn([EXE, "run", st, "--start", "--duration", str(args.duration + warm + 1),
                  "--stats-json", stats, "--log-level", "warning"],
                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_port(mport)
    time.sleep(warm)
    cpu0, t0 = proc_cpu(gw.pid), time.monotonic()
    out: dict = {}
    if phase == "loaded":
        out["plc"] = plc_load(mport, 1, args.clients, args.regs, args.duration)
    else:
        time.sleep(args.duration)
    out["gateway_cpu_percent"] = round(100 * (proc_cpu(gw.pid) - cpu0) / (time.monotonic() - t0), 1)
    gw.wait(args.duration + warm + 60)
    links["proc"].send_signal(signal.SIGTERM)
    links["proc"].wait(20)
    with open(stats) as f:
        s = json.load(f)[name]
    out.update({k: s[k] for k in ("slots", "filled_ratio", "overrun_slots", "lateness_ms_p50",
                                  "lateness_ms_p99", "lateness_ms_max")})
    return out


def run_plc(args) -> dict:
    work = tempfile.mkdtemp(prefix="hw-bench-nb-")
    b = Bench(work)
    rounds = []
    try:
        broker = b.broker()
        for n in range(args.rounds):
            order = ("idle", "loaded") if n % 2 == 0 else ("loaded", "idle")
            r = {ph: _phase(b, args, broker, ph, n) for ph in order}
            r["delta_p99_ms"] = round(r["loaded"]["lateness_ms_p99"] - r["idle"]["lateness_ms_p99"], 3)
            rounds.append(r)
            print(f"round {n + 1}: {r['loaded']['plc']['requests_per_s']:.0f} requests/s; lateness p99 "
                  f"idle {r['idle']['lateness_ms_p99']:.2f} ms, loaded {r['loaded']['lateness_ms_p99']:.2f} ms "
                  f"(Δ {r['delta_p99_ms']:+.2f}); gateway CPU {r['idle']['gateway_cpu_percent']:.0f} % → "
                  f"{r['loaded']['gateway_cpu_percent']:.0f} %", flush=True)
    finally:
        b.close()
        shutil.rmtree(work, ignore_errors=True)
    rps = statistics.median(r["loaded"]["plc"]["requests_per_s"] for r in rounds)
    errs = sum(r["loaded"]["plc"]["errors"] for r in rounds)
    p_idle = statistics.median(r["idle"]["lateness_ms_p99"] for r in rounds)
    p_load = statistics.median(r["loaded"]["lateness_ms_p99"] for r in rounds)
    d = statistics.median(r["delta_p99_ms"] for r in rounds)
    print(f"PLC load: {args.clients} clients × {args.regs} input registers, {args.duration:.0f} s × "
          f"{args.rounds} round(s): {rps:.0f} requests/s served, {errs} errors [goal ≥ 2000]")
    print(f"  slot lateness p99 (median over rounds): without load {p_idle:.2f} ms, with load {p_load:.2f} ms, "
          f"median Δ {d:+.2f} ms [goal: within 1 ms]")
    return {"rounds": rounds, "requests_per_s": rps, "lateness_p99_idle_ms": p_idle,
            "lateness_p99_loaded_ms": p_load, "delta_p99_ms": d}


# ------------------------------------------------------------------ EoL latency
def _parse(s: str) -> float:
    return dt.datetime.strptime(s, "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=dt.UTC).timestamp()


def run_latency(args) -> dict:
    import yaml

    work = tempfile.mkdtemp(prefix="hw-bench-nb-")
    b = Bench(work)
    lat_alarm, lat_events = [], []
    try:
        broker = b.broker()
        for i in range(args.lives):
            sc = {"description": "bench life", "seed": 7 + i,
                  "meter": {"map": os.path.join(ROOT, "config", "meters", "zn-s.yaml")},
                  "stm32": {"watchdog_s": 0.2}, "plant": {"grade": "I", "t_set": 0.5, "time_scale": 600},
                  "method": {"w_ss": 5, "w_hold": 20, "tau": 5, "t_end": 70}, "faults": []}
            scp = os.path.join(work, f"life{i}.yaml")
            with open(scp, "w") as f:
                yaml.safe_dump(sc, f)
            links = b.sim(scp, f"life{i}")
            name = f"life{i}"
            st = b.station(name, links, method={"w_ss": 5, "w_hold": 20, "tau": 5},
                           test={"sample_id": "L-1", "grade": "I", "t_set_n": 0.5, "t_end_s": 70},
                           mqtt={"enabled": True, "port": broker})
            sub = b.spawn(["mosquitto_sub", "-h", "127.0.0.1", "-p", str(broker), "-q", "1", "-t",
                           f"hookwatch/lab/bench/l1/{name}/#", "-F", "%t\t%p"],
                          stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
            got: list = []

            def reader(sub=sub, got=got):
                for line in sub.stdout:
                    got.append((time.time(), line.rstrip("\n")))
            t = threading.Thread(target=reader, daemon=True)
            t.start()
            time.sleep(0.5)
            gw = b.spawn([EXE, "run", st, "--start", "--exit-when-done", "--log-level", "warning"],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            gw.wait(240)
            time.sleep(1.0)
            sub.terminate()
            t.join(5)
            links["proc"].send_signal(signal.SIGTERM)
            links["proc"].wait(20)
            for t_recv, line in got:
                topic, _, payload = line.partition("\t")
                try:
                    p = json.loads(payload)
                except json.JSONDecodeError:
                    continue
                if topic.endswith("/alarm/end_of_life") and p.get("state") == "active":
                    lat_alarm.append((t_recv - _parse(p["raised_at"])) * 1e3)
                elif "/event/" in topic:
                    lat_events.append((p["type"], (t_recv - _parse(p["time"])) * 1e3))
    finally:
        b.close()
        shutil.rmtree(work, ignore_errors=True)
    if lat_alarm:
        print(f"end of life → mosquitto_sub: {', '.join(f'{x:.1f}' for x in lat_alarm)} ms "
              f"(median {statistics.median(lat_alarm):.1f} ms) [goal ≤ 100 ms]")
    else:
        print("end of life → mosquitto_sub: no alarm received (the life did not reach its end)")
    for typ, ms in lat_events:
        print(f"  event {typ} → mosquitto_sub: {ms:.1f} ms")
    return {"alarm_ms": [round(x, 2) for x in lat_alarm],
            "events_ms": [(k, round(v, 2)) for k, v in lat_events]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=("plc", "latency", "all"))
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--clients", type=int, default=10)
    ap.add_argument("--regs", type=int, default=20)
    ap.add_argument("--lives", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=1, help="plc: idle/loaded pairs (order alternates)")
    ap.add_argument("--json", metavar="PATH", help="also write the figures here")
    args = ap.parse_args()
    res = {}
    if args.what in ("plc", "all"):
        res["plc"] = run_plc(args)
    if args.what in ("latency", "all"):
        res["latency"] = run_latency(args)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
