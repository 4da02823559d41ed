"""The closed loop (METHOD.md §8) on the drifting, rippling virtual plant of the e2e closed-loop
test, in one process and in plant time (no clock, no I/O): the mean tension over one period of the
drift stays within the dead band of the setpoint wherever slot 0 falls in the drift's phase — the
controller (dead band, slew limit, incremental PID) has no steady-state bias."""
import dataclasses

import numpy as np
import pytest

from drivers.sim.plant import Plant, params_from_dict
from gateway.core.control import Controller, ControlParams

DRIFT_PERIOD = 50.0
DEAD_BAND = 0.01


def closed_loop_mean(slot0_s, *, notch=True, settle=20.0, seed=3):
    """Mean (T1 + T2)/2 over [settle, settle + one drift period] s after slot 0 (the motor runs
    from plant time 0, the log starts at ``slot0_s``); one reading per 20 ms slot, 5 ms in."""
    plant = Plant(params_from_dict({
        "grade": "I", "t_set": 0.5, "time_scale": 1,
        "drift": {"sine_amp": 0.08, "sine_period_s": DRIFT_PERIOD},
        "ripple": {"amplitude": 0.12}}), seed=seed)
    p = ControlParams(dead_band_n=DEAD_BAND)
    if not notch:
        p = dataclasses.replace(p, notch=dataclasses.replace(p.notch, enabled=False))
    ctl = Controller(p, 0.5)
    plant.enable(True)
    t_from, t_to = slot0_s + settle, slot0_s + settle + DRIFT_PERIOD
    means = []
    k = 0
    while (t := k * p.ts) < t_to:
        plant.advance_to(t + 0.005)
        t1, t2 = plant.tensions()
        out = ctl.step((t1 + t2) / 2.0, plant.speed_rpm)
        plant.set_command(out.u)
        if t >= t_from:
            means.append((t1 + t2) / 2.0)
        assert not out.saturated
        k += 1
    return float(np.mean(means))


@pytest.mark.parametrize("slot0_s", [0.0, 12.5, 25.0, 37.5])
def test_closed_loop_mean_within_the_dead_band_at_any_drift_phase(slot0_s):
    m = closed_loop_mean(slot0_s)
    # the e2e run measured 0.5000-0.5007; the bound the incremental PID allows is the dead band
    assert abs(m - 0.5) <= 0.0025, m


def test_closed_loop_mean_without_notch_too():
    assert abs(closed_loop_mean(6.0, notch=False) - 0.5) <= 0.0025
