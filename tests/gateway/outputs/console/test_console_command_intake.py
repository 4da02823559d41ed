"""Issue 21: the console's commands go through the one bounded intake of every door (real HTTP to
`hookwatch run` with the console on): strict types, bounded strings never echoed, no forged log
line, deep JSON answered (not a 500), refusals logged once per kind per minute with a count."""
from __future__ import annotations

import json
import re
import time

from kit.console_helpers import Client, console_fleet
from kit.e2e import wait_log

PW = "correct horse battery"
CMD = "/api/station/loom-a/command"


def test_console_commands_are_bounded_like_every_other_door(tmp_path):
    with console_fleet(tmp_path, ("loom-a",), users={"alice": PW}) as (url, gw, _sims):
        c = Client(url)
        assert c.login("alice", PW)[0] == 200
        t_end = time.monotonic() + 30        # the station runs (its series grows)
        while len(c.get("/api/station/loom-a")[1].get("rows", ())) < 20:
            assert time.monotonic() < t_end, "the station did not run"
            time.sleep(0.3)
        # strict types: a string is not a number, a boolean is not a number
        st, r, _ = c.post(CMD, {"command": "setpoint", "t_set": "0.6"})
        assert st == 400 and r["code"] == 9 and "must be a number" in r["reason"], r
        st, r, _ = c.post(CMD, {"command": "shelve", "alarm": "end_of_life", "duration_s": True})
        assert st == 400 and r["code"] == 9, r
        st, r, _ = c.post(CMD, {"command": "start", "sample_id": "S-1", "t_set": [0.5]})
        assert st == 400 and r["code"] == 9, r
        # a 12 KB sample ID (the body is within the 16 KiB limit): refused, not echoed
        big = "S" * 12_000
        st, r, _ = c.post(CMD, {"command": "start", "sample_id": big, "t_set": 0.5})
        assert st == 400 and r["code"] == 9 and len(json.dumps(r)) < 300, r
        # a sample ID of 60 characters: the station's code 4, the value clipped in the reason
        st, r, _ = c.post(CMD, {"command": "start", "sample_id": "A" * 60, "t_set": 0.5})
        assert st == 400 and r["code"] == 4 and "A" * 41 not in r["reason"], r
        st, r, _ = c.post(CMD, {"command": "start", "sample_id": "S\x1b[2J", "t_set": 0.5})
        assert st == 400 and r["code"] == 4 and "\x1b" not in r["reason"], r
        # a newline in the command name cannot forge a log line
        forged = ("stop\n2026-11-26 08:00:00,000 INFO hookwatch.console: FORGED command stop on "
                  "loom-a by admin: accepted")
        st, r, _ = c.post(CMD, {"command": forged})
        assert st == 400 and r["code"] == 9 and "\n" not in r["reason"], r
        # deep JSON: an answer, not an HTTP 500 with a traceback
        for raw in (b'{"command": "stop", "x": ' + b"[" * 5000 + b"]" * 5000 + b"}", b"[" * 15_000,
                    b'{"command": "stop", "request_id": "' + b"r" * 3000 + b'"}'):
            st, r, _ = c.post(CMD, raw=raw)
            assert st == 400 and r["code"] == 9 and len(r["reason"]) < 200, (st, r)
        # a flood of refusals of one kind is not a flood of log lines
        for _ in range(60):
            assert c.post(CMD, {"command": "setpoint", "t_set": "0.6"})[0] == 400
        # a stop naming a test that is not the running one (one that ended) stops nothing (issue
        # 34): the station refuses it, 15 WRONG_TEST
        st, r, _ = c.post(CMD, {"command": "stop", "test_id": "20260101T000000.000Z-OLD"})
        assert st == 409 and r["code"] == 15 and "OLD" in r["reason"], r
        # a good command still works
        st, r, _ = c.post(CMD, {"command": "stop", "request_id": "r-1"})
        assert st == 200 and r["ok"], r
        wait_log(gw, "command stop on loom-a by alice: accepted")
        log = gw.log_all()
        assert "Traceback" not in log
        for line in log.splitlines():
            assert not line.lstrip().startswith("2026-11-26 08:00:00,000"), line
            assert "FORGED" not in line or "\\n" in line, line
            assert big[:200] not in line
        refused = [ln for ln in log.splitlines() if "console: command" in ln and "refused" in ln]
        # 61 refusals of the kind (command, code 9) in the first minute: one line (×1); the others
        # are counted into the line that ends the window
        assert 1 <= len(refused) <= 3, refused
        assert all(re.search(r"\(×\d+", ln) for ln in refused), refused
