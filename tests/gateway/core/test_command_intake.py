"""Issue 21, item 1 and 2: the one bounded intake (gateway/core/command_intake.py ``intake``) —
the same raw command gets the same answer whichever door it came through (MQTT or console JSON
bytes, Sparkplug metrics, PLC registers or the CLI as a mapping); types strict, strings bounded;
client text clipped and escaped (gateway/plumbing/ratelog.py); refusals logged once per kind per window
with the count."""
import asyncio
import json
import logging
import threading

import pytest

from gateway.core.command_intake import MAX_STRING_CHARS, intake
from gateway.core.records import Command, CommandKind
from gateway.outputs.plc.server import ModbusOutput, ModbusSettings
from gateway.plumbing import doors as D
from gateway.plumbing.ratelog import RateLog, clip, safe
from gateway.station.command_desk import Rejection


def both(name, args):
    """The answer of the JSON doors (bytes) and of the mapping doors, which must agree."""
    a = intake(name, json.dumps(args).encode(), "mqtt")
    b = intake(name, args, "sparkplug")
    c = intake(None, json.dumps({"command": name, **args}).encode(), "console:alice")
    codes = {x.code if isinstance(x, Rejection) else 0 for x in (a, b, c)}
    assert len(codes) == 1, (a, b, c)
    return b


@pytest.mark.parametrize("name,args,code", [
    ("setpoint", {"t_set": "0.6"}, 9),                  # a string is not a number
    ("setpoint", {"t_set": True}, 9),                   # nor a boolean
    ("setpoint", {"t_set": [0.6]}, 9),
    ("setpoint", {"t_set": {"v": 0.6}}, 9),
    ("shelve", {"alarm": "end_of_life", "duration_s": False}, 9),
    ("shelve", {"alarm": 7, "duration_s": 60}, 9),
    ("shelve", {"alarm": "end\n_of_life", "duration_s": 60}, 9),
    ("start", {"sample_id": 5, "t_set": 0.5}, 9),
    ("start", {"sample_id": "S" * 10_000, "t_set": 0.5}, 9),
    ("start", {"sample_id": "S" * 40, "t_set": 0.5}, 4),   # longer than SAMPLE_ID_MAX (32)
    ("start", {"sample_id": "S-1\r\nX", "t_set": 0.5}, 4),
    ("start", {"sample_id": "S-1", "t_set": 0.5, "grade": "I" * 100}, 9),
    ("start", {"sample_id": "S-1", "t_set": 0.5, "request_id": "r" * 65}, 9),
    ("start", {"sample_id": "S-1", "t_set": 0.5, "request_id": 17}, 9),
    ("stop", {"evil": 1}, 9),
    ("fly", {}, 9),
    ("stop\nINFO forged", {}, 9),
])
def test_the_same_bad_command_is_refused_alike_by_every_door(name, args, code):
    r = both(name, args)
    assert isinstance(r, Rejection) and r.code == code, r
    assert len(r.reason) < 300 and "\n" not in r.reason and "\r" not in r.reason


def test_non_finite_and_huge_numbers_from_a_mapping_door():
    for v in (float("nan"), float("inf"), -float("inf"), 10 ** 400):
        r = intake("setpoint", {"t_set": v}, "plc:127.0.0.1")
        assert isinstance(r, Rejection) and r.code == 9 and len(r.reason) < 200, r


def test_a_good_command_is_the_same_command_from_every_door():
    args = {"sample_id": "S-1", "t_set": 0.6, "grade": "I", "t_end": 600, "request_id": "r-1"}
    r = both("start", args)
    assert isinstance(r, Command) and r.kind == CommandKind.START and r.request_id == "r-1"
    assert r.args == {"sample_id": "S-1", "t_set": 0.6, "grade": "I", "t_end": 600}
    assert intake("stop", None, "cli").args == {}
    assert isinstance(intake("ack", b"", "mqtt"), Command)
    assert intake("start", {"sample_id": "S-1", "t_set": 0.5, "grade": None}, "sparkplug").args == \
        {"sample_id": "S-1", "t_set": 0.5}


def test_bodies_are_bounded_before_parsing():
    for raw in (b"[" * 100_000, b'{"command": "stop", "x": ' + b"[" * 3000 + b"]" * 3000 + b"}",
                b"{" + b'"a": 1, ' * 2000 + b"}", b"\xff\xfe", json.dumps({"command": "stop" * 20}).encode()):
        r = intake(None, raw, "console:alice")
        assert isinstance(r, Rejection) and r.code == 9 and len(r.reason) < 200, r
    many = {f"k{i}": 1 for i in range(1000)}
    r = intake("stop", many, "sparkplug")
    assert isinstance(r, Rejection) and "1000 arguments" in r.reason
    assert isinstance(intake("stop", 7, "cli"), Rejection)          # type: ignore[arg-type]


def test_clip_and_safe_keep_client_text_short_and_on_one_line():
    assert clip("a\nb") == "'a\\nb'"
    big = "x" * 1_000_000
    assert len(clip(big)) < 80 and "1000000 chars" in clip(big)
    assert len(clip(b"\x00" * 50_000)) < 120
    assert safe("start") == "start" and safe("st\nart") == "'st\\nart'"
    assert "\x1b" not in safe("\x1b[2J") and len(safe("y" * MAX_STRING_CHARS * 100)) < 80


class _Clock:
    t = 0.0

    def __call__(self):
        return self.t


def test_rate_log_logs_once_per_kind_per_window_with_the_count(caplog):
    clock = _Clock()
    rl = RateLog(logging.getLogger("hookwatch.test_ratelog"), window_s=60.0, clock=clock)
    caplog.set_level(logging.INFO, logger="hookwatch.test_ratelog")
    for i in range(3000):
        clock.t = i * 0.01
        rl.info(("write", "t_set"), "PLC wrote t_set=%s: out of range", i)
    rl.info(("command", "stop"), "PLC command %s refused", "stop")
    assert [r.getMessage() for r in caplog.records] == ["PLC wrote t_set=0: out of range (×1)",
                                                        "PLC command stop refused (×1)"]
    clock.t = 61.0
    rl.flush()
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs[2:] == ["PLC wrote t_set=2999: out of range (×2999 in the last 60 s)"]
    rl.close()


def test_rate_log_without_a_timer_thread_still_counts_every_refusal(caplog, monkeypatch):
    """No thread to be had (the process at its thread limit): the refusal is still counted, its
    count comes with the next line of the log, and the next refusal arms the timer again (the log
    is never left without one)."""
    clock = _Clock()
    rl = RateLog(logging.getLogger("hookwatch.test_ratelog"), window_s=0.2, clock=clock)
    caplog.set_level(logging.INFO, logger="hookwatch.test_ratelog")
    real_start = threading.Timer.start

    def no_thread(self):
        raise RuntimeError("can't start new thread")
    monkeypatch.setattr(threading.Timer, "start", no_thread)
    rl.info("k", "refused %s", 1)
    rl.info("k", "refused %s", 2)                     # counted; no timer could start
    monkeypatch.setattr(threading.Timer, "start", real_start)
    rl.info("k", "refused %s", 3)                     # counted; the timer starts now
    clock.t = 1.0
    msgs = []
    for _ in range(200):                              # the timer says the count (real time)
        msgs = [r.getMessage() for r in caplog.records]
        if len(msgs) == 2:
            break
        threading.Event().wait(0.01)
    assert msgs == ["refused 1 (×1)", "refused 3 (×2 in the last 0 s)"], msgs
    rl.close()


def test_a_door_or_output_that_stops_says_its_last_counts_and_leaves_no_timer(caplog):
    """A PLC output and a door stop in the middle of a refusal window: the counts of the window
    are logged at the stop (not lost, not a minute later by a timer of an object that is gone —
    ci: timers of earlier tests' outputs wrote into a later test's log)."""
    caplog.set_level(logging.INFO, logger="hookwatch")
    out = ModbusOutput(ModbusSettings("stx", port=1, unit_id=9), None)
    door = D.Door("test door", D.DoorLimits(10, 1.0, 5.0), lambda sock, conn: None)
    for rl in (out.refusal_log, door.rlog):
        for i in range(5):
            rl.info("k", "refused %s", i)
        assert rl._timer is not None                   # the window's count is due later

    async def stop():
        await out.stop()
        await door.close()
    asyncio.run(stop())
    counts = [r.getMessage() for r in caplog.records if "×4 in the last" in r.getMessage()]
    assert len(counts) == 2, [r.getMessage() for r in caplog.records]
    assert out.refusal_log._timer is None and door.rlog._timer is None
