"""Issue 28 item 6, operator words, in a real browser (Playwright driving Debian's chromium): the
station page's events are sentences (one per event type), each event's raw JSON one click away
(and it stays open while new events arrive); a test whose life ended and was then stopped is
shown as such — on the station page, its events and the history — not just "aborted".

The console is fed through the real hand-over (ConsoleOutput) with a constructed station state
and events as the station emits them (gateway/station/status.py)."""
from __future__ import annotations

import json
import os
import time

from gateway.core import records as R
from gateway.core.records import Event, EventType, StationState
from kit.browser import wait_js
from kit.console_helpers import START, fleet_states, start_console

TID = "20261126T060000.000Z"
T_LIFE = 7980.0                     # 2 h 13 min
WORDS = "end of life found at 2 h 13 min, then stopped"


def _events(t0: float) -> list[Event]:
    st = "loom-c"
    return [
        Event(EventType.TEST_STARTED, st, t0, TID, 0,
              {"sample_id": "S-C", "grade": "G3", "t_set": 1.2, "t_end": 14400.0, "source": "console:alice",
               "prior_mean": None}),
        Event(EventType.BASELINE, st, t0 + 600, TID, 30000,
              {"mu_ss": 0.242, "mu_th": 0.29, "k_b": 30000, "stable_first": 20000}),
        Event(EventType.WEAR_WARNING, st, t0 + 7000, TID, 350000,
              {"warn_slot": 349999, "t_warn": 7000.0, "headroom": 0.18, "t_cross": 7900.0,
               "reasons": ["headroom", "trend"], "mu_ss": 0.242, "mu_th": 0.29}),
        Event(EventType.END_OF_LIFE, st, t0 + T_LIFE, TID, 399000,
              {"k_life": 399000, "t_life": T_LIFE, "mu_ss": 0.242, "mu_th": 0.29, "sample_id": "S-C"}),
        Event(EventType.TEST_ENDED, st, t0 + 8100, TID, 405000,
              {"reason": "stop", "test_status": "aborted", "source": "console:alice",
               "result": {"status": "failure", "t_life": T_LIFE, "interrupted": True}}),
    ]


def test_events_in_words_with_the_raw_json_one_click_away(tmp_path, browser):
    states = fleet_states()
    states["loom-c"] = StationState(station="loom-c", state=R.TestState.ABORTED, test_id=TID,
                                    sample_id="S-C", grade="G3", test_started_utc=START,
                                    t_life=T_LIFE, status="failure", end_reason="stop", stopped=True,
                                    mu_ss=0.242, mu_th=0.29)
    srv, url, outs, dirs = start_console(tmp_path, states)
    # the recorded test, as the history lists it
    td = os.path.join(dirs["loom-c"], TID)
    os.makedirs(td)
    with open(os.path.join(td, "result.json"), "w", encoding="utf-8") as f:
        json.dump({"test_id": TID, "test_status": "aborted", "end_reason": "stop", "sample_id": "S-C",
                   "grade": "G3", "method": {"status": "failure", "t_life": T_LIFE, "mu_ss": 0.242}}, f)
    t0 = time.time() - 9000
    for ev in _events(t0):
        outs["loom-c"].on_event(ev)
    outs["loom-c"].on_state(states["loom-c"])
    try:
        ctx = browser.new_context(viewport={"width": 1300, "height": 1000}, bypass_csp=True)
        page = ctx.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url + "/#/station/loom-c")
        wait_js(page, "document.querySelectorAll('#events .event').length === 5", 30)
        text = {t: page.locator(f'#events .event[data-type="{t}"] .ev-text').inner_text()
                for t in ("test_started", "baseline_established", "wear_warning", "end_of_life",
                          "test_ended")}
        assert text["test_started"].startswith("Test started by console:alice: sample S-C (G3) at 1.20 N"), text
        assert "planned for 4 h 00 min" in text["test_started"]
        assert text["baseline_established"] == "Baseline found: μ_ss 0.242, so the threshold μ_th is 0.290."
        assert text["wear_warning"].startswith("Wear warning at 1 h 56 min: headroom 0.18; the headroom is "
                                               "below its bound, the μ trend reaches the threshold soon"), text
        assert text["end_of_life"] == ("End of life detected at 2 h 13 min (μ above the threshold 0.290; "
                                       "baseline μ_ss 0.242).")
        assert text["test_ended"] == f"Test: {WORDS} by console:alice."
        # newest first
        order = page.locator("#events .event").evaluate_all("els => els.map(e => e.dataset.type)")
        assert order == ["test_ended", "end_of_life", "wear_warning", "baseline_established", "test_started"]
        # the state says what was found before the stop, not just "aborted"
        assert page.locator("#state").inner_text() == WORDS
        assert page.locator("#state").get_attribute("data-state") == "aborted"

        # the raw JSON: hidden, one click shows it (the event as recorded), one more hides it
        eol = page.locator('#events .event[data-type="end_of_life"]')
        assert not eol.locator("pre.raw").is_visible()
        eol.locator("button.raw-toggle").click()
        assert eol.locator("pre.raw").is_visible()
        raw = json.loads(eol.locator("pre.raw").inner_text())
        assert raw["type"] == "end_of_life" and raw["t_life"] == T_LIFE and raw["k_life"] == 399000
        assert raw["mu_th"] == 0.29 and raw["test_id"] == TID
        # it stays open while new events arrive (the list is drawn again)
        outs["loom-c"].on_event(Event(EventType.PORT_LOST, "loom-c", time.time(), TID, None,
                                      {"port": "meter", "brief": True, "times": 3}))
        wait_js(page, "document.querySelectorAll('#events .event').length === 6", 30)
        assert page.locator('#events .event[data-type="port_lost"] .ev-text').inner_text() == \
            "The meter port was lost (3 times)."
        eol = page.locator('#events .event[data-type="end_of_life"]')
        assert eol.locator("pre.raw").is_visible()
        assert not page.locator('#events .event[data-type="test_ended"] pre.raw').is_visible()
        eol.locator("button.raw-toggle").click()
        assert not eol.locator("pre.raw").is_visible()
        page.screenshot(path=str(tmp_path / "events.png"), full_page=True)

        # the fleet card and the history say the same
        page.goto(url + "/#/")
        page.wait_for_selector('.card[data-station="loom-c"]')
        assert page.locator('.card[data-station="loom-c"] .state').inner_text().startswith(WORDS)
        page.goto(url + "/#/history/loom-c")
        page.wait_for_selector("#tests td.status")
        assert page.locator("#tests td.status").first.inner_text() == WORDS
        assert errors == [], errors
    finally:
        srv.stop()
