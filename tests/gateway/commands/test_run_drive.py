"""`hookwatch run`'s one main loop (gateway/commands/run.py: drive) over the Runtime contract
(gateway/ports.py): the same loop drives the stations of one process and a fleet's supervisor.
Here it drives a runtime that records what it is asked, so the loop's own rules are seen alone:
start once, tick, READY once, watchdog only while healthy, SIGHUP → reload, --exit-when-done,
stop once, the report written and printed."""
import argparse
import json
import os
import signal
import threading

from gateway.commands.run import drive
from gateway.ports import Runtime


class Recorder:
    """A Runtime that is done after ``done_after`` ticks."""

    def __init__(self, done_after=5, alive=True):
        self.calls = []
        self.ticks = 0
        self.done_after = done_after
        self._alive = alive

    def start(self):
        self.calls.append("start")

    def tick(self, now):
        self.ticks += 1

    def alive(self):
        return self._alive

    def ready(self):
        return self.ticks >= 2

    def healthy(self):
        self.calls.append("healthy")
        return True

    def status(self):
        return f"{self.ticks} ticks"

    def tests_done(self):
        return self.ticks >= self.done_after

    def reload(self):
        self.calls.append("reload")

    def stop(self):
        self.calls.append("stop")

    def report(self):
        return {"st1": {"slots": 10, "results": [
            {"test_id": "T-1", "test_status": "completed", "end_reason": "completed",
             "method": {"status": "failure", "stop_reasons": None, "t_life": 12.5, "mu_ss": 0.2}}],
            "start_failures": [{"sample_id": "S-2", "reason": "no tension after 8 s"}]},
            "st2": None}


def args(tmp_path, **kw):
    base = {"duration": None, "exit_when_done": True, "stats_json": str(tmp_path / "stats.json")}
    return argparse.Namespace(**{**base, **kw})


def test_the_loop_runs_a_runtime_to_its_end_and_reports(tmp_path, capsys, monkeypatch):
    rt: Runtime = Recorder(done_after=4)
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert drive(rt, args(tmp_path)) == 0
    assert rt.calls[0] == "start" and rt.calls[-1] == "stop" and rt.calls.count("stop") == 1
    assert rt.ticks == 4                                 # --exit-when-done after the 4th tick
    with open(tmp_path / "stats.json") as f:
        assert json.load(f)["st1"]["slots"] == 10
    out = capsys.readouterr().out.splitlines()
    assert out == ["st1: start of S-2 failed: no tension after 8 s",
                   "st1: test T-1 completed (completed): status failure, t_life 12.5, mu_ss 0.2"]


def test_sighup_reloads_and_sigterm_stops(tmp_path, monkeypatch):
    rt = Recorder(done_after=10**9)
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    old = {s: signal.getsignal(s) for s in (signal.SIGHUP, signal.SIGTERM, signal.SIGINT)}

    def later():
        os.kill(os.getpid(), signal.SIGHUP)
        threading.Timer(0.6, lambda: os.kill(os.getpid(), signal.SIGTERM)).start()
    threading.Timer(0.5, later).start()
    try:
        assert drive(rt, args(tmp_path, exit_when_done=False, stats_json=None)) == 0
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    assert rt.calls.count("reload") == 1 and rt.calls[-1] == "stop"


def test_a_runtime_with_nothing_to_run_is_an_error(tmp_path):
    rt = Recorder(alive=False)
    assert drive(rt, args(tmp_path)) == 1
    assert rt.calls == ["start", "stop"] and rt.ticks == 0
