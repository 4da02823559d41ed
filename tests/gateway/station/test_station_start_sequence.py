"""The station's slot loop with METHOD.md §3a (start), §3 (a test ended on purpose) and §5a (wear
headroom and warning), on a virtual clock that runs flat out and a small fake plant: the meter
reads the plant's tension only while the STM32 has the motor enabled."""
import asyncio
import json
import math
import os

import yaml

from gateway.core.control import ControlParams
from gateway.core.records import Command, CommandKind, EventType
from gateway.core.records import TestState as TState
from gateway.offline.analysis import analyze_file
from gateway.station.station import Station, TestPlan
from kit.fakes import Capture, Reading
from kit.vclock import VirtualClock

THETA = math.radians(105.0)
FAST = {"w_ss": 0.2, "w_hold": 0.4, "tau": 0.2, "settle_time": 0.5, "start_timeout": 3.0}


class Motor:
    """The STM32 port of the fake plant: remembers whether the motor may run."""

    def __init__(self):
        self.connected = True
        self.counters = {}
        self.enabled = False
        self.calls = []
        self.speeds_while_off = 0
        self.turning_until = None      # the take-up runs down until this meter read (None: no status)
        self.meter = None

    async def open(self):
        pass

    async def close(self):
        pass

    async def enable(self):
        self.enabled = True
        self.calls.append("enable")

    async def set_speed(self, rpm):
        if "enable" not in self.calls:          # a speed command before the spin-up
            self.speeds_while_off += 1

    async def stop(self, reason=""):
        self.enabled = False
        self.calls.append(f"stop:{reason}")

    async def read_status(self):
        if self.turning_until is None:
            return None
        return Status(100.0 if self.meter is None or self.meter.reads < self.turning_until else 0.0)


class Status:
    def __init__(self, rpm):
        self.actual_rpm = rpm


class PlantMeter:
    """Motor off: the zero reading (plus ``offset`` on T1). Motor on: T1 ``t1`` N and
    T2 = T1·ratio(n), n counting the readings since the motor was enabled."""

    def __init__(self, motor, *, t1=0.4, ratio=lambda n: 1.5, offset=0.0, threaded=True,
                 connect_after=0):
        self.motor, self.t1, self.ratio, self.offset, self.threaded = motor, t1, ratio, offset, threaded
        self.connect_after = connect_after      # reads before the port opens (None: never)
        self.connected = connect_after == 0
        self.counters = {}
        self.n_on = 0
        self.reads = 0

    async def open(self):
        pass

    async def close(self):
        pass

    async def read(self):
        self.reads += 1
        if self.motor.turning_until is not None and self.reads < self.motor.turning_until:
            return Reading(0.3, 0.45)          # the yarn is still under tension
        if not self.connected:
            self.connected = self.connect_after is not None and self.reads > self.connect_after
            return None
        if not (self.motor.enabled and self.threaded):
            return Reading(0.001 + self.offset, 0.002)
        self.n_on += 1
        return Reading(self.t1, self.t1 * self.ratio(self.n_on))


def make(tmp_path, meter_kw=None, method=None, t_end=100.0, turning_until=None):
    motor = Motor()
    meter = PlantMeter(motor, **(meter_kw or {}))
    motor.meter, motor.turning_until = meter, turning_until
    st = Station(station_id="ss", method={**FAST, **(method or {})}, control=ControlParams(),
                 meter=meter, stm32=motor, records_dir=str(tmp_path),
                 default_plan=TestPlan("S-1", "I", 0.5, t_end), autostart=True,
                 idle_status_interval_s=0.0)
    vclock = VirtualClock(st.ts)
    st.clock_factory = lambda ts: vclock
    tap = Capture()
    st.outputs.append(tap)
    return st, motor, tap




def run(st, max_slots, during=None):
    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(st.run(stop, max_slots=max_slots))
        if during is not None:
            await during(st, stop)
        await task
    asyncio.run(main())


async def until(cond):
    while not cond():
        await asyncio.sleep(0)


def only_test(tmp_path):
    d = tmp_path / "ss"
    dirs = [x for x in os.listdir(d) if (d / x).is_dir()] if d.exists() else []
    assert len(dirs) == 1, dirs
    return d / dirs[0]


def kinds(events):
    return [e.type for e in events]


# ------------------------------------------------------------------------------------------------
def test_zero_check_with_motor_off_then_spin_up_then_slot_0_and_a_stop_command_writes_end_slot(tmp_path):
    st, motor, tap = make(tmp_path)

    async def during(st, stop):
        await until(lambda: st.state.state == TState.STARTING)
        await until(lambda: st.session is not None and st.session.monitor.k >= 300)
        reply = await st.submit(Command(CommandKind.STOP, "plc:127.0.0.1"))
        assert reply.ok, reply

    run(st, 2000, during)
    # the zero check ran with the motor off (1 s = 50 slots), then the motor was enabled
    assert motor.calls[0].startswith("stop:gateway start") and "enable" in motor.calls
    assert motor.speeds_while_off == 0
    k = kinds(tap.events)
    assert k.index(EventType.TEST_STARTING) < k.index(EventType.TEST_STARTED)
    started = next(e for e in tap.events if e.type == EventType.TEST_STARTED)
    assert started.k == 0 and 0.5 <= started.data["settle_s"] < 1.5, started.data
    assert abs(started.data["zero_offsets_n"]["T1"] - 0.001) < 1e-9
    d = only_test(tmp_path)
    res = json.loads((d / "result.json").read_text())
    m = res["method"]
    assert res["end_reason"] == "stopped by command" and res["test_status"] == "aborted"
    assert m["status"] == "aborted" and m["stop_reasons"] == ["STOPPED"], m
    meta = yaml.safe_load((d / "log.meta.yaml").read_text())
    assert meta["method"]["end_slot"] == m["n_slots"] == m["stop_slot"], (meta["method"], m)
    assert 300 <= m["n_slots"] <= 302, m
    assert meta["start"]["settle_s"] == started.data["settle_s"]
    # online == offline (the sidecar's end_slot gives the same slots; the spin-up is in no log)
    assert analyze_file(str(d / "log.csv.gz")).as_dict() == m
    assert m["reasons"]["LOW_TENSION"] == 0 and m["reasons"]["MISSING"] == 0, m
    assert st.state.state == TState.ABORTED and motor.calls[-1].startswith("stop:")


def test_clean_shutdown_writes_end_slot_and_reads_the_same_offline(tmp_path):
    st, _motor, _tap = make(tmp_path)

    async def during(st, stop):
        await until(lambda: st.session is not None and st.session.monitor.k >= 200)
        stop.set()

    run(st, 5000, during)
    d = only_test(tmp_path)
    res = json.loads((d / "result.json").read_text())
    m = res["method"]
    assert res["end_reason"] == "gateway shutdown" and m["stop_reasons"] == ["STOPPED"], res
    meta = yaml.safe_load((d / "log.meta.yaml").read_text())
    assert meta["method"]["end_slot"] == m["n_slots"]
    assert analyze_file(str(d / "log.csv.gz")).as_dict() == m


def test_a_test_that_reaches_t_end_has_no_end_slot(tmp_path):
    st, _motor, _tap = make(tmp_path, t_end=4.0)
    run(st, 1000)
    d = only_test(tmp_path)
    res = json.loads((d / "result.json").read_text())
    assert res["test_status"] == "completed" and res["method"]["n_slots"] == 200, res
    meta = yaml.safe_load((d / "log.meta.yaml").read_text())
    assert meta["method"].get("end_slot") is None
    assert analyze_file(str(d / "log.csv.gz")).as_dict() == res["method"]


def test_no_tension_start_fails_after_the_timeout_motor_stopped_nothing_recorded(tmp_path):
    st, motor, tap = make(tmp_path, meter_kw={"threaded": False})
    run(st, 400)
    failed = [e for e in tap.events if e.type == EventType.START_FAILED]
    assert len(failed) == 1, kinds(tap.events)
    assert failed[0].data["reason"].startswith("no tension after 3 s: T̄ 0.00 N"), failed[0].data
    assert failed[0].data["spin_up_s"] == 3.0
    assert EventType.TEST_STARTED not in kinds(tap.events)
    assert not (tmp_path / "ss").exists() or not [x for x in os.listdir(tmp_path / "ss")
                                                 if (tmp_path / "ss" / x).is_dir()]
    assert "enable" in motor.calls and motor.calls[-2].startswith("stop:no tension after 3 s")
    assert st.state.state == TState.IDLE and st.session is None and st.starting is None
    assert st.start_failures and st.results == []


def test_a_zero_offset_refuses_the_start_the_motor_never_runs(tmp_path):
    st, motor, tap = make(tmp_path, meter_kw={"offset": 0.06})
    run(st, 200)
    failed = [e for e in tap.events if e.type == EventType.START_FAILED]
    assert len(failed) == 1
    assert failed[0].data["reason"] == "zero check failed: T1 0.061 N (allowed ±0.02 N)", failed[0].data
    assert failed[0].data["zero_offsets_n"]["T1"] > 0.06
    assert "enable" not in motor.calls and motor.speeds_while_off == 0
    assert st.state.state == TState.IDLE


def test_swapped_channels_refuse_the_start(tmp_path):
    st, motor, tap = make(tmp_path, meter_kw={"t1": 0.6, "ratio": lambda n: 1 / 1.5})
    run(st, 400)
    failed = [e for e in tap.events if e.type == EventType.START_FAILED]
    assert len(failed) == 1 and failed[0].data["reason"].startswith(
        "channels swapped? set meter.swap_channels"), failed
    assert st.state.state == TState.IDLE and motor.calls[-2].startswith("stop:channels swapped")


def test_a_stop_during_the_start_cancels_it(tmp_path):
    st, motor, tap = make(tmp_path, meter_kw={"threaded": False})

    async def during(st, stop):
        await until(lambda: motor.enabled)
        reply = await st.submit(Command(CommandKind.STOP, "mqtt"))
        assert reply.ok

    run(st, 300, during)
    failed = [e for e in tap.events if e.type == EventType.START_FAILED]
    assert len(failed) == 1 and failed[0].data["reason"] == "start cancelled by command (mqtt)"
    assert not motor.enabled and st.state.state == TState.IDLE


def test_a_start_while_starting_is_busy(tmp_path):
    st, _motor, _tap = make(tmp_path, meter_kw={"threaded": False})
    replies = []

    async def during(st, stop):
        await until(lambda: st.state.state == TState.STARTING)
        replies.append(await st.submit(Command(CommandKind.START, "mqtt",
                                               {"sample_id": "S-2", "t_set": 0.5})))

    run(st, 100, during)
    assert not replies[0].ok and "already running" in replies[0].reason


def test_headroom_and_the_wear_warning_reach_state_events_and_the_alarm_store(tmp_path):
    # μ steady, then rising: the headroom falls, the warning (2 windows under 0.5) comes before
    # the end of life (μ above μ_th for τ = 10 slots); lead 0: the headroom run is the warning's
    # only reason (METHOD.md §5b: no prior, and no t_cross lies within a lead of 0 s)
    def ratio(n):
        return 1.5 if n < 150 else 1.5 + 0.001 * (n - 150)

    st, _motor, tap = make(tmp_path, meter_kw={"ratio": ratio},
                              method={"n_warn": 2, "h_warn": 0.5, "lead": 0})
    run(st, 800)
    events, states = tap.events, tap.states
    k = kinds(events)
    assert k.count(EventType.WEAR_WARNING) == 1, k
    assert k.index(EventType.BASELINE) < k.index(EventType.WEAR_WARNING) < k.index(EventType.END_OF_LIFE)
    ww = next(e for e in tap.events if e.type == EventType.WEAR_WARNING)
    assert ww.data["headroom"] < 0.5 and ww.data["warn_slot"] == ww.k
    # every window's headroom went out in the state; the projection once 10 windows had a value
    hs = [s.headroom for s in states if s.headroom is not None]
    assert len(set(hs)) >= 10 and hs[0] > 0.9 and min(hs) < 0
    assert any(s.t_cross is not None for s in states)
    assert any(s.wear_warning for s in states) and states[-1].wear_warning
    # the alarm store: the warning (priority 2) and the end of life (priority 1), both active
    w, eol = st.alarms.warning, st.alarms.record
    assert w.state.value == "unacknowledged" and w.priority == 2 and w.warn_slot == ww.data["warn_slot"]
    assert eol.state.value == "unacknowledged" and eol.priority == 1 and st.alarms.highest() is eol
    kept = json.loads((tmp_path / "ss" / "alarm.json").read_text())
    assert kept["alarm"] == "unacknowledged" and kept["warning"]["alarm"] == "unacknowledged"
    res = json.loads((only_test(tmp_path) / "result.json").read_text())["method"]
    assert res["warn_slot"] == ww.data["warn_slot"]
    assert analyze_file(str(only_test(tmp_path) / "log.csv.gz")).as_dict() == res


def test_the_zero_check_waits_for_the_meter_port_then_starts(tmp_path):
    """A gateway start: the meter's port opens 2 s after the start was accepted (it was locked or
    not there yet). The zero check waits for it instead of judging the silence."""
    st, motor, tap = make(tmp_path, meter_kw={"connect_after": 100})
    run(st, 600)
    k = kinds(tap.events)
    assert EventType.START_FAILED not in k and EventType.TEST_STARTED in k, [e.data for e in tap.events]
    assert motor.calls.index("enable") > 0


def test_a_meter_port_that_never_opens_fails_the_start_after_the_timeout(tmp_path):
    st, motor, tap = make(tmp_path, meter_kw={"connect_after": None})
    run(st, 400)
    failed = [e for e in tap.events if e.type == EventType.START_FAILED]
    assert len(failed) == 1 and failed[0].data["reason"] == (
        "zero check not possible: the meter's port is not open after 3 s"), failed
    assert "enable" not in motor.calls and st.state.state == TState.IDLE


def test_the_zero_check_waits_until_the_take_up_has_run_down(tmp_path):
    """A restart right after a crash (or a start right after a stop): the take-up still turns and
    the yarn is under tension for 2 s. The zero check measures the yarn at rest, not that."""
    st, motor, tap = make(tmp_path, turning_until=100)
    run(st, 700)
    k = kinds(tap.events)
    assert EventType.START_FAILED not in k and EventType.TEST_STARTED in k, [e.data for e in tap.events]
    started = next(e for e in tap.events if e.type == EventType.TEST_STARTED)
    assert abs(started.data["zero_offsets_n"]["T1"] - 0.001) < 1e-9


def test_a_take_up_that_never_stops_fails_the_start(tmp_path):
    st, motor, tap = make(tmp_path, turning_until=10**9)
    run(st, 400)
    failed = [e for e in tap.events if e.type == EventType.START_FAILED]
    assert len(failed) == 1 and failed[0].data["reason"] == (
        "zero check not possible: the take-up still turns after 3 s (100 rpm)"), failed
    assert "enable" not in motor.calls
