"""The planner's pages in a real browser (Playwright driving Debian's chromium).

1. Against a console fed through the real hand-over with constructed station states (the
   station does not publish the forecast fields yet): the due list's order, its line/area filters,
   the due rows highlighted, the CSV link downloaded by the browser with the filter and its
   cells defused; the fleet cards' wear warning and a hook past its threshold drawn as past it;
   no projection after the end of life; the hook-replaced dialog sends the new hook's sample id
   and grade.
2. Against `hookwatch sim` + `hookwatch run` (a real station): the alarm journal and its actions
   (out of service / in service, shelve / unshelve after the end of life) reach the station — its
   state and its own events.jsonl say so, with the user — and the hook-replaced dialog's command
   goes through the one intake to the station.

Screenshots in the test's tmp folder (due.png, fleet-cards.png, journal.png)."""
from __future__ import annotations

import csv
import glob
import io
import json
import time

import pytest

from gateway.core.records import CommandKind
from gateway.station.command_desk import COMMAND_KEYS
from kit.browser import wait_js
from kit.console_helpers import CONSOLE_PW, HOSTILE_IDS, INJECT, console_fleet, hostile_states, start_console

PW = "correct horse battery"


def _login(page, user, pw):
    page.fill("#login-user", user)
    page.fill("#login-pw", pw)
    page.click("#login button")
    page.wait_for_selector("#logout:not(.hidden)")


def _click_command(page, button: str, name: str) -> str:
    """Click a command button and wait for the console's answer; it must be accepted."""
    page.evaluate("document.querySelector('#msg').textContent = ''")
    page.click(button)
    page.wait_for_function("document.querySelector('#msg').textContent !== ''")
    msg = page.locator("#msg").inner_text()
    assert msg == f"{name}: accepted", msg
    return msg


def _commands(page) -> list[dict]:
    """The bodies of the command POSTs the page sends (appended as they go)."""
    sent: list[dict] = []
    page.on("request", lambda r: sent.append(json.loads(r.post_data or "{}"))
            if r.method == "POST" and r.url.endswith("/command") else None)
    return sent


def test_due_list_cards_and_replace_dialog_in_a_browser(tmp_path, browser):
    srv, url, outs, _dirs = start_console(tmp_path)
    try:
        ctx = browser.new_context(viewport={"width": 1300, "height": 1000}, bypass_csp=True,
                                  accept_downloads=True)
        page = ctx.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        # --- the due list: every station, soonest due first, the due ones highlighted
        page.goto(url + "/#/due")
        wait_js(page, "window.hw.due && window.hw.due.length === 4")
        assert page.evaluate("window.hw.due") == ["loom-c", "loom-b", "loom-a", "loom-d"]
        assert page.locator("#due tbody tr").evaluate_all("els => els.map(e => e.dataset.station)") == \
            ["loom-c", "loom-b", "loom-a", "loom-d"]
        assert page.locator("#due tr.due").evaluate_all("els => els.map(e => e.dataset.station)") == \
            ["loom-c", "loom-b"]
        bg = page.locator('#due tr[data-station="loom-b"] td').first.evaluate(
            "e => getComputedStyle(e).backgroundColor")
        plain = page.locator('#due tr[data-station="loom-a"] td').first.evaluate(
            "e => getComputedStyle(e).backgroundColor")
        assert bg != plain                                              # drawn highlighted
        assert "past its end of life" in page.locator('#due tr[data-station="loom-c"] .when').inner_text()
        when_a = page.locator('#due tr[data-station="loom-a"] .when').inner_text()
        assert "–" in when_a and when_a.count(":") >= 3                 # p10 – p90 (p50) as clock times
        assert "headroom, trend" in page.locator('#due tr[data-station="loom-b"]').inner_text()
        # the life prior of each test: from how many lives of each kind (METHOD.md §7a v3)
        assert page.locator('#due tr[data-station="loom-a"] td.prior').inner_text() == (
            "5400 ± 600 s · history: 3 wear-out failures, 2 censored, 1 early failure")
        assert page.locator('#due tr[data-station="loom-b"] td.prior').inner_text() == "–"
        page.screenshot(path=str(tmp_path / "due.png"), full_page=True)
        # --- filters by line, then area
        page.select_option("#f-line", "line-1")
        wait_js(page, "JSON.stringify(window.hw.due) === '[\"loom-b\",\"loom-a\"]'")
        assert page.get_attribute("#csv", "href") == "/api/due.csv?line=line-1"
        with page.expect_download() as dl:
            page.click("#csv")
        with open(dl.value.path(), encoding="utf-8") as fh:
            rows = list(csv.reader(io.StringIO(fh.read())))
        assert [r[0] for r in rows[1:]] == ["loom-b", "loom-a"]
        head = rows[0]
        a = dict(zip(head, rows[2], strict=True))
        assert a["sample_id"] == "'" + INJECT and a["grade"] == "'+G1"
        assert (a["prior_n"], a["prior_n_censored"], a["prior_n_early"]) == ("3", "2", "1")
        page.select_option("#f-area", "hall-2")
        wait_js(page, "JSON.stringify(window.hw.due) === '[\"loom-b\"]'")
        assert page.get_attribute("#csv", "href") == "/api/due.csv?line=line-1&area=hall-2"
        page.select_option("#f-line", "")
        wait_js(page, "JSON.stringify(window.hw.due) === '[\"loom-b\",\"loom-d\"]'")

        # --- fleet cards: the wear warning; a hook past its threshold drawn as past it
        page.goto(url + "/#/")
        page.wait_for_selector('.card[data-station="loom-d"]')
        assert "wear warning: headroom, trend" in page.locator('.card[data-station="loom-b"] .wear-cell').inner_text()
        assert page.locator('.card[data-station="loom-c"] .bar.past').count() == 1
        assert "past threshold" in page.locator('.card[data-station="loom-c"] .bar.past').inner_text()
        assert page.locator('.card[data-station="loom-a"] .bar.past').count() == 0
        assert page.locator('.card[data-station="loom-d"] .wear-cell').inner_text() == "none"
        page.screenshot(path=str(tmp_path / "fleet-cards.png"), full_page=True)

        # --- station pages: a projection while running; none after the end of life
        page.goto(url + "/#/station/loom-a")
        wait_js(page, "document.querySelector('#projection') && "
                       "document.querySelector('#projection').textContent.includes('projected end')")
        assert "P_end 0.12" in page.locator("#projection").inner_text()
        # where the life prior came from (issue 29): the site's lives of other stations, and how
        # many lives of each kind (§7a v3)
        assert page.locator("#prior").inner_text() == (
            "5400 ± 600 s from history:3 (the site: 6 tests from 2 stations (0 of this station; b 4, c 2)) "
            "(3 wear-out failures, 2 censored, 1 early failure)")
        page.goto(url + "/#/station/loom-c")
        wait_js(page, "document.querySelector('#state') && "
                       "document.querySelector('#state').dataset.state === 'end_of_life'")
        assert page.locator("#state").inner_text() == "end of life found at 16 min 40 s"
        assert page.locator("#projection").inner_text() == "–"
        assert page.locator("#prior").inner_text() == "none"
        assert "projected crossing" not in page.locator("#headroom").inner_text()
        assert page.locator("#headroom .bar.past").count() == 1

        # --- the hook-replaced dialog sends the new hook's sample id and grade (no station runs
        # here: the console's refusal is shown; the real station is the next test's)
        _login(page, "alice", CONSOLE_PW)
        sent = _commands(page)
        page.click("#b-hook")
        page.wait_for_selector("#hook-dlg[open]")
        page.click("#h-send")                                   # empty: the dialog stays open
        assert page.locator("#hook-dlg[open]").count() == 1 and sent == []
        page.click("#h-cancel")
        assert page.locator("#hook-dlg[open]").count() == 0 and sent == []
        page.click("#b-hook")
        page.fill("#h-sample", "S-C-2")
        page.fill("#h-grade", "G3")
        page.click("#h-send")
        page.wait_for_function("document.querySelector('#msg').textContent.includes('hook_replaced')")
        assert sent == [{"command": "hook_replaced", "sample_id": "S-C-2", "grade": "G3"}]
        assert "hook_replaced refused" in page.locator("#msg").inner_text()
        assert errors == []
        ctx.close()
    finally:
        srv.stop()


def _station_events(tmp_path, etype: str, **match) -> list[dict]:
    """The station's own record: lines of type ``etype`` in its tests' events.jsonl."""
    out = []
    for p in glob.glob(str(tmp_path / "records" / "loom-a" / "*" / "events.jsonl")):
        with open(p, encoding="utf-8") as f:
            for ln in f:
                try:
                    e = json.loads(ln)
                except ValueError:
                    continue
                if e.get("type") == etype and all(e.get(k) == v for k, v in match.items()):
                    out.append(e)
    return out


def _wait(cond, timeout_s=40.0):
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        v = cond()
        if v:
            return v
        time.sleep(0.25)
    raise AssertionError("condition not met in time")


def test_journal_actions_and_hook_replaced_reach_a_real_station(tmp_path, browser):
    # the kit's twice-compressed life (QUICK_*): the end of life ≈ 23 s after slot 0
    with console_fleet(tmp_path, ("loom-a",), users={"alice": PW}, quick=True) as (url, gw, _sims):
        ctx = browser.new_context(viewport={"width": 1300, "height": 1200}, bypass_csp=True)
        page = ctx.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        # the due list shows the real station with its line and area (station.line / .area)
        page.goto(url + "/#/due")
        wait_js(page, "window.hw.due && window.hw.due.length === 1")
        row = page.locator('#due tr[data-station="loom-a"]').inner_text()
        assert "l1" in row and "hall" in row
        page.goto(url + "/#/station/loom-a")
        wait_js(page, "window.hw.points > 0", 60)
        _login(page, "alice", PW)
        sent = _commands(page)

        # --- out of service, then in service: the station's state and its events say so
        _click_command(page, "#b-oos", "out_of_service")
        page.wait_for_selector("#alarm .alarm-out_of_service", timeout=30000)
        wait_js(page, "[...document.querySelectorAll('#journal tbody tr')].filter(r => "
                       "r.textContent.includes('out_of_service') && "
                       "r.textContent.includes('console:alice')).length === 2")
        _wait(lambda: _station_events(tmp_path, "alarm_out_of_service", source="console:alice"))
        _click_command(page, "#b-ins", "in_service")
        wait_js(page, "[...document.querySelectorAll('#journal tbody tr')].some(r => "
                       "r.textContent.includes('return_to_service') && r.textContent.includes('console:alice'))")
        _wait(lambda: _station_events(tmp_path, "alarm_in_service", source="console:alice"))
        page.wait_for_selector("#alarm:not(:has(.alarm-out_of_service))", timeout=30000)

        # --- the end of life (≈ 25 s into the virtual life), then shelve and unshelve it
        page.wait_for_selector("#alarm .alarm-active", timeout=120000)
        page.select_option("#j-alarm", "end_of_life")
        page.fill("#j-minutes", "30")
        _click_command(page, "#b-shelve", "shelve")
        page.wait_for_selector("#alarm .alarm-shelved", timeout=30000)
        ev = _wait(lambda: _station_events(tmp_path, "alarm_shelved", source="console:alice"))
        assert ev[0]["until"] - ev[0]["time"] == pytest.approx(1800, abs=5)
        wait_js(page, "[...document.querySelectorAll('#journal tbody tr.j-shelved')].some(r => "
                       "r.textContent.includes('end_of_life') && r.textContent.includes('console:alice'))")
        _click_command(page, "#b-unshelve", "unshelve")
        page.wait_for_selector("#alarm .alarm-active", timeout=30000)
        _wait(lambda: _station_events(tmp_path, "alarm_unshelved", source="console:alice"))
        page.screenshot(path=str(tmp_path / "journal.png"), full_page=True)
        # the journal JSON: every transition with who and when, in time order
        j = json.loads(page.evaluate(
            "async () => JSON.stringify(await (await fetch('/api/station/loom-a/journal')).json())"))
        acts = [(e["alarm"], e["action"], e["by"]) for e in j["journal"]]
        assert ("end_of_life", "shelve", "console:alice") in acts
        assert ("end_of_life", "unshelve", "console:alice") in acts
        assert any(a == ("end_of_life", "activate", None) or a[1] == "activate" for a in acts)
        times = [e["time"] for e in j["journal"]]
        assert times == sorted(times)

        # --- hook replaced: the dialog sends the new hook's sample id through the one intake
        page.click("#b-hook")
        page.fill("#h-sample", "S-loom-a-R1")
        page.click("#h-send")
        page.wait_for_function("document.querySelector('#msg').textContent.includes('hook_replaced')")
        assert sent[-1] == {"command": "hook_replaced", "sample_id": "S-loom-a-R1"}
        msg = page.locator("#msg").inner_text()
        if "sample_id" in COMMAND_KEYS[CommandKind.HOOK_REPLACED]:
            # the station takes the new hook (issue 20 item 5, branch fc-runtime): its alarm is
            # closed by the replacement, its life log has the line, the history page lists it
            assert "hook_replaced: accepted" in msg, msg
            wait_js(page, "[...document.querySelectorAll('#journal tbody tr')].some(r => "
                           "r.textContent.includes('hook_replaced') && r.textContent.includes('console:alice'))")
            hooks = tmp_path / "records" / "loom-a" / "hooks.jsonl"
            line = _wait(lambda: hooks.exists() and [json.loads(x) for x in hooks.read_text().splitlines()])
            assert line[-1]["new_sample_id"] == "S-loom-a-R1" and line[-1]["old_sample_id"] == "S-loom-a"
            page.goto(url + "/#/history/loom-a")
            page.wait_for_selector("#hooks-table")
            assert "S-loom-a-R1" in page.locator("#hooks-table").inner_text()
        else:
            # this tree's station does not take a sample id with hook_replaced yet: the one
            # intake refuses the key (as over MQTT), the alarm stands
            assert "hook_replaced refused" in msg and "sample_id" in msg, msg
            assert page.locator("#alarm .alarm-active").count() == 1
        assert "console:alice" in gw.log_all()
        assert errors == []
        ctx.close()


def test_pages_draw_with_non_finite_figures_and_formula_ids(tmp_path, browser):
    """Station states whose every figure is ±Infinity or NaN and whose sample IDs hide formulas
    (issue 27): the due list, the fleet cards and a station page are drawn — before, one
    `Infinity` in the JSON made the browser's parser refuse it and the page stayed empty."""
    srv, url, _outs, _dirs = start_console(tmp_path, hostile_states())
    try:
        page = browser.new_context(viewport={"width": 1300, "height": 1000}, bypass_csp=True).new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url + "/#/due")
        wait_js(page, "window.hw.due && window.hw.due.length === 4", 30)
        assert HOSTILE_IDS[0] in page.locator('#due tr[data-station="loom-a"]').inner_text()
        page.goto(url + "/#/")
        page.wait_for_selector('.card[data-station="loom-d"]', timeout=30000)
        assert page.locator(".card").count() == 4
        page.goto(url + "/#/station/loom-a")
        wait_js(page, "document.querySelector('#state') && "
                       "document.querySelector('#state').textContent === 'monitoring'", 30)
        assert "Infinity" not in page.locator("body").inner_text()
        assert "NaN" not in page.locator("body").inner_text()
        page.screenshot(path=str(tmp_path / "non-finite.png"), full_page=True)
        assert errors == []
    finally:
        srv.stop()
