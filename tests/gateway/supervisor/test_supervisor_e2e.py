"""Issue 16: process per station, one supervisor — with real processes: `hookwatch sim` virtual
stations over pseudo-terminals, `hookwatch run FLEET_DIR` (a supervisor and one worker process per
station), `kill -9` of a worker, SIGSTOP (a stuck worker), SIGHUP, `hookwatch check`."""
from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import threading
import time

import yaml

from conftest import ROOT, hookwatch_cmd
from gateway.supervisor.fleetcfg import RunOptions
from gateway.supervisor.supervisor import Supervisor
from kit.e2e import (
    QUICK_END,
    QUICK_METHOD,
    QUICK_SCALE,
    analyze_cli,
    assert_no_slot_lost,
    fleet_dir,
    read_json,
    run_gateway,
    test_dirs,
    virtual_station,
    wait_log,
)
from kit.tools import wait_for

METER_MAP = os.path.join(ROOT, "config", "meters", "zn-s.yaml")


def _scenario(path, seed, quick=False):
    """The one-minute life of config/scenarios/quick.yaml with its own seed (and grade);
    ``quick``: compressed twice more (the kit's QUICK_SCALE)."""
    with open(os.path.join(ROOT, "config", "scenarios", "quick.yaml")) as f:
        sc = yaml.safe_load(f)
    sc.update(seed=seed, meter={"map": METER_MAP})
    if quick:
        sc["plant"]["time_scale"] = QUICK_SCALE
    sc["plant"]["grade"] = "I" if seed % 2 else "II"
    path.write_text(yaml.safe_dump(sc))
    return str(path)


def _stations(stack, tmp_path, fleet, names, seed0=21, quick=False, **station):
    sims = {}
    for i, name in enumerate(names):
        sub = tmp_path / name
        sub.mkdir()
        sims[name] = stack.enter_context(virtual_station(sub, _scenario(sub / "sc.yaml", seed0 + i,
                                                                        quick)))
        links = sims[name][1]
        (fleet / "stations" / f"{name}.yaml").write_text(yaml.safe_dump({
            "station": {"id": name}, "meter": {"port": links["meter"]},
            "stm32": {"port": links["stm32"]}, "test": {"sample_id": f"S-{name}"}, **station}))
    return sims


def _worker_pids(gw, name) -> list[int]:
    return [int(p) for p in re.findall(rf"{name}: worker started \(pid (\d+)\)", gw.log_all())]


def _wait_pids(gw, name, n, timeout=30.0) -> list[int]:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        pids = _worker_pids(gw, name)
        if len(pids) >= n:
            return pids
        time.sleep(0.2)
    raise AssertionError(f"{name}: fewer than {n} worker starts:\n{gw.log()}")


def test_killed_worker_restarts_neighbours_fill_their_slots_broken_file_refused(tmp_path):
    # the kit's twice-compressed lives: end of life ~23 s (Grade I) / less (Grade II) after slot 0,
    # before QUICK_END; the victim's second test runs QUICK_END s after its restart
    fleet = fleet_dir(tmp_path, control={"dead_band_n": 0.01}, method=QUICK_METHOD,
                      test={"t_end_s": QUICK_END, "autostart": True})
    names = ("st-a", "st-b", "st-c")
    victim = "st-b"
    broken = fleet / "stations" / "st-x.yaml"
    broken.write_text("station: {id: st-x}\nmeter: {port: /dev/ttyX, baud: 12345}\nstm32: {port: /dev/ttyY}\n")
    with contextlib.ExitStack() as stack:
        _stations(stack, tmp_path, fleet, names, quick=True)
        chk = subprocess.run(hookwatch_cmd() + ["check", "--skip-local", str(fleet)],
                             capture_output=True, text=True, cwd=ROOT, timeout=60)
        assert chk.returncode == 1, chk.stdout + chk.stderr
        assert "st-x.yaml" in chk.stdout + chk.stderr and "baud" in chk.stdout + chk.stderr
        stats = tmp_path / "stats.json"
        gw = run_gateway(tmp_path, str(fleet), "--exit-when-done", "--stats-json", str(stats))
        try:
            wait_log(gw, f"{victim}: test_started", timeout=30)
            pids = {n: _wait_pids(gw, n, 1)[0] for n in names}
            assert len(set(pids.values())) == 3 and gw.p.pid not in pids.values()
            # mid-test: slot 0 came (test_started is its event) and a few seconds of slots more;
            # the victim's second test, run after its restart, is what the wall time waits for
            time.sleep(3)
            os.kill(pids[victim], signal.SIGKILL)
            new = _wait_pids(gw, victim, 2)[1]
            assert new != pids[victim]
            assert gw.p.wait(180) == 0, gw.log()
        finally:
            gw.stop()
    log = gw.log_all()
    # the broken file: refused alone, loudly, named with its problem
    line = next(ln for ln in log.splitlines() if "station st-x refused" in ln)
    assert "st-x.yaml" in line and "baud" in line, line
    assert f"{victim}: worker ended (signal 9); restarting in" in log
    for n in names:
        if n != victim:
            assert _worker_pids(gw, n) == [pids[n]], n           # the neighbours never restarted
    st = read_json(str(stats))
    assert st["st-x"]["refused"]
    assert st[victim]["restarts"] == 1
    for name in names:
        dirs = test_dirs(tmp_path, name)
        results = [read_json(os.path.join(d, "result.json")) for d in dirs]
        for d, res in zip(dirs, results):
            assert analyze_cli(os.path.join(d, "log.csv.gz")) == res["method"], (name, d)
        if name == victim:
            # the test cut off by kill -9 is closed at the worker's restart; a new one ran through
            assert [r["end_reason"] for r in results] == ["gateway restart", "completed"], results
            continue
        (res,) = results
        assert res["test_status"] == "completed" and res["method"]["status"] == "failure", res
        # nothing lost (the share of filled slots is a bench/ figure: bench_fleet.py)
        assert_no_slot_lost(dirs[0], res["method"], st[name])


def test_sighup_reloads_only_the_changed_station(tmp_path):
    fleet = fleet_dir(tmp_path, test={"t_end_s": 30})
    with contextlib.ExitStack() as stack:
        _stations(stack, tmp_path, fleet, ("one", "two"))
        gw = run_gateway(tmp_path, str(fleet))
        try:
            pids = {n: _wait_pids(gw, n, 1)[0] for n in ("one", "two")}
            time.sleep(3)
            f = fleet / "stations" / "one.yaml"
            d = yaml.safe_load(f.read_text())
            d["method"] = {"delta": 0.5}
            f.write_text(yaml.safe_dump(d))
            gw.p.send_signal(signal.SIGHUP)
            wait_log(gw, "one: configuration reloaded; station restarts")
            wait_log(gw, "one: config_reloaded")
            time.sleep(2)
            # SIGHUP again with nothing changed does nothing
            gw.p.send_signal(signal.SIGHUP)
            time.sleep(2)
        finally:
            assert gw.stop() == 0, gw.log()
    log = gw.log_all()
    assert "one: one.yaml changed: reload sent to its worker" in log
    assert log.count("reload sent to its worker") == 1, log[-3000:]
    assert "two: configuration reloaded" not in log and "two: config_reloaded" not in log
    assert {n: _worker_pids(gw, n) for n in pids} == {n: [p] for n, p in pids.items()}
    assert "Traceback" not in log


def test_commands_flow_back_and_a_stuck_worker_is_killed_and_restarted(tmp_path):
    """The supervisor as a library (how the shared Modbus TCP port, console and metrics use it):
    a command reaches station.submit in the worker and its reply comes back; a worker that stops
    answering makes a command time out, then the watchdog kills and restarts it."""
    fleet = fleet_dir(tmp_path, test={"t_end_s": 30})
    with contextlib.ExitStack() as stack:
        _stations(stack, tmp_path, fleet, ("cmd",))
        sup = Supervisor(str(fleet), RunOptions(no_northbound=True, log_level="warning"),
                         watchdog_s=3.0, backoff_s=0.5)
        sup.start()
        stop = threading.Event()

        def supervise():
            while not stop.wait(0.2):
                sup.tick()
        th = threading.Thread(target=supervise)
        th.start()
        try:
            hub = sup.hubs["cmd"]
            box = hub.subscribe()
            t_end = time.monotonic() + 30
            while not sup.all_up() or hub.state is None:
                assert time.monotonic() < t_end, "worker did not come up"
                time.sleep(0.1)
            r3 = hub.command("start", {"sample_id": "CMD-3", "t_set": 99.0})
            assert not r3.ok and "t_set" in r3.reason, r3      # the station's own validation
            r = hub.command("start", {"sample_id": "CMD-1", "t_set": 0.5, "t_end": 30}, source="plc:test")
            assert r.ok, r
            r2 = hub.command("start", {"sample_id": "CMD-2", "t_set": 0.5})
            assert not r2.ok and "already running" in r2.reason, r2
            t_end = time.monotonic() + 10
            while not (hub.state and hub.state.get("test_id") and hub.state["state"] == 1
                       and hub.last_slots):
                assert time.monotonic() < t_end, hub.state
                time.sleep(0.1)
            assert hub.snapshot()["slots"]["n"] == 10
            assert hub.command("stop", source="console").ok
            # the worker stops answering (SIGSTOP: a stuck process)
            w = hub.worker
            pid = w.proc.pid
            os.kill(pid, signal.SIGSTOP)
            # kill() only queues the stop: wait until the kernel shows the process stopped, so
            # that the command below cannot be answered in the moment before
            wait_for(lambda: _proc_state(pid) in ("T", "t"), 5, 0.01, what="worker stopped")
            # answered by the supervisor itself, not by the stuck worker (which cannot)
            r4 = hub.command("ack", timeout=0.5)
            assert not r4.ok and "did not answer within 0.5 s" in r4.reason
            t_end = time.monotonic() + 20
            while not (w.proc is not None and w.proc.pid != pid and w.hello):
                assert time.monotonic() < t_end, "stuck worker not restarted"
                time.sleep(0.1)
            kinds = [b.get("type") for k, b in box.drain()]
            assert "test_started" in kinds and "test_ended" in kinds and "command_rejected" in kinds
            assert kinds.index("worker_stuck") < kinds.index("worker_exited") < kinds.index("worker_restarted")
            # the new worker answers (yes or no) once its station runs (its hello may come a moment
            # before the station's loop does: "station is not running" until then)
            t_end = time.monotonic() + 20
            while True:
                r5 = hub.command("ack", timeout=5.0)
                if "not running" not in r5.reason or time.monotonic() > t_end:
                    break
                time.sleep(0.2)
            assert "did not answer" not in r5.reason and "not running" not in r5.reason, r5
        finally:
            stop.set()
            th.join()
            sup.stop()
    (d,) = test_dirs(tmp_path, "cmd")
    res = read_json(os.path.join(d, "result.json"))
    assert res["end_reason"] == "stopped by command" and res["sample_id"] == "CMD-1"


def test_fleet_unit_notify_follows_the_workers(tmp_path):
    """hookwatch-fleet.service (Type=notify, WatchdogSec): READY from the supervisor (MAINPID) once
    its workers run; WATCHDOG=1 every 2 s while they are healthy, none while a worker is stuck,
    again once the supervisor has restarted it — over a real unix datagram socket."""
    import socket

    from kit.proc import Proc

    rx = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    rx.bind(str(tmp_path / "notify.sock"))
    rx.settimeout(0.2)
    got: list[tuple[float, str]] = []

    def listen(seconds):
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            try:
                got.append((time.monotonic(), rx.recv(4096).decode()))
            except TimeoutError:
                pass

    fleet = fleet_dir(tmp_path, test={"t_end_s": 30})
    env = {**os.environ, "NOTIFY_SOCKET": str(tmp_path / "notify.sock"), "WATCHDOG_USEC": "10000000"}
    with contextlib.ExitStack() as stack:
        _stations(stack, tmp_path, fleet, ("n1", "n2"))
        gw = Proc(hookwatch_cmd() + ["run", str(fleet), "--worker-watchdog", "5"],
                  str(tmp_path / "gw.log"), env=env)
        try:
            t_end = time.monotonic() + 60
            while not any("READY=1" in m for _, m in got):
                assert time.monotonic() < t_end, (got, gw.log())
                listen(0.5)
            ready = next(m for _, m in got if "READY=1" in m)
            assert f"MAINPID={gw.p.pid}" in ready
            listen(5)
            assert sum(m == "WATCHDOG=1" for _, m in got) >= 2, got
            pid = _wait_pids(gw, "n1", 1)[0]
            os.kill(pid, signal.SIGSTOP)
            t_stop = time.monotonic()
            _wait_pids(gw, "n1", 2, timeout=30)               # killed after 5 s silent, restarted
            t_restart = time.monotonic()
            listen(8)
        finally:
            rc = gw.stop()
            rx.close()
    assert rc == 0, gw.log()
    beats = [t for t, m in got if m == "WATCHDOG=1"]
    during = [t for t in beats if t_stop + 3.5 < t < t_restart]
    assert not during, (t_stop, t_restart, beats)
    assert len([t for t in beats if t > t_restart]) >= 2, (t_restart, beats)
    assert "n1: worker pid" in gw.log_all() and "stuck loop?" in gw.log_all()


def _proc_state(pid: int) -> str:
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0]
