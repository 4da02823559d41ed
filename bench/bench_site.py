#!/usr/bin/env python3
"""Issue 29 item 5: a site bench — N gateways on one Mosquitto, and on a 3-node RabbitMQ cluster.

Each gateway is a ``hookwatch run`` with its own virtual station (``hookwatch sim``, the
compressed quick life) and ``mqtt.servers`` listing the broker(s); the gateways run ``--lives``
lives one after another. Every ``--kill-every`` s the broker is killed (``kill -9``) and started
again: on Mosquitto the single broker (the site's single point of failure: every gateway is cut
off until it is back), on the cluster one node in turn (the gateways on it move to the next node).

Per setup: the slots held (filled / slots of every life, from ``--stats-json``), and the reconnect
time of every link loss a gateway saw (from its log: the `connection lost` / `disconnected` line
to the next `connected to` line), p50/p99/max; then the site-history sync of a joining gateway
(``mqtt.share_lives``, gateway/outputs/mqtt/sitelives.py): while the N gateways run again (what
they recorded, without their instruments: no test), a new gateway of the same site (its own
virtual station, no test, the first server of gateway 0's list) runs 30 s; how many of the N
stations' lives it received (retained on its node, or answering its lives request) and how long
after its start the last of them came. Results as JSON lines on stdout.

    bench/bench_site.py [--gateways 3] [--lives 3] [--kill-every 25] [--setups mosquitto,cluster]
"""
from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import os
import pathlib
import re
import sys
import tempfile
import threading
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)

from kit.broker import Broker  # noqa: E402
from kit.e2e import (  # noqa: E402
    QUICK_END,
    QUICK_METHOD,
    quick_scenario,
    read_json,
    run_gateway,
    station_yaml,
    virtual_station,
    wait_exit,
    wait_log,
)
from kit.rabbitmq import Cluster  # noqa: E402

STAMP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) ")


def _t(line: str) -> float | None:
    m = STAMP.match(line)
    if m is None:
        return None
    return dt.datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()


def reconnects(log_text: str) -> list[float]:
    """Seconds from each link loss to the next connect, from a gateway's log."""
    out, lost = [], None
    for line in log_text.splitlines():
        t = _t(line)
        if t is None or "hookwatch.mqtt" not in line:
            continue
        if "MQTT connection lost" in line or "MQTT disconnected" in line:
            lost = t if lost is None else lost
        elif "connected to" in line and lost is not None:
            out.append(t - lost)
            lost = None
    return out


def pct(xs: list[float], q: float) -> float | None:
    if not xs:
        return None
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(round(q * (len(xs) - 1))))]


class Killer(threading.Thread):
    def __init__(self, kill_restart, every: float):
        super().__init__(daemon=True)
        self.kill_restart, self.every = kill_restart, every
        self.stop_evt = threading.Event()
        self.kills = 0

    def run(self) -> None:
        i = 0
        while not self.stop_evt.wait(self.every):
            self.kill_restart(i)
            self.kills += 1
            i += 1


def run_setup(base: pathlib.Path, name: str, servers_of, kill_restart, args) -> dict:
    killer = Killer(kill_restart, args.kill_every)
    killer.start()
    slots = filled = 0
    rec: list[float] = []
    try:
        for life in range(args.lives):
            with contextlib.ExitStack() as stack:
                gws = []
                for g in range(args.gateways):
                    d = base / name / f"gw{g}"
                    d.mkdir(parents=True, exist_ok=True)
                    sc = quick_scenario(d, "quick.yaml")
                    _sim, links = stack.enter_context(virtual_station(d, sc, seed=10 * g + life))
                    st = station_yaml(d, links, name=f"st{g}", control={"dead_band_n": 0.01},
                                      method=QUICK_METHOD, test={"t_end_s": QUICK_END},
                                      mqtt={"enabled": True, "servers": servers_of(g), "protocol": "3.1.1",
                                            "prefix": "bench"})
                    gw = run_gateway(d, st, "--start", "--exit-when-done", "--stats-json",
                                     str(d / f"stats-{life}.json"), name=f"gw-{life}")
                    stack.callback(gw.stop)
                    gws.append((g, d, gw))
                for g, d, gw in gws:
                    wait_exit(gw, QUICK_END + 180)
                    s = read_json(str(d / f"stats-{life}.json"))[f"st{g}"]
                    slots += s["slots"]
                    filled += s["filled"]
                    rec += reconnects(gw.log_all())
    finally:
        killer.stop_evt.set()
        killer.join(120)
    sync = join(base / name / "join", servers_of(0),
                [(base / name / f"gw{g}", f"st{g}", servers_of(g)) for g in range(args.gateways)])
    return {**sync, "setup": name, "gateways": args.gateways, "lives": args.lives, "kills": killer.kills,
            "kill_every_s": args.kill_every, "slots_held_pct": round(100.0 * filled / max(1, slots), 3),
            "reconnects": len(rec), "reconnect_p50_s": pct(rec, 0.5), "reconnect_p99_s": pct(rec, 0.99),
            "reconnect_max_s": max(rec) if rec else None}


SITE_LINE = re.compile(r"the site's lives: (\d+) tests of (\d+) other station")


def join(d: pathlib.Path, servers: list[str], site: list[tuple[pathlib.Path, str, list[str]]]) -> dict:
    """A gateway joining the site while the site's gateways run (each again, with what it recorded
    and without its instruments: no test, its lives shared): the stations whose lives it received,
    and when (s after its start). Their lives reach it retained (when on its node) or through its
    request on ``<prefix>/<site>/lives_request``."""
    d.mkdir(parents=True, exist_ok=True)
    sc = quick_scenario(d, "quick.yaml")
    with contextlib.ExitStack() as stack:
        for gd, name, srv in site:
            absent = {"meter": str(gd / "absent-meter"), "stm32": str(gd / "absent-stm32")}
            st = station_yaml(gd, absent, name=name, method=QUICK_METHOD,
                              mqtt={"enabled": True, "servers": srv, "protocol": "3.1.1", "prefix": "bench"})
            g = run_gateway(gd, st, "--duration", "90", name="site")
            stack.callback(g.stop)
            wait_log(g, "connected to", 120)
        _sim, links = stack.enter_context(virtual_station(d, sc, seed=99))
        st = station_yaml(d, links, name="joiner", method=QUICK_METHOD,
                          mqtt={"enabled": True, "servers": servers, "protocol": "3.1.1", "prefix": "bench"})
        t0 = time.time()
        gw = run_gateway(d, st, "--duration", "30", name="join")
        wait_exit(gw, 120)
    best, at = 0, None
    for line in gw.log_all().splitlines():
        m = SITE_LINE.search(line)
        t = _t(line)
        if m and t is not None and int(m.group(2)) > best:
            best, at = int(m.group(2)), t - t0
    return {"join_stations_received": best, "join_sync_s": None if at is None else round(at, 2)}


def on_mosquitto(base: pathlib.Path, args) -> dict:
    b = Broker(base).start()

    def restart(_i: int) -> None:
        if b.p is not None:
            b.p.kill()
            b.p.wait(10)
        b.start()
    try:
        return run_setup(base, "mosquitto", lambda g: [f"127.0.0.1:{b.port}"], restart, args)
    finally:
        b.stop()


def on_cluster(base: pathlib.Path, args) -> dict:
    c = Cluster(base).start()
    servers = c.servers

    def kill_node(i: int) -> None:
        n = i % len(c.nodes)
        c.kill(n)
        c.restart(n)
    try:        # each gateway prefers another node first: every kill cuts one off
        return run_setup(base, "cluster", lambda g: servers[g % 3:] + servers[:g % 3], kill_node, args)
    finally:
        c.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--gateways", type=int, default=3)
    ap.add_argument("--lives", type=int, default=3)
    ap.add_argument("--kill-every", type=float, default=25.0)
    ap.add_argument("--setups", default="mosquitto,cluster")
    args = ap.parse_args()
    base = pathlib.Path(tempfile.mkdtemp(prefix="bench-site-"))
    setups = {"mosquitto": on_mosquitto, "cluster": on_cluster}
    for setup in args.setups.split(","):
        print(json.dumps(setups[setup](base, args)), flush=True)


if __name__ == "__main__":
    main()
