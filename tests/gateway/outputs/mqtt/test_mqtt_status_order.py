"""The JSON contract around `status` (issue 15 item 4): `status` has no outbox `seq` (its own
`session` counter), `online` arrives before the backlog of an outage, and a MES applying the
documented de-duplication rule (docs/mqtt.md, Delivery) through a real Mosquitto loses nothing."""
import json
import time

import jsonschema

from gateway.core.records import Event, EventType
from gateway.outputs.mqtt import schema as S
from gateway.outputs.mqtt import schema_gen
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker, Sub, pub
from kit.northbound import LoopThread
from kit.tools import wait_for

BASE = "hookwatch/lab/hall/l1/st1"


def mes_apply(messages):
    """The documented rule: per station keep H, the highest seq processed; drop seq <= H; status
    has no seq and never moves H (keep the highest session instead)."""
    h, session, processed = 0, 0, []
    for _r, topic, p, _t in messages:
        if topic.endswith("/status"):
            session = max(session, p["session"])
            continue
        if p["seq"] <= h:
            continue
        processed.append((topic, p))
        h = p["seq"]
    return processed, session


def test_online_precedes_the_backlog_and_the_dedup_rule_loses_nothing(tmp_path):
    status_schema = jsonschema.Draft202012Validator(json.loads(schema_gen.render_all()["status.json"]))
    lt = LoopThread()
    b = Broker(tmp_path, persistent=True).start()
    sub = Sub(b.port, BASE + "/#", client_id="mes-order", clean=False)
    out = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, port=b.port,
                                  outbox_path=str(tmp_path / "outbox.sqlite"), reconnect_min_s=0.2,
                                  reconnect_max_s=0.5))

    def emit(n):
        out.on_event(Event(EventType.PORT_LOST if n % 2 else EventType.PORT_BACK, "st1", time.time(),
                           "T-1", n, {"port": "meter", "n": n}))

    def events(s):
        return [m for m in s.messages() if "/event/" in m[1]]

    try:
        lt.call(out.start())
        sub.wait(lambda s: s.messages("status"), 20)
        for n in range(5):
            emit(n)
        sub.wait(lambda s: len(events(s)) >= 5, 20)
        # the MES's PUBACKs are read by the broker before it stops (a probe round trip)
        pub(b.port, BASE + "/probe", "{}")
        sub.wait(lambda s: s.messages("probe"), 20)
        b.stop()
        wait_for(lambda: not out.connected, 20, what="link down")
        for n in range(5, 15):        # the backlog of the outage
            emit(n)
        wait_for(lambda: out.outbox.count() >= 10, 20, what="the backlog in the outbox")
        b.start()
        sub.wait(lambda s: len({m[2]["data"]["n"] for m in events(s)}) >= 15, 30, what="the backlog")
        time.sleep(0.5)               # anything late would show up now
        msgs = [m for m in sub.messages() if not m[1].endswith("/probe")]

        statuses = [m for m in msgs if m[1].endswith("/status")]
        for m in statuses:
            assert "seq" not in m[2]
            status_schema.validate(m[2])
        # session 1's `online` may reach the MES as the retained copy (its subscription can come
        # a moment after the first publish on a loaded machine); session 2's comes live
        online = [(m[0], m[2]["session"]) for m in statuses if m[2]["status"] == "online"]
        first_seen = list(dict.fromkeys(s for _, s in online))    # a reconnect repeats the retained
        assert first_seen == [1, 2] and (False, 2) in online, statuses
        # `online` of session 2 arrives before every message of the backlog
        i_online = next(i for i, m in enumerate(msgs) if m[1].endswith("/status") and not m[0]
                        and m[2]["session"] == 2)
        i_backlog = next(i for i, m in enumerate(msgs) if "/event/" in m[1] and m[2]["data"]["n"] == 5)
        assert i_online < i_backlog
        # a MES applying the documented rule processes every event once, in order
        processed, session = mes_apply(msgs)
        assert [p["data"]["n"] for t, p in processed if "/event/" in t] == list(range(15))
        assert session == 2
    finally:
        lt.call(out.stop())
        lt.close()
        sub.stop()
        b.stop()


def test_status_session_keeps_increasing_across_restarts(tmp_path):
    with Broker(tmp_path) as b:
        sub = Sub(b.port, BASE + "/status")
        try:
            for k in (1, 2):
                lt = LoopThread()
                out = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, port=b.port,
                                              outbox_path=str(tmp_path / "outbox.sqlite")))
                lt.call(out.start())
                wait_for(lambda out=out: out.connected, 60, what="connected")
                lt.call(out.stop())
                lt.close()
                sub.wait(lambda s, k=k: len([m for m in s.messages() if not m[0]]) >= 2 * k, 60)
            got = sub.messages()
            live = [(m[2]["status"], m[2]["session"]) for m in got if not m[0]]
            assert live == [("online", 1), ("offline", 1), ("online", 2), ("offline", 2)]
            assert all(list(m[2]) == S.field_names("status") for m in got)
        finally:
            sub.stop()
