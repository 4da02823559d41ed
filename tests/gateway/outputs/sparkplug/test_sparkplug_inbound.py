"""What the edge node receives, bounded (pure: the state machine, no broker): hostile STATE
payloads, oversized or over-long NCMD/DCMD, a STATE from the future, a Rebirth flood, the
rate-limited log of bad inputs, and the one thread→loop hand-over."""
from __future__ import annotations

import json
import os

import pytest

from conftest import ROOT
from gateway.outputs.sparkplug import metrics as M
from gateway.outputs.sparkplug.actions import Disconnect, Publish
from gateway.outputs.sparkplug.inbound import InboundLimits, parse_state
from gateway.outputs.sparkplug.node import EdgeNode
from gateway.outputs.sparkplug.sparkplug_b_pb2 import Payload

NCMD = "spBv1.0/plant-a/NCMD/hall-2-line-3"
DCMD = "spBv1.0/plant-a/DCMD/hall-2-line-3/loom-01"

HOSTILE_STATES = [
    b"[" * 100_000 + b"]" * 100_000,                                   # RecursionError in json
    b'{"online": true, "timestamp": ' + b"[" * 50_000 + b"]" * 50_000 + b"}",
    b'{"online": true, "timestamp": [[[[[[[[1]]]]]]]]}',                  # nested (small)
    b'{"online": true, "timestamp": 1e400}',                            # inf → int() overflow
    b'{"online": false, "timestamp": 1e400}',
    b'{"online": true, "timestamp": ' + b"9" * 5000 + b"}",             # a 5000-digit integer
    b'{"online": true, "timestamp": -1}',
    b'{"online": true, "timestamp": 18446744073709551616}',
    b'{"online": true, "timestamp": NaN}',
    b'{"online": true, "timestamp": 1.5}',
    b'{"online": true, "online": false, "timestamp": 5}',
    b'{"online": 1, "timestamp": 5}',
    b'{"online": true, "timestamp": "5"}',
    b'{"online": true, "timestamp": 5, "pad": "' + b"x" * 5000 + b'"}',
    b"\xff\xfe",
    b"",
    b"null",
]


def kinds(outs) -> list[str]:
    return [o.topic.split("/")[2] for o in outs if isinstance(o, Publish)]


def state(online: bool, ts: int) -> bytes:
    return json.dumps({"online": online, "timestamp": ts}).encode()


def online_node(**kw) -> EdgeNode:
    n = EdgeNode("plant-a", "hall-2-line-3", primary_host_id="scada", **kw)
    n.connecting()
    n.device_up("loom-01", {"Test/State": "idle"}, 1)
    assert n.connected_ok(2) == []
    assert kinds(n.host_state(state(True, 10), 3)) == ["NBIRTH", "DBIRTH"]
    return n


def ncmd(name: str, n: int = 1, **value) -> bytes:
    p = Payload()
    for _ in range(n):
        m = p.metrics.add()
        m.name = name
        if value:
            for k, v in value.items():
                setattr(m, k, v)
        else:
            m.boolean_value = True
    return p.SerializeToString()


@pytest.mark.parametrize("bad", HOSTILE_STATES, ids=range(len(HOSTILE_STATES)))
def test_a_hostile_state_is_counted_never_raised(bad):
    n = online_node()
    assert n.host_state(bad, 100) == []
    assert n.publishing, "a bad STATE must change nothing"
    assert n.counters["bad_state"] == 1
    [(kind, reason)] = n.take_bad()
    assert kind == "state" and len(reason) < 200          # the payload is never echoed whole
    # the session goes on: a good STATE still counts
    assert kinds(n.host_state(state(False, 20), 101)) == ["NDEATH"]


def test_state_parser_accepts_the_spec_form_only():
    lim = InboundLimits()
    assert parse_state(b'{"online": true, "timestamp": 1700000000000}', lim) == (True, 1700000000000)
    assert parse_state(b' {"timestamp": 0, "online": false, "extra": [1]} ', lim) == (False, 0)


def test_command_payloads_are_bounded_before_and_after_decoding():
    n = online_node(limits=InboundLimits(max_payload_bytes=2048, max_metrics=8, max_string_chars=64))
    assert n.command(NCMD, b"\x00" * 2049, 5) == []
    assert n.counters["bad_ncmd"] == 1
    assert n.command(NCMD, ncmd(M.REBIRTH, 9), 5) == []                 # 9 metrics > 8
    assert n.command(DCMD, ncmd(M.ARG_SAMPLE_ID, 1, string_value="x" * 65), 5) == []
    assert n.command(NCMD, ncmd("x" * 65), 5) == []                      # a 65-character name
    deep = Payload()
    m = deep.metrics.add()
    m.name = "t"
    t = m.template_value
    for _ in range(150):                         # nested templates: the decoder's recursion limit
        t = t.metrics.add().template_value
    assert n.command(NCMD, deep.SerializeToString()[:2048], 5) == []
    assert n.command("spBv1.0/plant-a/NCMD/other-node", ncmd(M.REBIRTH), 5) == []
    assert n.counters["bad_ncmd"] >= 4 and n.counters["bad_dcmd"] == 1 and n.counters["bad_topic"] == 1
    assert n.publishing
    # a good one still works
    assert kinds(n.command(NCMD, ncmd(M.REBIRTH), 5000)) == ["NBIRTH", "DBIRTH"]


def test_rebirth_flood_gives_one_birth_per_interval_and_one_coalesced():
    n = online_node(rebirth_min_interval_ms=2000)
    births = []
    t = 3
    for i in range(3000):                        # 3000 requests within 3 s of node time
        t = 3 + i
        births += kinds(n.command(NCMD, ncmd(M.REBIRTH), t))
        births += kinds(n.tick(t))
    # the first request falls inside the interval of the session's own birth (at 3 ms): pending;
    # due at 2003 ms: one birth; the requests after it: pending again, due at 4003 ms
    assert births.count("NBIRTH") == 1, births.count("NBIRTH")
    assert n.pacing.rebirth_pending and n.counters["rebirths_coalesced"] > 2900
    assert n.tick(t + 1) == []
    assert kinds(n.tick(4003)) == ["NBIRTH", "DBIRTH"]
    assert not n.pacing.rebirth_pending and n.tick(10_000) == []


def test_reboot_and_next_server_floods_end_one_session_per_interval():
    """Issue 27: Reboot and Next Server are rate-limited like Rebirth (one session end per
    interval after the birth and after the last one; the rest coalesced into one, Next Server
    over Reboot, carried out by tick when due)."""
    n = online_node(rebirth_min_interval_ms=2000)       # born at 3 ms
    ends: list[Disconnect] = []
    deaths = 0
    for i in range(300):                         # 300 requests within 300 ms of node time
        t = 4 + i
        name = M.NEXT_SERVER if i == 150 else M.REBOOT
        for o in list(n.command(NCMD, ncmd(name), t)) + list(n.tick(t)):
            if isinstance(o, Disconnect):
                ends.append(o)
            elif isinstance(o, Publish) and "/NDEATH/" in o.topic:
                deaths += 1
    # inside the interval of the session's own birth: nothing yet, one pending (Next Server wins)
    assert ends == [] and deaths == 0
    assert n.pacing.disconnect_pending == Disconnect(M.NEXT_SERVER, next_server=True)
    assert n.counters["reboots_coalesced"] == 299
    out = n.tick(2003)
    assert kinds(out) == ["NDEATH"] and out[-1] == Disconnect(M.NEXT_SERVER, next_server=True)
    assert n.pacing.disconnect_pending is None and n.counters["reboots"] == 1
    # a new session (born at 2100); a Reboot right after its birth waits for the interval
    n.disconnected()
    n.connecting()
    assert n.connected_ok(2050) == []
    assert kinds(n.host_state(state(True, 20), 2100)) == ["NBIRTH", "DBIRTH"]
    assert n.command(NCMD, ncmd(M.REBOOT), 2200) == [] and n.tick(4099) == []
    out = n.tick(4100)
    assert kinds(out) == ["NDEATH"] and out[-1] == Disconnect(M.REBOOT)
    # a session that ends otherwise takes its pending request with it
    n.disconnected()
    n.connecting()
    n.connected_ok(4200)
    n.host_state(state(True, 30), 4300)
    assert n.command(NCMD, ncmd(M.REBOOT), 4400) == []
    n.disconnected()
    assert n.pacing.disconnect_pending is None and n.tick(10_000) == []


def test_a_state_from_the_future_cannot_lock_the_host_out():
    now = 1_800_000_000_000
    n = EdgeNode("plant-a", "hall-2-line-3", primary_host_id="scada", state_future_skew_ms=300_000)
    n.connecting()
    n.connected_ok(now)
    year = 365 * 24 * 3600 * 1000
    assert kinds(n.host_state(state(True, now + 10 * year), now)) == ["NBIRTH"]
    assert n.counters["future_state"] == 1
    # the host, with a correct clock, goes offline: acted on (the future stamp was taken as now)
    outs = n.host_state(state(False, now + 1000), now + 1000)
    assert kinds(outs) == ["NDEATH"] and isinstance(outs[-1], Disconnect) and outs[-1].next_server
    n.disconnected()
    # a new session compares nothing with the old one: a STATE older than the last one is fine
    n.connecting()
    n.connected_ok(now + 2000)
    assert kinds(n.host_state(state(True, now - 5000), now + 2000)) == ["NBIRTH"]
    # within a session a stale offline is ignored (spec: -termination-host-offline-timestamp)
    assert n.host_state(state(False, now - 6000), now + 2001) == []
    assert n.publishing and n.counters["stale_state"] == 1
    # a small skew ahead is kept as is
    assert n.host_state(state(True, now + 60_000), now + 2002) == []
    assert n.host_state(state(False, now + 3000), now + 3000) == []      # older than +60 s: stale
    assert kinds(n.host_state(state(False, now + 61_000), now + 4000)) == ["NDEATH"]


def test_one_thread_to_loop_hand_over():
    """The Sparkplug node's thread reaches a station's loop through gateway/plumbing/threadloop.py only
    (it used to call asyncio.run_coroutine_threadsafe itself)."""
    bad = []
    for d, _dirs, files in os.walk(os.path.join(ROOT, "gateway", "outputs", "sparkplug")):
        for f in files:
            if f.endswith(".py"):
                p = os.path.join(d, f)
                with open(p, encoding="utf-8") as fh:
                    if "run_coroutine_threadsafe(" in fh.read():
                        bad.append(os.path.relpath(p, ROOT))
    assert bad == []
