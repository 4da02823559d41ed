"""Issue 13 end to end (SHORT_METHOD.md §3, §3a): `hookwatch sim` + `hookwatch run` as processes over
pseudo-terminals — how a test really starts (zero check, spin-up, settle, timeout, swapped
channels) and how a test stopped on purpose reads (`end_slot`, STOPPED, online == offline)."""
import csv
import os
import time

import yaml

from conftest import ROOT
from gateway.outputs.plc import registers as R
from kit.e2e import (
    QUICK_END,
    QUICK_METHOD,
    SHORT_METHOD,
    analyze_cli,
    assert_no_slot_lost,
    events,
    quick_scenario,
    read_json,
    run_gateway,
    scenario_file,
    station_yaml,
    test_dirs,
    virtual_station,
    wait_exit,
)
from kit.northbound import mbpoll
from kit.tools import free_port, require_tool

SCENARIOS = os.path.join(ROOT, "config", "scenarios")
TUNED = {"dead_band_n": 0.01}








def logged_events(gw, kind):
    """The gateway's log lines of events of ``kind`` (`station: kind {data}`)."""
    return [x for x in gw.log_all().splitlines() if f": {kind} " in x]


def trace_speeds(path):
    with open(path) as f:
        return [(float(r["t"]), float(r["speed_rpm"])) for r in csv.DictReader(f)]


def refused_start(tmp_path, sc, name, *, method=None, meter=None, run_s=None):
    """Start a test on a plant where §3a refuses it; returns (gateway, wall seconds to exit,
    plant trace)."""
    trace = tmp_path / "trace.csv"
    with virtual_station(tmp_path, sc, extra=["--trace", str(trace)]) as (_sim, links):
        st = station_yaml(tmp_path, links, name=name, control=TUNED, method={**SHORT_METHOD, **(method or {})},
                          test={"t_end_s": 70}, meter=meter)
        t0 = time.monotonic()
        gw = run_gateway(tmp_path, st, "--start", "--exit-when-done")
        assert wait_exit(gw, run_s or 90) == 0, gw.log()
        took = time.monotonic() - t0
        gw.stop()
        time.sleep(0.5)             # the plant traces the motor after the stop
    return gw, took, trace_speeds(trace)


# ------------------------------------------------------------------------------------------------
def test_slow_take_up_starts_after_settling_and_ends_in_failure_identical_offline(tmp_path):
    """The shipped scenario: 6 s of slack yarn. Slot 0 at the start command aborted every test
    (protection stop after 1 s of LOW_TENSION); with §3a the test starts once settled. Its plant
    as shipped (the slack is running seconds, not wear), its life compressed twice more (the
    kit's QUICK_*: the end of life after ~23 s of test instead of ~53 s)."""
    sc = quick_scenario(tmp_path, "start-slow-take-up.yaml")
    with virtual_station(tmp_path, sc) as (_sim, links):
        st = station_yaml(tmp_path, links, name="slow", control=TUNED, method=QUICK_METHOD,
                          test={"t_end_s": QUICK_END})
        gw = run_gateway(tmp_path, st, "--start", "--exit-when-done")
        assert wait_exit(gw, 180) == 0, gw.log()
        gw.stop()
    dirs = test_dirs(tmp_path, "slow")
    assert len(dirs) == 1, dirs
    d = dirs[0]
    res = read_json(os.path.join(d, "result.json"))
    online = res["method"]
    assert res["test_status"] == "completed", res
    assert online["status"] == "failure", online
    assert online["reasons"]["LOW_TENSION"] < 50, online     # the slack is not in the test
    assert online == analyze_cli(os.path.join(d, "log.csv.gz"))
    with open(os.path.join(d, "log.meta.yaml")) as f:
        meta = yaml.safe_load(f)
    # the spin-up took the slack (6 s) and the settle time (2 s); the offsets are information
    assert meta["start"]["settle_s"] >= 6.0 + 2.0, meta["start"]
    assert abs(meta["start"]["zero_offsets_n"]["T1"]) <= 0.02, meta["start"]
    assert "end_slot" not in meta["method"] or meta["method"]["end_slot"] is None
    kinds = [e["type"] for e in events(d)]
    assert kinds.count("test_started") == 1 and "protection_stop" not in kinds, kinds
    started = next(e for e in events(d) if e["type"] == "test_started")
    assert started["k"] == 0 and started["settle_s"] == meta["start"]["settle_s"]
    assert len(logged_events(gw, "test_starting")) == 1, gw.log()


def test_yarn_not_threaded_start_fails_within_the_timeout_motor_stopped_nothing_recorded(tmp_path):
    sc = os.path.join(SCENARIOS, "start-not-threaded.yaml")
    gw, took, speeds = refused_start(tmp_path, sc, "nothr", method={"start_timeout": 8})
    assert test_dirs(tmp_path, "nothr") == []
    failed = logged_events(gw, "start_failed")
    assert len(failed) == 1 and "no tension after 8 s" in failed[0], gw.log()
    assert "start of S-1 failed: no tension after 8 s" in "".join(gw.stdout_lines())
    # within the timeout: the station's own count says 8 s (above); the wall time to exit
    # (1 s of zero check + 8 s of spin-up + the process' start and stop) is information only
    print(f"refused start: {took:.1f} s from `hookwatch run` to its exit")
    # the motor ran during the spin-up and was stopped after the failure
    assert max(v for _t, v in speeds) > 10, speeds[-5:]
    assert speeds[-1][1] < 1.0, speeds[-5:]


def test_zero_offset_refuses_the_start_with_the_offset_motor_never_runs(tmp_path):
    sc = os.path.join(SCENARIOS, "start-zero-offset.yaml")
    gw, _took, speeds = refused_start(tmp_path, sc, "zoff")
    assert test_dirs(tmp_path, "zoff") == []
    failed = logged_events(gw, "start_failed")
    assert len(failed) == 1 and "zero check failed: T1 0.0" in failed[0], gw.log()
    assert "T2" not in failed[0].split("zero check failed:")[1].split("(")[0], failed[0]
    assert max(v for _t, v in speeds) < 1.0


def test_swapped_channels_refuse_the_start(tmp_path):
    sc = scenario_file(tmp_path, "swap", faults=[{"at_s": 0, "duration_s": 600, "fault": "swap_channels"}])
    gw, _took, speeds = refused_start(tmp_path, sc, "swap")
    assert test_dirs(tmp_path, "swap") == []
    failed = logged_events(gw, "start_failed")
    assert len(failed) == 1 and "channels swapped? set meter.swap_channels" in failed[0], gw.log()
    assert speeds[-1][1] < 1.0


# ------------------------------------------------------------------------------------------------
def test_a_plc_stop_mid_test_is_stopped_not_missing_and_identical_offline(tmp_path):
    require_tool("mbpoll")
    sc = scenario_file(tmp_path, "stop", t_end=600)
    mport = free_port()
    with virtual_station(tmp_path, sc) as (_sim, links):
        st = station_yaml(tmp_path, links, name="stop", control=TUNED, method=SHORT_METHOD,
                          test={"t_end_s": 600},
                          modbus_tcp={"enabled": True, "port": mport, "unit_id": 3,
                                      "writes": {"enabled": True, "allowed_clients": ["127.0.0.1"]}})
        gw = run_gateway(tmp_path, st, "--start", "--exit-when-done")
        t_wait = time.monotonic() + 60
        d = None
        while time.monotonic() < t_wait and d is None:
            dirs = test_dirs(tmp_path, "stop")
            d = dirs[0] if dirs else None
            time.sleep(0.2)
        assert d is not None, gw.log()
        time.sleep(8.0)
        rc, _v, err = mbpoll(mport, "-t", "4", "-r", str(R.HR["command"].address), unit=3, values=[2])
        assert rc == 0, err
        assert wait_exit(gw, 30) == 0, gw.log()
        gw.stop()
    res = read_json(os.path.join(d, "result.json"))
    online = res["method"]
    assert res["test_status"] == "aborted" and res["end_reason"] == "stopped by command", res
    assert online["status"] == "aborted" and online["stop_reasons"] == ["STOPPED"], online
    with open(os.path.join(d, "log.meta.yaml")) as f:
        meta = yaml.safe_load(f)
    assert meta["method"]["end_slot"] == online["n_slots"] == online["stop_slot"], (meta["method"], online)
    assert 7.0 / 0.02 < online["n_slots"] < 30.0 / 0.02, online
    assert_no_slot_lost(d, online)     # every slot up to the stop recorded, in order
    assert online == analyze_cli(os.path.join(d, "log.csv.gz"))
    out = "".join(gw.stdout_lines())
    # the line a person reads says STOPPED, not MISSING
    assert "status aborted (STOPPED)" in out and "MISSING" not in out, out
