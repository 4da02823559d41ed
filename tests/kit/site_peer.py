"""Another station of the site on a real broker: a paho client that publishes retained ``lives``
snapshots as a gateway of the site does (gateway/outputs/mqtt/sitelives.py), as fast as asked —
the careless or hostile site member of issue 34."""
from __future__ import annotations

import json
import re
import time
import urllib.request

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from gateway.core.method.prior import STOPPED, PastTest
from gateway.outputs.mqtt.schema import SCHEMA_VERSION
from gateway.outputs.mqtt.sitelives import record_of

SITE_BASE = "hookwatch/lab/test/l1"


def failure(station: str, tid: str, t_life: float, grade: str = "I") -> PastTest:
    """A plausible failure of ``grade`` at 0.5 N (ts 0.02 s, planned 600 s)."""
    return PastTest(grade, 0.5, "failure", t_life, k_b=400, n_slots=round(t_life / 0.02) + 50, ts=0.02,
                    test_id=tid, station=station, t_end=600.0, end_reason="failure")


def replaced(station: str, tid: str, n_slots: int) -> PastTest:
    """A test of grade I at 0.5 N ended on purpose after its baseline (a censored life)."""
    return PastTest("I", 0.5, "aborted", None, k_b=400, stop_reasons=(STOPPED,), n_slots=n_slots, ts=0.02,
                    test_id=tid, station=station, t_end=600.0, end_reason="hook_replaced")


def payload(station: str, tests: list[PastTest], seq: int = 0) -> bytes:
    doc = {"schema": SCHEMA_VERSION, "seq": seq, "station": station, "time": "2026-01-01T00:00:00.000Z",
           "lives": [record_of(t) for t in tests]}
    return json.dumps(doc, separators=(",", ":")).encode()


class SitePeer:
    """A station ``station`` of the site (topic ``<SITE_BASE>/<station>/lives``) on ``port``."""

    def __init__(self, port: int, station: str, base: str = SITE_BASE) -> None:
        self.station = station
        self.topic = f"{base}/{station}/lives"
        self.sent = 0
        self.c = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"peer-{station}-{time.monotonic_ns()}")
        self.c.max_inflight_messages_set(100)
        self.c.connect("127.0.0.1", port)
        self.c.loop_start()

    def publish(self, tests: list[PastTest]) -> None:
        """One retained snapshot, confirmed by the broker (QoS 1)."""
        self.c.publish(self.topic, payload(self.station, tests, self.sent), qos=1, retain=True).wait_for_publish(30)
        self.sent += 1

    def churn_payloads(self, n: int, n_lives: int = 500) -> list[bytes]:
        """``n`` valid snapshots of ``n_lives`` lives that all differ (the newest test changes in
        each), built before they are sent so that they go out as fast as the broker takes them."""
        fixed = [failure(self.station, f"{self.station}-T{i}", 20.0 + (i % 50) / 10) for i in range(n_lives - 1)]
        head = payload(self.station, fixed)[:-2]               # without the closing `]}`
        out = []
        for k in range(n):
            last = json.dumps(record_of(failure(self.station, f"{self.station}-C{self.sent + k}",
                                                21.0 + (k % 97) / 10)), separators=(",", ":"))
            out.append(head + b"," + last.encode() + b"]}")
        return out

    def send_raw(self, payloads: list[bytes]) -> None:
        """Send these snapshots back to back (QoS 1, retained), then wait for the broker's PUBACKs."""
        infos = [self.c.publish(self.topic, p, qos=1, retain=True) for p in payloads]
        for i in infos:
            i.wait_for_publish(120)
        self.sent += len(payloads)

    def close(self) -> None:
        self.c.loop_stop()
        self.c.disconnect()


_METRIC = re.compile(r'^hookwatch_link_(?:operations|errors)_total\{(?P<labels>[^}]*)\} (?P<v>\S+)$', re.M)


def mqtt_counters(metrics_port: int, station: str) -> dict[str, int]:
    """The station's MQTT counters as its Prometheus endpoint exposes them (link="mqtt")."""
    with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10) as r:
        text = r.read().decode()
    out: dict[str, int] = {}
    for m in _METRIC.finditer(text):
        labels = dict(re.findall(r'(\w+)="([^"]*)"', m.group("labels")))
        if labels.get("link") == "mqtt" and labels.get("station") == station:
            out[labels["kind"]] = int(float(m.group("v")))
    return out
