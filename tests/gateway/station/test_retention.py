"""Record retention (gateway/station/retention.py): the pure policy, and passes over real folders on a
real small tmpfs with a real outbox (SQLite, as the MQTT output keeps it)."""
from __future__ import annotations

import json
import os
import time

import pytest

from gateway.outputs.broker.outbox import Outbox, Row
from gateway.station import retention as R
from kit.smallfs import small_tmpfs

DAY = 86400.0


def F(tid, closed, size=1000, completed=True):
    return R.Folder(test_id=tid, path=f"/x/{tid}", closed=closed, size=size, completed=completed)


def ids(plan):
    return [f.test_id for f, _ in plan.prune]


def test_age_keeps_the_newest_and_the_protected():
    now = 100 * DAY
    fs = [F(f"t{i}", i * DAY) for i in range(10)]
    p = R.select(fs, R.Policy(max_age_days=50, min_free_percent=0, keep_last=3), now, protected={"t1"})
    assert ids(p) == ["t0", "t2", "t3", "t4", "t5", "t6"]      # all closed > 50 days ago but t1
    # keep_last wins over the age
    p = R.select(fs, R.Policy(max_age_days=1, min_free_percent=0, keep_last=8), now, protected=set())
    assert ids(p) == ["t0", "t1"]


def test_size_budget_prunes_oldest_first_until_under():
    fs = [F(f"t{i}", i, size=1_000_000) for i in range(6)]
    p = R.select(fs, R.Policy(max_total_mb=3.5, min_free_percent=0, keep_last=1), 0, protected=set())
    assert ids(p) == ["t0", "t1", "t2"] and {r for _, r in p.prune} == {"max_total_mb"}


def test_free_space_floor_counts_what_it_frees():
    fs = [F(f"t{i}", i, size=10) for i in range(6)]
    p = R.select(fs, R.Policy(min_free_percent=50, keep_last=2), 0, set(), R.Disk(total=100, free=25))
    assert ids(p) == ["t0", "t1", "t2"]                       # 25 → 55 ≥ 50


def test_never_the_running_or_unclosed_ones():
    fs = [F("old-running", 0, completed=False), F("a", 1), F("b", 2), F("c", 3)]
    p = R.select(fs, R.Policy(max_age_days=1, min_free_percent=0, keep_last=1), 10 * DAY, protected={"a"})
    assert ids(p) == ["b"]


def _test_folder(d, tid, nbytes, closed):
    p = os.path.join(d, tid)
    os.makedirs(p)
    with open(os.path.join(p, "log.csv.gz"), "wb") as f:
        f.write(os.urandom(nbytes))
    with open(os.path.join(p, "result.json"), "w") as f:
        json.dump({"test_id": tid, "test_status": "completed"}, f)
    os.utime(os.path.join(p, "result.json"), (closed, closed))
    return p


def test_prune_on_a_small_tmpfs_keeps_pending_results(tmp_path):
    with small_tmpfs(tmp_path / "fs", "2m") as fs:
        st = os.path.join(fs, "loom-01")
        os.makedirs(st)
        now = time.time()
        for i in range(8):
            _test_folder(st, f"T{i}", 200_000, now - (8 - i) * 60)
        os.makedirs(os.path.join(st, "RUNNING"))               # no result.json: the running test
        # T0's result has not left: it is still a row of the outbox
        ob = Outbox(os.path.join(fs, "outbox.sqlite"))
        ob.add([Row(seq=ob.next_seq(), kind="result", topic="x/result", payload=json.dumps({"test_id": "T0"}).encode(),
                    qos=1, retain=False)])
        ob.close()
        pol = R.Policy(min_free_percent=60, keep_last=2)
        res = R.prune("loom-01", st, pol, now, running="RUNNING", outbox_path=os.path.join(fs, "outbox.sqlite"))
        assert res is not None and res.failed == []
        left = sorted(os.listdir(st))
        assert "T0" in left and "RUNNING" in left and "T6" in left and "T7" in left
        assert res.tests and res.tests[0] == "T1"              # oldest eligible first
        d = R.disk_of(st)
        assert d.free >= d.total * 0.6 or set(left) == {"T0", "RUNNING", "T6", "T7"}
        # a second pass has nothing more to do
        assert R.prune("loom-01", st, pol, now, running="RUNNING",
                       outbox_path=os.path.join(fs, "outbox.sqlite")) is None


def test_an_unreadable_outbox_prunes_nothing(tmp_path):
    st = tmp_path / "st"
    st.mkdir()
    for i in range(5):
        _test_folder(str(st), f"T{i}", 10, time.time() - 10 * DAY)
    bad = tmp_path / "outbox.sqlite"
    bad.write_bytes(b"not a database" * 100)
    assert R.prune("s", str(st), R.Policy(max_age_days=1, keep_last=1), time.time(), None, str(bad)) is None
    assert len(os.listdir(st)) == 5


@pytest.mark.parametrize("name", ["", "nonexistent"])
def test_a_missing_station_folder_is_no_error(tmp_path, name):
    assert R.prune("s", str(tmp_path / "nope" / name), R.Policy(), time.time(), None, None) is None
