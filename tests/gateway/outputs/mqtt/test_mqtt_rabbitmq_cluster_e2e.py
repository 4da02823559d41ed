"""Clustered brokers (issue 29 item 4) on a real 3-node RabbitMQ cluster (Debian's 3.10: MQTT
3.1.1 only, retained messages per node): three gateways (`hookwatch run` against their own
`hookwatch sim` virtual stations), each with the three nodes as its `mqtt.servers`, run compressed
lives one after another while a node is killed (`kill -9`) every 30–60 s and started again. An
MES (a paho 3.1.1 client with a persistent session and the same server list) receives every
event and every result the stations recorded, counted once by each station's `seq`, none missing
(duplicates — a resend of what was not confirmed, a retained topic published again after a
reconnect — are allowed and marked); every outbox is empty at the end; no station loses a slot
to any of it. Nothing here is timed: the reconnect figures are
bench/bench_site.py's."""
from __future__ import annotations

import collections
import contextlib
import json
import os
import random
import re
import threading
import time

from gateway.outputs.broker.outbox import Outbox
from gateway.outputs.mqtt.schema import LIVES_REQUEST
from kit.e2e import (
    QUICK_END,
    QUICK_METHOD,
    assert_no_slot_lost,
    events,
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

N_GATEWAYS = 3
#: lives per gateway while nodes are killed; then one more with every node up
LIVES_UNDER_KILLS = 3
KILL_EVERY_S = (30.0, 60.0)
TUNED = {"dead_band_n": 0.01}


class Killer:
    """Kills a node (kill -9) every 30–60 s and starts it again at once: a node a running
    gateway is connected to (from the gateways' logs), so that every kill cuts one off."""

    def __init__(self, cluster: Cluster, tmp_path, seed: int = 29):
        self.cluster = cluster
        self.tmp_path = tmp_path
        self.rng = random.Random(seed)
        self.kills: list[str] = []
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def start(self) -> Killer:
        self._t.start()
        return self

    def _target(self) -> int | None:
        """The node the most recently connected running gateway is on (None: none is)."""
        ports = {n.mqtt_port: i for i, n in enumerate(self.cluster.nodes)}
        best = None
        for log in self.tmp_path.glob("gw*/gw-*.log"):
            text = log.read_text(errors="replace")
            if "slot stats" in text:            # that run has ended
                continue
            hits = re.findall(r"^(\S+ \S+) .*connected to 127\.0\.0\.1:(\d+)", text, re.M)
            if hits and (best is None or hits[-1][0] > best[0]):
                best = hits[-1]
        return None if best is None else ports.get(int(best[1]))

    def _run(self) -> None:
        while not self._stop.wait(self.rng.uniform(*KILL_EVERY_S)):
            node = None
            for _ in range(60):                 # between two lives no gateway is connected
                node = self._target()
                if node is not None or self._stop.wait(0.5):
                    break
            if node is None:
                continue
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


def _life(tmp_path, cluster: Cluster, life: int) -> dict[int, str]:
    """One compressed life on each gateway's own virtual station, the three at once; the test
    folder each gateway recorded (none when the start failed: a meter too slow to answer the
    zero check on a loaded box is the station's refusal, not the broker's doing)."""
    before = {g: set(test_dirs(tmp_path / f"gw{g}", f"st{g}")) for g in range(N_GATEWAYS)}
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
    out = {}
    for g in range(N_GATEWAYS):
        new = sorted(set(test_dirs(tmp_path / f"gw{g}", f"st{g}")) - before[g])
        assert len(new) <= 1, new
        if new:
            out[g] = new[0]
    return out


def test_three_gateways_on_a_rabbitmq_cluster_lose_nothing_while_nodes_are_killed(tmp_path, rabbitmq_cluster):
    cluster = rabbitmq_cluster
    servers = [("127.0.0.1", n.mqtt_port) for n in cluster.nodes]
    mes = Mes(servers, "hookwatch/#").start()
    killer = None
    try:
        wait_for(lambda: mes.connects >= 1, 60, what="the MES connected")
        killer = Killer(cluster, tmp_path).start()
        lives = []
        for life in range(LIVES_UNDER_KILLS):
            lives.append(_life(tmp_path, cluster, life))
        killer.stop()
        assert not killer.errors, killer.errors
        for i, n in enumerate(cluster.nodes):        # every node up for the last life
            if not n.running:
                cluster.restart(i)
        lives.append(_life(tmp_path, cluster, LIVES_UNDER_KILLS))

        # every outbox emptied: whatever the gateways produced was confirmed by a node
        for g in range(N_GATEWAYS):
            ob = Outbox(str(tmp_path / f"gw{g}" / "records" / f"st{g}" / "outbox.sqlite"))
            try:
                assert ob.count() == 0, f"st{g}: messages left in the outbox"
            finally:
                ob.close()
        # what the stations recorded: every event of every life, and its result
        recorded: collections.Counter = collections.Counter()
        for g in range(N_GATEWAYS):
            for td in test_dirs(tmp_path / f"gw{g}", f"st{g}"):
                for ev in events(td):
                    recorded[(f"st{g}", "event", ev["type"], ev["test_id"])] += 1
                recorded[(f"st{g}", "result", None, read_json(os.path.join(td, "result.json"))["test_id"])] += 1
        # most lives ran (a start refused on an overloaded box is the station's own business)
        assert sum(len(lv) for lv in lives) >= N_GATEWAYS * (LIVES_UNDER_KILLS + 1) // 2, lives

        def at_mes() -> tuple[collections.Counter, dict[str, int]]:
            """The MES's messages counted once by (station, seq); duplicates marked."""
            got: collections.Counter = collections.Counter()
            seen: set[tuple[str, int]] = set()
            dup: collections.Counter = collections.Counter()
            for topic, payload, _retained in mes.snapshot():
                if topic.endswith("/" + LIVES_REQUEST):
                    continue                          # the gateways' site-level request, no MES message
                doc = json.loads(payload)
                if "seq" not in doc:
                    continue                          # status: no seq
                key = (doc["station"], doc["seq"])
                if key in seen:
                    dup[doc["station"]] += 1          # a resend or a retained replay: marked
                    continue
                seen.add(key)
                if "/event/" in topic:
                    got[(doc["station"], "event", doc["type"], doc["test_id"])] += 1
                elif topic.endswith("/result"):
                    got[(doc["station"], "result", None, doc["test_id"])] += 1
            return got, dict(dup)

        def missing() -> dict:
            got, _ = at_mes()
            return {k: n - got[k] for k, n in recorded.items() if got[k] < n}

        try:
            wait_for(lambda: not missing(), 120, what="every event and result at the MES")
        except AssertionError:
            raise AssertionError(f"missing at the MES: {missing()}") from None
        got, dup = at_mes()
    finally:
        if killer is not None:
            killer.stop()
        mes.stop()
    assert not mes.violations, mes.violations[:3]
    report = {"recorded": len(recorded), "duplicates": dup}
    # the nodes were killed while the gateways ran, and the gateways moved between them
    assert len(killer.kills) >= 2, killer.kills
    logs = "".join((tmp_path / f"gw{g}" / f"gw-{life}.log").read_text()
                   for g in range(N_GATEWAYS) for life in range(LIVES_UNDER_KILLS + 1))
    assert "refused MQTT 5" in logs                 # RabbitMQ 3.10: the 3.1.1 fallback
    assert "MQTT connection lost" in logs or "MQTT disconnected" in logs
    # at least one gateway moved to another node of its list
    moved = []
    for g in range(N_GATEWAYS):
        text = "".join((tmp_path / f"gw{g}" / f"gw-{life}.log").read_text()
                       for life in range(LIVES_UNDER_KILLS + 1))
        if len(set(re.findall(r"connected to (127\.0\.0\.1:\d+)", text))) > 1:
            moved.append(g)
    assert moved, "no gateway changed nodes"
    (tmp_path / "report.json").write_text(json.dumps({"kills": killer.kills, **report}))

    # no station lost a slot to it: every slot of every life accounted for
    for life, dirs in enumerate(lives):
        for g, td in dirs.items():
            res = read_json(os.path.join(td, "result.json"))
            stats = read_json(str(tmp_path / f"gw{g}" / f"stats-{life}.json"))[f"st{g}"]
            assert_no_slot_lost(td, res["method"], stats)


def test_a_node_that_stays_down_does_not_lock_its_stations_out(tmp_path, rabbitmq_cluster):
    """RabbitMQ homes a subscriber's queue on the node the session was made on; while that node is
    down, a new session under the same client ID on another node is refused (the queue's home
    node is unreachable) — a station that kept one client ID would stay cut off until the node
    came back. With a client ID per server (paho_session.PahoSession.client_id_for) the output
    moves to the other node and delivers there while the first stays down."""
    from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
    from kit.northbound import LoopThread, RunningStation, make_station

    base = "hookwatch/lab/hall/l1/st1"
    cluster = rabbitmq_cluster       # three nodes: the MES's quorum queue keeps a majority
    a, b = cluster.nodes[:2]
    mes = Mes([("127.0.0.1", b.mqtt_port)], base + "/#").start()
    lt = LoopThread()
    station = make_station(tmp_path, [])
    out = MqttOutput(MqttSettings(station_id="st1", base_topic=base, protocol="3.1.1",
                                  servers=[("127.0.0.1", a.mqtt_port), ("127.0.0.1", b.mqtt_port)],
                                  outbox_path=str(tmp_path / "outbox.sqlite"),
                                  reconnect_min_s=0.2, reconnect_max_s=1.0), station)
    station.outputs.append(out)
    run = None
    try:
        wait_for(lambda: mes.connects >= 1, 60, what="the MES connected")
        run = RunningStation(lt, station)
        wait_for(lambda: out.connected and out.pump.server[1] == a.mqtt_port, 60, what="on node 1")
        wait_for(lambda: out.outbox.count() == 0, 60, what="confirmed by node 1")
        cluster.kill(0)                     # and it stays down
        wait_for(lambda: out.connected and out.pump.server[1] == b.mqtt_port, 60, what="on node 2")
        # a command sent now on node 2 reaches the station (its subscription on node 2) and
        # its reply comes back through the outbox, confirmed by node 2
        def replies():
            return [json.loads(p) for t, p, _r in mes.snapshot() if t == base + "/reply"]
        # "connected" is the CONNACK; the session's command subscription on node 2 follows it,
        # and a command published before the broker has made it is routed to nobody (MQTT). The
        # MES sends it again until answered, as an MES does: the same request_id acts once
        # (CommandDesk), the repeats get the first answer
        last = [0.0]

        def answered():
            if time.monotonic() - last[0] >= 2.0:
                last[0] = time.monotonic()
                mes.c.publish(base + "/cmd/ack", b'{"request_id": "after-the-kill"}', qos=1)
            return any(r.get("request_id") == "after-the-kill" for r in replies())
        try:
            wait_for(answered, 60, what="the reply to a command sent on node 2")
        except AssertionError as e:
            raise AssertionError(f"{e}: {dict(out.counters)}, {out.pump._client_cid}, "
                                 f"{[t for t, _p, _r in mes.snapshot()][-5:]}") from None
        assert not a.running
    finally:
        if run is not None:
            run.stop()
        lt.close()
        mes.stop()


def test_what_a_test_leaves_on_the_shared_cluster_never_reaches_the_next(rabbitmq_cluster):
    """The cluster is shared by the tests of its xdist group (tests/kit/rabbitmq_pool.py):
    a message one test left retained, and its persistent session, stay on its virtual host; the
    next test, on a fresh one, with the same client ID and subscription, finds neither."""
    cluster = rabbitmq_cluster
    servers = [("127.0.0.1", n.mqtt_port) for n in cluster.nodes]

    def received(client_id: str, payload: bytes, retain: bool = False) -> list[bytes]:
        """Subscribe to probe/t (a persistent session; RabbitMQ sends a retained message only to a
        subscription to its very topic, no wildcard), publish ``payload`` there, and return the
        payloads that came until it came back."""
        mes = Mes(servers, "probe/t", client_id=client_id).start()
        try:
            wait_for(lambda: mes.connects >= 1, 60, what=f"{client_id} connected")
            # sent after the subscription: a retained message comes before it
            mes.c.publish("probe/t", payload, qos=1, retain=retain)
            wait_for(lambda: any(p == payload for _t, p, _r in mes.snapshot()), 60, what=payload)
            return [p for _t, p, _r in mes.snapshot()]
        finally:
            mes.stop()

    assert received("probe", b'{"n": 1}', retain=True) == [b'{"n": 1}']
    # the control: on the same vhost a new subscriber gets the retained message; the second
    # message is queued for the first client's session too
    assert received("probe-2", b'{"n": 2}') == [b'{"n": 1}', b'{"n": 2}']
    cluster.fresh_vhost("probe-next")
    # the next test's vhost: neither the retained message nor the first session's queued one
    assert received("probe", b'{"n": 3}') == [b'{"n": 3}']
