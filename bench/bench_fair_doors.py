#!/usr/bin/env python3
"""Issue 27 item 7 benchmark: fair doors, in one process (the console's own thread and loop, as
in `hookwatch run`).

1. ``reopen``: one client (127.0.0.1) holds SOCKETS idle sockets to the console and re-opens at
   once every one the door closes; the operator (127.0.0.2) sends GETS sequential GETs of
   /api/session, each on a new connection: how many are answered and their wall times (median,
   worst). Before issue 27: 3 of 13 answered.
2. ``logins``: FLOOD_S seconds of wrong logins (8 threads, a new client address each try, three
   user names): hashes performed, hashes per second, 429s, and the process's CPU over the flood
   (utime + stime of every thread, from /proc/self/stat). Before issue 27: 1,405 wrong logins in
   30 s took 194 % CPU.

    bench/bench_fair_doors.py [--sockets 300] [--gets 13] [--flood-s 30]
"""
from __future__ import annotations

import argparse
import errno
import http.client
import json
import os
import selectors
import socket
import statistics
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)

from gateway.outputs.console import auth  # noqa: E402
from gateway.outputs.console.app import ConsoleServer  # noqa: E402
from gateway.outputs.console.settings import ConsoleSettings  # noqa: E402


def console(tmp: str) -> tuple[ConsoleServer, int]:
    users = os.path.join(tmp, "u.json")
    if not os.path.exists(users):
        auth.add_user(users, "alice", "a long password")
    srv = ConsoleServer(ConsoleSettings(listen=("127.0.0.1:0",), users_file=users),
                        {"s1": os.path.join(tmp, "s1")})
    return srv, int(srv.start()[0].rstrip("/").rsplit(":", 1)[1])


def reopen(n: int, gets: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        srv, port = console(tmp)
        sel = selectors.DefaultSelector()
        stop = threading.Event()

        def open_one() -> None:
            s = socket.socket()
            s.setblocking(False)
            s.bind(("127.0.0.1", 0))
            if s.connect_ex(("127.0.0.1", port)) in (0, errno.EINPROGRESS):
                sel.register(s, selectors.EVENT_READ)
            else:
                s.close()

        def hostile() -> None:
            for _ in range(n):
                open_one()
            while not stop.is_set():
                for key, _ in sel.select(0.1):
                    s = key.fileobj
                    try:
                        data = s.recv(4096)
                    except OSError:
                        data = b""
                    if not data:
                        sel.unregister(s)
                        s.close()
                        open_one()
        t = threading.Thread(target=hostile, daemon=True)
        t.start()
        time.sleep(2.0)
        times, answered = [], 0
        for _ in range(gets):
            t0 = time.monotonic()
            c = http.client.HTTPConnection("127.0.0.1", port, timeout=60, source_address=("127.0.0.2", 0))
            try:
                c.request("GET", "/api/session", headers={"Host": f"127.0.0.1:{port}"})
                r = c.getresponse()
                r.read()
                answered += r.status == 200
            except (OSError, http.client.HTTPException):
                pass
            finally:
                c.close()
            times.append(time.monotonic() - t0)
        counters = dict(srv.door.counters)
        stop.set()
        t.join(10)
        for key in list(sel.get_map().values()):
            key.fileobj.close()
        srv.stop()
    return {"sockets": n, "answered": f"{answered} of {gets}", "get_s_median": round(statistics.median(times), 3),
            "get_s_worst": round(max(times), 3), "refused_per_address": counters["refused_per_address"],
            "accepted": counters["accepted"]}


def cpu_s() -> float:
    with open("/proc/self/stat") as f:
        v = f.read().rsplit(")", 1)[1].split()
    return (int(v[11]) + int(v[12])) / os.sysconf("SC_CLK_TCK")


def logins(flood_s: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        srv, port = console(tmp)
        stop = threading.Event()
        lock = threading.Lock()
        counts: dict[int, int] = {}
        seq = iter(range(10 ** 7))

        def flood() -> None:
            while not stop.is_set():
                with lock:
                    i = next(seq)
                body = json.dumps({"user": ("admin", "root", "plc")[i % 3], "password": f"wrong {i}"})
                c = http.client.HTTPConnection("127.0.0.1", port, timeout=60,
                                               source_address=(f"127.6.{(i // 250) % 250}.{1 + i % 250}", 0))
                try:
                    c.request("POST", "/api/login", body=body, headers={
                        "Host": f"127.0.0.1:{port}", "Content-Type": "application/json"})
                    r = c.getresponse()
                    r.read()
                    with lock:
                        counts[r.status] = counts.get(r.status, 0) + 1
                except (OSError, http.client.HTTPException):
                    pass
                finally:
                    c.close()
        c0, t0 = cpu_s(), time.monotonic()
        threads = [threading.Thread(target=flood, daemon=True) for _ in range(8)]
        for t in threads:
            t.start()
        time.sleep(flood_s)
        stop.set()
        for t in threads:
            t.join(60)
        wall, cpu = time.monotonic() - t0, cpu_s() - c0
        hashes = srv.hasher.hashes
        srv.stop()
    return {"flood_s": round(wall, 1), "tries": sum(counts.values()), "answers": counts, "hashes": hashes,
            "hashes_per_s": round(hashes / wall, 2),
            "process_cpu_percent (flood clients included)": round(100 * cpu / wall, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sockets", type=int, default=300)
    ap.add_argument("--gets", type=int, default=13)
    ap.add_argument("--flood-s", type=float, default=30.0)
    a = ap.parse_args()
    with open("/proc/loadavg") as f:
        print("load", f.read().split()[:3])
    print("reopen", json.dumps(reopen(a.sockets, a.gets)))
    print("logins", json.dumps(logins(a.flood_s)))


if __name__ == "__main__":
    main()
