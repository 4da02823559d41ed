"""Issue 12, items 1, 8, 10: bounded command intake (gateway/core/command_intake.py) — pure
checks, and a hypothesis fuzzer of MQTT commands through a real Mosquitto into a running station."""
import json
import threading

import paho.mqtt.client as paho
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from paho.mqtt.enums import CallbackAPIVersion

from gateway.core.command_intake import ECHO_CHARS, clip, nesting_depth, parse_command, rejected_event_data
from gateway.core.records import Command, CommandKind
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from gateway.plumbing.ratelog import RefusalWindow
from gateway.station.command_desk import Rejection
from kit.broker import Broker, Sub, check_message
from kit.northbound import LoopThread, RunningStation, make_station
from kit.tools import wait_for

BASE = "hookwatch/lab/hall/l1/st1"


def code(r):
    return 0 if isinstance(r, Command) else r.code


@pytest.mark.parametrize("payload", [
    b"[" * 50_000 + b"]" * 50_000,                     # deep nesting: refused on size
    b"[" * 1000,                                       # deep and cut off
    b'{"t_set": ' + b"[" * 2000 + b"]" * 2000 + b"}",
    b'{"a":{"b":{"c":{"d":{"e":1}}}}}',                # 5 levels
])
def test_deep_payloads_are_refused_before_json_recursion(payload):
    r = parse_command("start", payload)
    assert isinstance(r, Rejection) and r.code == 9 and len(r.reason) < 200


def test_numbers_strings_and_types_are_bounded():
    r = parse_command("setpoint", b'{"t_set": ' + b"9" * 400 + b"}")
    assert code(r) == 9 and "400 characters" in r.reason          # no OverflowError
    r = parse_command("setpoint", b'{"t_set": 1e999999}')
    assert code(r) == 9 or code(r) == 0 and r.args["t_set"] == float("inf")
    assert code(parse_command("setpoint", b'{"t_set": "0.6"}')) == 9
    assert code(parse_command("setpoint", b'{"t_set": true}')) == 9
    assert code(parse_command("setpoint", b'{"t_set": NaN}')) == 9
    assert code(parse_command("start", b'{"sample_id": 5, "t_set": 0.5}')) == 9
    assert code(parse_command("start", b'{"sample_id": "a", "sample_id": "b", "t_set": 0.5}')) == 9
    ok = parse_command("start", b'{"sample_id": "S-1", "t_set": 0.6, "grade": "I", "request_id": "r"}')
    assert isinstance(ok, Command) and ok.kind == CommandKind.START and ok.args["t_set"] == 0.6
    assert ok.request_id == "r" and ok.source == "mqtt"
    assert isinstance(parse_command("stop", b""), Command)
    assert isinstance(parse_command("ack", b"  {}  "), Command)


def test_long_input_is_never_echoed_in_full():
    big = "x" * 1_000_000
    for name, payload in [("start", json.dumps({"sample_id": big, "t_set": 0.5}).encode()),
                          ("start", json.dumps({"sample_id": "S", "t_set": 0.5, big[:3000]: 1}).encode()),
                          ("y" * 100_000, b"{}"),
                          ("start", b"\xff" * 3000),
                          ("start", b"{" + b"x" * 3000)]:
        r = parse_command(name, payload)
        assert isinstance(r, Rejection) and r.code == 9
        assert len(r.reason) < 300, r.reason
        ev = rejected_event_data(name, r, "mqtt")
        assert len(json.dumps(ev)) < 500
    assert len(clip("z" * 10_000)) < ECHO_CHARS + 30


def test_nesting_scan_ignores_brackets_in_strings():
    assert nesting_depth(b'{"a": "[[[[[[[[[[", "b": [1]}', 10) == 2
    assert nesting_depth(b'{"a": "\\"[[[[["}', 10) == 1


def _depth_byte_by_byte(data: bytes, limit: int) -> int:
    """The scan as it was written first (a Python loop over every byte): the reference."""
    depth = deepest = 0
    in_str = esc = False
    for b in data:
        if in_str:
            if esc:
                esc = False
            elif b == 0x5C:
                esc = True
            elif b == 0x22:
                in_str = False
        elif b == 0x22:
            in_str = True
        elif b in (0x5B, 0x7B):
            depth += 1
            if depth > deepest:
                deepest = depth
                if deepest > limit:
                    return deepest
        elif b in (0x5D, 0x7D):
            depth -= 1
    return deepest


@settings(max_examples=2000, deadline=None)
@given(st.lists(st.sampled_from([b"[", b"]", b"{", b"}", b'"', b"\\", b"a", b",", b":", b" "]), max_size=60),
       st.integers(0, 12))
def test_the_fast_nesting_scan_is_the_byte_by_byte_one(parts, limit):
    """Issue 34: the scan at C speed (strings removed, brackets walked) gives what the byte-by-byte
    scan gives, for any bytes (unterminated strings, stray escapes, unbalanced brackets)."""
    data = b"".join(parts)
    assert nesting_depth(data, limit) == _depth_byte_by_byte(data, limit)


def test_refusal_window_reports_the_first_and_counts_the_rest():
    w = RefusalWindow(window_s=60.0)
    assert [w.add("k", 0.0, "a"), w.add("k", 1.0, "b"), w.add("k", 2.0, "c"), w.add("j", 2.0)] == [1, 0, 0, 1]
    assert w.next_due() == 60.0 and w.due(59.0) == []
    assert w.due(60.0) == [("k", 2, ("c",))]      # the count of the window, with the last detail
    assert w.add("k", 61.0) == 1                  # a new window


# ------------------------------------------------------------------ the fuzzer through Mosquitto
json_leaf = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**6),
                      st.floats(allow_nan=False), st.text(max_size=80))
json_val = st.recursive(json_leaf,
                        lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=12), c, max_size=4),
                        max_leaves=12)
fields = st.fixed_dictionaries({}, optional={
    "sample_id": st.one_of(st.text(max_size=40), st.text(min_size=5000, max_size=6000), json_val),
    "t_set": st.one_of(st.floats(), st.integers(-10**3, 10**3), st.just("0.6"), json_val),
    "grade": st.one_of(st.sampled_from(["I", "II", "III"]), json_val),
    "t_end": st.one_of(st.floats(0, 1e9), json_val),
    "request_id": st.one_of(st.text(max_size=100), json_val),
})


def _dump(d):
    return json.dumps(d, allow_nan=True).encode()


payloads = st.one_of(
    fields.map(_dump),
    json_val.map(_dump),
    st.binary(max_size=300),
    st.integers(1, 20_000).map(lambda n: b"[" * n + b"]" * n),
    st.integers(1, 2_000).map(lambda n: b'{"t_set": ' + b"7" * n + b"}"),
    st.integers(4000, 70_000).map(lambda n: b'{"sample_id": "' + b"A" * n + b'"}'),
)
names = st.sampled_from(["start", "stop", "ack", "setpoint", "frob", "x" * 300, "reply", ""])


class Cmds:
    """A paho client publishing commands; one request at a time, waiting for its reply."""

    def __init__(self, port):
        self.c = paho.Client(CallbackAPIVersion.VERSION2, client_id="fuzz", protocol=paho.MQTTv311)
        self.replies: list[dict] = []
        self.sizes: list[int] = []
        self.status: list[str] = []
        self.bad: list[str] = []
        self.cv = threading.Condition()
        self.c.on_message = self._msg
        self.c.connect("127.0.0.1", port)
        self.c.subscribe([(BASE + "/reply", 1), (BASE + "/status", 1)])
        self.c.loop_start()

    def _msg(self, c, u, m):
        bad = check_message(m.topic, m.payload)     # pure: fine on paho's thread; raised in ask()
        with self.cv:
            if bad:
                self.bad.append(bad)
            if m.topic.endswith("/status"):
                self.status.append(json.loads(m.payload).get("status"))
            else:
                self.replies.append(json.loads(m.payload))
                self.sizes.append(len(m.payload))
            self.cv.notify_all()

    def ask(self, name, payload, timeout=20.0):
        with self.cv:
            n = len(self.replies)
        self.c.publish(f"{BASE}/cmd/{name}", payload, qos=1).wait_for_publish(10)
        with self.cv:
            assert self.cv.wait_for(lambda: len(self.replies) > n, timeout), (name, payload[:80])
            assert len(self.replies) == n + 1
            assert not self.bad, self.bad[0]
            return self.replies[n], self.sizes[n]

    def close(self):
        self.c.loop_stop()
        self.c.disconnect()


@pytest.fixture(scope="module")
def mqtt_station(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fuzz")
    lt = LoopThread()
    with Broker(tmp) as b:
        station = make_station(tmp, [])
        out = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, port=b.port,
                                      outbox_path=str(tmp / "outbox.sqlite"), reconnect_min_s=0.2,
                                      reconnect_max_s=1.0), station)
        station.outputs.append(out)
        lt.call(out.start())
        run = RunningStation(lt, station)
        wait_for(lambda: out.connected, 20, what="connected")
        sub = Sub(b.port, BASE + "/event/command_rejected")
        cmds = Cmds(b.port)
        try:
            yield station, out, cmds, sub
        finally:
            cmds.close()
            sub.stop()
            run.stop()
            lt.call(out.stop())
            lt.close()


@settings(max_examples=120, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
@given(name=names, payload=payloads)
def test_fuzzed_mqtt_commands_each_get_one_small_reply_and_the_link_stays_up(mqtt_station, name, payload):
    station, out, cmds, _sub = mqtt_station
    slots = station.stats.slots
    r, size = cmds.ask(name, payload)
    assert isinstance(r["ok"], bool) and isinstance(r["code"], int)
    if not r["ok"]:
        assert r["code"] > 0 and r["reason"]
    # no amplification: the reply stays small whatever came in
    assert size < 1500, (size, r)
    assert out.connected
    wait_for(lambda: station.stats.slots > slots + 2, 10, what="slots keep filling")


def test_after_fuzzing_the_station_still_answers_and_events_are_bounded(mqtt_station):
    station, out, cmds, sub = mqtt_station
    if station.monitor is not None:
        r, _ = cmds.ask("stop", b"{}")
        assert r["ok"]
    r, _ = cmds.ask("start", b'{"sample_id": "S-ok", "t_set": 0.5, "request_id": "fin"}')
    assert r["ok"] and r["request_id"] == "fin"
    r, _ = cmds.ask("setpoint", b'{"t_set": "0.6"}')
    assert r["code"] == 9
    r, _ = cmds.ask("setpoint", b'{"t_set": ' + b"4" * 400 + b"}")
    assert r["code"] == 9 and "OverflowError" not in r["reason"]
    assert out.connected and cmds.status[-1] == "online"
    evs = sub.messages("command_rejected")
    assert evs and any(e[2]["data"].get("code") == 9 for e in evs)
    assert max(len(json.dumps(e[2])) for e in evs) < 2000
    r, _ = cmds.ask("stop", b"{}")
    assert r["ok"]
