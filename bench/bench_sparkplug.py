"""Sparkplug edge node state machine: cost of live DDATA, of storing while the host is offline,
and of the replay (encode + seq + hand-over), per message; no broker (the pure node on an
in-memory buffer, and on the SQLite store). Prints medians over several runs.

    python bench/bench_sparkplug.py [--runs 5] [--n 5000]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from gateway.outputs.broker.outbox import Outbox  # noqa: E402
from gateway.outputs.sparkplug.node import EdgeNode  # noqa: E402
from gateway.outputs.sparkplug.node_store import OutboxBuffer  # noqa: E402

VALUES = {"Tension/T1": 0.43, "Tension/T2": 0.57, "Tension/Mean": 0.5, "Friction/mu": 0.256,
          "Quality/Valid Ratio": 0.98, "Control/Speed Command": 120.4, "Control/Speed Actual": 120.1,
          "Control/Saturation": False}


def state(online: bool, ts: int) -> bytes:
    return json.dumps({"online": online, "timestamp": ts}).encode()


def one_run(n: int, store: str | None) -> dict[str, float]:
    node = EdgeNode("g", "e", primary_host_id="h", buffer=OutboxBuffer(Outbox(store)) if store else None)
    node.connecting()
    node.device_up("d", {"Test/State": "monitoring"}, 0)
    node.connected_ok(0)
    node.host_state(state(True, 1), 1)
    t0 = time.perf_counter()
    for i in range(n):
        node.device_update("d", VALUES, 10 + i)
    live = (time.perf_counter() - t0) / n
    node.host_state(state(False, 2), 2)
    node.disconnected()
    node.connecting()
    node.connected_ok(3)
    t0 = time.perf_counter()
    for i in range(n):
        node.device_update("d", VALUES, 10 + n + i)
    stored = (time.perf_counter() - t0) / n
    node.host_state(state(True, 3), 4)
    t0 = time.perf_counter()
    sent = 0
    while node.replaying:
        pubs, keys = node.drain(5)
        node.buffer.remove(keys)
        sent += len(pubs)
    replay = (time.perf_counter() - t0) / max(sent, 1)
    return {"live": live, "stored": stored, "replay": replay}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--n", type=int, default=5000)
    a = ap.parse_args()
    for label, use_store in (("memory buffer", False), ("SQLite store", True)):
        runs = []
        for _ in range(a.runs):
            with tempfile.TemporaryDirectory() as d:
                runs.append(one_run(a.n, os.path.join(d, "s.sqlite") if use_store else None))
        for k in ("live", "stored", "replay"):
            print(f"{label:14s} {k:7s} median {statistics.median(r[k] for r in runs) * 1e6:8.1f} µs/message "
                  f"({a.runs} runs × {a.n})")


if __name__ == "__main__":
    main()
