"""The console's site view (gateway/outputs/console/site.py): what a station of another box of the site
says on the broker is kept bounded, checked, clipped and shown read-only with its liveness."""
from __future__ import annotations

import json
import logging
import shutil

from gateway.outputs.console import site as S
from gateway.outputs.console.feed import due_list
from gateway.outputs.console.site import SiteView

BASE = "hookwatch/plant/hall-2/l2"


def state(sid: str, **kw) -> bytes:
    d = {"schema": 3, "seq": 7, "time": "2026-11-27T10:00:00.000Z", "station": sid,
         "test_state": "monitoring", "test_id": "T-1", "sample_id": "S-1", "grade": "I",
         "headroom": 0.4, "end_p10": 100.0, "end_p50": 200.0, "end_p90": 300.0, "p_end": 0.2,
         "due": True, "warn_reasons": ["prior"], "test_started_utc": "2026-11-27T09:00:00.000Z",
         "alarm": "normal", "meter_ok": True, "stm32_ok": True}
    d.update(kw)
    return json.dumps(d).encode()


def status(sid: str, st: str) -> bytes:
    return json.dumps({"schema": 3, "session": 3, "time": "2026-11-27T09:59:00.000Z", "station": sid,
                       "status": st, "software": "x", "map_version": 4}).encode()


def test_filters_are_the_sites_state_and_status():
    assert S.filters("hookwatch/plant/hall-1/l1/a-1") == ("hookwatch/plant/+/+/+/state",
                                                          "hookwatch/plant/+/+/+/status",
                                                          "hookwatch/plant/box/+/config")


def test_box_reports_are_bounded_checked_and_a_will_keeps_the_last_report():
    """The Boxes page's reports (gateway/outputs/console/boxes.py): a malformed or oversized report is
    refused and counted, a report on another box's topic too; the Will updates `online` only."""
    from gateway.outputs.console.boxes import MAX_BOXES
    view = SiteView()
    t = "hookwatch/plant/box/b1/config"
    rep = {"schema": 1, "box": "b1", "site": "plant", "online": True, "version": "a" * 40,
           "deferred": ["st-1"], "pending": ["st-1"], "drift": False, "drift_files": [],
           "last_rollback": {"from": "b" * 40, "to": "a" * 40, "why": "x" * 390, "time": "2026"},
           "stations": {"st-1": {"version": "c" * 40, "pending": "a" * 40, "in_test": True}}}
    assert view.receive(t, json.dumps(rep).encode())
    assert not view.receive(t, json.dumps({**rep, "box": "b2"}).encode())           # not its topic
    assert not view.receive(t, json.dumps({**rep, "online": "yes"}).encode())
    assert not view.receive(t, json.dumps({**rep, "deferred": list(range(5))}).encode())
    assert not view.receive(t, b"{" + b" " * 70_000 + b"}")
    assert view.boxes.counters["refused"] == 4
    assert view.receive(t, json.dumps({"schema": 1, "box": "b1", "site": "plant", "online": False}).encode())
    (row,) = view.boxes.rows()
    assert row["online"] is False and row["version"] == "a" * 40 and row["deferred"] == ["st-1"]
    assert len(row["last_rollback"]["why"]) == 300 and row["stations"]["st-1"]["in_test"] is True
    for i in range(MAX_BOXES + 5):
        view.receive(f"hookwatch/plant/box/x{i}/config", json.dumps({"box": f"x{i}"}).encode())
    assert len(view.boxes.rows()) == MAX_BOXES and view.boxes.counters["over_bound"] >= 5
    assert view.receive(t, b"") and "b1" not in [r["box"] for r in view.boxes.rows()]


def test_a_remote_station_is_shown_read_only_with_its_place_and_liveness():
    v = SiteView({"a-1"})
    assert v.receive(f"{BASE}/b-1/state", state("b-1"), now=1000.0)
    assert v.receive(f"{BASE}/b-1/status", status("b-1", "online"), now=1000.0)
    # this box's own stations are never shown twice
    assert not v.receive("hookwatch/plant/hall-1/l1/a-1/state", state("a-1"), now=1000.0)
    (c,) = v.cards(now=1010.0)
    assert c["station"] == "b-1" and c["remote"] is True and c["online"] is True
    assert (c["line"], c["area"], c["state"], c["silent_since"]) == ("l2", "hall-2", "monitoring", None)
    assert c["end_p50"] == 200.0 and c["due"] is True
    row = due_list([c])[0]
    assert row["remote"] is True and row["end_utc_p50"] == "2026-11-27T09:03:20Z"
    # its life prior and the lives it came from (§7a v3), for the planner's due list
    v.receive(f"{BASE}/b-1/state", state("b-1", prior_mean=3156.1, prior_sd=182.3, prior_source="history:4",
                                         prior_n=4, prior_n_censored=3, prior_n_early=1), now=1000.0)
    row = due_list(v.cards(now=1010.0))[0]
    assert (row["prior_source"], row["prior_n"], row["prior_n_censored"], row["prior_n_early"]) == (
        "history:4", 4, 3, 1)
    # the Will: silent since the last thing it said (its last state's time)
    assert v.receive(f"{BASE}/b-1/status", status("b-1", "offline"), now=1020.0)
    (c,) = v.cards(now=1021.0)
    assert c["online"] is False and c["silent_since"] == "2026-11-27T10:00:00.000Z"
    # back online with a new state
    v.receive(f"{BASE}/b-1/status", status("b-1", "online"), now=1030.0)
    v.receive(f"{BASE}/b-1/state", state("b-1", time="2026-11-27T10:00:30.000Z"), now=1030.0)
    assert v.cards(now=1031.0)[0]["online"] is True
    # a state older than STALE_S without a Will (a box cut off the network): silent too
    (c,) = v.cards(now=1030.0 + S.STALE_S + 1)
    assert c["online"] is False and c["silent_since"] == "2026-11-27T10:00:30.000Z"
    # a cleared (retired) station goes
    assert v.receive(f"{BASE}/b-1/state", b"", now=1040.0) and v.cards() == []


def test_no_projection_outside_a_running_test():
    v = SiteView()
    v.receive(f"{BASE}/b-2/state", state("b-2", test_state="completed"), now=0.0)
    c = v.cards(now=1.0)[0]
    assert c["end_p50"] is None and c["due"] is False


def test_malformed_remote_state_refused_with_one_counted_line(caplog):
    v = SiteView()
    bad = [
        b"{not json", b"[1, 2]", state("b-1", station="other"),            # station not its topic's
        state("b-1", headroom="0.4"), state("b-1", due="yes"), state("b-1", p_end=1e999),
        state("b-1", sample_id=["x"]), state("b-1", warn_reasons=["<script>"]),
        state("b-1", grade="x" * 300),                                       # a string over the bound
        state("b-1", prior_n_early=-1), state("b-1", prior_n=2.5), state("b-1", prior_n_censored=True),
        b'{"a":' * 10 + b"1" + b"}" * 10,                                    # too deep
        b" " * (S.MAX_MESSAGE_BYTES + 1),                                    # too many bytes
        json.dumps({"station": "b-1"}).encode(),                             # no test_state
        status("b-1", "maybe"),
    ]
    with caplog.at_level(logging.WARNING, logger="hookwatch.console"):
        for i, p in enumerate(bad):
            topic = f"{BASE}/b-1/status" if i == len(bad) - 1 else f"{BASE}/b-1/state"
            assert not v.receive(topic, p, now=0.0), p[:60]
    assert v.counters["refused"] == len(bad) and v.stations() == 0
    lines = [r for r in caplog.records if "refused" in r.getMessage()]
    assert 1 <= len(lines) <= 2          # one line per kind (state, status) in the window
    v.close()


def test_strings_from_other_boxes_are_clipped_printable_text():
    v = SiteView()
    evil = "<img src=x onerror=alert(1)>\u202e\x07" + "y" * 100
    assert v.receive(f"{BASE}/b-1/state", state("b-1", sample_id=evil[:200]), now=0.0)
    s = v.cards(now=1.0)[0]["sample_id"]
    assert len(s) <= S.MAX_TEXT + 20 and all(0x20 <= ord(ch) <= 0x7E for ch in s)
    assert "\x07" not in s and "\u202e" not in s


def test_stations_of_the_site_are_bounded():
    v = SiteView()
    for i in range(S.MAX_SITE_STATIONS + 5):
        v.receive(f"{BASE}/s{i}/state", state(f"s{i}"), now=0.0)
    assert v.stations() == S.MAX_SITE_STATIONS and v.counters["over_bound"] == 5
    # a station already kept still gets its news
    assert v.receive(f"{BASE}/s0/state", state("s0", grade="II"), now=1.0)
    v.close()


def test_the_pump_routes_site_messages_lives_and_commands_apart(tmp_path):
    """One MQTT session carries the station's commands, the site's lives and the console's site
    view: each message goes to its own consumer."""
    from types import SimpleNamespace

    from gateway.outputs.mqtt.pump import MqttPump
    from gateway.outputs.mqtt.settings import MqttSettings

    got: dict[str, list] = {"cmd": [], "lives": [], "site": []}
    base = "hookwatch/plant/hall-1/l1/a-1"
    pump = MqttPump(MqttSettings(station_id="a-1", base_topic=base, outbox_path=str(tmp_path / "o.sqlite")),
                    on_command=lambda n, p, r, s: got["cmd"].append((n, s)),
                    on_lives=lambda t, p: got["lives"].append(t))
    pump.add_site_feed(S.filters(base), lambda t, p: got["site"].append(t))
    for topic in (f"{base}/cmd/ack", f"{BASE}/b-1/lives", f"{BASE}/b-1/state", f"{BASE}/b-1/status"):
        pump.inbound.on_message(None, None, SimpleNamespace(topic=topic, payload=b"{}", properties=None))
    assert got == {"cmd": [("ack", "mqtt")], "lives": [f"{BASE}/b-1/lives"],
                   "site": [f"{BASE}/b-1/state", f"{BASE}/b-1/status"]}
    pump.outbox.close()


def test_the_console_attaches_the_site_view_to_one_session(tmp_path):
    from gateway.outputs.console.app import ConsoleServer
    from gateway.outputs.console.settings import ConsoleSettings

    feeds: list[tuple] = []
    srv = ConsoleServer(ConsoleSettings(users_file=str(tmp_path / "u.json")),
                        {"a-1": str(tmp_path / "a-1"), "a-2": str(tmp_path / "a-2")})
    add = lambda f, cb: feeds.append((f, cb))                            # noqa: E731
    assert srv.attach_site("a-1", "hookwatch/plant/hall-1/l1/a-1", add)
    assert not srv.attach_site("a-2", "hookwatch/plant/hall-1/l1/a-2", add)   # one session only
    assert srv.attach_site("a-1", "hookwatch/plant/hall-1/l1/a-1", add)       # a-1 rebuilt: again
    assert [f for f, _ in feeds] == [S.filters("hookwatch/plant/hall-1/l1/a-1")] * 2
    assert srv.site is not None and srv.site.local == {"a-1", "a-2"}
    off = ConsoleServer(ConsoleSettings(users_file=str(tmp_path / "u.json"), site_view=False),
                        {"a-1": str(tmp_path / "a-1")})
    assert off.site is None and not off.attach_site("a-1", "hookwatch/plant/hall-1/l1/a-1", add)
    for c in (srv, off):
        shutil.rmtree(c._cache, ignore_errors=True)
