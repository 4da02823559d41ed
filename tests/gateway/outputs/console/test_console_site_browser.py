"""The planner's site view in a real browser (Playwright driving Debian's chromium), with THREE
gateways on one real Mosquitto:

- box A: this test's process — a console with its stations a-1, a-2 (fed through the real
  hand-over) and a-1's real MQTT output, whose session carries the site view (as
  gateway/compose.py attaches it);
- boxes B and C: processes of real MQTT outputs (tests/kit/site_box.py), one session per station
  with its `offline` Last Will.

The due list and the fleet cards list all three boxes' stations once the whole site is switched
on; remote stations have no command buttons (and the console refuses a command to one); a remote
string is shown as text, never parsed as HTML; sorting and filtering work; the CSV has every
station; box C killed (SIGKILL) shows "silent since …". Screenshots: site-due.png,
site-fleet.png in the test's folder."""
from __future__ import annotations

import csv
import io
import json
import os
import signal
import sys
import threading
import time

from conftest import TESTS
from gateway.core import records as R
from gateway.outputs.console.site import MAX_TEXT
from gateway.outputs.mqtt import schema as mqtt_schema
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker, pub
from kit.browser import wait_js as _wait_js
from kit.console_helpers import CONSOLE_PW, INJECT, Client, start_console
from kit.northbound import LoopThread
from kit.proc import Proc
from kit.tools import wait_for

PREFIX, SITE = "hookwatch", "plant"
HTML = '<img src=x onerror="window.pwned=1">'
START = "2026-11-26T05:00:00.000Z"     # an hour before the console fixture's tests


def _box(tmp_path, port, name, stations, site=SITE):
    d = tmp_path / name
    d.mkdir()
    spec = {"prefix": PREFIX, "site": site, "stations": stations}
    p = Proc([sys.executable, os.path.join(TESTS, "kit", "site_box.py"),
              str(port), str(d), json.dumps(spec)], str(tmp_path / f"{name}.log"))
    p.readline_until("connected", timeout=60)
    return p


B = [{"id": "b-1", "area": "hall-2", "line": "l2",
      "state": {"state": "MONITORING", "test_id": "T-B1", "sample_id": "S-B1", "grade": "I",
                "test_started_utc": START, "headroom": 0.3, "end_p10": 1000.0, "end_p50": 1200.0,
                "end_p90": 1500.0, "p_end": 0.6, "due": True, "warn_reasons": ["prior"],
                "alarm": "unacknowledged"}},
     {"id": "b-2", "area": "hall-2", "line": "l2", "state": {"state": "IDLE", "sample_id": INJECT}}]
C = [{"id": "c-1", "area": "hall-3", "line": "l3",
      "state": {"state": "MONITORING", "test_id": "T-C1", "sample_id": HTML, "grade": "II",
                "test_started_utc": START, "headroom": 0.8, "end_p10": 5000.0, "end_p50": 6000.0,
                "end_p90": 7000.0, "p_end": 0.05}}]


def test_site_view_three_gateways_in_a_browser(tmp_path, browser):  # noqa: F811
    lt = LoopThread()
    procs: list[Proc] = []
    srv = out = None
    with Broker(tmp_path) as broker:
        try:
            procs.append(_box(tmp_path, broker.port, "box-b", B))
            procs.append(_box(tmp_path, broker.port, "box-c", C))
            # box A: the console (stations loom-a … loom-d of start_console's fixture are this box's)
            srv, url, outs, _dirs = start_console(tmp_path)
            a_base = mqtt_schema.base_topic(PREFIX, SITE, "hall-1", "line-1", "loom-a")
            out = MqttOutput(MqttSettings(station_id="loom-a", base_topic=a_base, port=broker.port,
                                          outbox_path=str(tmp_path / "a.sqlite"),
                                          reconnect_min_s=0.2, reconnect_max_s=1.0))
            assert srv.attach_site("loom-a", a_base, out.pump.add_site_feed)
            lt.call(out.start())
            # box A's own station on the broker is not shown twice
            lt.loop.call_soon_threadsafe(out.on_state, R.StationState(station="loom-a"))

            ctx = browser.new_context(viewport={"width": 1400, "height": 1100}, bypass_csp=True,
                                      accept_downloads=True)
            page = ctx.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url + "/#/due")
            _wait_js(page, "window.hw.due && window.hw.due.length === 4")       # this box only
            page.check("#f-site")
            _wait_js(page, "window.hw.due && window.hw.due.length === 7")
            due = page.evaluate("window.hw.due")
            assert sorted(due) == ["b-1", "b-2", "c-1", "loom-a", "loom-b", "loom-c", "loom-d"]
            assert due[:3] == ["loom-c", "b-1", "loom-b"]                   # soonest due first, across boxes
            remote = page.locator("#due tr[data-remote]").evaluate_all("e => e.map(x => x.dataset.station)")
            assert sorted(remote) == ["b-1", "b-2", "c-1"]
            assert page.locator("#due tr[data-remote] a").count() == 0       # no link to a station page here
            assert "other box · online" in page.locator('#due tr[data-station="b-1"] .box').inner_text()
            assert page.locator('#due tr[data-station="loom-a"] .box').inner_text() == "this box"
            # a remote string is text: shown literally, never an element
            c1 = page.locator('#due tr[data-station="c-1"]').inner_text()
            assert "<img" in c1 and page.locator("#due img").count() == 0
            assert page.evaluate("window.pwned === undefined")
            # sort by a column (click, again to reverse), filter by text and by area
            page.click('#due th[data-sort="station"]')
            _wait_js(page, "window.hw.due[0] === 'b-1'")
            assert page.evaluate("window.hw.due") == sorted(due)
            page.click('#due th[data-sort="station"]')
            _wait_js(page, "window.hw.due[0] === 'loom-d'")
            page.fill("#f-text", "hall-2")
            _wait_js(page, "window.hw.due.length < 7")
            assert sorted(page.evaluate("window.hw.due")) == ["b-1", "b-2", "loom-b", "loom-d"]
            page.fill("#f-text", "")
            page.select_option("#f-area", "hall-3")
            _wait_js(page, "JSON.stringify(window.hw.due) === '[\"c-1\"]'")
            assert page.get_attribute("#csv", "href") == "/api/due.csv?area=hall-3&site=1"
            page.select_option("#f-area", "")
            _wait_js(page, "window.hw.due.length === 7")
            # the CSV has every station of the site, its cells defused as today
            assert page.get_attribute("#csv", "href") == "/api/due.csv?site=1"
            with page.expect_download() as dl:
                page.click("#csv")
            with open(dl.value.path(), encoding="utf-8") as fh:
                rows = list(csv.reader(io.StringIO(fh.read())))
            head = rows[0]
            cells = {r[0]: dict(zip(head, r, strict=True)) for r in rows[1:]}
            assert sorted(cells) == sorted(due)
            assert cells["b-2"]["sample_id"] == "'" + INJECT and cells["b-2"]["remote"] == "true"
            assert cells["loom-a"]["remote"] == "false" and cells["b-1"]["end_utc_p50"] == "2026-11-26T05:20:00Z"
            assert len(cells["c-1"]["sample_id"]) <= MAX_TEXT + 20
            page.screenshot(path=str(tmp_path / "site-due.png"), full_page=True)

            # --- fleet cards: every box's stations; the remote ones read-only
            page.goto(url + "/#/")
            page.wait_for_selector('.card[data-station="c-1"]')        # the switch is remembered
            assert page.locator(".card").count() == 7
            assert page.locator(".card[data-remote] button").count() == 0
            assert page.locator('.card[data-station="b-1"] .alarm').inner_text() == "unacknowledged"
            assert page.locator('.card[data-station="loom-c"] button.ack').count() == 1   # this box: its button
            assert page.locator(".card img").count() == 0
            page.fill("#filter", "l3")
            _wait_js(page, "JSON.stringify(window.hw.fleet) === '[\"c-1\"]'")
            page.fill("#filter", "")
            # the console refuses a command to a station of another box (only this box's stations)
            cl = Client(url)
            assert cl.login("alice", CONSOLE_PW)[0] == 200
            st, body, _ = cl.post("/api/station/b-1/command", {"command": "ack"})
            assert st == 404, body

            # --- box C dies: its stations' Wills → "silent since …"
            procs[1].p.send_signal(signal.SIGKILL)
            procs[1].p.wait(10)
            _wait_js(page, "document.querySelector('.card[data-station=\"c-1\"] .liveness')"
                     ".textContent.includes('silent since')")
            assert "online" in page.locator('.card[data-station="b-1"] .liveness').inner_text()
            page.select_option("#sort", "silent")
            _wait_js(page, "window.hw.fleet[0] === 'c-1'")
            page.screenshot(path=str(tmp_path / "site-fleet.png"), full_page=True)
            page.goto(url + "/#/due")
            box = "document.querySelector('#due tr[data-station=\"c-1\"] .box')"
            _wait_js(page, f"{box} && {box}.textContent.includes('silent since')")
            assert not errors, errors
            assert srv.site is not None and srv.site.counters["refused"] == 0
            # a malformed or oversized state from a box is refused (counted), never shown
            evil = "hookwatch/plant/hall-9/l9/evil/state"
            pub(broker.port, evil, '{"station": "evil", "test_state": 5}', retain=True)
            pub(broker.port, evil.replace("evil", "huge"), '{"station": "huge", "test_state": "idle", '
                '"sample_id": "' + "x" * 100_000 + '"}', retain=True)
            wait_for(lambda: srv.site.counters["refused"] >= 2, 30, what="the bad states refused")
            page.evaluate("window.hw.due = null")                     # the page's next refresh
            _wait_js(page, "window.hw.due && window.hw.due.length > 0")
            assert "evil" not in page.evaluate("window.hw.due") and len(page.evaluate("window.hw.due")) == 7
            ctx.close()
        finally:
            for p in procs:
                p.stop()
            if out is not None:
                lt.call(out.stop())
            # the LoopThread's close runs a loop: not on this thread, where Playwright's runs
            closer = threading.Thread(target=lt.close)
            closer.start()
            closer.join(30)
            if srv is not None:
                srv.stop()


def test_hookwatch_run_feeds_its_console_the_site_from_its_own_session(tmp_path):
    """`hookwatch run` as deployed (a station file: the console in the station's process): the
    console's site view rides on the station's MQTT session (gateway/compose.py) and lists the
    station of another box; the station's own state is not shown twice."""
    from kit.console_helpers import Client as HttpClient
    from kit.e2e import run_gateway, station_yaml, wait_log

    with Broker(tmp_path) as broker:
        procs: list[Proc] = []
        try:
            procs.append(_box(tmp_path, broker.port, "box-b", [{**B[0], "area": "test", "line": "l2"}],
                              site="lab"))
            dev = tmp_path / "absent"            # no instruments: a state, not a crash
            st = station_yaml(tmp_path, {"meter": str(dev / "meter"), "stm32": str(dev / "stm32")},
                              name="a", mqtt={"enabled": True, "port": broker.port},
                              extra={"console": {"enabled": True, "listen": ["127.0.0.1:0"],
                                                 "users_file": str(tmp_path / "users.json")}})
            gw = run_gateway(tmp_path, st, name="gw-a")
            procs.append(gw)
            url = gw.readline_until("console:", timeout=60).strip().rstrip("/")
            wait_log(gw, "the site view reads hookwatch/lab/+/+/+/state, hookwatch/lab/+/+/+/status, "
                         "hookwatch/lab/box/+/config (on the MQTT session of a)", 60)
            c = HttpClient(url)

            def site_cards():
                st_, body, _ = c.get("/api/fleet?site=1")
                assert st_ == 200, body
                return body

            body = site_cards()
            t_end = time.monotonic() + 60
            while not any(s["station"] == "b-1" for s in body["stations"]) and time.monotonic() < t_end:
                time.sleep(0.5)
                body = site_cards()
            cards = {s["station"]: s for s in body["stations"]}
            assert sorted(cards) == ["a", "b-1"], sorted(cards)
            assert cards["a"]["remote"] is False and cards["b-1"]["remote"] is True
            assert cards["b-1"]["online"] is True and cards["b-1"]["line"] == "l2"
            assert body["site"]["fed"] is True and body["site"]["refused"] == 0
            st_, body, _ = c.get("/api/fleet")                          # this box only
            assert [s["station"] for s in body["stations"]] == ["a"]
        finally:
            for p in procs:
                p.stop()


def test_a_supervised_fleet_feeds_its_console_the_site_through_one_worker(tmp_path):
    """`hookwatch run FLEET_DIR`: the console lives in the supervisor, the MQTT sessions in the
    workers; one worker's session carries the site view to it (IPC frame SITE)."""
    import yaml

    from kit.console_helpers import Client as HttpClient
    from kit.e2e import fleet_dir, run_gateway, wait_log

    with Broker(tmp_path) as broker:
        procs: list[Proc] = []
        try:
            procs.append(_box(tmp_path, broker.port, "box-b", [{**B[0], "area": "hall", "line": "l2"}],
                              site="lab"))
            fleet = fleet_dir(tmp_path, mqtt={"enabled": True, "port": broker.port},
                              console={"enabled": True, "listen": ["127.0.0.1:0"],
                                       "users_file": str(tmp_path / "users.json")})
            dev = tmp_path / "absent"            # no instruments: a state, not a crash
            for sid in ("a1", "a2"):
                (fleet / "stations" / f"{sid}.yaml").write_text(yaml.safe_dump({
                    "station": {"id": sid}, "meter": {"port": str(dev / f"{sid}-meter")},
                    "stm32": {"port": str(dev / f"{sid}-stm32")}}))
            gw = run_gateway(tmp_path, str(fleet), name="gw-a")
            procs.append(gw)
            url = gw.readline_until("console:", timeout=60).strip().rstrip("/")
            wait_log(gw, "the site view reads hookwatch/lab/+/+/+/state", 60)
            c = HttpClient(url)
            t_end = time.monotonic() + 90
            while True:
                st_, body, _ = c.get("/api/fleet?site=1")
                assert st_ == 200, body
                cards = {s["station"]: s for s in body["stations"]}
                if "b-1" in cards or time.monotonic() > t_end:
                    break
                time.sleep(0.5)
            assert sorted(cards) == ["a1", "a2", "b-1"], sorted(cards)
            assert cards["b-1"]["remote"] is True and cards["b-1"]["online"] is True
            assert not cards["a1"]["remote"] and not cards["a2"]["remote"]
            assert body["site"]["fed"] is True and body["site"]["refused"] == 0
        finally:
            for p in procs:
                p.stop()
