"""The virtual plant's start faults (slow take-up, zero offset, yarn not threaded, swapped
channels) and the §3a start sequence driven by the gateway's real controller, slot by slot, the
way the station will drive it (pure: plant, controller and method in one loop, no I/O)."""
import os
from dataclasses import replace

import pytest

from conftest import ROOT
from drivers.sim.plant import Plant
from drivers.sim.scenario import ScenarioError, load_scenario, scenario_from_dict
from gateway.core.control import Controller, ControlParams
from gateway.core.method import MethodParams, StreamingMonitor
from gateway.core.method.start import FAILED, SETTLED, StartSequence

SCEN = os.path.join(ROOT, "config", "scenarios")
TS = 0.02


def scenario(name):
    return load_scenario(os.path.join(SCEN, name + ".yaml"))


class Bench:
    """Plant + controller at 50 Hz; k counts slots of plant time."""

    def __init__(self, plant_params, seed=1, swap=False):
        self.plant = Plant(plant_params, seed=seed)
        self.plant.faults.swap_channels = swap
        self.ctl = Controller(ControlParams(dead_band_n=0.01), plant_params.t_set)
        self.k = 0

    def read(self):
        self.plant.advance_to(self.k * TS)
        self.k += 1
        return self.plant.tensions()

    def motor_off_slot(self):
        self.plant.enable(False)
        return self.read()

    def closed_loop_slot(self):
        a, b = self.read()
        out = self.ctl.step((a + b) / 2.0, self.plant.speed_rpm)
        self.plant.enable(True)
        self.plant.set_command(out.u)
        return a, b, out.y


def start(bench, p):
    """Run §3a on the bench; returns the sequence."""
    seq = StartSequence(p)
    while seq.phase == "zero_check":
        seq.zero_slot(True, *bench.motor_off_slot())
    while seq.phase == "spin_up":
        a, b, y = bench.closed_loop_slot()
        seq.spin_slot(True, a, b, y)
    if seq.phase == FAILED:
        bench.plant.enable(False)
    return seq


def method_params(sc, **kw):
    return MethodParams(t_set=sc.plant.t_set, **{**sc.method, **kw})


def test_slow_take_up_has_seconds_of_low_tension_then_settles_and_the_life_ends_in_failure():
    sc = scenario("start-slow-take-up")
    assert sc.plant.tension.slack_s == 6.0
    p = method_params(sc)
    bench = Bench(sc.plant)
    seq = start(bench, p)
    assert seq.phase == SETTLED, seq.reason
    settle = seq.outcome().settle_s
    assert 8.0 < settle < 15.0
    assert bench.plant.wear_s == pytest.approx((settle - 6.0) * 600, rel=0.15)   # no wear on slack
    # slot 0 is the next slot: the test runs to its end and finds t_life
    mon = StreamingMonitor(p)
    while not mon.finished:
        a, b, _ = bench.closed_loop_slot()
        mon.push(True, a, b)
    r = mon.result()
    assert r.status == "failure" and 40.0 < r.t_life < 70.0, r


def test_slow_take_up_aborts_when_slot_0_is_the_start_command():
    """What the old start did: the low-tension slack phase is a protection stop at the 51st slot."""
    sc = scenario("start-slow-take-up")
    bench = Bench(sc.plant)
    for _ in range(50):
        bench.motor_off_slot()
    mon = StreamingMonitor(method_params(sc))
    while not mon.finished:
        a, b, _ = bench.closed_loop_slot()
        mon.push(True, a, b)
    r = mon.result()
    assert (r.status, r.stop_slot, r.stop_reasons) == ("aborted", 50, ["LOW_TENSION"])


def test_a_zero_offset_refuses_the_start_with_the_offset_and_the_motor_never_runs():
    sc = scenario("start-zero-offset")
    bench = Bench(sc.plant)
    seq = start(bench, method_params(sc))
    assert seq.phase == FAILED
    assert seq.reason.startswith("zero check failed: T1 0.06")
    assert 0.055 < seq.offsets["T1"] < 0.075 and abs(seq.offsets["T2"]) < 0.02
    assert bench.plant.speed_rpm == 0.0 and bench.plant.run_s == 0.0


def test_yarn_not_threaded_fails_after_the_start_timeout():
    sc = scenario("start-not-threaded")
    bench = Bench(sc.plant)
    seq = start(bench, method_params(sc))
    assert seq.phase == FAILED and seq.reason.startswith("no tension after 30 s: T̄ 0.00 N")
    assert seq.spin_slots == 1500
    assert bench.plant.wear_s == 0.0 and not bench.plant.enabled


def test_swapped_channels_are_refused():
    sc = scenario("quick")
    bench = Bench(sc.plant, swap=True)
    seq = start(bench, method_params(sc))
    assert seq.phase == FAILED and seq.reason.startswith("channels swapped? set meter.swap_channels")


def test_the_plain_plant_starts_quickly():
    sc = scenario("quick")
    seq = start(Bench(sc.plant), method_params(sc))
    assert seq.phase == SETTLED and seq.outcome().settle_s < 6.0
    assert seq.sidecar()["zero_offsets_n"]["T1"] == pytest.approx(0.0, abs=0.02)


def test_plant_slack_forms_again_at_standstill_and_offsets_add_to_readings():
    sc = scenario("quick")
    pp = replace(sc.plant, tension=replace(sc.plant.tension, slack_s=1.0),
                 sensor=replace(sc.plant.sensor, offset_ch2=-0.05, noise_n=0.0))
    pl = Plant(pp, seed=3)
    assert pl.tensions()[1] == pytest.approx(-0.05 + pl.t2_true, abs=0.001)
    pl.enable(True)
    pl.set_command(200.0)
    pl.advance_to(1.0)
    assert pl.t_mean < 0.02 and pl.slack_left_s > 0          # still winding the slack up
    pl.advance_to(3.0)
    assert pl.t_mean > 0.3 and pl.slack_left_s <= 0
    pl.enable(False)
    pl.advance_to(5.0)
    assert pl.speed_rpm < 1.0 and pl.slack_left_s == 1.0   # standstill: slack again


def test_scenario_keys_are_validated():
    for plant, words in (({"threaded": "no"}, "plant.threaded"), ({"sensor": {"offset_ch1": 2.0}}, "offset_ch1"),
                         ({"tension": {"slack_s": -1}}, "slack_s")):
        with pytest.raises(ScenarioError, match=words):
            scenario_from_dict({"plant": plant}, "x.yaml")
    sc = scenario_from_dict({"plant": {"threaded": False, "sensor": {"offset_ch1": -0.03}}}, "x.yaml")
    assert sc.plant.threaded is False and sc.plant.sensor.offset_ch1 == -0.03
