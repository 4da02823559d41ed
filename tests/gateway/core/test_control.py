"""Tension control (METHOD.md §8), pure."""
import math

import numpy as np
import pytest
from scipy import signal

from gateway.core.control import Controller, ControlParams, Notch, NotchParams, notch_coefficients


@pytest.mark.parametrize("f0,q", [(0.5, 2.0), (3.0, 3.75), (6.6, 12.0), (10.0, 8.0)])
def test_notch_coefficients_equal_scipy_iirnotch(f0, q):
    b, a = notch_coefficients(f0, q, 50.0)
    bs, as_ = signal.iirnotch(f0, q, fs=50.0)
    assert np.allclose(b, bs, rtol=0, atol=1e-14) and np.allclose(a, as_, rtol=0, atol=1e-14)


def test_notch_bypassed_below_n_min_and_attenuates_its_frequency():
    n = Notch(NotchParams(), 0.02)
    assert n.step(0.5, 20.0) == 0.5 and not n.active
    speed = 180.0                      # 3 Hz ripple
    t = np.arange(3000) * 0.02
    x = 0.5 + 0.05 * np.sin(2 * np.pi * 3.0 * t)
    y = np.array([n.step(v, speed) for v in x])
    tail = y[1500:]
    assert n.active
    assert (tail.max() - tail.min()) < 0.05 * (x.max() - x.min())   # > 26 dB down
    assert abs(tail.mean() - 0.5) < 1e-3                              # DC passes


def test_notch_coefficient_updates_are_thresholded():
    n = Notch(NotchParams(), 0.02)
    for _ in range(200):
        n.step(0.5, 180.0)
    u0 = n.updates
    for _ in range(200):
        n.step(0.5, 180.0 + 6.0)         # f_tar moves by 0.1 Hz < 0.2 Hz: no recomputation
    assert n.updates == u0
    for _ in range(200):
        n.step(0.5, 240.0)               # 1 Hz away: recomputed
    assert n.updates > u0


def test_slew_limit_and_clamp_anti_windup():
    p = ControlParams(kp=1000.0, ki=5000.0, notch=NotchParams(enabled=False))
    c = Controller(p, t_set=0.5)
    outs = [c.step(0.0, 0.0) for _ in range(60)]          # tension far below setpoint
    steps = np.diff([0.0] + [o.u for o in outs])
    assert np.all(steps <= 16.0 + 1e-12)
    assert outs[-1].u == 400.0 and outs[-1].saturated
    # no hidden integrator: as soon as the error reverses, the command comes down
    o = c.step(2.0, 400.0)
    assert o.u < 400.0


def test_dead_band_zeroes_small_errors():
    p = ControlParams(notch=NotchParams(enabled=False))
    c = Controller(p, t_set=0.5, u0=200.0)
    for _ in range(100):
        o = c.step(0.51, 200.0)
    assert o.e == 0.0 and o.u == 200.0


def test_missing_feedback_holds_then_freezes_command():
    p = ControlParams(notch=NotchParams(enabled=False))
    c = Controller(p, t_set=0.5, u0=100.0)
    c.step(0.3, 100.0)
    held = [c.step(None, 100.0) for _ in range(50)]
    assert all(o.feedback_ok for o in held)
    o = c.step(None, 100.0)
    assert not o.feedback_ok and o.u == held[-1].u


def test_plant_sign_reverses_the_action():
    for sign, expect_up in ((1, True), (-1, False)):
        c = Controller(ControlParams(plant_sign=sign, notch=NotchParams(enabled=False)), 0.5, u0=200.0)
        for _ in range(20):
            o = c.step(0.3, 200.0)
        assert (o.u > 200.0) == expect_up


def test_open_loop_holds_fixed_command():
    c = Controller(ControlParams(mode="open", open_loop_rpm=150.0), 0.5)
    us = [c.step(0.2 + 0.1 * math.sin(k), 150.0).u for k in range(100)]
    assert us[-1] == 150.0 and max(np.diff(us)) <= 16.0


def test_closed_loop_settles_on_first_order_plant_with_drift():
    """A lagged plant (0.003 N/rpm, τ = 0.3 s) with drift: the loop holds the setpoint."""
    p = ControlParams()
    c = Controller(p, t_set=0.5)
    T, n_act, ys = 0.0, 0.0, []
    for k in range(6000):
        drift = 0.1 * math.sin(2 * math.pi * k / 3000)
        o = c.step(T, n_act)
        n_act += (o.u - n_act) * 0.02 / 0.1
        T += (0.003 * n_act + drift - T) * 0.02 / 0.3
        ys.append(T)
    tail = np.array(ys[2000:])
    assert abs(tail.mean() - 0.5) < 0.01
    assert tail.std() < 0.02
