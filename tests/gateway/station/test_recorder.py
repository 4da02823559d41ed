"""The recorder: exact round trip of the values the method used, flushed each second, kill -9 safe."""
import json
import math
import signal
import subprocess
import sys
import textwrap

import numpy as np

from gateway.core.records import SlotRecord
from gateway.offline.logio import read_log
from gateway.station.recorder import LOG_NAME, RESULT_NAME, TestRecorder, incomplete_tests, recover_incomplete

META = {"station": "t", "sample_id": "S", "method": {"t_set": 0.5, "t_end": 100.0}}


def rec(k, t1, t2, present=True):
    return SlotRecord(k=k, t=k * 0.02, present=present, t1=t1, t2=t2, q=1, mask=0, ratio=t2 / t1,
                      mu=math.log(t2 / t1) / 1.8, mean_filt=(t1 + t2) / 2, speed_cmd=150.0,
                      speed_act=149.5, saturated=False)


def test_values_round_trip_exactly(tmp_path):
    rng = np.random.default_rng(3)
    vals = rng.uniform(0.1, 4.9, (500, 2)).astype(np.float32).astype(np.float64)
    r = TestRecorder(str(tmp_path / "x"), META)
    for k, (a, b) in enumerate(vals):
        r.on_record(rec(k, float(a), float(b), present=(k % 7 != 3)))
    r.close({"ok": True})
    lg = read_log(str(tmp_path / "x" / LOG_NAME))
    keep = np.array([k % 7 != 3 for k in range(500)])
    assert np.array_equal(lg.t1, vals[keep, 0]) and np.array_equal(lg.t2, vals[keep, 1])
    assert np.array_equal(np.floor(lg.t / 0.02 + 0.5), np.flatnonzero(keep))
    assert lg.meta["sample_id"] == "S"
    assert lg.columns[:3] == ["t", "T1", "T2"] and "speed_cmd" in lg.columns
    assert json.loads((tmp_path / "x" / RESULT_NAME).read_text()) == {"ok": True}


WRITER = textwrap.dedent("""
    import sys, time
    from gateway.core.records import SlotRecord
    from gateway.station.recorder import TestRecorder
    last = 0.0
    def clock():                    # the recorder's clock; its last reading is printed per record
        global last
        last = time.monotonic()
        return last
    r = TestRecorder(sys.argv[1], {"station": "t", "method": {"t_set": 0.5, "t_end": 1000.0}},
                     flush_interval_s=1.0, clock=clock)
    t0 = time.monotonic(); k = 0
    while True:
        while time.monotonic() < t0 + k * 0.02:
            time.sleep(0.001)
        r.on_record(SlotRecord(k=k, t=k * 0.02, present=True, t1=0.3, t2=0.6, q=1, mask=0,
                               ratio=2.0, mu=0.37, mean_filt=0.45, speed_cmd=1.0, speed_act=1.0,
                               saturated=False))
        print(k, repr(last), flush=True)
        k += 1
""")


def test_kill_9_loses_at_most_the_last_second_and_restart_closes_as_aborted(tmp_path):
    """What is lost to kill -9 is counted on the recorder's own clock (the time the writer had,
    however loaded the machine): the rows written are slots 0…m-1 in order, and the records handed
    over after them all came within one flush interval (1 s) of the last flush."""
    d = tmp_path / "station" / "test1"
    p = subprocess.Popen([sys.executable, "-c", WRITER, str(d)], stdout=subprocess.PIPE, text=True)
    handed: dict[int, float] = {}
    while len(handed) < 175:            # 3.5 s of slots handed to the recorder (≥ 3 flushes)
        line = p.stdout.readline()
        assert line, p.wait()
        k, t = line.split()
        handed[int(k)] = float(t)
    p.send_signal(signal.SIGKILL)
    p.wait()
    for line in p.stdout.read().splitlines():
        k, _, t = line.partition(" ")
        if t:                          # (a line cut by the kill has no time)
            handed[int(k)] = float(t)
    p.stdout.close()
    lg = read_log(str(d / LOG_NAME))
    m = lg.t.size
    assert m > 0 and np.array_equal(np.floor(lg.t / 0.02 + 0.5), np.arange(m))   # in order, no gap
    k_last = max(handed)
    if m - 1 in handed and k_last >= m:
        # the records lost (m…k_last) came less than flush_interval_s after the flush that wrote
        # m-1 (the clock's last reading in that call is the flush's)
        assert handed[k_last] - handed[m - 1] < 1.0, (m, k_last, handed[k_last] - handed[m - 1])
    assert m <= k_last + 2, (m, k_last)          # (+1: a record handed but not yet printed)
    assert incomplete_tests(str(tmp_path / "station")) == [str(d)]
    closed = recover_incomplete(str(tmp_path / "station"))
    assert len(closed) == 1
    res = json.loads((d / RESULT_NAME).read_text())
    assert res["test_status"] == "aborted" and res["end_reason"] == "gateway restart"
    assert res["method"]["status"] == "aborted"      # t_end not reached: the rest is MISSING
    assert res["method"]["n_slots"] >= lg.t.size
    assert incomplete_tests(str(tmp_path / "station")) == []


def test_a_test_start_never_waits_for_the_disk_on_the_slot_loop(tmp_path, monkeypatch):
    """A recorder opens at the test's slot 0, on the station's slot loop: the sidecar, the log's
    header and the events file are written there but synced by the background thread (an fsync
    on a busy disk once took ~0.2 s: 9 slots MISSING, the STM32's watchdog stopped the motor, a
    protection stop). The files are synced all the same, and read back."""
    import os
    import threading
    import time

    from gateway.offline.logio import read_meta
    from gateway.station import recorder as R

    calls: list[str] = []
    real = os.fsync

    def spy(fd):
        calls.append(threading.current_thread().name)
        return real(fd)

    monkeypatch.setattr(R.os, "fsync", spy)
    here = threading.current_thread().name
    r = TestRecorder(str(tmp_path / "x"), META)
    r.update_meta(["method", "end_slot"], 7)
    t_end = time.monotonic() + 20
    while len(calls) < 5 and time.monotonic() < t_end:
        time.sleep(0.01)
    assert here not in calls, calls
    assert len(calls) >= 5 and all(c.startswith("fsync") for c in calls), calls
    assert read_meta(os.path.join(r.dir, LOG_NAME))["method"]["end_slot"] == 7
    r.close({"test_status": "completed"})
