#!/usr/bin/env python3
"""Issue 34 item 7: the soak — a box of N stations for hours with the site's lives flowing.

One real Mosquitto (free loopback port), one ``hookwatch sim --count N`` (the life-I-0.5 plant,
115200 baud), and ONE ``hookwatch run FLEET_DIR`` carrying the N stations in process-per-station
mode (a supervisor and N workers), ``mqtt.share_lives`` on, each station running one long test
(autostart, t_end 10 h) for the whole soak, and each seeded with ``--seed-lives`` completed tests so
the stations share their lives with one another from the start. Beside them, ``--peers`` site
peers (other stations of the same site, a paho client each) publish *changing* retained lives
snapshots of ``--peer-lives`` lives at ``--peer-rate`` snapshots per second each, and every
``--burst-every`` seconds one of them floods ``--burst`` snapshots as fast as it can (the churn
attack of issue 34).

Every ``--sample-every`` seconds one JSON line goes to ``--out`` (flushed at once, so a partial
run keeps its samples): per gateway process (supervisor and workers) its pid, RSS, threads, open
descriptors and CPU seconds; their sums; Mosquitto's RSS; the disk used by the records folder, the
outboxes and the ``site_lives.json`` files; the snapshots published so far. The gateway ends by
itself after ``--duration`` (``hookwatch run --duration``), the script then writes one ``end``
line with the stations' slot figures (``--stats-json``) and stops everything it started.

    nohup bench/soak_site_lives.py --out /work/coord/soak/lives-soak.jsonl --duration 7500 &
    bench/soak_report.py /work/coord/soak/lives-soak.jsonl     # the bench/README.md table
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

import paho.mqtt.client as paho  # noqa: E402
import yaml  # noqa: E402
from bench_station import EXE, child_pids  # noqa: E402

from gateway.core.method.prior import PastTest  # noqa: E402
from gateway.outputs.mqtt.schema import SCHEMA_VERSION  # noqa: E402
from gateway.outputs.mqtt.sitelives import record_of  # noqa: E402
from kit.broker import Broker  # noqa: E402

SITE, AREA, LINE = "lab", "bench", "l1"
PAGE = os.sysconf("SC_PAGE_SIZE")
TICK = os.sysconf("SC_CLK_TCK")


def base(station: str) -> str:
    return f"hookwatch/{SITE}/{AREA}/{LINE}/{station}"


def past(station: str, i: int, rnd: random.Random) -> PastTest:
    """A plausible completed test of grade I at 0.5 N (a failure, or a hook replaced early)."""
    tid = f"2026010{i % 10}T{i:06d}Z-{station}-{i}"
    if rnd.random() < 0.7:
        x = round(rnd.gauss(24.0, 2.0), 2)
        return PastTest("I", 0.5, "failure", x, k_b=400, n_slots=round(x / 0.02) + 50, ts=0.02,
                        test_id=tid, station=station, t_end=36000.0, end_reason="failure")
    n = rnd.randint(900, 1300)
    return PastTest("I", 0.5, "aborted", None, k_b=400, stop_reasons=("STOPPED",), n_slots=n, ts=0.02,
                    test_id=tid, station=station, t_end=36000.0, end_reason="hook_replaced")


def seed_records(root: pathlib.Path, station: str, n: int) -> None:
    rnd = random.Random(station)
    for i in range(n):
        t = past(station, i, rnd)
        d = root / station / str(t.test_id)
        d.mkdir(parents=True)
        (d / "result.json").write_text(json.dumps({
            "test_id": t.test_id, "station": station, "test_status": "completed" if t.status == "failure"
            else "aborted", "end_reason": t.end_reason, "sample_id": f"{station}-{i}", "grade": "I",
            "t_set": 0.5, "ts": 0.02, "t_end": t.t_end,
            "method": {"status": t.status, "t_life": t.t_life, "k_b": t.k_b, "n_slots": t.n_slots,
                       "stop_reasons": None if t.stop_reasons is None else list(t.stop_reasons)}}))


class Peer(threading.Thread):
    """A station of the site elsewhere: changing retained snapshots at ``rate`` per second; a
    burst of ``burst`` snapshots every ``burst_every`` s (0: never)."""

    def __init__(self, port: int, station: str, n_lives: int, rate: float, burst: int,
                 burst_every: float, stop: threading.Event) -> None:
        super().__init__(daemon=True, name=f"peer-{station}")
        self.port, self.station, self.rate = port, station, rate
        self.burst, self.burst_every, self.stop_ev = burst, burst_every, stop
        self.rnd = random.Random(station)
        self.lives = [past(station, i, self.rnd) for i in range(n_lives)]
        self.next_i = n_lives
        self.sent = 0
        self.c = paho.Client(paho.CallbackAPIVersion.VERSION2, client_id=f"soak-{station}")
        self.c.max_queued_messages_set(0)
        self.c.connect("127.0.0.1", port)
        self.c.loop_start()

    def snapshot(self) -> bytes:
        self.lives = self.lives[1:] + [past(self.station, self.next_i, self.rnd)]   # one test more
        self.next_i += 1
        doc = {"schema": SCHEMA_VERSION, "station": self.station,
               "time": time.strftime("%Y-%m-%dT%H:%M:%S.000Z", time.gmtime()), "seq": self.sent,
               "lives": [record_of(t) for t in self.lives]}
        return json.dumps(doc, separators=(",", ":")).encode()

    def publish(self) -> None:
        self.c.publish(f"{base(self.station)}/lives", self.snapshot(), qos=1, retain=True)
        self.sent += 1

    def run(self) -> None:
        period = 1.0 / self.rate if self.rate > 0 else None
        next_burst = time.monotonic() + self.burst_every if self.burst and self.burst_every else None
        while not self.stop_ev.is_set():
            now = time.monotonic()
            if next_burst is not None and now >= next_burst:
                for _ in range(self.burst):
                    self.publish()
                next_burst = now + self.burst_every
            if period is not None:
                self.publish()
            self.stop_ev.wait(period or 1.0)
        self.c.loop_stop()
        self.c.disconnect()


def proc(pid: int) -> dict | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            parts = f.read().rsplit(")", 1)[1].split()
        with open(f"/proc/{pid}/statm") as f:
            rss = int(f.read().split()[1]) * PAGE
        return {"pid": pid, "rss_mb": round(rss / 1e6, 2), "threads": int(parts[17]),
                "fds": len(os.listdir(f"/proc/{pid}/fd")),
                "cpu_s": round((int(parts[11]) + int(parts[12])) / TICK, 2)}
    except (OSError, IndexError, ValueError):
        return None


def du(path: pathlib.Path, pattern: str = "**/*") -> int:
    n = 0
    for p in path.glob(pattern):
        try:
            if p.is_file() and not p.is_symlink():
                n += p.stat().st_blocks * 512
        except OSError:
            pass
    return n


def sample(gw: subprocess.Popen, broker_pid: int | None, work: pathlib.Path, t0: float,
           peers: list[Peer]) -> dict:
    procs = [p for p in (proc(x) for x in [gw.pid, *child_pids(gw.pid)]) if p is not None]
    mosq = proc(broker_pid) if broker_pid else None
    records = work / "records"
    return {"kind": "sample", "t_s": round(time.monotonic() - t0, 1), "time": time.time(),
            "procs": procs, "n_procs": len(procs),
            "rss_mb_sum": round(sum(p["rss_mb"] for p in procs), 1),
            "rss_mb_max": max((p["rss_mb"] for p in procs), default=0),
            "threads_sum": sum(p["threads"] for p in procs),
            "fds_sum": sum(p["fds"] for p in procs),
            "cpu_s_sum": round(sum(p["cpu_s"] for p in procs), 1),
            "mosquitto": mosq,
            "disk_records_mb": round(du(records) / 1e6, 2),
            "disk_site_lives_mb": round(du(records, "*/site_lives.json") / 1e6, 3),
            "disk_outbox_mb": round(du(work, "**/*outbox*") / 1e6, 3),
            "disk_work_mb": round(du(work) / 1e6, 2),
            "peer_snapshots": sum(p.sent for p in peers),
            "loadavg_1min": os.getloadavg()[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="the samples, JSON lines (appended)")
    ap.add_argument("--stations", type=int, default=8)
    ap.add_argument("--duration", type=float, default=7500.0, help="seconds (default 2 h 05 min)")
    ap.add_argument("--sample-every", type=float, default=180.0)
    ap.add_argument("--seed-lives", type=int, default=40, help="completed tests per station at the start")
    ap.add_argument("--peers", type=int, default=2)
    ap.add_argument("--peer-lives", type=int, default=500)
    ap.add_argument("--peer-rate", type=float, default=0.5, help="snapshots per second per peer")
    ap.add_argument("--burst", type=int, default=400)
    ap.add_argument("--burst-every", type=float, default=900.0)
    ap.add_argument("--work", help="the work folder (default: a new temporary one)")
    args = ap.parse_args()

    work = pathlib.Path(args.work or tempfile.mkdtemp(prefix="hw-soak-lives-"))
    work.mkdir(parents=True, exist_ok=True)
    out = open(args.out, "a", buffering=1)

    def emit(d: dict) -> None:
        out.write(json.dumps(d) + "\n")
        out.flush()

    broker = Broker(work).start()
    stop = threading.Event()
    sims: subprocess.Popen | None = None
    gw: subprocess.Popen | None = None
    peers: list[Peer] = []
    try:
        fleet = work / "fleet"
        (fleet / "stations").mkdir(parents=True)
        records = work / "records"
        names = [f"s{i:02d}" for i in range(args.stations)]
        for n in names:
            seed_records(records, n, args.seed_lives)
        (fleet / "fleet.yaml").write_text(yaml.safe_dump({"defaults": {
            "station": {"site": SITE, "area": AREA, "line": LINE},
            "meter": {"map": os.path.join(ROOT, "config", "meters", "zn-s.yaml")},
            "control": {"dead_band_n": 0.01},
            "test": {"t_set_n": 0.5, "t_end_s": 36000, "autostart": True},
            "recorder": {"dir": str(records)},
            "mqtt": {"enabled": True, "host": "127.0.0.1", "port": broker.port, "share_lives": True},
            "modbus_tcp": {"enabled": False},
            "logging": {"level": "info"}}}))
        scen = os.path.join(ROOT, "config", "scenarios", "life-I-0.5.yaml")
        links = work / "links"
        sims = subprocess.Popen([EXE, "sim", scen, "--count", str(args.stations), "--seed", "1",
                                 "--link-dir", str(links)], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, text=True)
        while True:
            line = sims.stdout.readline() if sims.stdout else ""
            if not line or line.startswith("ready:"):
                break
        for i, n in enumerate(names):
            lk = links / f"sim{i + 1:02d}"
            (fleet / "stations" / f"{n}.yaml").write_text(yaml.safe_dump({
                "station": {"id": n}, "meter": {"port": str(lk / "meter")},
                "stm32": {"port": str(lk / "stm32")}, "test": {"sample_id": f"SOAK-{i}"}}))
        stats = work / "stats.json"
        log = open(work / "gateway.log", "w")
        gw = subprocess.Popen([EXE, "run", str(fleet), "--duration", str(args.duration),
                               "--stats-json", str(stats)], stdout=log, stderr=subprocess.STDOUT)
        t0 = time.monotonic()
        emit({"kind": "start", "time": time.time(), "work": str(work), "stations": args.stations,
              "duration_s": args.duration, "peers": args.peers, "peer_lives": args.peer_lives,
              "peer_rate": args.peer_rate, "burst": args.burst, "burst_every": args.burst_every,
              "seed_lives": args.seed_lives, "gateway_pid": gw.pid, "broker_port": broker.port,
              "exe": EXE, "root": ROOT})
        time.sleep(20)
        peers = [Peer(broker.port, f"peer{k}", args.peer_lives, args.peer_rate, args.burst,
                      args.burst_every, stop) for k in range(args.peers)]
        for p in peers:
            p.start()
        bpid = broker.p.pid if broker.p is not None else None
        next_at = time.monotonic()
        while gw.poll() is None:
            if time.monotonic() >= next_at:
                emit(sample(gw, bpid, work, t0, peers))
                next_at += args.sample_every
            time.sleep(1.0)
        stop.set()
        end: dict = {"kind": "end", "time": time.time(), "t_s": round(time.monotonic() - t0, 1),
                     "rc": gw.returncode, "peer_snapshots": sum(p.sent for p in peers)}
        try:
            end["stats"] = json.loads(stats.read_text())
        except (OSError, ValueError) as e:
            end["stats_error"] = str(e)
        with open(work / "gateway.log", errors="replace") as f:
            text = f.read()
        end["log_lines"] = text.count("\n")
        end["log_lines_site_lives"] = text.count("the site's lives")
        end["log_bytes"] = len(text)
        emit(end)
    finally:
        stop.set()
        if gw is not None and gw.poll() is None:
            gw.send_signal(signal.SIGTERM)
            try:
                gw.wait(60)
            except subprocess.TimeoutExpired:
                gw.kill()
        if sims is not None:
            sims.send_signal(signal.SIGTERM)
            try:
                sims.wait(20)
            except subprocess.TimeoutExpired:
                sims.kill()
        broker.stop()
        out.close()


if __name__ == "__main__":
    main()
