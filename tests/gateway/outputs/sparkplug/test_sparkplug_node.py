"""The Sparkplug edge node state machine (pure: no broker), decoded with our generated code."""
from __future__ import annotations

import ast
import json
import os

from conftest import ROOT
from gateway.outputs.sparkplug import metrics as M
from gateway.outputs.sparkplug.actions import Disconnect, Publish, Submit
from gateway.outputs.sparkplug.namespace import DEVICE_OUT, NODE_OUT
from gateway.outputs.sparkplug.node import EdgeNode
from gateway.outputs.sparkplug.sparkplug_b_pb2 import Payload


def dec(p: Publish) -> Payload:
    x = Payload()
    x.ParseFromString(p.payload)
    return x


def kinds(outs) -> list[str]:
    return [o.topic.split("/")[2] for o in outs if isinstance(o, Publish)]


def state(online: bool, ts: int) -> bytes:
    return json.dumps({"online": online, "timestamp": ts}).encode()


def online_node(**kw) -> EdgeNode:
    kw.setdefault("rebirth_min_interval_ms", 0)     # the rate limit: test_sparkplug_inbound.py
    n = EdgeNode("plant-a", "hall-2-line-3", primary_host_id="scada", **kw)
    n.connecting()
    n.device_up("loom-01", {"Test/State": "idle"}, 1)
    assert n.connected_ok(2) == []                      # waits for the host's STATE
    outs = n.host_state(state(True, 10), 3)
    assert kinds(outs) == ["NBIRTH", "DBIRTH"]
    return n


def test_will_and_bdseq_sequence():
    n = EdgeNode("g", "e")
    will = n.connecting()
    assert (will.topic, will.qos, will.retain) == ("spBv1.0/g/NDEATH/e", 1, False)
    assert dec(will).metrics[0].name == "bdSeq" and dec(will).metrics[0].long_value == 0
    birth = n.connected_ok(5)[0]
    b = dec(birth)
    assert b.seq == 0 and [m.long_value for m in b.metrics if m.name == "bdSeq"] == [0]
    rebirth = [m for m in b.metrics if m.name == M.REBIRTH][0]
    assert not rebirth.HasField("alias") and rebirth.datatype == 11 and rebirth.boolean_value is False
    n.disconnected()
    assert dec(n.connecting()).metrics[0].long_value == 1
    # a refused TCP connection sent no CONNECT: its bdSeq is not used up
    n.connecting()
    n.connect_failed()
    assert dec(n.connecting()).metrics[0].long_value == 2
    # a restart continues after the persisted value, wrapping at 256
    n2 = EdgeNode("g", "e", last_bdseq=255)
    assert dec(n2.connecting()).metrics[0].long_value == 0


def test_dbirth_has_every_metric_and_ddata_uses_aliases_only():
    n = online_node()
    outs = n.device_update("loom-01", {"Test/State": "monitoring", "Tension/T1": 0.5}, 4)
    assert kinds(outs) == ["DDATA"]
    d = dec(outs[0])
    assert all(not m.name and m.alias and not m.HasField("datatype") and m.timestamp for m in d.metrics)
    n2 = online_node()
    birth = [o for o in n2.rebirth(9) if "DBIRTH" in o.topic][0]
    b = dec(birth)
    assert [m.name for m in b.metrics] == [m.name for m in M.DEVICE_METRICS]
    aliases = {m.alias: m.name for m in b.metrics}
    assert len(aliases) == len(M.DEVICE_METRICS)
    assert {aliases[m.alias] for m in d.metrics} == {"Test/State", "Tension/T1"}
    t1 = [m for m in b.metrics if m.name == "Tension/T1"][0]
    assert dict(zip(t1.properties.keys, [v.string_value for v in t1.properties.values]))["engUnit"] == "N"


def test_seq_wraps_and_nbirth_resets():
    n = online_node()
    seqs = []
    for i in range(300):
        o = n.device_update("loom-01", {"Tension/T1": float(i)}, 10 + i)
        seqs.append(dec(o[0]).seq)
    assert seqs[:3] == [2, 3, 4] and 255 in seqs and seqs[seqs.index(255) + 1] == 0
    assert dec(n.rebirth(999)[0]).seq == 0


def test_host_offline_holds_data_and_replays_historical_in_order():
    n = online_node()
    outs = n.host_state(state(False, 20), 30)
    assert kinds(outs) == ["NDEATH"] and isinstance(outs[-1], Disconnect)
    n.disconnected()
    n.connecting()
    assert n.connected_ok(31) == []
    for i in range(120):
        assert n.device_update("loom-01", {"Tension/T1": float(i)}, 100 + i) == []
    assert len(n.buffer) == 120
    # STATE timestamps are compared within one session: the retained offline STATE this session
    # starts with, then an older online one, which is ignored
    assert n.host_state(state(False, 45), 39) == []
    assert n.host_state(state(True, 5), 40) == []       # older than the last STATE seen: ignored
    outs = n.host_state(state(True, 50), 300)
    assert kinds(outs) == ["NBIRTH", "DBIRTH"] and n.replaying
    # live data during the replay waits behind the history
    assert n.device_update("loom-01", {"Tension/T1": 999.0}, 301) == []
    got = []
    while n.replaying:
        pubs, keys = n.drain(302)
        n.buffer.remove(keys)
        got.extend(pubs)
    values = [(dec(p).metrics[0].float_value, dec(p).metrics[0].is_historical) for p in got]
    assert values[:120] == [(float(i), True) for i in range(120)]
    assert values[-1] == (999.0, False)
    assert [dec(p).seq for p in got] == [(2 + i) % 256 for i in range(len(got))]


def test_rebirth_and_node_controls():
    n = online_node()
    cmd = Payload()
    m = cmd.metrics.add()
    m.name = M.REBIRTH
    m.boolean_value = True
    assert kinds(n.command("spBv1.0/plant-a/NCMD/hall-2-line-3", cmd.SerializeToString(), 5)) == \
        ["NBIRTH", "DBIRTH"]
    m.name = M.NEXT_SERVER
    outs = n.command("spBv1.0/plant-a/NCMD/hall-2-line-3", cmd.SerializeToString(), 6)
    assert kinds(outs) == ["NDEATH"] and outs[-1].next_server
    assert n.command("spBv1.0/plant-a/NCMD/hall-2-line-3", b"\xff\xff garbage", 7) == []


def test_dcmd_becomes_a_submit_by_name_or_alias():
    n = online_node()
    base = n.devices["loom-01"].alias_base
    idx = {d.name: i for i, d in enumerate(M.DEVICE_METRICS)}
    p = Payload()
    a = p.metrics.add()
    a.alias = base + idx[M.START]
    a.boolean_value = True
    b = p.metrics.add()
    b.name = M.ARG_SAMPLE_ID
    b.string_value = "S-9"
    c = p.metrics.add()
    c.name = M.ARG_T_SET
    c.float_value = 0.5
    outs = n.command("spBv1.0/plant-a/DCMD/hall-2-line-3/loom-01", p.SerializeToString(), 5)
    assert outs == [Submit("loom-01", "start", {"sample_id": "S-9", "t_set": 0.5})]
    assert n.command("spBv1.0/plant-a/DCMD/hall-2-line-3/other", p.SerializeToString(), 5) == []


def test_station_stopped_while_offline_is_born_replayed_then_buried():
    n = online_node()
    n.host_state(state(False, 20), 30)
    n.disconnected()
    n.connecting()
    n.connected_ok(31)
    n.device_update("loom-01", {"Tension/T1": 1.0}, 32)
    assert n.device_down("loom-01", 33) == []
    outs = n.host_state(state(True, 50), 40)
    assert kinds(outs) == ["NBIRTH", "DBIRTH"]
    pubs, keys = n.drain(41)
    assert kinds(pubs) == ["DDATA", "DDEATH"] and "loom-01" not in n.devices


def test_alias_blocks_of_two_devices_never_overlap(monkeypatch):
    monkeypatch.setattr(M, "device_alias_base", lambda device_id: 7 << 12)   # a forced CRC clash
    n = online_node()
    n.device_up("loom-02", {}, 5)
    a, b = n.devices["loom-01"].alias_base, n.devices["loom-02"].alias_base
    assert a != b and abs(a - b) >= len(M.DEVICE_METRICS)


def test_bad_state_and_commands_are_counted_not_fatal():
    n = online_node()
    for bad in (b"", b"online", b'{"online": "yes", "timestamp": 1}', b'{"online": true}', b"\xff"):
        assert n.host_state(bad, 5) == []
    assert n.publishing
    assert n.command("spBv1.0/plant-a/DCMD/hall-2-line-3/loom-01", b"\x0a\xff", 6) == []
    assert n.counters["ignored_commands"] >= 6


def test_store_not_writable_holds_rows_in_memory_then_writes_them(tmp_path):
    import sqlite3

    from gateway.outputs.broker.outbox import Outbox
    from gateway.outputs.sparkplug.node_store import OutboxBuffer

    ob = Outbox(str(tmp_path / "s.sqlite"))
    buf = OutboxBuffer(ob, memory_max=5)
    buf.put("t/a", b"1", True)
    real_add = ob.add

    def full(*a, **k):
        raise sqlite3.OperationalError("database or disk is full")
    ob.add = full
    for i in range(2, 9):
        buf.put("t/a", str(i).encode(), i != 4)      # 4 is a state change: never dropped first
    assert buf.store_errors >= 1 and len(buf.memory) == 5 and buf.dropped == 2
    assert [p for _k, _t, p in buf.peek(10)] == [b"1", b"4", b"5", b"6", b"7", b"8"]
    ob.add = real_add
    buf.put("t/a", b"9", True)
    assert not buf.memory and ob.count() == 7
    got = buf.peek(10)
    assert [p for _k, _t, p in got] == [b"1", b"4", b"5", b"6", b"7", b"8", b"9"]
    buf.remove([k for k, _t, _p in got])
    assert len(buf) == 0
    ob.close()



#: the edge node and its parts: pure (the node's thread, session, stations and store are the others)
PURE_NODE = ("node", "actions", "namespace", "bdseq", "payloads", "devices", "primary_host", "pacing",
             "node_commands", "replay", "inbound", "metrics")
PKG = "gateway.outputs.sparkplug"
#: what a pure module of the node must not import: I/O, clocks, threads, and the node's runtime side
IMPURE_TOP = {"time", "datetime", "threading", "asyncio", "socket", "sqlite3", "logging", "os", "paho"}
IMPURE = {"gateway.outputs.broker.outbox", "gateway.plumbing.threadloop"} | {
    f"{PKG}.{m}" for m in ("runtime", "node_session", "node_stations", "node_store", "output")}


def _imports(src: str, package: str = PKG) -> list[str]:
    """The absolute names of the modules (and names) a module of ``package`` imports."""
    out = []
    for n in ast.walk(ast.parse(src)):
        if isinstance(n, ast.Import):
            out += [a.name for a in n.names]
        elif isinstance(n, ast.ImportFrom):
            base = ".".join(package.split(".")[:len(package.split(".")) - n.level + 1]) if n.level else ""
            mod = ".".join(x for x in (base, n.module or "") if x)
            out += [mod] + [f"{mod}.{a.name}" for a in n.names]
    return out


def _impure(src: str) -> list[str]:
    return [m for m in _imports(src) if m.split(".")[0] in IMPURE_TOP
            or any(m == x or m.startswith(x + ".") for x in IMPURE)]


def test_the_edge_node_and_its_parts_are_pure():
    """The edge node is a pure state machine (no sockets, no clock, no threads) and so is each part
    it was split into: none imports I/O, a clock or a thread, nor the node's runtime side."""
    assert _impure("import time\nfrom . import runtime\nfrom .node_store import NodeStore\n"
                   "from ..broker.outbox import Outbox\nfrom ...plumbing.threadloop import Mailbox\n"
                   "from .devices import Device\n"
                   "from . import metrics as M\n") == [
        "time", f"{PKG}.runtime", f"{PKG}.node_store", f"{PKG}.node_store.NodeStore",
        "gateway.outputs.broker.outbox", "gateway.outputs.broker.outbox.Outbox", "gateway.plumbing.threadloop",
        "gateway.plumbing.threadloop.Mailbox"]
    bad = {}
    for mod in PURE_NODE:
        with open(os.path.join(ROOT, *PKG.split("."), f"{mod}.py"), encoding="utf-8") as f:
            found = _impure(f.read())
        if found:
            bad[mod] = found
    assert bad == {}


def test_the_node_publishes_only_the_verbs_its_permissions_name():
    """The broker's permissions (gateway/outputs/acl/broker_acl.py) give a node NODE_OUT and DEVICE_OUT of its
    namespace and nothing else: every topic the node's code builds uses one of them."""
    folder = os.path.join(ROOT, "gateway", "outputs", "sparkplug")
    verbs = set()
    for name in ("payloads.py", "replay.py", "node.py", "node_session.py", "runtime.py"):
        with open(os.path.join(folder, name), encoding="utf-8") as f:
            tree = ast.parse(f.read())
        for n in ast.walk(tree):
            if (isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "topic"
                    and n.args and isinstance(n.args[0], ast.Constant)):
                verbs.add(n.args[0].value)
    assert verbs and verbs <= set(NODE_OUT) | set(DEVICE_OUT), verbs
