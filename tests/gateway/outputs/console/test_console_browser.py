"""The console in a real browser (Playwright from PyPI driving Debian's chromium) against
`hookwatch sim` + `hookwatch run` as processes: the fleet page lists the stations, the station page's
μ curve grows through a virtual life (the kit's twice-compressed one: the end of life ≈ 23 s
after slot 0) until the end-of-life alarm, a page opened mid-test
shows the curve from slot 0, the station's "all values" shows every value the catalog labels, and
acknowledge needs a login and the CSRF token.

Screenshots are written to the test's tmp folder (fleet.png, station-mid.png, station-alarm.png,
station-acked.png, history.png)."""
from __future__ import annotations

import time

from playwright.sync_api import TimeoutError as PlaywrightTimeout

from gateway.outputs.console.feed import VALUES
from kit.browser import wait_js
from kit.console_helpers import console_fleet
from kit.e2e import wait_log

PW = "correct horse battery"


def test_console_in_a_browser(tmp_path, browser):
    with console_fleet(tmp_path, ("loom-a", "loom-b"), users={"alice": PW}, quick=True) as (url, gw,
                                                                                          _sims):
        t0 = time.monotonic()
        # the page's CSP forbids eval; Playwright's wait_for_function needs it (the header is tested over HTTP)
        ctx = browser.new_context(viewport={"width": 1300, "height": 1100}, bypass_csp=True)
        page = ctx.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        # --- fleet: one card per station of the running fleet
        page.goto(url + "/")
        page.wait_for_selector('.card[data-station="loom-b"]', timeout=20000)
        cards = page.locator(".card").evaluate_all("els => els.map(e => e.dataset.station)")
        assert sorted(cards) == ["loom-a", "loom-b"]
        wait_js(page, "document.querySelector('.card .state').textContent.includes('baseline')", 20)
        page.screenshot(path=str(tmp_path / "fleet.png"), full_page=True)

        # --- station page: the μ curve grows
        page.goto(url + "/#/station/loom-a")
        wait_js(page, "window.hw.points > 10", 30)
        n1 = page.evaluate("window.hw.points")
        t1 = page.evaluate("window.hw.lastT")
        time.sleep(3)
        wait_js(page, f"window.hw.lastT > {t1} + 1", 20)
        assert page.evaluate("window.hw.points") > n1

        # --- every value of the station the catalog labels, under its label (GET /api/values:
        # the page keeps no list of its own; gateway/core/catalog.py)
        page.click("#all-values summary")
        wait_js(page, "window.hw.values > 0", 10)
        assert page.locator("#values-kv > span:nth-child(odd)").all_inner_texts() == [v.label for v in VALUES]
        shown = page.locator("#values-kv [data-value]").evaluate_all("els => els.map(e => e.dataset.value)")
        assert shown == [v.name for v in VALUES]
        assert page.locator('#values-kv [data-value="test_state"]').inner_text() in ("baseline_search",
                                                                                     "monitoring")

        # --- a page opened mid-test shows the curve from slot 0
        while time.monotonic() - t0 < 15:      # the station's §3a start, then ~10 s of its test
            time.sleep(0.5)
        late = ctx.new_page()
        late.goto(url + "/#/station/loom-a")
        wait_js(late, "window.hw.points > 0", 20)
        assert late.evaluate("window.hw.firstT") == 0
        # … up to where the first page had been (how far the test got in 15 s is the machine's)
        assert late.evaluate("window.hw.lastT") > t1 + 1
        late.screenshot(path=str(tmp_path / "station-mid.png"), full_page=True)
        late.close()

        # --- the end-of-life alarm appears (t_life ≈ 23 s, known ≈ 25 s into the life)
        try:
            page.wait_for_selector("#alarm .alarm-active", timeout=120000)
        except PlaywrightTimeout:
            raise AssertionError("no end-of-life alarm on the page; the gateway said:\n"
                                 + gw.log()[-6000:]) from None
        assert page.locator("#t-life").inner_text().endswith(" s")
        page.screenshot(path=str(tmp_path / "station-alarm.png"), full_page=True)

        # --- acknowledge without a login: refused, the alarm stays active
        page.click("#b-ack")
        page.wait_for_function("document.querySelector('#msg').textContent.includes('refused')")
        assert "log in first" in page.locator("#msg").inner_text()
        assert page.locator("#alarm .alarm-active").count() == 1

        # --- log in; a POST without the CSRF token is still refused
        page.fill("#login-user", "alice")
        page.fill("#login-pw", PW)
        page.click("#login button")
        page.wait_for_selector("#logout:not(.hidden)")
        st = page.evaluate("""async () => (await fetch('/api/station/loom-a/command', {method: 'POST',
            headers: {'Content-Type': 'application/json'}, body: JSON.stringify({command: 'ack'})})).status""")
        assert st == 403
        assert page.locator("#alarm .alarm-active").count() == 1

        # --- acknowledge with the login and the token: accepted; the page shows it
        page.click("#b-ack")
        page.wait_for_function("document.querySelector('#msg').textContent.includes('ack: accepted')")
        page.wait_for_selector("#alarm .alarm-acknowledged", timeout=15000)
        page.screenshot(path=str(tmp_path / "station-acked.png"), full_page=True)
        assert "console:alice" in gw.log_all()

        # --- fleet card shows the acknowledged alarm too; no script errors anywhere
        page.goto(url + "/")
        page.wait_for_selector('.card[data-station="loom-a"] .alarm-acknowledged', timeout=10000)

        # --- history: the ended test with its status and the Fig. 7 from the report code
        wait_log(gw, "loom-a: test_ended", timeout=60)      # the planned end (QUICK_END)
        page.goto(url + "/#/history/loom-a")
        page.wait_for_selector("button.fig7", timeout=20000)
        row = page.locator("#tests tr").nth(1).inner_text()
        # in words: the life ran to its planned end after the end of life (the method's status in
        # the cell's title)
        assert "S-loom-a" in row and "completed; end of life found at" in row, row
        assert "failure" in page.locator("#tests td.status").first.get_attribute("title")
        page.click("button.fig7")
        page.wait_for_function("document.querySelector('img.fig') && document.querySelector('img.fig')"
                               ".complete && document.querySelector('img.fig').naturalWidth > 1000",
                               timeout=120000)
        page.screenshot(path=str(tmp_path / "history.png"), full_page=True)
        assert errors == []
        ctx.close()
