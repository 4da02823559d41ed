"""The ISA-18.2 alarm model (gateway/core/alarms.py): the transition diagram, shelving with expiry,
out of service during a needle change, hook replaced, priorities, one event per transition,
persistence round trip."""
import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gateway.core.alarms import ALARMS, Alarm, AlarmError, AlarmState, Priority

S = AlarmState


def path(a, *steps):
    return [(t.from_state, t.to_state, t.action) for step in steps for t in step(a)]


def test_end_of_life_raise_ack_hook_replaced():
    a = Alarm("end_of_life")
    assert path(a, lambda a: a.activate(10.0, hook="T-1", t_life=123.4),
                lambda a: a.acknowledge(11.0, by="plc:10.0.0.5"),
                lambda a: a.hook_replaced(50.0, by="sparkplug")) == [
        (S.NORMAL, S.UNACKNOWLEDGED, "activate"), (S.UNACKNOWLEDGED, S.ACKNOWLEDGED, "acknowledge"),
        (S.ACKNOWLEDGED, S.NORMAL, "hook_replaced")]
    assert a.closed_by == "hook_replaced" and a.acknowledged_by == "plc:10.0.0.5" and a.hook == "T-1"
    with pytest.raises(AlarmError, match="hook replaced"):
        a.hook_replaced(51.0)


def test_return_to_normal_unacknowledged_then_ack():
    a = Alarm("wear_warning")
    a.activate(1.0)
    assert [t.to_state for t in a.return_to_normal(2.0)] == [S.RTN_UNACKNOWLEDGED]
    assert [t.to_state for t in a.acknowledge(3.0)] == [S.NORMAL]
    a.activate(4.0)
    a.acknowledge(5.0)
    assert [t.to_state for t in a.return_to_normal(6.0)] == [S.NORMAL]


def test_shelve_expires_back_to_unacknowledged_and_is_bounded():
    a = Alarm("end_of_life")
    a.activate(0.0)
    with pytest.raises(AlarmError):
        a.shelve(1.0, until=1.0)
    with pytest.raises(AlarmError):
        a.shelve(1.0, until=1.0 + 13 * 3600)
    assert [t.to_state for t in a.shelve(1.0, until=100.0, by="op")] == [S.SHELVED]
    assert a.tick(99.9) == []
    tr = a.tick(100.0)
    assert [(t.to_state, t.action) for t in tr] == [(S.UNACKNOWLEDGED, "shelve_expired")]


def test_out_of_service_while_the_needle_is_changed():
    a = Alarm("end_of_life")
    a.activate(0.0)
    a.acknowledge(1.0)
    assert [t.to_state for t in a.remove_from_service(2.0, by="maint")] == [S.OUT_OF_SERVICE]
    assert a.activate(3.0) == []                      # silent while out of service
    assert [t.to_state for t in a.hook_replaced(4.0)] == [S.NORMAL]
    b = Alarm("wear_warning")
    b.remove_from_service(0.0)
    b.activate(1.0)
    assert [t.to_state for t in b.return_to_service(2.0)] == [S.UNACKNOWLEDGED]


def test_priorities():
    assert ALARMS["end_of_life"].priority < ALARMS["wear_warning"].priority   # 1 is the highest
    a = Alarm("end_of_life")
    assert a.activate(0.0)[0].priority == int(Priority.CRITICAL)   # 1, as MQTT and the PLC show it
    with pytest.raises(AlarmError):
        Alarm("coffee_empty")


ACTIONS = ["activate", "return_to_normal", "acknowledge", "shelve", "unshelve", "tick",
           "remove_from_service", "return_to_service", "hook_replaced"]


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.sampled_from(ACTIONS), st.floats(0, 50)), max_size=25),
       st.sampled_from(sorted(ALARMS)))
def test_every_transition_is_one_event_and_the_record_reads_back(steps, name):
    a = Alarm(name)
    now = 0.0
    for action, dt in steps:
        now += dt
        before = a.state
        try:
            if action == "shelve":
                tr = a.shelve(now, now + 60.0)
            elif action in ("activate", "return_to_normal", "tick"):
                tr = getattr(a, action)(now)
            else:
                tr = getattr(a, action)(now, by="t")
        except AlarmError:
            assert a.state == before                 # a refused action changes nothing
            continue
        assert len(tr) <= 1
        if tr:
            assert (tr[0].from_state, tr[0].to_state) == (before, a.state)
            assert tr[0].from_state != tr[0].to_state
            json.dumps(tr[0].as_dict())
        else:
            assert a.state == before
        back = Alarm.from_dict(json.loads(json.dumps(a.to_dict())))
        assert back.to_dict() == a.to_dict()


@pytest.mark.parametrize("bad", [None, [], {"name": "end_of_life", "state": "bogus"},
                                 {"name": "end_of_life", "raised_at": "yesterday"},
                                 {"name": "end_of_life", "condition": "yes"},
                                 {"name": "end_of_life", "state": "shelved"},
                                 {"name": "nope"}])
def test_damaged_records_are_refused_with_the_field(bad):
    with pytest.raises(AlarmError):
        Alarm.from_dict(bad)
