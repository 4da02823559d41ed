"""The start of a test (METHOD.md §3a) as the station runs it, without a station: the
:class:`StartAttempt` state machine fed slot by slot with numbers (no ports, no clock, no loop)."""
import math

from gateway.core.control import ControlParams
from gateway.station.session import TestPlan
from gateway.station.starting import REST_S, StartAttempt, StartStep

FAST = {"w_ss": 0.2, "w_hold": 0.4, "tau": 0.2, "settle_time": 0.5, "start_timeout": 3.0}
TS = 0.02


def attempt(**method):
    return StartAttempt.begin(TestPlan("S-1", "I", 0.5, 100.0), {**FAST, **method}, ControlParams(),
                              "st", "test")


def feed_zero(att, n, *, port_open=True, speed_act=math.nan, off_for_s=10.0, t=(0.001, 0.002)):
    out = []
    for _ in range(n):
        out.append(att.slot(True, *t, port_open=port_open, speed_act=speed_act, speed_cmd=0.0,
                            off_for_s=off_for_s))
        if att.next_step()[0] is not StartStep.WAIT:
            break
    return out


def test_zero_check_then_spin_up_then_settled():
    att = attempt()
    assert att.next_step() == (StartStep.WAIT, None) and att.waiting_for_rest
    outs = feed_zero(att, 200)
    assert all(math.isnan(y) and u == 0.0 for y, _, u in outs)      # the motor stays off
    assert not att.waiting_for_rest
    assert att.next_step() == (StartStep.ENABLE_MOTOR, None)
    assert not att.motor_on
    att.motor_enabled = True                                        # the station enabled it
    assert att.motor_on
    speeds, step = [], StartStep.WAIT
    for _ in range(int(3.0 / TS)):
        y, sat, u = att.slot(True, 0.4, 0.6, port_open=True, speed_act=math.nan, speed_cmd=0.0,
                             off_for_s=0.0)
        speeds.append(u)
        step, _ = att.next_step()
        if step is not StartStep.WAIT:
            break
    assert step is StartStep.SETTLED
    assert all(math.isfinite(u) for u in speeds)                    # the loop was closed
    info = att.seq.sidecar()
    assert info["settle_s"] >= 0.5 and set(info["zero_offsets_n"]) == {"T1", "T2"}


def test_the_zero_check_waits_for_the_take_up_to_run_down():
    att = attempt()
    # turning (100 rpm): no zero-check slot counts, however long it takes below the timeout
    feed_zero(att, 100, speed_act=100.0)
    assert att.waiting_for_rest and att.next_step()[0] is StartStep.WAIT
    # commanded off only a moment ago: still waiting
    feed_zero(att, 10, speed_act=0.0, off_for_s=REST_S / 2)
    assert att.waiting_for_rest
    feed_zero(att, 1, speed_act=0.0, off_for_s=REST_S)
    assert not att.waiting_for_rest


def test_a_port_that_never_opens_fails_the_start_after_the_timeout():
    att = attempt()
    outs = feed_zero(att, 1000, port_open=False)
    assert len(outs) == int(round(3.0 / TS))                         # start_timeout, not later
    step, reason = att.next_step()
    assert step is StartStep.FAILED and "meter's port is not open after 3 s" in reason
    data = att.failure_data(TS)
    assert data["sample_id"] == "S-1" and data["spin_up_s"] == 0.0


def test_a_take_up_still_turning_fails_the_start_after_the_timeout():
    att = attempt()
    feed_zero(att, 1000, speed_act=80.0)
    step, reason = att.next_step()
    assert step is StartStep.FAILED and "still turns after 3 s (80 rpm)" in reason


def test_an_offset_meter_fails_the_zero_check():
    att = attempt()
    feed_zero(att, 200, t=(0.3, 0.002))
    step, reason = att.next_step()
    assert step is StartStep.FAILED and reason.startswith("zero check failed: T1")
    assert att.failure_data(TS)["zero_offsets_n"]["T1"] > 0.2


def test_without_zero_check_the_motor_is_enabled_at_once():
    att = attempt(zero_check=False)
    assert att.next_step() == (StartStep.ENABLE_MOTOR, None)
    att.motor_enabled = True
    y, _, _ = att.slot(True, 0.4, 0.6, port_open=True, speed_act=math.nan, speed_cmd=0.0,
                       off_for_s=0.0)
    assert math.isfinite(y) and att.seq.sidecar().get("zero_offsets_n") is None
