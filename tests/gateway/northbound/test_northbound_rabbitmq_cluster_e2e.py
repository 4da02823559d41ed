"""Clustered brokers (issue 29 item 4) on a real 3-node RabbitMQ cluster (Debian's 3.10: MQTT
3.1.1 only, retained messages per node): three gateways (`hookwatch run` against their own
`hookwatch sim` virtual stations), each with the three nodes as its `mqtt.servers`, run compressed
lives one after another while a node is killed (`kill -9`) every 30–60 s and started again. An
MES (a paho 3.1.1 client with a persistent session and the same server list) receives every
message the gateways put in their outboxes: counted by each station's `seq`, none missing
(duplicates — a resend of what was not confirmed, a retained topic published again after a
reconnect — are allowed and counted as such); every life's result and events among them; no
station loses a slot to any of it. Nothing here is timed: the reconnect figures are
bench/bench_site.py's."""
from __future__ import annotations

import contextlib
import json
import os
import random
import threading

import pytest

from gateway.northbound.outbox import Outbox
from kit.e2e import (
    QUICK_END,
    QUICK_METHOD,
    assert_no_slot_lost,
    quick_scenario,
    read_json,
    run_gateway,
    station_yaml,
    test_dirs,
    virtual_station,
    wait_exit,
)
from kit.rabbitmq import Cluster, Mes
from kit.tools import wait_for

pytestmark = pytest.mark.slow

N_GATEWAYS = 3
#: lives per gateway while nodes are killed; then one more with every node up
LIVES_UNDER_KILLS = 3
KILL_EVERY_S = (30.0, 60.0)
TUNED = {"dead_band_n": 0.01}


class Killer:
    """Kills a node (kill -9) every 30–60 s, the nodes in turn, and starts it again at once."""

    def __init__(self, cluster: Cluster, seed: int = 29):
        self.cluster = cluster
        self.rng = random.Random(seed)
        self.kills: list[str] = []
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def start(self) -> Killer:
        self._t.start()
        return self

    def _run(self) -> None:
        i = 1
        while not self._stop.wait(self.rng.uniform(*KILL_EVERY_S)):
            node = i % len(self.cluster.nodes)
            i += 1
            try:
                self.cluster.kill(node)
                self.kills.append(self.cluster.nodes[node].name)
                self.cluster.restart(node)
            except Exception as e:  # noqa: BLE001 - reported by the test
                self.errors.append(f"{type(e).__name__}: {e}")
                return

    def stop(self) -> None:
        self._stop.set()
        self._t.join(300)


def _life(tmp_path, cluster: Cluster, life: int) -> None:
    """One compressed life on each gateway's own virtual station, the three at once."""
    with contextlib.ExitStack() as stack:
        gws = []
        for g in range(N_GATEWAYS):
            d = tmp_path / f"gw{g}"
            d.mkdir(exist_ok=True)
            sc = quick_scenario(d, "quick.yaml")
            _sim, links = stack.enter_context(virtual_station(d, sc, seed=10 * g + life))
            st = station_yaml(d, links, name=f"st{g}", control=TUNED, method=QUICK_METHOD,
                              test={"t_end_s": QUICK_END},
                              # each gateway prefers another node: every kill cuts one off
                              mqtt={"enabled": True, "servers": cluster.servers[g:] + cluster.servers[:g],
                                    "protocol": "auto",
                                    "prefix": "hookwatch"})
            gw = run_gateway(d, st, "--start", "--exit-when-done", "--stats-json",
                             str(d / f"stats-{life}.json"), name=f"gw-{life}")
            stack.callback(gw.stop)
            gws.append(gw)
        for gw in gws:
            rc = wait_exit(gw, QUICK_END + 180)
            assert rc == 0, gw.log_all()


def test_three_gateways_on_a_rabbitmq_cluster_lose_nothing_while_nodes_are_killed(tmp_path):
    cluster = Cluster(tmp_path)
    with cluster:
        servers = [("127.0.0.1", n.mqtt_port) for n in cluster.nodes]
        mes = Mes(servers, "hookwatch/#").start()
        killer = None
        try:
            wait_for(lambda: mes.connects >= 1, 60, what="the MES connected")
            killer = Killer(cluster).start()
            for life in range(LIVES_UNDER_KILLS):
                _life(tmp_path, cluster, life)
            killer.stop()
            assert not killer.errors, killer.errors
            for i, n in enumerate(cluster.nodes):        # every node up for the last life
                if not n.running:
                    cluster.restart(i)
            _life(tmp_path, cluster, LIVES_UNDER_KILLS)

            # what each gateway produced: seq 1 … last of its outbox, which is empty now
            last = {}
            for g in range(N_GATEWAYS):
                ob = Outbox(str(tmp_path / f"gw{g}" / "records" / f"st{g}" / "outbox.sqlite"))
                try:
                    assert ob.count() == 0, f"st{g}: messages left in the outbox"
                    last[f"st{g}"] = ob.last_seq
                finally:
                    ob.close()

            def by_station():
                seen: dict[str, list[int]] = {s: [] for s in last}
                kinds: dict[str, dict[int, str]] = {s: {} for s in last}
                for topic, payload, _retained in mes.snapshot():
                    doc = json.loads(payload)
                    if "seq" not in doc or doc.get("station") not in seen:
                        continue                          # status: no seq
                    seen[doc["station"]].append(doc["seq"])
                    kinds[doc["station"]][doc["seq"]] = topic.rsplit("/", 2)[-2:]
                return seen, kinds

            wait_for(lambda: all(set(range(1, last[s] + 1)) <= set(v) for s, v in by_station()[0].items()),
                     120, what="every message at the MES")
        finally:
            if killer is not None:
                killer.stop()
            mes.stop()
        assert not mes.violations, mes.violations[:3]
        seen, kinds = by_station()
        report = {}
        for s, seqs in seen.items():
            missing = set(range(1, last[s] + 1)) - set(seqs)
            assert not missing, (s, sorted(missing)[:20])
            dup = len(seqs) - len(set(seqs))        # marked: a resend or a retained replay
            ks = kinds[s]
            results = [q for q, k in ks.items() if k[-1] == "result"]
            started = [q for q, k in ks.items() if k == ["event", "test_started"]]
            ended = [q for q, k in ks.items() if k == ["event", "test_ended"]]
            assert len(results) == len(started) == len(ended) == LIVES_UNDER_KILLS + 1, (s, ks)
            report[s] = {"messages": last[s], "duplicates": dup}
        # the nodes were killed while the gateways ran, and the gateways moved between them
        assert len(killer.kills) >= 2, killer.kills
        logs = "".join((tmp_path / f"gw{g}" / f"gw-{life}.log").read_text()
                       for g in range(N_GATEWAYS) for life in range(LIVES_UNDER_KILLS + 1))
        assert "refused MQTT 5" in logs                 # RabbitMQ 3.10: the 3.1.1 fallback
        assert "MQTT connection lost" in logs or "MQTT disconnected" in logs
        (tmp_path / "report.json").write_text(json.dumps({"kills": killer.kills, "stations": report}))

        # no station lost a slot to it: every slot of every life accounted for
        for g in range(N_GATEWAYS):
            d = tmp_path / f"gw{g}"
            dirs = test_dirs(d, f"st{g}")
            assert len(dirs) == LIVES_UNDER_KILLS + 1, dirs
            for life, td in enumerate(dirs):
                res = read_json(os.path.join(td, "result.json"))
                stats = read_json(str(d / f"stats-{life}.json"))[f"st{g}"]
                assert_no_slot_lost(td, res["method"], stats)
