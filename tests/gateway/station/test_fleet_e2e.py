"""Issue 6: many stations in one gateway process, each isolated. Four virtual stations (separate
`hookwatch sim` processes) and one `hookwatch run FLEET_DIR`; one meter dies mid-test, the other
three keep their slots and finish their lives with results identical to offline analysis."""
import contextlib
import os
import subprocess

import yaml

from conftest import ROOT, hookwatch_cmd
from kit.e2e import (
    QUICK_END,
    QUICK_METHOD,
    QUICK_SCALE,
    analyze_cli,
    assert_no_slot_lost,
    fleet_dir,
    kill_virtual_station,
    read_json,
    run_gateway,
    test_dirs,
    virtual_station,
)
from kit.tools import wait_for

METER_MAP = os.path.join(ROOT, "config", "meters", "zn-s.yaml")
STATIONS = ("st-a", "st-b", "st-c", "st-d")
VICTIM = "st-b"


def _scenario(path, seed):
    path.write_text(yaml.safe_dump({
        "description": "fleet test life", "seed": seed, "meter": {"map": METER_MAP},
        "stm32": {"watchdog_s": 0.2},
        "plant": {"grade": "I" if seed % 2 else "II", "t_set": 0.5, "time_scale": QUICK_SCALE},
        "method": {**QUICK_METHOD, "t_end": QUICK_END}, "faults": []}))
    return str(path)


def test_four_stations_one_process_one_meter_killed(tmp_path):
    # the kit's twice-compressed lives (Grade I and II): each ends in failure before QUICK_END
    fleet = fleet_dir(tmp_path, control={"dead_band_n": 0.01}, method=QUICK_METHOD,
                      test={"t_end_s": QUICK_END, "autostart": True})
    with contextlib.ExitStack() as stack:
        sims = {}
        for i, name in enumerate(STATIONS):
            sub = tmp_path / name
            sub.mkdir()
            sims[name] = stack.enter_context(
                virtual_station(sub, _scenario(sub / "sc.yaml", seed=11 + i)))
            _proc, links = sims[name]
            (fleet / "stations" / f"{name}.yaml").write_text(yaml.safe_dump({
                "station": {"id": name}, "meter": {"port": links["meter"]},
                "stm32": {"port": links["stm32"]}, "test": {"sample_id": f"S-{name}"}}))
        chk = subprocess.run(hookwatch_cmd() + ["check", "--skip-local", str(fleet)],
                             capture_output=True, text=True, cwd=ROOT, timeout=60)
        assert chk.returncode == 0, chk.stdout + chk.stderr
        stats = tmp_path / "stats.json"
        # as deployed (the systemd units): slot loops under SCHED_FIFO 20 where permitted (root
        # here in CI). The share of filled slots (goal ≥ 99.9 %) is a figure of a quiet box:
        # bench/bench_fleet.py measures it; this test asserts what holds on a loaded one
        gw = run_gateway(tmp_path, str(fleet), "--exit-when-done", "--stats-json", str(stats),
                         "--realtime", "20")
        # mid-test, the victim's virtual station dies with both its ports: its meter is gone.
        # Mid-test by the victim's own progress (its test folder exists: slot 0 came, ~7 s after
        # the start on a quiet machine, later on a loaded one) and a few seconds of slots more —
        # not by the wall clock, which a loaded machine stretches
        import time
        wait_for(lambda: test_dirs(tmp_path, VICTIM), 120, 0.2, what="the victim's test started")
        time.sleep(3)
        kill_virtual_station(*sims[VICTIM])
        try:
            assert gw.p.wait(150) == 0, gw.log()
        finally:
            gw.stop()
    st = read_json(str(stats))
    for name in STATIONS:
        dirs = test_dirs(tmp_path, name)
        assert len(dirs) == 1, (name, dirs)
        res = read_json(os.path.join(dirs[0], "result.json"))
        online = res["method"]
        assert analyze_cli(os.path.join(dirs[0], "log.csv.gz")) == online, name
        if name == VICTIM:
            assert res["test_status"] == "aborted" and online["stop_reasons"] == ["MISSING"], res
            assert_no_slot_lost(dirs[0], online)     # recorded in order up to the stop
            continue
        # nothing lost: every slot recorded in order, read or counted MISSING by the station
        missing = assert_no_slot_lost(dirs[0], online, st[name])
        lived = res["test_status"] == "completed" and online["status"] == "failure"
        if missing <= 0.01 * online["n_slots"]:
            # the machine let the life through: it ends in failure (the hook's end of life)
            assert lived, (name, res)
        else:
            # starved by a loaded machine (> 1 % of its own slots MISSING: windows without a
            # value, the end of life seen late): the life ends in failure, or in the protection
            # stop on its own unsafe slots — never otherwise (the victim's loss is not theirs)
            assert lived or (res["end_reason"] == "protection stop"
                             and set(online["stop_reasons"]) <= {"MISSING", "LOW_TENSION"}), (name, res)
