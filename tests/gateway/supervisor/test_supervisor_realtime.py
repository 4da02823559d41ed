"""`hookwatch run FLEET --realtime 20`: in each worker exactly the slot-loop thread runs under
SCHED_FIFO 20 (read back from /proc by thread), every other thread and the supervisor stay normal."""
from __future__ import annotations

import os
import re

import pytest
import yaml

from conftest import ROOT, hookwatch_cmd
from kit.e2e import fleet_dir, run_gateway
from kit.proc import Proc
from kit.tools import wait_for

NAMES = ("sim01", "sim02")


def _policies(pid: int) -> list[tuple[int, int]]:
    """(policy, rt_priority) of every thread of pid (fields 41 and 40 of /proc/PID/task/TID/stat)."""
    out = []
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out.append((int(fields[38]), int(fields[37])))
    return out


@pytest.mark.skipif(os.geteuid() != 0, reason="SCHED_FIFO needs root (CI runs as root)")
def test_realtime_slot_thread_per_worker_only(tmp_path):
    with open(os.path.join(ROOT, "config", "scenarios", "quick.yaml")) as f:
        sc = yaml.safe_load(f)
    sc["meter"] = {"map": os.path.join(ROOT, "config", "meters", "zn-s.yaml")}
    (tmp_path / "sc.yaml").write_text(yaml.safe_dump(sc))
    links = tmp_path / "links"
    sim = Proc(hookwatch_cmd() + ["sim", str(tmp_path / "sc.yaml"), "--count", "2", "--link-dir",
                                  str(links), "--duration", "120"], str(tmp_path / "sim.log"))
    gw = None
    try:
        sim.readline_until("ready:")
        fleet = fleet_dir(tmp_path)
        for name in NAMES:
            (fleet / "stations" / f"{name}.yaml").write_text(yaml.safe_dump({
                "station": {"id": name}, "meter": {"port": str(links / name / "meter")},
                "stm32": {"port": str(links / name / "stm32")}}))
        gw = run_gateway(tmp_path, str(fleet), "--realtime", "20")
        for name in NAMES:
            wait_for(lambda n=name: f"{n}: slot loop runs at SCHED_FIFO priority 20" in gw.log_all(),
                     30, 0.2, what=f"{name}: real-time slot loop")
        pids = [int(p) for p in re.findall(r"worker started \(pid (\d+)\)", gw.log_all())]
        assert len(pids) == 2
        for pid in pids:
            pol = _policies(pid)
            fifo = [p for p in pol if p[0] == os.SCHED_FIFO]
            assert fifo == [(os.SCHED_FIFO, 20)], pol           # the slot thread, and only it
            assert len(pol) > 1 and all(p == (os.SCHED_OTHER, 0) for p in pol if p not in fifo), pol
        assert all(p == (os.SCHED_OTHER, 0) for p in _policies(gw.p.pid))   # the supervisor
    finally:
        if gw is not None:
            gw.stop()
        sim.stop()
