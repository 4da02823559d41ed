#!/usr/bin/env python3
"""Issue 21 benchmark: a flood on one door at a time, and what a running station keeps.

One virtual station (`hookwatch sim`) and one `hookwatch run` with the console, the metrics
endpoint and the PLC's Modbus TCP port on; the PLC (127.0.0.1, the allow-listed client) reads the
input registers every 100 ms throughout. Each run lasts DURATION s; after a few seconds one door
is flooded from another loopback address (127.0.0.3):

- ``none``: no flood (the reference of the same run series);
- ``console``: IDLE idle TCP connections to the console, held to the end;
- ``metrics``: IDLE idle TCP connections to the metrics endpoint;
- ``modbus``: 80 connections that each send a valid read request every 10 ms;
- ``trickle``: 64 connections to each HTTP door sending one byte every 2 s;
- ``sse``: live-stream (SSE) connects as fast as they are answered (connect churn);
- ``hooks``: HOOKS ``hook_replaced`` commands (issue 27: each with a new sample id) from the
  allow-listed PLC (127.0.0.1) as fast as they are answered: the station's command desk carries
  out a burst and then its rate (code 14 RATE_LIMITED, exception 06 for the rest); reported: the
  commands accepted and refused and the lines in hooks.jsonl (= accepted).

Per run: the station's slots filled (% of the grid), slot-lateness p99 (ms), the PLC's reads that
failed, and whether the test was aborted. The goal (issue 21): ≥ 99.9 % of the slots and the PLC
link kept under a flood on any one door, no test aborted.

    bench/bench_doors.py [--duration 40] [--idle 3000] [--doors none,console,…,hooks] [--hooks 1000]
                         [--in-process]
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import struct
import subprocess
import sys
import threading
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, ROOT)

from bench_fleet import make_fleet, stop_sims_read  # noqa: E402
from bench_station import EXE  # noqa: E402

FLOOD_FROM = "127.0.0.3"
#: extra options of `hookwatch run` (--in-process: the doors in the station's own process)
RUN_EXTRA: list[str] = []


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _conn(port: int, timeout: float = 2.0) -> socket.socket | None:
    s = socket.socket()
    s.settimeout(timeout)
    try:
        s.bind((FLOOD_FROM, 0))
        s.connect(("127.0.0.1", port))
        return s
    except OSError:
        s.close()
        return None


class Plc(threading.Thread):
    """The allow-listed PLC: a raw Modbus TCP read of 8 input registers every 100 ms."""

    def __init__(self, port: int, stop: threading.Event):
        super().__init__(daemon=True)
        self.port, self.stop = port, stop
        self.ok = self.failed = 0
        self.errors: dict[str, int] = {}

    def run(self) -> None:
        tid = 0
        sock = None
        while not self.stop.is_set():
            try:
                if sock is None:
                    sock = socket.create_connection(("127.0.0.1", self.port), timeout=2)
                tid = (tid + 1) & 0xFFFF
                sock.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 4, 0, 8))
                data = sock.recv(256)
                if len(data) >= 9 and data[7] == 4:
                    self.ok += 1
                else:
                    raise OSError("bad reply")
            except OSError as e:
                self.failed += 1
                self.errors[type(e).__name__ + (f" {e}" if str(e) == "bad reply" else "")] = \
                    self.errors.get(type(e).__name__, 0) + 1
                if sock is not None:
                    sock.close()
                sock = None
            self.stop.wait(0.1)
        if sock is not None:
            sock.close()


def flood(kind: str, ports: dict[str, int], idle: int, stop: threading.Event) -> list[socket.socket]:
    held: list[socket.socket] = []
    if kind in ("console", "metrics"):
        for _ in range(idle):
            if stop.is_set():
                break
            s = _conn(ports[kind])
            if s is not None:
                held.append(s)
    elif kind == "modbus":
        def busy():
            s = _conn(ports["modbus"])
            tid = 0
            while s is not None and not stop.is_set():
                tid = (tid + 1) & 0xFFFF
                try:
                    s.sendall(struct.pack(">HHHBBHH", tid, 0, 6, 1, 4, 0, 8))
                    s.recv(256)
                except OSError:
                    s.close()
                    s = _conn(ports["modbus"])
                stop.wait(0.01)
        for _ in range(80):
            threading.Thread(target=busy, daemon=True).start()
    elif kind == "trickle":
        def trickle(port):
            s = _conn(port)
            while s is not None and not stop.is_set():
                try:
                    s.sendall(b"G")
                except OSError:
                    s.close()
                    s = _conn(port)
                stop.wait(2.0)
        for door in ("console", "metrics"):
            for _ in range(64):
                threading.Thread(target=trickle, args=(ports[door],), daemon=True).start()
    elif kind == "hooks":
        threading.Thread(target=_hook_flood, args=(ports["modbus"], HOOKS[0], stop), daemon=True).start()
    elif kind == "sse":
        def churn():
            while not stop.is_set():
                s = _conn(ports["console"])
                if s is None:
                    continue
                try:
                    s.sendall(b"GET /api/station/s00/stream HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
                    s.recv(512)
                except OSError:
                    pass
                s.close()
        for _ in range(8):
            threading.Thread(target=churn, daemon=True).start()
    return held


#: hook_replaced commands of the ``hooks`` flood; what the gateway answered
HOOKS = [1000]
HOOK_ANSWERS: dict[str, int] = {}


def _hook_flood(port: int, n: int, stop: threading.Event) -> None:
    """The PLC's hook_replaced n times: the new hook's sample id, then command 5 (FC 16 each)."""
    from gateway.outputs.plc import registers as R

    sid, cmd = R.HR["sample_id"], R.HR["command"]
    s = socket.create_connection(("127.0.0.1", port), timeout=5)

    def write(tid: int, addr: int, regs: list[int]) -> int:
        body = struct.pack(">BHHB", 16, addr, len(regs), 2 * len(regs)) + struct.pack(f">{len(regs)}H", *regs)
        s.sendall(struct.pack(">HHHB", tid, 0, len(body) + 1, 1) + body)
        data = s.recv(256)
        return data[8] if len(data) >= 9 and data[7] & 0x80 else 0

    try:
        for i in range(n):
            if stop.is_set():
                break
            write(2 * i & 0xFFFF, sid.address, R.encode_value(sid, f"F-{i}"))
            exc = write((2 * i + 1) & 0xFFFF, cmd.address, [R.COMMAND_CODE["hook_replaced"]])
            key = "accepted" if exc == 0 else f"exception_{exc:02d}"
            HOOK_ANSWERS[key] = HOOK_ANSWERS.get(key, 0) + 1
    except OSError as e:
        HOOK_ANSWERS["error"] = HOOK_ANSWERS.get("error", 0) + 1
        print("hooks flood:", e, flush=True)
    finally:
        s.close()


def _plc_read(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=1) as sk:
            sk.sendall(struct.pack(">HHHBBHH", 1, 0, 6, 1, 4, 0, 8))
            data = sk.recv(256)
            return len(data) >= 9 and data[7] == 4
    except OSError:
        return False


def _ready(ports: dict[str, int], t_end: float) -> bool:
    """The console answers and the PLC port serves a read (under the supervisor the port opens
    once the worker's station reports, a few seconds after the console)."""
    while time.monotonic() < t_end:
        try:
            urllib.request.urlopen(f"http://127.0.0.1:{ports['console']}/api/fleet", timeout=1).read()
            if _plc_read(ports["modbus"]):
                return True
        except OSError:
            pass
        time.sleep(0.2)
    return False


def run(kind: str, duration: float, idle: int) -> dict:
    ports = {"console": free_port(), "metrics": free_port(), "modbus": free_port()}
    work, fleet, sims = make_fleet(1, f"hw-bench-doors-{kind}-", {
        "console": {"enabled": True, "listen": [f"127.0.0.1:{ports['console']}"]},
        "metrics": {"enabled": True, "host": "127.0.0.1", "port": ports["metrics"]},
        "modbus_tcp": {"enabled": True, "host": "127.0.0.1", "port": ports["modbus"],
                       "writes": {"enabled": True, "allowed_clients": ["127.0.0.1"]}}})
    stats = os.path.join(work, "stats.json")
    gw = subprocess.Popen([EXE, "run", fleet, *RUN_EXTRA, "--duration", str(duration), "--stats-json", stats,
                           "--log-level", "warning"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t_gw = time.monotonic()
    if not _ready(ports, time.monotonic() + 60):
        print(f"{kind:8s}: the gateway's doors did not answer within 60 s", flush=True)
    stop = threading.Event()
    plc = Plc(ports["modbus"], stop)
    plc.start()
    time.sleep(3.0)
    # the PLC and the flood end a second before the gateway does: a read refused by a gateway
    # that has ended is not a lost link
    ender = threading.Timer(max(0.0, t_gw + duration - 1.0 - time.monotonic()), stop.set)
    ender.start()
    held = flood(kind, ports, idle, stop) if kind != "none" else []
    gw.wait()
    ender.cancel()
    stop.set()
    plc.join(5)
    for s in held:
        s.close()
    st = stop_sims_read(sims, stats)
    s = next(iter(st.values()))
    aborted = False
    for dp, _d, fs in os.walk(os.path.join(work, "records")):
        if "result.json" in fs:
            with open(os.path.join(dp, "result.json")) as f:
                aborted |= json.load(f).get("end_reason") == "protection stop"
    hook_lines = 0
    for dp, _d, fs in os.walk(os.path.join(work, "records")):
        if "hooks.jsonl" in fs:
            with open(os.path.join(dp, "hooks.jsonl")) as f:
                hook_lines += sum(1 for _ in f)
    out = {"door": kind, "filled_pct": 100 * s["filled_ratio"], "p99_ms": s["lateness_ms_p99"],
           "plc_ok": plc.ok, "plc_failed": plc.failed, "plc_errors": plc.errors, "held": len(held),
           "aborted": aborted}
    if kind == "hooks":
        out.update(hook_answers=dict(HOOK_ANSWERS), hooks_jsonl_lines=hook_lines,
                   missing_slots=s.get("slots", 0) - s.get("filled", 0))
        print(f"hooks   : answers {HOOK_ANSWERS}, hooks.jsonl {hook_lines} lines", flush=True)
    print(f"{kind:8s}: filled {out['filled_pct']:.3f} %, p99 lateness {out['p99_ms']:.2f} ms, PLC reads "
          f"{plc.ok} ok / {plc.failed} failed {plc.errors or ''}, {len(held)} connections held, "
          f"aborted {aborted}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=40.0)
    ap.add_argument("--idle", type=int, default=3000)
    ap.add_argument("--doors", default="none,console,metrics,modbus,trickle,sse")
    ap.add_argument("--hooks", type=int, default=1000, help="hook_replaced commands of the hooks flood")
    ap.add_argument("--in-process", action="store_true", help="the station in the doors' process "
                    "(hookwatch run --in-process); default: a worker process under the supervisor")
    a = ap.parse_args()
    if a.in_process:
        RUN_EXTRA.append("--in-process")
    HOOKS[0] = a.hooks
    with open("/proc/loadavg") as f:
        print("load before:", f.read().split()[:3], flush=True)
    res = [run(k, a.duration, a.idle) for k in a.doors.split(",")]
    with open("/proc/loadavg") as f:
        print("load after:", f.read().split()[:3], flush=True)
    print(json.dumps(res))


if __name__ == "__main__":
    main()
