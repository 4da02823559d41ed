"""METHOD.md §3a start sequence (pure): zero check, settle, swapped channels, timeout."""
import math

import pytest

from gateway.core.control import lowpass_alpha
from gateway.core.method import MethodParams
from gateway.core.method.start import FAILED, SETTLED, SPIN_UP, ZERO_CHECK, StartSequence

P = MethodParams(t_set=0.5)          # settle_band 0.1, settle_time 2 s, start_timeout 30 s


def zero(seq, t1, t2, n=50):
    for _ in range(n):
        ph = seq.zero_slot(True, t1, t2)
    return ph


def test_zero_check_passes_and_records_offsets_then_the_motor_may_run():
    seq = StartSequence(P)
    assert seq.phase == ZERO_CHECK and not seq.motor_on
    for _ in range(49):
        assert seq.zero_slot(True, 0.01, -0.005) == ZERO_CHECK
    assert seq.zero_slot(True, 0.01, -0.005) == SPIN_UP and seq.motor_on
    assert seq.offsets == pytest.approx({"T1": 0.01, "T2": -0.005})


def test_zero_check_refuses_an_offset_and_names_the_channel():
    seq = StartSequence(P)
    assert zero(seq, 0.061, 0.0) == FAILED
    assert seq.reason.startswith("zero check failed: T1 0.061 N") and "T2" not in seq.reason
    assert not seq.motor_on and seq.done
    seq = StartSequence(P)
    zero(seq, -0.03, 0.025)
    assert seq.reason.startswith("zero check failed: T1 -0.030 N, T2 0.025 N")
    # exactly at the tolerance passes
    assert zero(StartSequence(P), 0.0199, -0.0199) == SPIN_UP


def test_zero_check_needs_readings_and_can_be_switched_off():
    seq = StartSequence(P)
    for k in range(50):
        seq.zero_slot(k % 3 == 0, 0.0, 0.0)      # 17 of 50 readings
    assert seq.phase == FAILED and seq.reason == "zero check failed: 17 of 50 readings in 1 s"
    seq = StartSequence(P.__class__(**{**P.as_dict(), "zero_check": False}))
    assert seq.phase == SPIN_UP and seq.offsets is None
    with pytest.raises(RuntimeError):
        seq.zero_slot(True, 0.0, 0.0)


def spin(seq, readings):
    """Feed (t1, t2) readings through the controller's real pre-filter; returns the phase and the
    number of slots fed."""
    alpha = lowpass_alpha(0.02, 2.0)       # the pre-filter of METHOD.md §8.2
    y = math.nan
    for i, (a, b) in enumerate(readings):
        present = not (math.isnan(a) or math.isnan(b))
        if present:
            x = (a + b) / 2.0
            y = x if math.isnan(y) else y + alpha * (x - y)
        ph = seq.spin_slot(present, a, b, y)
        if ph != SPIN_UP:
            return ph, i + 1
    return seq.phase, len(readings)


def ramp(slow_s, n, t1=0.4, t2=0.6):
    """A take-up that needs slow_s seconds to bring the yarn from 0 to tension."""
    k_slow = int(slow_s / 0.02)
    out = []
    for k in range(n):
        f = min(1.0, k / k_slow) if k_slow else 1.0
        out.append((t1 * f, t2 * f))
    return out


def test_a_slow_take_up_settles_after_its_ramp_and_settle_time():
    seq = StartSequence(zero_off())
    ph, n = spin(seq, ramp(8.0, 3000))
    assert ph == SETTLED
    # the low-tension ramp (8 s ≫ stop_after) resets nothing once the tension is there; y enters
    # the band shortly before the ramp ends and then stays 2 s
    assert 8.0 + 2.0 - 1.0 <= n * 0.02 <= 8.0 + 2.0 + 0.5
    assert seq.outcome().settle_s == pytest.approx(n * 0.02)
    assert seq.sidecar()["settle_s"] == pytest.approx(n * 0.02)


def zero_off():
    return MethodParams(t_set=0.5, zero_check=False)


def test_settle_needs_settle_time_in_band_without_interruption():
    seq = StartSequence(zero_off())
    band = [(0.4, 0.6)] * 60 + [(0.6, 0.9)] * 40 + [(0.4, 0.6)] * 200   # out of band for 0.8 s
    ph, n = spin(seq, band)
    assert ph == SETTLED and n > 100 + 100     # restarted counting after the excursion


def test_a_protection_stop_condition_resets_the_settle_count():
    seq = StartSequence(zero_off())
    nan = float("nan")
    # y is held by the caller through missing slots; 51 missing slots are a protection-stop
    # condition, 50 are not
    # a shorter run holds the count (missing slots do not count toward settle_time)
    for gap, settled_at in ((50, 60 + 50 + 40), (51, 60 + 51 + 100)):
        seq = StartSequence(zero_off())
        readings = [(0.4, 0.6)] * 60 + [(nan, nan)] * gap + [(0.4, 0.6)] * 300
        assert spin(seq, readings) == (SETTLED, settled_at)


def test_swapped_channels_refuse_the_start_when_the_tension_settles():
    seq = StartSequence(zero_off())
    ph, n = spin(seq, ramp(3.0, 3000, t1=0.6, t2=0.4))
    assert ph == FAILED and seq.reason.startswith("channels swapped? set meter.swap_channels")
    assert not seq.motor_on
    # slack-yarn noise during a slow spin-up does not vote
    seq = StartSequence(zero_off())
    noise = [(0.01, 0.005)] * 400 + ramp(2.0, 1000)
    assert spin(seq, noise)[0] == SETTLED


def test_yarn_not_threaded_fails_after_the_start_timeout():
    seq = StartSequence(zero_off())
    ph, n = spin(seq, [(0.01, 0.03)] * 5000)
    assert ph == FAILED and n == 1500
    assert seq.reason.startswith("no tension after 30 s: T̄ 0.02 N")
    assert seq.sidecar() == {"settle_s": None}
    # a tension that is there but never settles says so
    seq = StartSequence(zero_off())
    ph, _ = spin(seq, [(0.55, 0.8)] * 2000)
    assert ph == FAILED and seq.reason.startswith("tension not settled after 30 s: T̄ 0.68 N")
    # a meter that gives nothing
    seq = StartSequence(zero_off())
    ph, _ = spin(seq, [(float("nan"), float("nan"))] * 2000)
    assert seq.reason == "no tension after 30 s: no readings from the meter"


def test_full_sequence_zero_then_spin_up_and_parameters_from_the_station():
    p = MethodParams(t_set=0.3, zero_tol=0.05, settle_band=0.2, settle_time=1.0, start_timeout=10.0)
    seq = StartSequence(p)
    assert zero(seq, 0.04, 0.0) == SPIN_UP
    ph, n = spin(seq, ramp(1.0, 2000, t1=0.25, t2=0.35))
    assert ph == SETTLED and n * 0.02 < 3.0
    assert seq.sidecar() == {"settle_s": pytest.approx(n * 0.02),
                             "zero_offsets_n": pytest.approx({"T1": 0.04, "T2": 0.0})}
    with pytest.raises(RuntimeError):
        seq.spin_slot(True, 0.25, 0.35, 0.3)
