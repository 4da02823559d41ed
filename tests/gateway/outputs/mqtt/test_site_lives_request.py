"""Issue 29 items 2 and 4: the site's lives never rely on a retained message. A clustered broker
keeps a retained message on the node that received it (RabbitMQ 3.10) and loses it with that
node; here the same situation on one real Mosquitto is made by clearing A's retained snapshot
(an empty retained message) before B joins. B (no history) still gets A's lives: B's station
asks the site on `<prefix>/<site>/lives_request` when it connects and A's station answers with
its lives. A flood of requests is answered at most once per interval (counts, one log line),
and a station ignores its own request."""
import json
import logging

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from gateway.outputs.mqtt import schema as S
from gateway.outputs.mqtt import sitelives as SL
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker, Sub, pub
from kit.northbound import LoopThread
from kit.tools import wait_for

BASE_A = "hookwatch/lab/hall/l1/a"
BASE_B = "hookwatch/lab/hall/l2/b"
LIVES_A = BASE_A + "/lives"
FLOOD = 200


def seed(folder, station, n=5):
    """``n`` failures of grade I at 0.5 N in a station's records folder."""
    for i in range(n):
        tid = f"2026030{i}T080000Z-{station}-{i}"
        d = folder / tid
        d.mkdir(parents=True)
        (d / "result.json").write_text(json.dumps({
            "test_id": tid, "station": station, "test_status": "completed", "end_reason": "completed",
            "sample_id": f"{station}-{i}", "grade": "I", "t_set": 0.5, "ts": 0.02, "t_end": 60.0,
            "method": {"status": "failure", "t_life": 20.0 + i, "k_b": 400, "n_slots": 1100 + 50 * i,
                       "stop_reasons": None}}))


def settings(tmp_path, port, station, base):
    folder = tmp_path / station
    folder.mkdir(exist_ok=True)
    return MqttSettings(station_id=station, base_topic=base, port=port, share_lives=True,
                        records_dir=str(folder), outbox_path=str(tmp_path / f"outbox-{station}.sqlite"),
                        reconnect_min_s=0.2, reconnect_max_s=1.0)


def flood(port: int, topic: str, n: int) -> None:
    """``n`` lives requests from one client (QoS 1, each confirmed before the disconnect)."""
    c = paho.Client(CallbackAPIVersion.VERSION2, client_id="flood", protocol=paho.MQTTv311)
    c.connect("127.0.0.1", port)
    c.loop_start()
    try:
        infos = [c.publish(topic, b"flood", qos=1) for _ in range(n)]
        for info in infos:
            info.wait_for_publish(20)
            assert info.is_published()
    finally:
        c.disconnect()
        c.loop_stop()


def test_a_late_joiner_gets_the_lives_without_the_retained_copy_and_a_flood_costs_one_answer(
        tmp_path, monkeypatch, caplog):
    # one interval covers the whole test: every request after the first answer is deferred
    monkeypatch.setattr(SL, "ANSWER_INTERVAL_S", 3600.0)
    seed(tmp_path / "a", "a")
    caplog.set_level(logging.INFO, logger="hookwatch.site")
    assert S.lives_request_topic(BASE_A) == "hookwatch/lab/lives_request"
    with Broker(tmp_path) as b:
        mes = Sub(b.port, "hookwatch/lab/#")
        lt = LoopThread()
        out_a = out_b = None
        try:
            out_a = MqttOutput(settings(tmp_path, b.port, "a", BASE_A))
            lt.call(out_a.start())
            first = mes.wait(lambda s: [m for m in s.messages("lives") if m[2].get("lives")], 60,
                             what="A's lives")
            assert first[0][1] == LIVES_A and len(first[0][2]["lives"]) == 5
            # A's retained copy is gone (a node of a cluster that never had it, or was killed)
            pub(b.port, LIVES_A, "", retain=True)
            wait_for(lambda: any(m[1] == LIVES_A and m[2].get("_raw") == "" for m in mes.messages()), 20,
                     what="the cleared retained copy")
            n_lives_before = len([m for m in mes.messages("lives") if m[2].get("lives")])
            # B joins: no history, nothing retained; its request brings A's lives
            out_b = MqttOutput(settings(tmp_path, b.port, "b", BASE_B))
            lt.call(out_b.start())
            site_b = out_b.site
            assert site_b is not None
            wait_for(lambda: len(site_b.tests()) == 5, 60, what="A's lives at B")
            assert sorted(t.test_id for t in site_b.tests()) == sorted(
                f"2026030{i}T080000Z-a-{i}" for i in range(5))
            assert {t.station for t in site_b.tests()} == {"a"}
            # A heard B's request (its own was ignored) and answered it once
            assert out_a.counters["lives_requests"] == 1 and out_a.counters["lives_answers"] == 1
            assert out_b.counters["lives_requests"] == 0     # B's own request, and A asked before B was there
            wait_for(lambda: len([m for m in mes.messages("lives") if m[1] == LIVES_A and m[2].get("lives")])
                     > n_lives_before, 20, what="A's answer on the MES")
            answered = len([m for m in mes.messages("lives") if m[1] == LIVES_A and m[2].get("lives")])
            # a flood of requests within the interval: counted, no answer, one log line
            flood(b.port, S.lives_request_topic(BASE_A), FLOOD)
            wait_for(lambda: out_a.counters["lives_requests"] == 1 + FLOOD, 30, what="the flood heard by A")
            wait_for(lambda: out_b.counters["lives_requests"] == FLOOD, 30, what="the flood heard by B")
            assert out_a.counters["lives_answers"] == 1
            assert out_a.counters["lives_requests_deferred"] == FLOOD
            # B answered the first request of the flood (its first), deferred the rest
            assert out_b.counters["lives_answers"] == 1
            assert out_b.counters["lives_requests_deferred"] == FLOOD - 1
            flood_lines = [r for r in caplog.records if "answered at most once per" in r.getMessage()]
            assert len(flood_lines) == 2 and {r.getMessage().split(":")[0] for r in flood_lines} == {"a", "b"}
            # the MES saw A's lives no more since its answer
            assert len([m for m in mes.messages("lives") if m[1] == LIVES_A and m[2].get("lives")]) == answered
        finally:
            for out in (out_b, out_a):
                if out is not None:
                    lt.call(out.stop())
            lt.close()
            mes.stop()


def test_requests_within_the_interval_share_one_answer_at_its_end():
    """The answer gate alone: the first request is answered at once, the next ones within the
    interval once together when it ends; a publication of the lives in between answers them
    instead; the station's own request is ignored."""
    sent = []
    counters: dict[str, int] = {"lives_requests": 0, "lives_answers": 0, "lives_requests_deferred": 0}
    ans = SL.LivesAnswers("a", lambda: sent.append(1) or True, counters, interval_s=0.5)
    try:
        ans.request(b"a")
        assert counters["lives_requests"] == 0 and sent == []
        ans.request(b"b")
        assert len(sent) == 1
        for _ in range(50):
            ans.request(b"c")
        assert counters["lives_requests_deferred"] == 50 and len(sent) == 1
        wait_for(lambda: counters["lives_answers"] == 2, 20, what="the deferred answer")
        assert len(sent) == 2 and ans._timer is None
        # requests deferred, then the lives go out anyway (a test ended): no deferred answer
        ans.request(b"d")
        ans.published()
        assert ans._timer is None
    finally:
        ans.close()
