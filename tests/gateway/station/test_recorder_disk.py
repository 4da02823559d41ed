"""Issue 12, items 3, 4 and 7: the recorder on a full and on an unwritable disk (a real tmpfs
filled during a test), and test ids that cannot collide."""
import gzip
import json
import math
import os
import random
import subprocess
import time

from gateway.core.method.rules import LOST
from gateway.core.records import Command, CommandKind, SlotRecord
from gateway.offline.logio import read_log
from gateway.station import recorder as recmod
from gateway.station.recorder import LOG_NAME, RESULT_NAME, TestRecorder, floor_ms, new_test_dir, utc_iso
from kit.e2e import (
    analyze_cli,
    events,
    first_test_dir,
    read_json,
    run_gateway,
    scenario_file,
    station_yaml,
    test_dirs,
    virtual_station,
)
from kit.northbound import LoopThread, RunningStation, make_station
from kit.smallfs import fill, small_tmpfs
from kit.tools import wait_for

TUNED = {"dead_band_n": 0.01}   # the virtual plant wants the finer dead band (as the station e2e tests)

_rng = random.Random(5)


def rec(k):
    # random values: blocks that compress little, so a page's slack cannot hide a full disk
    return SlotRecord(k=k, t=k * 0.02, present=True, t1=_rng.uniform(0.2, 0.4), t2=_rng.uniform(0.5, 0.7), q=1, mask=0,
                      ratio=2.0, mu=math.log(2) / 1.8, mean_filt=0.45, speed_cmd=150.0,
                      speed_act=149.5, saturated=False)


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def feed(r, k):
    """One slot as the station feeds it: asked first; a refused slot goes by as LOST (no row)."""
    if r.accepts():
        r.on_record(rec(k))
    else:
        r.on_record(SlotRecord(k=k, t=k * 0.02, present=True, t1=0.3, t2=0.6, q=0, mask=LOST,
                               ratio=None, mu=None, mean_filt=0.45, speed_cmd=150.0,
                               speed_act=149.5, saturated=False))


def test_full_disk_keeps_members_whole_refuses_the_newest_and_resumes(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv(recmod.RESERVE_ENV, "200")
    states = []
    with small_tmpfs(tmp_path / "fs", "1m") as fs:
        clk = Clock()
        r = TestRecorder(os.path.join(fs, "t1"), {"station": "s", "test_id": "t1",
                                                  "method": {"t_set": 0.5, "t_end": 100.0}},
                         clock=clk, on_disk_state=lambda ok, info: states.append((ok, info)))
        assert r.reserve == 200
        k = 0
        for _ in range(5):                                  # 5 s on a good disk
            for _ in range(50):
                feed(r, k)
                k += 1
            clk.t += 1.0
        r.flush()
        filler = fill(fs)
        for _ in range(10):                                 # 10 s on a full disk: 500 rows
            for _ in range(50):
                feed(r, k)
                k += 1
            clk.t += 1.0
        assert not r.disk_ok and states == [(False, states[0][1])]
        assert not r.accepts()                              # the reserve is full: newest refused
        # what reached the disk (a tmpfs page's slack may take a block or two) reads back whole
        assert read_log(os.path.join(fs, "t1", LOG_NAME)).t.size >= 250
        with gzip.open(os.path.join(fs, "t1", LOG_NAME)) as f:
            f.read()                                        # every member complete (trailer, CRC)
        errors = [m for m in caplog.messages if "cannot write" in m]
        assert len(errors) == 1, errors                     # once, not once per slot
        os.unlink(filler)
        for _ in range(3):
            for _ in range(50):
                feed(r, k)
                k += 1
            clk.t += 1.0
        assert r.disk_ok and states[-1][0] is True and r.accepts()
        r.close({"test_status": "completed"})
        assert 0 < r.lost_rows <= 500 - 200
        # every row that was accepted is on disk; only the refused (LOST) slots are missing
        assert read_log(os.path.join(fs, "t1", LOG_NAME)).t.size == 900 - r.lost_rows


def test_full_disk_lost_span_is_the_refused_slots_and_analyze_reads_it(tmp_path, monkeypatch):
    monkeypatch.setenv(recmod.RESERVE_ENV, "200")
    with small_tmpfs(tmp_path / "fs", "1m") as fs:
        clk = Clock()
        d = os.path.join(fs, "t1")
        r = TestRecorder(d, {"station": "s", "test_id": "t1",
                             "method": {"t_set": 0.5, "t_end": 100.0}}, clock=clk)
        k = 0
        for sec in range(20):
            if sec == 5:
                filler = fill(fs)
            if sec == 15:
                os.unlink(filler)
            for _ in range(50):
                feed(r, k)
                k += 1
            clk.t += 1.0
        (a, b), = r.lost_spans
        # the sidecar has the span as soon as the disk takes writes again (a crash keeps it)
        assert read_log(os.path.join(d, LOG_NAME)).meta["lost_spans"] == [[a, b]]
        r.close({"test_status": "completed"})
        lg = read_log(os.path.join(d, LOG_NAME))
        ks = {int(math.floor(t / 0.02 + 0.5)) for t in lg.t}
        lost = set(range(1000)) - ks
        assert len(lost) == r.lost_rows > 0
        assert lost == set(range(a, b + 1))
        assert lg.meta["lost_spans"] == [[a, b]]
        with open(os.path.join(d, "events.jsonl")) as f:
            evs = [json.loads(x) for x in f]
        assert [e["type"] for e in evs] == ["disk_full", "disk_ok"]
        assert evs[1]["data"]["lost_spans"] == [[a, b]]
        res = read_json(os.path.join(d, RESULT_NAME))
        assert res["recorder"]["lost_rows"] == r.lost_rows
        out = analyze_cli(os.path.join(d, LOG_NAME))
        # the lost span is read as LOST slots (not MISSING: no protection stop at the gap; the
        # log of 1000 slots of a planned 5000 stops after its end)
        assert out["reasons"]["LOST"] == b - a + 1, out
        assert out["stop_slot"] >= 1000, out


def test_rows_still_in_memory_at_close_reach_the_log_with_the_result(tmp_path, monkeypatch):
    """A test that ends while the disk is full: the rows the method analysed are kept and written
    before the result when the disk takes them again (the log still gives the live result)."""
    monkeypatch.setattr(recmod, "RESULT_RETRY_S", 0.2)
    with small_tmpfs(tmp_path / "fs", "1m") as fs:
        clk = Clock()
        d = os.path.join(fs, "t1")
        r = TestRecorder(d, {"station": "s", "test_id": "t1",
                             "method": {"t_set": 0.5, "t_end": 100.0}}, clock=clk)
        for k in range(100):
            feed(r, k)
        clk.t += 1.0
        r.flush()
        filler = fill(fs)
        for k in range(100, 200):
            feed(r, k)
        r.close({"test_status": "completed"})
        assert not os.path.exists(os.path.join(d, RESULT_NAME))
        os.unlink(filler)
        wait_for(lambda: os.path.exists(os.path.join(d, RESULT_NAME)), 10, what="result written")
        assert read_log(os.path.join(d, LOG_NAME)).t.size == 200
        assert r.lost_rows == 0


# ------------------------------------------------------------------ a real station on a small disk


def test_station_on_a_disk_filled_then_freed_mid_test(tmp_path):
    sc = scenario_file(tmp_path, "full", method={"t_end": 600})
    with small_tmpfs(tmp_path / "records", "2m"), virtual_station(tmp_path, sc) as (_sim, links):
        st = station_yaml(tmp_path, links, name="full", control=TUNED, test={"t_end_s": 600})
        gw = run_gateway(tmp_path, st, "--start", "--duration", "40")
        try:
            d = first_test_dir(tmp_path, "full", timeout=30.0)
            time.sleep(3)
            filler = fill(str(tmp_path / "records"))
            time.sleep(5)
            # while full: the log on disk reads back (what reached the disk)
            assert read_log(os.path.join(d, LOG_NAME)).t.size > 0
            os.unlink(filler)
            time.sleep(4)
        finally:
            gw.stop()    # also when an assertion failed: no gateway left holding the test's ports
        glog = gw.log_all()
        assert "station failed" not in glog and "Traceback" not in glog, glog
        assert glog.count("cannot write") == 1, glog
        evs = events(d)
        types = [e["type"] for e in evs]
        assert "disk_full" in types and "disk_ok" in types, types
        res = read_json(os.path.join(d, RESULT_NAME))
        # 5 s full < the in-memory reserve: no row lost; the offline result equals the live one
        ok_ev = next(e for e in evs if e["type"] == "disk_ok")
        assert ok_ev["data"]["lost_rows"] == 0
        assert res.get("recorder", {"lost_rows": 0})["lost_rows"] == 0
        assert read_log(os.path.join(d, LOG_NAME)).t.size > 0
        out = analyze_cli(os.path.join(d, LOG_NAME))
        assert out == res["method"], (out, res["method"])


def test_station_folder_unwritable_mid_test_completes_and_keeps_its_result(tmp_path):
    sc = scenario_file(tmp_path, "ro", method={"t_end": 10})
    with small_tmpfs(tmp_path / "records", "8m"), virtual_station(tmp_path, sc) as (_sim, links):
        st = station_yaml(tmp_path, links, name="ro", control=TUNED, test={"t_end_s": 10})
        gw = run_gateway(tmp_path, st, "--start", "--duration", "30")
        d = None
        try:
            d = first_test_dir(tmp_path, "ro", timeout=30.0)
            time.sleep(2)
            # the test folder becomes unwritable (immutable: no new file, also for root)
            subprocess.run(["chattr", "+i", d], check=True)
            t_end = time.monotonic() + 25
            while time.monotonic() < t_end and "cannot write result.json" not in gw.log_all():
                time.sleep(0.2)
            assert "cannot write result.json" in gw.log_all(), gw.log()
            assert not os.path.exists(os.path.join(d, RESULT_NAME))
            subprocess.run(["chattr", "-i", d], check=True)
            t_end = time.monotonic() + 15
            while time.monotonic() < t_end and not os.path.exists(os.path.join(d, RESULT_NAME)):
                time.sleep(0.2)
        finally:
            gw.stop()    # also when an assertion failed: no gateway left, no immutable folder left
            if d is not None:
                subprocess.run(["chattr", "-i", d], check=False)
        glog = gw.log_all()
        assert "station failed" not in glog and "Traceback" not in glog, glog
        res = read_json(os.path.join(d, RESULT_NAME))
        assert res["test_status"] == "completed", res
        assert res["method"] == analyze_cli(os.path.join(d, LOG_NAME))


# ------------------------------------------------------------------ item 7: ids that cannot collide
def test_test_dirs_are_exclusive_within_one_millisecond(tmp_path):
    ids = [new_test_dir(str(tmp_path), "S 1", 1_700_000_000.25) for _ in range(3)]
    assert [i for i, _ in ids] == ["20231114T221320.250Z-S_1", "20231114T221320.250Z-S_1-2",
                                   "20231114T221320.250Z-S_1-3"]
    assert len({p for _, p in ids}) == 3 and all(os.path.isdir(p) for _, p in ids)


def test_a_test_id_is_never_earlier_nor_later_than_its_start(tmp_path):
    """Issue 27.9: a start at hh:mm:30.9996 (the station's clock read at that instant; no real
    clock here) was named ``…30.000Z`` (rounded to 1000 ms, then wrapped: 1 s early). Floored,
    the id and the start time written beside it name the same millisecond, never a later one."""
    base = 1_700_000_010.0                         # 2023-11-14T22:13:30Z
    for frac, want in ((0.9996, "30.999"), (0.99999, "30.999"), (0.0004, "30.000"), (0.5, "30.500")):
        tid, _ = new_test_dir(str(tmp_path), f"S{frac}", base + frac)
        assert tid.startswith(f"20231114T2213{want}Z-"), (frac, tid)
        assert utc_iso(base + frac) == f"2023-11-14T22:13:{want}Z", frac
    # whatever the fraction, the named instant is at or before the start and within 1 ms of it
    for i in range(1000):
        ts = base + i / 1000.0 + 0.0009999
        s, ms = floor_ms(ts)
        assert s + ms / 1000.0 <= ts < s + (ms + 1) / 1000.0 + 1e-9, ts


def test_two_tests_started_within_one_second_get_two_folders(tmp_path):
    """A real station (slot loop at 50 Hz, fake ports): start, stop, start again with the same
    sample within one second → two folders, each with its own log, result and events."""
    lt = LoopThread()
    st = make_station(tmp_path, [], station_id="twice")
    run = RunningStation(lt, st)
    try:
        wait_for(lambda: st.stats.slots > 5, 10, what="slots")
        # a test's folder is made at its slot 0, after the start sequence (METHOD.md §3a; the fake
        # plant settles within ~0.2 s): start, wait for slot 0, stop, start again, wait for slot 0
        starts = []
        for kind, args in ((CommandKind.START, {"sample_id": "S-1", "t_set": 0.5}),
                           (CommandKind.STOP, {}),
                           (CommandKind.START, {"sample_id": "S-1", "t_set": 0.5})):
            r = lt.call(st.submit(Command(kind, "cli", args)))
            assert r.ok, r.reason
            if kind == CommandKind.START:
                wait_for(lambda: st.session is not None, 5, what="slot 0")
                starts.append(time.time())
                time.sleep(0.1)                 # a few rows in each log
        assert starts[1] - starts[0] < 1.0      # both ids fall within one second
        r = lt.call(st.submit(Command(CommandKind.STOP, "cli", {})))
        assert r.ok
    finally:
        run.stop()
        lt.close()
    dirs = test_dirs(tmp_path, "twice")
    assert len(dirs) == 2, dirs
    ids = set()
    for d in dirs:
        res = read_json(os.path.join(d, RESULT_NAME))
        ids.add(res["test_id"])
        assert res["test_id"] == os.path.basename(d)
        assert read_log(os.path.join(d, LOG_NAME)).t.size > 0
        evs = events(d)
        assert {e["test_id"] for e in evs} == {res["test_id"]}
        assert [e["type"] for e in evs].count("test_started") == 1
    assert len(ids) == 2
