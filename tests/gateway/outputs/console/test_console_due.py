"""The planner's due list, the alarm journal and the hooks of a station over real HTTP, against a
real console whose feeds get station states and events through the real hand-over
(``ConsoleOutput``) — the states are constructed here because the station does not fill the
forecast fields yet (issue 20; the wave-2 contract names them).

The due list: every station, soonest due first (past its end of life, then by the median
projected end as wall-clock time = test_started_utc + end_p50), filters by line and area, and as
CSV whose cells are defused against formula injection. The journal: every ISA-18.2 transition
with who and when, from the recorded tests' events.jsonl and live, bounded. The hooks: the
station's hooks.jsonl, bounded, damaged lines skipped with one log line."""
from __future__ import annotations

import csv
import io
import json
import logging
import os

from gateway.core.records import Event, EventType
from gateway.offline.logio import tail_jsonl
from gateway.outputs.console.common import FILE_READS_PER_MIN
from gateway.outputs.console.feed import MAX_JOURNAL
from gateway.plumbing.safeout import csv_cell
from kit.console_helpers import INJECT, Client, start_console


def test_due_list_order_wall_times_filters_and_no_stale_projection(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    srv, url, _outs, _dirs = start_console(tmp_path)
    try:
        c = Client(url)
        st, data, _ = c.get("/api/due")
        assert st == 200
        rows = data["stations"]
        # c is past its end of life (due now), then b (median end 06:30), a (07:30), d (idle)
        assert [r["station"] for r in rows] == ["loom-c", "loom-b", "loom-a", "loom-d"]
        a = next(r for r in rows if r["station"] == "loom-a")
        assert (a["end_utc_p10"], a["end_utc_p50"], a["end_utc_p90"]) == (
            "2026-11-26T07:00:00Z", "2026-11-26T07:30:00Z", "2026-11-26T08:00:00Z")
        assert a["line"] == "line-1" and a["area"] == "hall-1" and a["sample_id"] == INJECT
        assert a["due"] is False and a["p_end"] == 0.12
        # the life prior and how many lives it came from (§7a v3: wear-out, censored, early)
        assert (a["prior_mean"], a["prior_sd"], a["prior_source"].split(" ")[0]) == (5400.0, 600.0, "history:3")
        assert (a["prior_n"], a["prior_n_censored"], a["prior_n_early"]) == (3, 2, 1)
        b = rows[1]
        assert b["prior_source"] is None and b["prior_n_early"] is None
        assert b["due"] is True and b["reasons"] == ["headroom", "trend"]
        cc = rows[0]
        # no projection after the end of life: the stale end_p*, p_end are not published
        assert cc["due"] is True and cc["t_life_utc"] == "2026-11-26T06:16:40Z"
        assert cc["end_utc_p50"] is None and cc["end_p50"] is None and cc["p_end"] is None
        assert data["lines"] == ["line-1", "line-2"] and data["areas"] == ["hall-1", "hall-2"]
        # … nor on the fleet card (the old "projected crossing" after the end of life)
        cards = {s["station"]: s for s in c.get("/api/fleet")[1]["stations"]}
        assert cards["loom-c"]["t_cross"] is None and cards["loom-c"]["past_threshold"] is True
        assert cards["loom-a"]["t_cross"] == 5400.0 and cards["loom-a"]["past_threshold"] is False
        assert cards["loom-d"]["end_p50"] is None and cards["loom-d"]["due"] is False
        # filters by line and area (together, too)
        assert [r["station"] for r in c.get("/api/due?line=line-1")[1]["stations"]] == ["loom-b", "loom-a"]
        assert [r["station"] for r in c.get("/api/due?area=hall-1")[1]["stations"]] == ["loom-c", "loom-a"]
        assert [r["station"] for r in c.get("/api/due?line=line-2&area=hall-2")[1]["stations"]] == ["loom-d"]
        assert c.get("/api/due?line=nowhere")[1]["stations"] == []
        # a malformed filter is a client error without a traceback
        st, body, _ = c.get("/api/due?line=" + "x" * 65)
        assert st == 400 and "line" in body["reason"]
        st, body, _ = c.get("/api/due.csv?area=%01")
        assert st == 400
        assert not [r for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR]
    finally:
        srv.stop()


def test_due_csv_cells_defused_against_formulas(tmp_path):
    srv, url, _outs, _dirs = start_console(tmp_path)
    try:
        c = Client(url)
        req = c.opener.open(url + "/api/due.csv?line=line-1", timeout=30)
        assert req.status == 200
        assert req.headers["Content-Type"].startswith("text/csv")
        assert req.headers["Content-Disposition"].startswith('attachment; filename="due-')
        text = req.read().decode("utf-8")
        rows = list(csv.reader(io.StringIO(text)))
        head, body = rows[0], rows[1:]
        assert head[:3] == ["station", "line", "area"] and "end_utc_p50" in head and "reasons" in head
        assert [r[0] for r in body] == ["loom-b", "loom-a"]            # the filter and the order
        cell = {r[0]: dict(zip(head, r, strict=True)) for r in body}
        # every cell that starts with = + - @ is prefixed with ' (no spreadsheet runs it)
        assert cell["loom-a"]["sample_id"] == "'" + INJECT
        assert cell["loom-a"]["grade"] == "'+G1" and cell["loom-b"]["grade"] == "'@G2"
        assert cell["loom-b"]["reasons"] == "headroom trend" and cell["loom-b"]["due"] == "true"
        assert cell["loom-a"]["end_utc_p50"] == "2026-11-26T07:30:00Z"
        for r in body:
            for v in r:
                assert not v.startswith(("=", "+", "-", "@")), v
        # past its end of life: the sample "-S-C" is defused; the negative headroom is a plain
        # number, which no spreadsheet reads as a formula, and stays one (gateway.plumbing.safeout)
        full = list(csv.reader(io.StringIO(c.opener.open(url + "/api/due.csv", timeout=30).read().decode())))
        rc = dict(zip(full[0], full[1], strict=True))
        assert rc["station"] == "loom-c" and rc["sample_id"] == "'-S-C" and rc["headroom"] == "-0.1"
        assert csv_cell("\tcmd") == "'\tcmd" and csv_cell("a=b") == "a=b" and csv_cell(None) == ""
        # reads from disk are rate-bounded per address: 429 + Retry-After beyond the budget
        statuses = []
        for _ in range(FILE_READS_PER_MIN + 2):
            st, _body, headers = c.get("/api/due.csv")
            statuses.append(st)
        assert statuses[-1] == 429 and int(headers["Retry-After"]) >= 1
        # the door's Host rule holds for the new endpoints
        import http.client
        port = int(url.rsplit(":", 1)[1])
        for path in ("/api/due", "/api/due.csv", "/api/station/loom-a/journal", "/api/station/loom-a/hooks"):
            h = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
            h.request("GET", path, headers={"Host": "evil.example"})
            assert h.getresponse().status == 421, path
            h.close()
    finally:
        srv.stop()


def _alarm_event(t: float, to: str, action: str, by: str, frm: str = "normal",
                 ev_type=EventType.ALARM_SHELVED) -> Event:
    return Event(ev_type, "loom-a", t, "20261126T060000Z-A", None, {"source": by, "transitions": [
        {"alarm": "end_of_life", "hook": "20261126T060000Z-A", "from": frm, "to": to,
         "action": action, "time": t, "by": by, "priority": 1}]})


def test_alarm_journal_from_disk_and_live_bounded(tmp_path):
    users = str(tmp_path / "users.json")
    # a recorded test's events.jsonl (as the recorder writes it) with two transitions and junk
    tdir = tmp_path / "records" / "loom-a" / "20261126T050000Z-A"
    tdir.mkdir(parents=True)
    lines = [json.dumps({"utc": "x", **_alarm_event(100.0, "unacknowledged", "activate", None,
                                                    ev_type=EventType.END_OF_LIFE).as_dict()}),
             "{not json", json.dumps([1, 2]),
             json.dumps({"utc": "x", **_alarm_event(160.0, "acknowledged", "acknowledge", "mqtt",
                                                    "unacknowledged", EventType.ALARM_ACK).as_dict()}),
             json.dumps({"type": "test_started", "time": 50.0})]
    (tdir / "events.jsonl").write_text("\n".join(lines) + "\n")
    srv, url, outs, _dirs = start_console(tmp_path)
    try:
        out = outs["loom-a"]
        # live: the same acknowledge again (seen live and on disk: once) and a shelving
        out.on_event(_alarm_event(160.0, "acknowledged", "acknowledge", "mqtt", "unacknowledged",
                                  EventType.ALARM_ACK))
        out.on_event(_alarm_event(200.0, "shelved", "shelve", "console:alice", "acknowledged"))
        out.on_event(Event(EventType.TEST_STARTED, "loom-a", 210.0, "t2", 0, {}))  # no transition
        c = Client(url)
        st, data, _ = c.get("/api/station/loom-a/journal")
        assert st == 200
        j = data["journal"]
        assert [(e["time"], e["to"], e["by"]) for e in j] == [
            (100.0, "unacknowledged", None), (160.0, "acknowledged", "mqtt"),
            (200.0, "shelved", "console:alice")]
        assert j[2]["action"] == "shelve" and j[2]["alarm"] == "end_of_life" and j[2]["event"] == "alarm_shelved"
        # a new test does not clear the journal (the event list is per test, the journal is not)
        out.on_event(_alarm_event(300.0, "acknowledged", "unshelve", "plc:1", "shelved",
                                  EventType.ALARM_UNSHELVED))
        j = c.get("/api/station/loom-a/journal")[1]["journal"]
        assert len(j) == 4 and j[-1]["by"] == "plc:1"
        # bounded: the newest MAX_JOURNAL transitions are kept
        for i in range(MAX_JOURNAL + 50):
            out.on_event(_alarm_event(1000.0 + i, "shelved", "shelve", f"u{i}", "acknowledged"))
        j = c.get("/api/station/loom-a/journal")[1]["journal"]
        assert len(j) == MAX_JOURNAL and j[-1]["by"] == f"u{MAX_JOURNAL + 49}"
        assert c.get("/api/station/nope/journal")[0] == 404
    finally:
        srv.stop()
    assert os.path.exists(users)


def test_hooks_of_a_station_bounded_damaged_lines_skipped(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    srv, url, _outs, dirs = start_console(tmp_path)
    try:
        c = Client(url)
        assert c.get("/api/station/loom-a/hooks")[1]["hooks"] == []        # no file yet
        rec = {"station": "loom-a", "grade": "G1", "by": "console:alice", "test_id": "T1"}
        with open(os.path.join(dirs["loom-a"], "hooks.jsonl"), "w") as f:
            f.write(json.dumps({**rec, "old_sample_id": "S-1", "new_sample_id": "S-2",
                                "utc": "2026-11-20T06:00:00.000Z", "life_s": 3600.5}) + "\n")
            f.write('{"station": "loom-a", "old_sa\n')                     # torn by a crash
            f.write("x" * 5000 + "\n")                                      # over 4 KiB
            f.write(json.dumps({**rec, "old_sample_id": "S-2", "new_sample_id": "S-3",
                                "utc": "2026-11-22T06:00:00.000Z", "life_s": None,
                                "test_id": None}) + "\n")
        st, data, _ = c.get("/api/station/loom-a/hooks")
        assert st == 200
        h = data["hooks"]
        assert [(x["old_sample_id"], x["new_sample_id"], x["life_s"]) for x in h] == [
            ("S-2", "S-3", None), ("S-1", "S-2", 3600.5)]                   # newest first
        warn = [r.getMessage() for r in caplog.records if "damaged" in r.getMessage()]
        assert len(warn) == 1 and "2 damaged line(s) skipped" in warn[0]
        assert not [r for r in caplog.records if r.exc_info]
        assert c.get("/api/station/nope/hooks")[0] == 404
    finally:
        srv.stop()


def test_tail_reads_only_the_last_lines(tmp_path):
    p = tmp_path / "big.jsonl"
    with open(p, "w") as f:
        for i in range(25_000):
            f.write(json.dumps({"i": i}) + "\n")
    rows, bad = tail_jsonl(str(p), max_lines=10_000, max_line_bytes=64)
    assert bad == 0 and len(rows) == 10_000 and rows[0]["i"] == 15_000 and rows[-1]["i"] == 24_999
    assert tail_jsonl(str(tmp_path / "missing.jsonl")) == ([], 0)
