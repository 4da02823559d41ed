"""The pure MQTT layer: station data in, (topic, payload, QoS, retain) out — no broker, no thread."""
import json
import time

from gateway.core.records import Event, EventType, StationState
from gateway.outputs.mqtt import messages as M
from gateway.outputs.mqtt import schema as S
from gateway.station.alarm_store import AlarmStore
from gateway.station.command_desk import CODE, Rejection

BASE = "acme/hw/site/area/line/st1"


def _ev(etype, **data):
    return Event(etype, "st1", 1_700_000_000.25, "T-1", 9, data)


def test_an_end_of_life_is_its_event_then_the_retained_alarm_from_the_store():
    store = AlarmStore(None, "st1")
    ev = _ev(EventType.END_OF_LIFE, k_life=9, t_life=0.18, mu_ss=0.2, mu_th=0.25, sample_id="S-1")
    store.on_event(ev)
    msgs = M.event_messages(BASE, ev, None, store.record)
    assert [(m.kind, m.topic, m.qos, m.retain) for m in msgs] == [
        ("event", f"{BASE}/event/end_of_life", 1, False), ("alarm", f"{BASE}/alarm/end_of_life", 1, True)]
    alarm = json.loads(msgs[1].encode(42))
    assert list(alarm) == S.field_names("alarm")
    assert (alarm["seq"], alarm["state"], alarm["active"], alarm["t_life"], alarm["test_id"]) == (
        42, "unacknowledged", True, 0.18, "T-1")   # ISA-18.2 (was "active")
    store.on_event(_ev(EventType.ALARM_CLEARED, reason="new test started"))
    # ISA-18.2: closed is `normal` (was "cleared")
    cleared = M.alarm_message(BASE, "st1", time.time(), store.record).payload(43)
    assert (cleared["state"], cleared["active"], cleared["test_id"]) == ("normal", False, "T-1")


def test_the_end_of_a_test_carries_its_retained_result():
    st = StationState(station="st1", test_id="T-1", sample_id="S-1", grade="I", t_set=0.5)
    msgs = M.event_messages(BASE, _ev(EventType.TEST_ENDED, test_status="completed", reason="completed",
                                      result={"status": "ok"}), st, AlarmStore(None).record)
    assert [m.kind for m in msgs] == ["event", "result"] and msgs[1].retain
    r = msgs[1].payload(7)
    assert (r["sample_id"], r["test_status"], r["result"]) == ("S-1", "completed", {"status": "ok"})


def test_state_key_ignores_the_elapsed_time_and_replies_carry_codes():
    a = StationState(station="st1", elapsed_s=1.0)
    b = StationState(station="st1", elapsed_s=2.0)
    assert M.state_key(a) == M.state_key(b)
    assert M.state_message(BASE, 0.0, a).retain
    rej = Rejection(False, "no test is running", "r-1", CODE["NOT_RUNNING"])
    p = M.reply_message(BASE, "st1", 0.0, "stop", None, rej).payload(3)
    assert (p["ok"], p["code"], p["request_id"], p["reason"]) == (False, 2, "r-1", "no test is running")
    assert M.command_filter(BASE) == f"{BASE}/cmd/+"
    assert M.status_message(BASE, "st1", 0.0, False).payload(5)["status"] == "offline"
