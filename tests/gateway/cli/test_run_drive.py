"""`hookwatch run`'s one main loop (gateway/cli/run.py: drive) over the Runtime contract
(gateway/core/ports.py): the same loop drives the stations of one process, a fleet's supervisor and
`hookwatch demo`. Here it drives a runtime that records what it is asked, so the loop's own rules
are seen alone: start once, tick, READY once, watchdog only while healthy, SIGHUP → reload (or
stop, for the demo), --exit-when-done, the demo's hold after the tests, stop once, the report
written and printed, the signal handlers put back."""
import json
import os
import signal
import threading

from gateway.cli.run import AfterDone, DriveOptions, Hangup, drive
from gateway.core.ports import Runtime

SIGNALS = (signal.SIGHUP, signal.SIGTERM, signal.SIGINT)


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
    base = {"duration_s": None, "exit_when_done": True, "stats_json": str(tmp_path / "stats.json")}
    return DriveOptions(**{**base, **kw})


def _later(*steps):
    """Send this process each (delay, signal) in turn, from a timer thread."""
    def send(i=0):
        if i < len(steps):
            os.kill(os.getpid(), steps[i][1])
            if i + 1 < len(steps):
                threading.Timer(steps[i + 1][0], send, (i + 1,)).start()
    threading.Timer(steps[0][0], send).start()


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
    old = {s: signal.getsignal(s) for s in SIGNALS}
    _later((0.5, signal.SIGHUP), (0.6, signal.SIGTERM))
    try:
        assert drive(rt, args(tmp_path, exit_when_done=False, stats_json=None)) == 0
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    assert rt.calls.count("reload") == 1 and rt.calls[-1] == "stop"


def test_the_loop_puts_the_signal_handlers_back(tmp_path, monkeypatch):
    """After the loop a second Ctrl-C is the caller's again (the demo's closing words after an
    interrupted life can be interrupted)."""
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    old = {s: signal.getsignal(s) for s in SIGNALS}
    assert drive(Recorder(done_after=2), args(tmp_path, stats_json=None)) == 0
    assert {s: signal.getsignal(s) for s in SIGNALS} == old


def test_a_hangup_that_means_stop_stops_without_a_reload(tmp_path, monkeypatch):
    """The demo's SIGHUP (its terminal closed) ends the loop as SIGTERM does; nothing reloads."""
    rt = Recorder(done_after=10**9)
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    _later((0.5, signal.SIGHUP))
    assert drive(rt, args(tmp_path, exit_when_done=False, stats_json=None, hangup=Hangup.STOP)) == 0
    assert "reload" not in rt.calls and rt.calls[-1] == "stop" and rt.calls.count("stop") == 1


def test_when_done_is_called_once_and_may_hold_the_runtime_until_a_signal(tmp_path, capsys, monkeypatch):
    """The demo's end of the life: its words once the tests are done, the stations (and the
    console) running on until Ctrl-C, then the usual stop; its report is not printed."""
    rt = Recorder(done_after=3)
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    seen = []

    def when_done():
        seen.append((rt.ticks, list(rt.calls)))
        threading.Timer(0.7, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
        return AfterDone.HOLD

    assert drive(rt, args(tmp_path, stats_json=None, when_done=when_done, print_report=False)) == 0
    assert len(seen) == 1 and seen[0][0] == 3 and "stop" not in seen[0][1]   # while it still ran
    assert rt.ticks > 3 and rt.calls[-1] == "stop" and rt.calls.count("stop") == 1
    assert capsys.readouterr().out == ""


def test_when_done_that_ends_ends_as_exit_when_done(tmp_path, monkeypatch):
    rt = Recorder(done_after=3)
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    calls = []
    assert drive(rt, args(tmp_path, stats_json=None,
                          when_done=lambda: calls.append(1) or AfterDone.END)) == 0
    assert calls == [1] and rt.ticks == 3 and rt.calls[-1] == "stop"


def test_a_runtime_with_nothing_to_run_is_an_error(tmp_path):
    rt = Recorder(alive=False)
    assert drive(rt, args(tmp_path)) == 1
    assert rt.calls == ["start", "stop"] and rt.ticks == 0
