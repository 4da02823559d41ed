#!/usr/bin/env python3
"""Issue 34 item 1: what a churn of the site's lives costs a station — commands and slots with
and without the churn attack, in one run.

One station as deployed (`hookwatch run STATION.yaml --realtime 20`, MQTT on a real Mosquitto,
`mqtt.share_lives` on) on a virtual station (`hookwatch sim`, the real-time life-I-0.5 plant,
115200 baud). Each run is two tests of ``--phase`` seconds one after the other, started and
stopped by an MES (a paho client): the first without anything else (control), the second under the
churn attack — another station of the site publishes ``--burst`` changing lives snapshots of 500
lives back to back, then ``--rate`` a second until the test ends. During both the MES sends an
``ack`` a second and measures each command's round trip (publish → reply). Per test: the round
trips (median, max; the stop's too), slots filled (1 − MISSING / slots of the test, its
result.json) and MISSING; per run the ratios churn / control. ``--runs`` runs; the medians over
the runs at the end.

    bench/bench_site_churn.py [--runs 3] [--phase 30] [--burst 400] [--rate 20] [--rev main]

``--no-share``: the station does not take the site's lives (``mqtt.share_lives: false``): what
the flood alone costs on this machine (the peer and the broker beside the station).

``--rev REV``: the gateway of git revision REV (e.g. ``main`` before issue 34) instead of this
tree's (the simulator and the MES stay this tree's); a command not answered within ``--phase``
+ 120 s counts as lost.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import subprocess
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.append(os.path.join(ROOT, "tests"))
sys.path.insert(0, HERE)

import paho.mqtt.client as paho  # noqa: E402
import yaml  # noqa: E402
from bench_stall import GC_PROBE  # noqa: E402
from bench_station import EXE, export_rev  # noqa: E402
from paho.mqtt.enums import CallbackAPIVersion  # noqa: E402

import gateway.core.method.prior  # noqa: E402,F401  (before kit: tests/gateway must not shadow it)
from kit.broker import Broker  # noqa: E402
from kit.site_peer import SitePeer  # noqa: E402

BASE = "hookwatch/lab/test/l1/st"


class Mes:
    """Commands with request ids; the time of each reply (paho, MQTT 5, QoS 1)."""

    def __init__(self, port: int) -> None:
        self.sent: dict[str, float] = {}
        self.answered: dict[str, tuple[float, bool]] = {}
        self.lock = threading.Lock()
        self.c = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"mes-{port}", protocol=paho.MQTTv5)
        self.c.on_message = self._on_message
        self.c.connect("127.0.0.1", port)
        self.c.subscribe(f"{BASE}/reply", qos=1)
        self.c.loop_start()
        time.sleep(0.5)

    def _on_message(self, _c, _u, msg) -> None:
        try:
            d = json.loads(msg.payload)
        except ValueError:
            return
        with self.lock:
            rid = d.get("request_id")
            if rid in self.sent and rid not in self.answered:
                self.answered[rid] = (time.monotonic(), bool(d.get("ok")))

    def send(self, kind: str, rid: str, **args) -> None:
        with self.lock:
            self.sent[rid] = time.monotonic()
        self.c.publish(f"{BASE}/cmd/{kind}", json.dumps({**args, "request_id": rid}), qos=1)

    def rtt(self, rid: str) -> float | None:
        with self.lock:
            a = self.answered.get(rid)
            return None if a is None else a[0] - self.sent[rid]

    def wait(self, rid: str, timeout: float) -> float | None:
        t_end = time.monotonic() + timeout
        while True:
            r = self.rtt(rid)
            if r is not None or time.monotonic() >= t_end:
                return r
            time.sleep(0.02)

    def close(self) -> None:
        self.c.loop_stop()
        self.c.disconnect()


def test_dir(records: pathlib.Path, sample: str) -> pathlib.Path | None:
    d = records / "st"
    if not d.exists():
        return None
    found = [d / x for x in sorted(os.listdir(d)) if x.endswith(sample)]
    return found[0] if found else None


def phase(mes: Mes, records: pathlib.Path, name: str, seconds: float, churn=None) -> dict:
    mes.send("start", f"{name}-start", sample_id=name, grade="I", t_set=0.5)
    t_start = mes.wait(f"{name}-start", 120 + seconds)
    t_end = time.monotonic() + 60
    while test_dir(records, name) is None and time.monotonic() < t_end:
        time.sleep(0.1)
    th = threading.Thread(target=churn, daemon=True) if churn is not None else None
    t0 = time.monotonic()
    if th is not None:
        th.start()
    ids = []
    while time.monotonic() - t0 < seconds:
        rid = f"{name}-ack-{len(ids)}"
        ids.append(rid)
        mes.send("ack", rid)
        time.sleep(1.0)
    mes.send("stop", f"{name}-stop")
    t_stop = mes.wait(f"{name}-stop", 120 + seconds)
    rtts = [mes.wait(r, 120.0) for r in ids]
    if th is not None:
        th.join(600)
    d = test_dir(records, name)
    res = None
    t_end = time.monotonic() + 120
    while d is not None and time.monotonic() < t_end:
        try:
            res = json.loads((d / "result.json").read_text())
            break
        except (OSError, ValueError):
            time.sleep(0.2)
    n = (res or {}).get("method", {}).get("n_slots") or 0
    miss = ((res or {}).get("method", {}).get("reasons") or {}).get("MISSING", 0)
    got = [r for r in rtts if r is not None]
    return {"phase": name, "commands": len(ids) + 2, "lost": sum(r is None for r in rtts)
            + (t_start is None) + (t_stop is None),
            "rtt_median_ms": 1000 * statistics.median(got) if got else None,
            "rtt_max_ms": 1000 * max(got) if got else None,
            "stop_rtt_ms": None if t_stop is None else 1000 * t_stop,
            "slots": n, "missing": miss, "filled_pct": 100.0 * (1 - miss / n) if n else None}


def one_run(args, k: int, gw_env: dict) -> dict:
    work = pathlib.Path(tempfile.mkdtemp(prefix="hw-bench-churn-"))
    broker = Broker(work).start()
    links = work / "links"
    sim = subprocess.Popen([EXE, "sim", os.path.join(ROOT, "config", "scenarios", "life-I-0.5.yaml"),
                            "--link-dir", str(links), "--seed", str(k + 1), "--realtime", "10"], stdout=subprocess.PIPE,
                           stderr=subprocess.DEVNULL, text=True)
    for _ in range(2):
        sim.stdout.readline()
    records = work / "records"
    st = work / "st.yaml"
    st.write_text(yaml.safe_dump({
        "station": {"id": "st", "site": "lab", "area": "test", "line": "l1"},
        "meter": {"port": str(links / "meter"), "map": os.path.join(ROOT, "config", "meters", "zn-s.yaml")},
        "stm32": {"port": str(links / "stm32")}, "control": {"dead_band_n": 0.01},
        "method": {"w_ss": 5, "w_hold": 20, "tau": 5, "stop_after": 5},
        "test": {"sample_id": "S-1", "grade": "I", "t_set_n": 0.5, "t_end_s": 3600},
        "recorder": {"dir": str(records)},
        "mqtt": {"enabled": True, "port": broker.port, "share_lives": not args.no_share},
        "logging": {"level": "info"}}))
    log = open(work / "gw.log", "w")
    env = {**gw_env, "BENCH_GC_OUT": str(work / "gc.json")}
    # the gateway under the garbage collector's probe (bench/bench_stall.py): its pauses by generation
    gw = subprocess.Popen([sys.executable, "-c", GC_PROBE, "run", str(st), "--realtime", "20"], stdout=log,
                          stderr=subprocess.STDOUT, env=env, cwd=str(work))   # `-c` imports from the cwd
    mes = peer = None
    try:
        t_end = time.monotonic() + 120
        while "connected to" not in (work / "gw.log").read_text(errors="replace") and time.monotonic() < t_end:
            time.sleep(0.2)
        time.sleep(2)
        mes = Mes(broker.port)
        control = phase(mes, records, f"CONTROL{k}", args.phase)
        peer = SitePeer(broker.port, "peer", base="hookwatch/lab/test/l1")
        payloads = peer.churn_payloads(args.burst + int(args.rate * args.phase) + 50)
        stop = threading.Event()

        def churn() -> None:
            peer.send_raw(payloads[:args.burst])
            for p in payloads[args.burst:]:
                if stop.is_set():
                    break
                peer.send_raw([p])
                time.sleep(1.0 / args.rate)

        t = threading.Timer(args.phase, stop.set)
        t.start()
        churned = phase(mes, records, f"CHURN{k}", args.phase, churn)
        churned["snapshots"] = peer.sent
    finally:
        if peer is not None:
            peer.close()
        if mes is not None:
            mes.close()
        gw.terminate()
        try:
            gw.wait(60)
        except subprocess.TimeoutExpired:
            gw.kill()
        sim.terminate()
        sim.wait(20)
        broker.stop()
        log.close()
    text = (work / "gw.log").read_text(errors="replace")
    try:
        pauses = json.loads((work / "gc.json").read_text())
    except (OSError, ValueError):
        pauses = []
    churned["gc_gen2"] = sum(1 for g, _ms, built in pauses if g == 2 and built)
    churned["gc_max_ms"] = max((ms for _g, ms, built in pauses if built), default=0.0)
    churned["site_log_lines"] = text.count("the site's lives")
    return {"run": k + 1, "control": control, "churn": churned, "load": os.getloadavg()[0]}


def ratio(a, b) -> float | None:
    return None if a is None or b in (None, 0) else a / b


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--phase", type=float, default=30.0)
    ap.add_argument("--burst", type=int, default=400)
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--rev", help="the gateway of this git revision")
    ap.add_argument("--json", help="append each run as a JSON line here")
    ap.add_argument("--no-share", action="store_true", help="the station with mqtt.share_lives off: the "
                    "flood goes through the broker, the station never takes it (what the flood costs "
                    "the machine, not the station's lives)")
    args = ap.parse_args()
    env = dict(os.environ)
    if args.rev:
        env["PYTHONPATH"] = export_rev(args.rev)
    rows = []
    for k in range(args.runs):
        r = one_run(args, k, env)
        rows.append(r)
        if args.json:
            with open(args.json, "a") as f:
                f.write(json.dumps(r) + "\n")
        c, x = r["control"], r["churn"]
        print(f"run {k + 1} (load {r['load']:.1f}): control: {c['commands']} commands, lost {c['lost']}, "
              f"RTT median {c['rtt_median_ms'] or 0:.1f} ms max {c['rtt_max_ms'] or 0:.1f} ms, stop "
              f"{c['stop_rtt_ms'] or 0:.1f} ms, MISSING {c['missing']} of {c['slots']} "
              f"({c['filled_pct'] or 0:.3f} % filled) | churn ({x['snapshots']} snapshots): "
              f"{x['commands']} commands, lost {x['lost']}, RTT median {x['rtt_median_ms'] or 0:.1f} ms "
              f"max {x['rtt_max_ms'] or 0:.1f} ms, stop {x['stop_rtt_ms'] or 0:.1f} ms, MISSING "
              f"{x['missing']} of {x['slots']} ({x['filled_pct'] or 0:.3f} % filled), "
              f"{x['site_log_lines']} log lines, GC gen-2 {x['gc_gen2']} (max pause {x['gc_max_ms']:.1f} ms) "
              f"| ratios churn/control: RTT median "
              f"{ratio(x['rtt_median_ms'], c['rtt_median_ms']) or 0:.2f}, max "
              f"{ratio(x['rtt_max_ms'], c['rtt_max_ms']) or 0:.2f}, filled "
              f"{ratio(x['filled_pct'], c['filled_pct']) or 0:.4f}", flush=True)

    def med(side: str, key: str) -> float:
        vals = [r[side][key] for r in rows if r[side][key] is not None]
        return statistics.median(vals) if vals else float("nan")
    print(f"medians over {len(rows)} runs{' (rev ' + args.rev + ')' if args.rev else ''}: "
          f"RTT median control {med('control', 'rtt_median_ms'):.1f} / churn {med('churn', 'rtt_median_ms'):.1f} ms; "
          f"RTT max {med('control', 'rtt_max_ms'):.1f} / {med('churn', 'rtt_max_ms'):.1f} ms; stop "
          f"{med('control', 'stop_rtt_ms'):.1f} / {med('churn', 'stop_rtt_ms'):.1f} ms; filled "
          f"{med('control', 'filled_pct'):.3f} / {med('churn', 'filled_pct'):.3f} %; MISSING "
          f"{med('control', 'missing'):.0f} / {med('churn', 'missing'):.0f}; commands lost "
          f"{sum(r['control']['lost'] + r['churn']['lost'] for r in rows)}")


if __name__ == "__main__":
    main()
