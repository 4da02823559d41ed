"""Nothing non-finite leaves the box northbound (issue 27, item 4): a station state whose every
figure is ±Infinity or NaN (a forecast from a prior of 1e308 made them so before the bounds) goes
out through the real MQTT output and the real Sparkplug edge node to a real Mosquitto. The MES
(``mosquitto_sub``) reads JSON that a strict parser accepts, with null where a number has no value;
the Sparkplug host reads ``is_null`` metrics, never a double that is not finite."""
from __future__ import annotations

import asyncio
import math
import time

from gateway.core.records import Event, EventType, StationState
from gateway.core.records import TestState as TState
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from gateway.outputs.sparkplug.node_settings import SparkplugSettings
from gateway.outputs.sparkplug.output import SparkplugOutput
from gateway.plumbing.safeout import loads_strict
from kit.broker import Broker, Sub
from kit.jsondoc import numbers
from kit.sparkplug_host import PrimaryHost, metric_value
from kit.tools import wait_for

BASE = "hookwatch/lab/hall/l1/st1"
INF, NAN = math.inf, math.nan


def hostile_state() -> StationState:
    return StationState(station="st1", state=TState.MONITORING, test_id="T-1", sample_id="x;=1+1;y",
                        grade="I", t_set=0.5, t_end=INF, mu_ss=NAN, mu_th=INF, t_life=-INF,
                        headroom=NAN, t_cross=INF, end_p10=INF, end_p50=INF, end_p90=NAN,
                        p_end=NAN, prior_mean=INF, prior_sd=NAN, lead_s=INF, p_due=NAN,
                        test_started_utc="2026-11-26T06:00:00.000Z", elapsed_s=12.0)



def test_mqtt_and_sparkplug_never_carry_a_non_finite_number(tmp_path):
    with Broker(tmp_path) as b:
        sub = Sub(b.port, BASE + "/#")
        host = PrimaryHost(b.port, "h", "g", tmp_path)
        try:
            mq = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, port=b.port,
                                         outbox_path=str(tmp_path / "outbox.sqlite"),
                                         reconnect_min_s=0.2, reconnect_max_s=1.0))
            sp = SparkplugOutput(SparkplugSettings(group_id="g", edge_node_id="n", device_id="st1",
                                                   servers=[("127.0.0.1", b.port)],
                                                   store_path=str(tmp_path / "sp.sqlite"), gather_s=0.0))

            async def scenario():
                await mq.start()
                await sp.start()
                await asyncio.to_thread(wait_for, lambda: mq.connected, 20, what="connected")
                await asyncio.to_thread(host.wait, lambda: host.all("DBIRTH"), 30, "DBIRTH")
                mark = host.mark()
                st = hostile_state()
                for out in (mq, sp):
                    out.on_state(st)
                    out.on_event(Event(EventType.END_OF_LIFE, "st1", time.time(), "T-1", 29,
                                       {"k_life": 20, "t_life": INF, "mu_ss": NAN, "mu_th": -INF,
                                        "sample_id": "x;=1+1;y"}))
                await asyncio.to_thread(sub.wait, lambda s: s.messages("state") and s.messages("event/end_of_life")
                                        and s.messages("alarm/end_of_life"), 20)
                await asyncio.to_thread(host.wait, lambda: len(host.all("DDATA", mark)) >= 2, 30, "DDATA")
                await mq.stop()
                await sp.stop()
                return mark

            mark = asyncio.run(scenario())
            # every MQTT payload as the MES's strict parser reads it
            raw = [(t, p) for _r, t, p, _ts in sub.lines]
            assert len(raw) >= 4
            for topic, payload in raw:
                assert "Infinity" not in payload and "NaN" not in payload, (topic, payload)
                doc = loads_strict(payload)
                assert all(math.isfinite(x) for x in numbers(doc)), (topic, payload)
            state = next(loads_strict(p) for t, p in raw if t.endswith("/state"))
            assert state["mu_ss"] is None and state["mu_th"] is None and state["t_cross"] is None
            assert state["end_p50"] is None and state["sample_id"] == "x;=1+1;y" and state["t_set"] == 0.5
            ev = next(loads_strict(p) for t, p in raw if t.endswith("/event/end_of_life"))
            assert ev["data"]["t_life"] is None and ev["data"]["mu_th"] is None
            # Sparkplug: a double that is not finite goes as is_null (the host sees no value)
            names = {x.alias: x.name for m in host.all("DBIRTH") for x in m.p.metrics}
            sent = {}
            for m in host.all("DDATA", mark):
                for x in m.p.metrics:
                    sent[x.name or names[x.alias]] = x
            assert "Method/mu_th" in sent and "Method/mu_ss" in sent
            for name, x in sent.items():
                v = metric_value(x)
                assert not (isinstance(v, float) and not math.isfinite(v)), (name, v)
            assert sent["Method/mu_th"].is_null and sent["Method/mu_ss"].is_null
            assert sent["Method/t_life"].is_null
        finally:
            host.close()
            sub.stop()
