"""The broker's permissions of a site (gateway/outputs/acl/broker_acl.py, `hookwatch config acl`): what each
identity may write and read, checked against the topics the gateway really publishes (its own
message builders), and every site that would let one box write another's topics refused.

Mosquitto enforces the Sparkplug part below; the brokers enforce the shipped permissions in
tests/deploy/test_deploy_acl.py (Mosquitto, RabbitMQ) and
tests/gateway/outputs/test_acl_prior_e2e.py (a forging box cannot poison a prior)."""
import re

import pytest
from paho.mqtt.client import topic_matches_sub

from gateway.core.command_rules import CommandReply
from gateway.core.records import Event, EventType, StationState
from gateway.outputs.acl import broker_acl as A
from gateway.outputs.mqtt import messages as M
from gateway.outputs.mqtt import schema as S
from gateway.outputs.mqtt.sitelives import lives_topic
from gateway.outputs.sparkplug.namespace import NodeTopics
from kit.broker import ACCEPTED, NOT_AUTHORIZED, Broker, Publisher

A1 = "hookwatch/plant-a/hall-2/line-1/loom-01"
A2 = "hookwatch/plant-a/hall-2/line-1/loom-02"
B1 = "hookwatch/plant-a/hall-3/line-2/loom-31"
NODE = A.SparkplugNode("plant-a", "hall-2-line-1", "loom-01", "scada")


def _site(**kw) -> A.SiteAcl:
    boxes = kw.pop("boxes", (A.Box("box-a", (A.StationTopics("loom-01", A1, ("panel",), sparkplug=NODE),
                                             A.StationTopics("loom-02", A2))),
                             A.Box("box-b", (A.StationTopics("loom-31", B1),))))
    return A.SiteAcl(boxes, kw.pop("commanders", (A.Commander("mes"), A.Commander("op", "panel"))),
                     kw.pop("readers", ("telegraf",)), **kw)


def _grant(gs, who) -> A.Grant:
    return next(g for g in gs if g.identity == who)


def may_write(g: A.Grant, topic: str) -> bool:
    return any(topic_matches_sub(f, topic) for f in g.writes)


def may_read(g: A.Grant, topic: str) -> bool:
    return any(topic_matches_sub(f, topic) for f in g.reads)


def rabbit_writes(g: A.Grant, topic: str) -> bool:
    return re.fullmatch(A.write_regex(g.writes), A.routing_key(topic)) is not None


def published(base: str, station: str) -> list[str]:
    """Every topic a station publishes, from the gateway's own message builders."""
    t = 1772352000.0
    st = StationState(station=station)
    ev = Event(EventType.TEST_ENDED, station, t, "T-1", 10, {"reason": "completed"})
    out = [M.state_message(base, t, st).topic, M.status_message(base, station, t, True).topic,
           M.telemetry_message(base, station, t, {}).topic, lives_topic(base),
           M.reply_message(base, station, t, "stop", "r1", CommandReply(True, "", "r1")).topic,
           S.topic_for(base, "reply") + "/mes/42", S.lives_request_topic(base)]
    out += [m.topic for m in M.event_messages(base, ev, st, None, None)]
    return out


def test_a_box_writes_its_own_stations_and_nobody_elses():
    gs = A.grants(_site())
    a, b = _grant(gs, "box-a"), _grant(gs, "box-b")
    for topic in published(A1, "loom-01") + published(A2, "loom-02"):
        assert may_write(a, topic) and rabbit_writes(a, topic), topic
        if not topic.endswith("/lives_request"):            # the site's one shared topic
            assert not may_write(b, topic) and not rabbit_writes(b, topic), topic
    for topic in published(B1, "loom-31"):
        assert may_write(b, topic) and rabbit_writes(b, topic), topic
    # a station that is in no box's files: nobody may pose as it
    for topic in published("hookwatch/plant-a/hall-2/line-1/loom-99", "loom-99"):
        if topic.endswith("/lives_request"):
            continue
        assert not any(may_write(g, topic) or rabbit_writes(g, topic) for g in gs), topic
    # the result and the events: from the builders above
    assert {f"{A1}/result", f"{A1}/event/test_ended"} <= set(published(A1, "loom-01"))


def test_commands_are_written_by_the_commanders_each_on_its_own_door():
    gs = A.grants(_site())
    mes, op = _grant(gs, "mes"), _grant(gs, "op")
    boxes = [_grant(gs, "box-a"), _grant(gs, "box-b")]
    for base in (A1, A2, B1):
        for name in ("start", "stop", "ack", "hook_replaced"):
            t = S.command_topic(base, name)
            assert may_write(mes, t) and rabbit_writes(mes, t)
            assert not may_write(op, t) and not rabbit_writes(op, t)
            assert not any(may_write(g, t) or rabbit_writes(g, t) for g in boxes)
            assert not may_write(mes, S.command_topic(base, name, "panel"))
    # the panel's door: only on the station that listens on it
    assert may_write(op, S.command_topic(A1, "stop", "panel"))
    assert not may_write(op, S.command_topic(A2, "stop", "panel"))
    # each box reads its own stations' commands, on every door they listen on, and no other's
    a, b = boxes
    assert may_read(a, S.command_topic(A1, "stop")) and may_read(a, S.command_topic(A1, "stop", "panel"))
    assert not may_read(b, S.command_topic(A1, "stop")) and not may_read(a, S.command_topic(B1, "stop"))


def test_every_box_reads_the_sites_lives_and_site_view():
    gs = A.grants(_site())
    for who in ("box-a", "box-b"):
        g = _grant(gs, who)
        for base in (A1, A2, B1):
            for topic in (lives_topic(base), S.topic_for(base, "state"), S.topic_for(base, "status")):
                assert may_read(g, topic), (who, topic)
        assert may_read(g, S.lives_request_topic(A1))
        assert not may_read(g, S.topic_for(B1, "telemetry"))
    for who in ("mes", "op", "telegraf"):
        g = _grant(gs, who)
        assert all(may_read(g, t) for t in published(A1, "loom-01") + published(B1, "loom-31"))
    assert _grant(gs, "telegraf").writes == ()


def test_sparkplug_a_box_is_its_edge_node_and_the_mes_its_host():
    gs = A.grants(_site())
    a, b, mes = _grant(gs, "box-a"), _grant(gs, "box-b"), _grant(gs, "mes")
    n = NodeTopics(NODE.group, NODE.node, NODE.host)
    for topic in n.publications(("loom-01",)):
        assert may_write(a, topic) and rabbit_writes(a, topic) and not may_write(b, topic)
    for topic, _ in n.subscriptions():
        assert may_read(a, topic.replace("+", "loom-01"))
    for topic in (n.topic("NCMD"), n.topic("DCMD", "loom-01"), n.state_topic()):
        assert may_write(mes, topic) and rabbit_writes(mes, topic)
        assert not may_write(a, topic) and not may_write(_grant(gs, "op"), topic)
    # RabbitMQ's sparkplug_b option routes spBv1.0 as spBv1_0: the same permissions hold
    assert re.fullmatch(A.write_regex(a.writes), A.routing_key(n.topic("NBIRTH")).replace("spBv1.0", "spBv1_0"))


def test_sparkplug_permissions_on_a_real_mosquitto(tmp_path):
    """The same on the broker: the node's births pass for its box only, its commands for the MES."""
    users = {"box-a": "a", "box-b": "b", "mes": "m"}
    n = NodeTopics(NODE.group, NODE.node, NODE.host)
    with Broker(tmp_path, users=users, acl=A.mosquitto(A.grants(_site()), [])) as b:
        clients = {u: Publisher(b.port, u, pw) for u, pw in users.items()}
        try:
            for topic in (n.topic("NBIRTH"), n.topic("DDATA", "loom-01")):
                assert clients["box-a"].publish(topic, b"x") in ACCEPTED
                assert clients["box-b"].publish(topic, b"x") == NOT_AUTHORIZED
                assert clients["mes"].publish(topic, b"x") == NOT_AUTHORIZED
            for topic in (n.topic("NCMD"), n.topic("DCMD", "loom-01"), n.state_topic()):
                assert clients["mes"].publish(topic, b"x") in ACCEPTED
                assert clients["box-a"].publish(topic, b"x") == NOT_AUTHORIZED
        finally:
            for c in clients.values():
                c.close()


def test_a_bridge_announces_itself():
    gs = A.grants(_site(bridges=True))
    assert may_write(_grant(gs, "box-a"), A.bridge_topic("hookwatch", "box-a"))
    assert not may_write(_grant(gs, "box-a"), A.bridge_topic("hookwatch", "box-b"))
    assert may_read(_grant(gs, "telegraf"), A.bridge_topic("hookwatch", "box-b"))
    assert not any(may_write(g, A.bridge_topic("hookwatch", "box-a")) for g in A.grants(_site()))


def test_rabbitmq_read_permissions_name_the_subscriptions():
    """RabbitMQ checks a subscription's own filter (its binding key) against the read permission."""
    gs = A.grants(_site())
    a, mes = _grant(gs, "box-a"), _grant(gs, "mes")
    rx = A.read_regex(a.reads, a.read_roots)
    for f in a.reads:
        assert re.fullmatch(rx, A.routing_key(f)), f
    assert re.fullmatch(rx, A.routing_key("hookwatch/plant-a/+/+/+/lives"))
    assert not re.fullmatch(rx, A.routing_key("hookwatch/#"))
    assert not re.fullmatch(rx, A.routing_key(f"{B1}/cmd/+"))
    mx = A.read_regex(mes.reads, mes.read_roots)
    assert re.fullmatch(mx, A.routing_key("hookwatch/plant-a/+/+/+/#"))
    assert re.fullmatch(mx, A.routing_key(f"{A1}/reply"))
    assert not re.fullmatch(mx, A.routing_key("hookwatch/plant-b/#"))


def _problems(site) -> list[str]:
    with pytest.raises(A.AclError) as e:
        A.grants(site)
    return e.value.problems


@pytest.mark.parametrize("site,says", [
    (A.SiteAcl(()), "no box"),
    (_site(boxes=(A.Box("box-a", (A.StationTopics("loom-01", A1),)), A.Box("box-b", (A.StationTopics("x", A1),)))),
     "is in box 'box-a' and in box 'box-b'"),
    (_site(boxes=(A.Box("box-a", (A.StationTopics("loom-01", A1, sparkplug=NODE),)),
                  A.Box("box-b", (A.StationTopics("loom-31", B1, sparkplug=NODE),))), commanders=()),
     "Sparkplug edge node 'hall-2-line-1'"),
    (_site(boxes=(A.Box("box-a", (A.StationTopics("loom-01", A1, reply_prefix=B1),)),
                  A.Box("box-b", (A.StationTopics("loom-31", B1),))), commanders=()),
     f"box 'box-a' would write {B1}/#, which reaches box 'box-b'"),
    (_site(boxes=(A.Box("box-a", (A.StationTopics("loom-01", A1, reply_prefix=f"{A1}/cmd"),)),),
           commanders=()), "which reaches the command door"),
    (_site(readers=("box-a",)), "identity 'box-a' is named twice"),
    (_site(readers=("tele graf",)), "reader identity 'tele graf'"),
    (_site(commanders=(A.Commander("op", "nobody"),)), "no station of the site listens on it"),
    (_site(commanders=(A.Commander("op", "stop"),)), "is a command's name"),
    (_site(commanders=(A.Commander("op", "panel"), A.Commander("op"))), "is given two doors"),
    (_site(boxes=(A.Box("box-a", ()),)), "box 'box-a' has no station"),
    (_site(boxes=(A.Box("box-a", (A.StationTopics("x", "hookwatch/plant a/h/l/x"),)),), commanders=()),
     "a space"),
])
def test_a_site_that_would_let_a_box_trespass_is_refused(site, says):
    found = _problems(site)
    assert any(says in p for p in found), found


def test_rabbitmq_refuses_a_level_it_would_read_as_two():
    site = _site(boxes=(A.Box("box-a", (A.StationTopics("st.1", "hookwatch/plant-a/h/l/st.1"),)),), commanders=())
    gs = A.grants(site)                 # Mosquitto takes it
    assert "user box-a" in A.mosquitto(gs, [])
    with pytest.raises(A.AclError, match="RabbitMQ's MQTT plugin reads as a level separator"):
        A.rabbitmq(gs, [])


def test_overlap():
    assert A.overlap("a/+/c", "a/b/#") and A.overlap("a/#", "a") and A.overlap("+/+", "x/y")
    assert not A.overlap("a/b", "a/c") and not A.overlap("a/b", "a/b/c") and not A.overlap("a/+", "a")


def test_a_sparkplug_only_station_gets_its_node_and_no_json_tree():
    site = A.SiteAcl((A.Box("box-a", (A.StationTopics("loom-01", None, sparkplug=NODE),)),), (A.Commander("mes"),))
    a, mes = A.grants(site)
    n = NodeTopics(NODE.group, NODE.node, NODE.host)
    assert set(a.writes) == set(n.publications(("loom-01",)))
    assert set(a.reads) == {t for t, _ in n.subscriptions()}
    assert set(mes.writes) == {n.topic("NCMD"), n.topic("DCMD", "loom-01"), n.state_topic()}
    assert "hookwatch" not in A.rabbitmq([a, mes], [])
