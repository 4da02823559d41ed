"""MQTT 5 when the broker speaks it (issue 15 item 6): the gateway connects with MQTT 5 to a real
Mosquitto and answers a command on the request's Response Topic with its Correlation Data (a paho
MQTT 5 client plays the MES); `mqtt.protocol: 3.1.1` keeps the `reply` topic; `auto` falls back to
3.1.1 when a broker refuses MQTT 5."""
import contextlib
import json
import queue
import socket
import threading

import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import CallbackAPIVersion
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from gateway.core import records
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker, Sub, check_message
from kit.northbound import LoopThread, make_station
from kit.tools import free_port, wait_for

BASE = "hookwatch/lab/hall/l1/st1"


class Mes:
    """A MES as an MQTT 5 client: requests with a Response Topic and Correlation Data."""

    def __init__(self, port: int, reply_filter: str):
        self.got: queue.Queue = queue.Queue()
        self.c = paho.Client(CallbackAPIVersion.VERSION2, client_id="mes-v5", protocol=paho.MQTTv5)
        self.bad: list[str] = []     # schema violations (checked on the test's thread, in next())
        self.c.on_message = lambda c, u, m: (
            self.bad.extend(filter(None, [check_message(m.topic, m.payload, "reply")])),
            self.got.put((m.topic, json.loads(m.payload), getattr(m.properties, "CorrelationData", None))))
        subscribed = threading.Event()
        self.c.on_subscribe = lambda *a: subscribed.set()
        self.c.connect("127.0.0.1", port)
        self.c.loop_start()
        self.c.subscribe(reply_filter, qos=1)
        assert subscribed.wait(10)

    def request(self, topic: str, payload: str, response_topic: str | None = None,
                correlation: bytes | None = None) -> None:
        props = Properties(PacketTypes.PUBLISH)
        if response_topic is not None:
            props.ResponseTopic = response_topic
        if correlation is not None:
            props.CorrelationData = correlation
        self.c.publish(topic, payload, qos=1, properties=props).wait_for_publish(10)

    def next(self, timeout: float = 20.0):
        got = self.got.get(timeout=timeout)
        assert not self.bad, self.bad[0]
        return got

    def close(self) -> None:
        self.c.disconnect()
        self.c.loop_stop()


def _output(tmp_path, port, protocol, reply_prefix="mes/replies"):
    """``reply_prefix``: the MES of these tests wants its answers below `mes/replies`
    (`mqtt.reply_prefix`; a Response Topic elsewhere is not obeyed)."""
    station = make_station(tmp_path, [])
    out = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, port=port, protocol=protocol,
                                  outbox_path=str(tmp_path / "outbox.sqlite"), reconnect_min_s=0.2,
                                  reconnect_max_s=0.5, reply_prefix=reply_prefix), station)
    station.outputs.append(out)
    return station, out


@contextlib.contextmanager
def gateway_and_mes(tmp_path, protocol):
    """A station with its MQTT output (``protocol``) on a real Mosquitto, mosquitto_sub on `reply`
    and the MQTT 5 MES subscribed to `mes/replies/#`."""
    lt = LoopThread()
    with Broker(tmp_path) as b:
        station, out = _output(tmp_path, b.port, protocol)
        sub = Sub(b.port, BASE + "/reply")
        mes = None
        try:
            lt.call(out.start())
            wait_for(lambda: out.connected, 20, what="connected")
            mes = Mes(b.port, "mes/replies/#")
            yield station, out, sub, mes
        finally:
            if mes is not None:
                mes.close()
            lt.call(out.stop())
            lt.close()
            sub.stop()


def test_commands_are_answered_on_the_response_topic_with_the_correlation_data(tmp_path):
    with gateway_and_mes(tmp_path, "auto") as (station, out, sub, mes):
        assert out.pump.version.v5
        mes.request(f"{BASE}/cmd/start", '{"sample_id": "S-5", "t_set": 0.5, "request_id": "r1"}',
                    "mes/replies/st1", b"\x00\x01corr-1")
        topic, p, corr = mes.next()
        assert topic == "mes/replies/st1" and corr == b"\x00\x01corr-1"
        assert p["ok"] and p["command"] == "start" and p["request_id"] == "r1"
        # the start was applied: no slot loop runs here, so the test stays in its start (§3a)
        assert station.starting is not None and station.plan.sample_id == "S-5"
        assert station.state.state == records.TestState.STARTING
        # a refusal too; and a request without correlation data
        mes.request(f"{BASE}/cmd/start", '{"sample_id": "S-6", "t_set": 0.5}', "mes/replies/st1", b"c2")
        topic, p, corr = mes.next()
        assert corr == b"c2" and not p["ok"] and p["code"] == 1
        mes.request(f"{BASE}/cmd/stop", "[[[[1]]]]", "mes/replies/other")
        topic, p, corr = mes.next()
        assert topic == "mes/replies/other" and corr is None and p["code"] == 9
        # no Response Topic, or one that may not be used (a wildcard): the answer is on `reply`
        mes.request(f"{BASE}/cmd/stop", '{"request_id": "halt"}')
        mes.request(f"{BASE}/cmd/ack", '{"request_id": "a1"}', "mes/replies/#", b"c3")
        sub.wait(lambda s: len(s.messages("reply")) >= 2, 20)
        on_reply = [m[2] for m in sub.messages("reply")]
        assert [(r["request_id"], r["command"]) for r in on_reply] == [("halt", "stop"), ("a1", "ack")]
        assert on_reply[0]["ok"]
        assert mes.got.empty() and out.counters["bad_response_topic"] == 1
        seqs = [r["seq"] for r in on_reply]
        assert seqs == sorted(seqs)


def test_protocol_3_1_1_answers_on_reply(tmp_path):
    with gateway_and_mes(tmp_path, "3.1.1") as (_station, out, sub, mes):
        assert not out.pump.version.v5
        mes.request(f"{BASE}/cmd/ack", '{"request_id": "a1"}', "mes/replies/st1", b"c1")
        sub.wait(lambda s: s.messages("reply"), 20)
        r = sub.messages("reply")[0][2]
        assert r["request_id"] == "a1" and r["code"] == 3
        assert mes.got.empty()


@pytest.mark.parametrize("refusal", ["connack", "close"])
def test_auto_falls_back_to_3_1_1_when_the_broker_refuses_mqtt_5(tmp_path, refusal, caplog):
    """A broker that speaks only 3.1.1 (a socket server answering CONNECT by the protocol level the
    client asks for: 5 → return code 1, unacceptable protocol version, or the connection closed
    without an answer; 4 → accepted). A closed connection counts as a refusal the second time in a
    row (a broker going down closes connections too)."""
    port = free_port()
    levels: list[int] = []
    srv = socket.create_server(("127.0.0.1", port))
    srv.settimeout(0.2)
    conns: list[socket.socket] = []
    stop = threading.Event()

    def serve():
        while not stop.is_set():
            try:
                c, _ = srv.accept()
            except TimeoutError:
                continue
            c.settimeout(5)
            data = c.recv(4096)
            # fixed header: 1 byte + the remaining length (1–4 bytes); then 00 04 "MQTT" level
            i = 1
            while data[i] & 0x80:
                i += 1
            level = data[i + 1 + 6]
            levels.append(level)
            if level == 5:
                if refusal == "connack":
                    c.sendall(b"\x20\x02\x00\x01")
                c.close()
            else:
                c.sendall(b"\x20\x02\x00\x00")
                conns.append(c)

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    lt = LoopThread()
    _station, out = _output(tmp_path, port, "auto")
    try:
        lt.call(out.start())
        wait_for(lambda: out.connected, 20, what="connected with 3.1.1")
        assert levels == ([5, 4] if refusal == "connack" else [5, 5, 4]) and not out.pump.version.v5
        # one log line says so, and what 3.1.1 costs (docs/mqtt.md)
        lines = [r.getMessage() for r in caplog.records if "refused MQTT 5" in r.getMessage()]
        assert len(lines) == 1, lines
        assert "Response Topic" in lines[0] and "user properties" in lines[0] and "message expiry" in lines[0]
        assert out.counters["mqtt311_fallbacks"] == 1
    finally:
        out.s.drain_on_stop_s = 0.0
        lt.call(out.stop())
        lt.close()
        stop.set()
        t.join(5)
        for c in conns:
            c.close()
        srv.close()
