"""Issue 21, item 3: an MQTT 5 Response Topic is obeyed only below the configured reply prefix
(`mqtt.reply_prefix`, default `<base>/reply`). A client allowed to publish on `cmd/…` only cannot
make the gateway publish on result topics, other stations' command topics or Sparkplug's
STATE/NCMD: such a request is answered on `reply` and the refusal is counted. A real Mosquitto;
the requests are sent by `mosquitto_pub -V 5 -D publish response-topic …`; `mosquitto_sub` on `#`
sees everything the gateway publishes."""
import json
import subprocess

from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker, Sub
from kit.northbound import LoopThread, make_station
from kit.tools import require_tool, wait_for

BASE = "hookwatch/lab/hall/l1/st1"
FORGED = (f"{BASE}/result", "hookwatch/lab/hall/l1/st2/cmd/stop", "spBv1.0/STATE/scada-host",
          "spBv1.0/lab/NCMD/hall-l1", f"{BASE}/replyX/evil", f"{BASE}/reply")


def _pub_v5(port: int, topic: str, payload: str, response_topic: str, correlation: str) -> None:
    exe = require_tool("mosquitto_pub")
    subprocess.run([exe, "-h", "127.0.0.1", "-p", str(port), "-V", "5", "-q", "1", "-t", topic, "-m", payload,
                    "-D", "publish", "response-topic", response_topic,
                    "-D", "publish", "correlation-data", correlation], check=True, timeout=20)


def test_response_topics_outside_the_reply_prefix_are_not_obeyed(tmp_path):
    lt = LoopThread()
    with Broker(tmp_path) as b:
        station = make_station(tmp_path, [])
        out = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, port=b.port, protocol="5",
                                      outbox_path=str(tmp_path / "outbox.sqlite"), reconnect_min_s=0.2,
                                      reconnect_max_s=0.5), station)   # reply_prefix: the default
        station.outputs.append(out)
        everything = Sub(b.port, "#")
        answers = Sub(b.port, f"{BASE}/reply/#", schema="reply")     # checked against reply.json
        try:
            lt.call(out.start())
            wait_for(lambda: out.connected, 20, what="connected")
            assert out.pump.inbound.response_prefix == f"{BASE}/reply/"
            for i, topic in enumerate(FORGED):
                _pub_v5(b.port, f"{BASE}/cmd/ack", json.dumps({"request_id": f"f{i}"}), topic, f"c{i}")
            # below the prefix: obeyed, with its correlation data
            _pub_v5(b.port, f"{BASE}/cmd/ack", '{"request_id": "ok1"}', f"{BASE}/reply/mes-7", "c-ok")
            everything.wait(lambda s: any(t == f"{BASE}/reply/mes-7" for _, t, _, _ in s.lines), 20,
                            what="the answer on the response topic below the prefix")
            everything.wait(lambda s: len([1 for _, t, _, _ in s.lines if t == f"{BASE}/reply"]) >= len(FORGED),
                            20, what="the forged requests answered on reply")
            lines = list(everything.lines)
            published = {t for _, t, _, _ in lines}
            # nothing of the gateway's on the forged topics (the cmd/ack requests are the client's own)
            for topic in FORGED[:-1]:
                assert topic not in published, topic
            on_reply = [json.loads(p) for _, t, p, _ in lines if t == f"{BASE}/reply"]
            assert sorted(r["request_id"] for r in on_reply) == sorted(f"f{i}" for i in range(len(FORGED)))
            assert all(r["command"] == "ack" and r["code"] == 3 for r in on_reply)
            ok = [json.loads(p) for _, t, p, _ in lines if t == f"{BASE}/reply/mes-7"]
            assert [r["request_id"] for r in ok] == ["ok1"]
            assert out.counters["response_topic_refused"] == len(FORGED)
            answers.wait(lambda s: len(s.lines) >= len(FORGED) + 1, 20, what="the answers")
            answers.check()
        finally:
            lt.call(out.stop())
            lt.close()
            answers.stop()
            # `#` sees the answer below the prefix, a topic the tree does not name (answers checks it)
            everything.violations = [v for v in everything.violations if f"{BASE}/reply/mes-7:" not in v]
            everything.stop()
