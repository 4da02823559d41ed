"""Issue 29 item 2 end to end: two gateways of one site on one real Mosquitto. Box A has recorded
grade I at 0.5 N: 3 failures and 2 hooks replaced early (STOPPED). Box B — its own records folder,
no history, no configured prior — receives A's retained lives, and a test it starts of that grade
and T_set gets the §7a prior of A's lives in its sidecar (`prior_source: history`, 3 failures,
2 censored, from the site). B keeps the site's lives locally (`site_lives.json`), and the MES sees
A's snapshot on its `lives` topic (valid for docs/schemas/lives.json). Restarted while the broker
is down, B still starts its next test with the site's prior (from its local copy).

The same on a real 3-node RabbitMQ cluster (issue 29 item 4: retained messages are kept per node):
A publishes its lives via node 1, B joins via node 2, where nothing of A is retained; B's request
on `<prefix>/<site>/lives_request` brings A's lives, and B's test gets the same prior."""
import json
import os

import pytest
import yaml

from gateway.core.method.prior import history_prior
from gateway.offline.history import read_history
from gateway.outputs.mqtt import schema as S
from gateway.outputs.mqtt.sitelives import STORE_NAME
from kit.broker import Broker, Sub, pub
from kit.e2e import (
    QUICK_END,
    QUICK_METHOD,
    quick_scenario,
    run_gateway,
    seed_lives,
    station_yaml,
    virtual_station,
    wait_log,
)
from kit.rabbitmq import Mes
from kit.tools import wait_for

FAILURES = (20.0, 23.0, 26.5)
STOPPED = (1100, 1250)          # slots (ts 0.02): 22 s and 25 s, hooks replaced early


def seed_box_a(root):
    """A's records: 3 failures and 2 tests ended on purpose after their baseline."""
    seed_lives(root, "a", FAILURES, STOPPED, QUICK_END)


def test_box_b_starts_with_the_site_prior_of_box_a(tmp_path):
    root_a, root_b = tmp_path / "A" / "records", tmp_path / "B" / "records"
    seed_box_a(root_a)
    expected = history_prior(list(FAILURES), [n * 0.02 for n in STOPPED])
    with Broker(tmp_path) as b:
        mes = Sub(b.port, "hookwatch/lab/+/+/+/lives")
        gw_a = gw_b = None
        try:
            # box A: a station without its instruments (its ports are absent: a state, not a
            # crash); its MQTT output shares what it recorded
            dev = tmp_path / "absent"
            st_a = station_yaml(tmp_path, {"meter": str(dev / "meter"), "stm32": str(dev / "stm32")},
                                name="a", mqtt={"enabled": True, "port": b.port},
                                extra={"recorder": {"dir": str(root_a)}})
            gw_a = run_gateway(tmp_path, st_a, name="gw-a")
            lives = mes.wait(lambda s: s.messages("lives"), 60, what="A's lives")
            retained, topic, doc, _ = lives[0]
            assert topic == "hookwatch/lab/test/l1/a/lives" and doc["station"] == "a"
            assert len(doc["lives"]) == 5 and doc["schema"] == S.SCHEMA_VERSION
            with virtual_station(tmp_path, quick_scenario(tmp_path, "quick.yaml")) as (_sim, links):
                st_b = station_yaml(tmp_path, links, name="b", method=QUICK_METHOD,
                                    test={"t_end_s": QUICK_END}, mqtt={"enabled": True, "port": b.port},
                                    extra={"recorder": {"dir": str(root_b)}})
                gw_b = run_gateway(tmp_path, st_b, name="gw-b")
                wait_log(gw_b, "the site's lives: 5 tests of 1 other station(s)", 60)
                pub(b.port, "hookwatch/lab/test/l1/b/cmd/start",
                    '{"sample_id": "B-1", "grade": "I", "t_set": 0.5}')
                meta_path = wait_for(lambda: _sidecar(root_b / "b"), 60, what="B's test started")
                with open(meta_path) as f:
                    meta = yaml.safe_load(f)
                gw_b.stop()
                # B restarts while the broker is down: the site's lives come from its local copy
                b.stop()
                gw_b = run_gateway(tmp_path, st_b, "--start", name="gw-b2")
                wait_log(gw_b, "the site's lives: 5 tests of 1 stations from", 60)
                meta2_path = wait_for(lambda: _sidecar(root_b / "b", 2), 60, what="B's second test")
                with open(meta2_path) as f:
                    meta2 = yaml.safe_load(f)
        finally:
            for gw in (gw_b, gw_a):
                if gw is not None:
                    gw.stop()
            mes.stop()
    # B's sidecar: the §7a prior of A's lives, from the site
    assert meta["prior_source"] == "history"
    assert (meta["prior_n"], meta["prior_n_censored"], meta["prior_stations"]) == (3, 2, 1)
    assert meta["prior_from"] == "the site: 5 tests from 1 station (0 of this station; a 5)"
    assert meta["prior_station_ids"] == ["a"]
    assert meta["method"]["prior_mean"] == pytest.approx(expected[0], rel=1e-12)
    assert meta["method"]["prior_sd"] == pytest.approx(expected[1], rel=1e-12)
    # B keeps the site's lives: a restart while the broker is down still has them
    with open(root_b / "b" / STORE_NAME) as f:
        kept = json.load(f)["stations"]
    assert list(kept) == ["a"] and len(kept["a"]) == 5
    # the second test of B (the broker down): A's lives and B's own first test, if it gave one
    own = [t.life() for t in read_history(str(root_b / "b")) if t.life() is not None]
    xs = list(FAILURES) + [v for k, v in own if k == "failure"]
    cs = [n * 0.02 for n in STOPPED] + [v for k, v in own if k == "censored"]
    again = history_prior(xs, cs)
    assert meta2["prior_source"] == "history" and (meta2["prior_n"], meta2["prior_n_censored"]) == (
        len(xs), len(cs))
    assert meta2["method"]["prior_mean"] == pytest.approx(again[0], rel=1e-12)
    assert meta2["method"]["prior_sd"] == pytest.approx(again[1], rel=1e-12)


def test_box_b_joining_through_another_rabbitmq_node_gets_the_site_prior_of_box_a(tmp_path, rabbitmq_cluster):
    root_a, root_b = tmp_path / "A" / "records", tmp_path / "B" / "records"
    seed_box_a(root_a)
    expected = history_prior(list(FAILURES), [n * 0.02 for n in STOPPED])
    cluster = rabbitmq_cluster
    node1, node2 = cluster.nodes[0], cluster.nodes[1]
    mes = Mes([("127.0.0.1", node1.mqtt_port)], "hookwatch/lab/+/+/+/lives").start()
    gw_a = gw_b = None
    try:
        dev = tmp_path / "absent"
        st_a = station_yaml(tmp_path, {"meter": str(dev / "meter"), "stm32": str(dev / "stm32")},
                            name="a", mqtt={"enabled": True, "servers": [cluster.servers[0]],
                                            "protocol": "3.1.1"},
                            extra={"recorder": {"dir": str(root_a)}})
        gw_a = run_gateway(tmp_path, st_a, name="gw-a")
        wait_for(lambda: [m for m in mes.snapshot() if m[0] == "hookwatch/lab/test/l1/a/lives"], 120,
                 what="A's lives on node 1")
        with virtual_station(tmp_path, quick_scenario(tmp_path, "quick.yaml")) as (_sim, links):
            st_b = station_yaml(tmp_path, links, name="b", method=QUICK_METHOD,
                                test={"t_end_s": QUICK_END},
                                mqtt={"enabled": True, "servers": [cluster.servers[1]], "protocol": "3.1.1"},
                                extra={"recorder": {"dir": str(root_b)}})
            gw_b = run_gateway(tmp_path, st_b, name="gw-b")
            wait_log(gw_b, f"connected to 127.0.0.1:{node2.mqtt_port}", 120)
            wait_log(gw_b, "the site's lives: 5 tests of 1 other station(s)", 120)
            pub(node2.mqtt_port, "hookwatch/lab/test/l1/b/cmd/start",
                '{"sample_id": "B-1", "grade": "I", "t_set": 0.5}')
            meta_path = wait_for(lambda: _sidecar(root_b / "b"), 120, what="B's test started")
            with open(meta_path) as f:
                meta = yaml.safe_load(f)
    finally:
        for gw in (gw_b, gw_a):
            if gw is not None:
                gw.stop()
        mes.stop()
    assert mes.violations == []
    assert meta["prior_source"] == "history"
    assert (meta["prior_n"], meta["prior_n_censored"], meta["prior_stations"]) == (3, 2, 1)
    assert meta["method"]["prior_mean"] == pytest.approx(expected[0], rel=1e-12)
    assert meta["method"]["prior_sd"] == pytest.approx(expected[1], rel=1e-12)


def _sidecar(station_dir, nth=1):
    """The sidecar of the station's ``nth`` test (None before it started)."""
    if not station_dir.exists():
        return None
    found = [station_dir / d / "log.meta.yaml" for d in sorted(os.listdir(station_dir))
             if (station_dir / d / "log.meta.yaml").exists()]
    return str(found[nth - 1]) if len(found) >= nth else None
