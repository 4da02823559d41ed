"""The console's Boxes page (issue 37) in a real browser (Playwright driving Debian's chromium):
three boxes publish their retained config reports on one real Mosquitto — each the real report
publisher (gateway/supervisor/boxpublish.py) with the report of a real state folder (staged
versions, the atomic switch, a rollback, a deferral, drift) — and the console's site view, riding
on a real MQTT output's session, shows version, deferred stations, drift and rollbacks per box;
a box killed with SIGKILL shows offline (its Will); a hostile string is shown as text."""
from __future__ import annotations

import json
import os
import signal
import sys
import threading

from conftest import TESTS
from gateway.config.site.repository import build
from gateway.config.site.versions import StateDir
from gateway.outputs.mqtt import schema as mqtt_schema
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker
from kit.browser import wait_js
from kit.console_helpers import start_console
from kit.northbound import LoopThread
from kit.proc import Proc
from kit.site_repo import SiteRepo

HTML = '<img src=x onerror="window.pwned=1">'


def _state(tmp_path, repo, box, versions, status, rollback=None):
    st = StateDir(str(tmp_path / f"state-{box}"))
    eff = build(str(repo.path), box)
    assert not eff.problems, eff.problems
    for v in versions:
        st.stage(v, eff, box)
    st.switch(versions[-1])
    st.mark_verified(versions[-1])
    if rollback:
        st.record_rollback(*rollback)
    (tmp_path / f"state-{box}" / "config" / "supervisor.json").write_text(json.dumps(status))
    return st


def _reporter(tmp_path, port, st, name):
    p = Proc([sys.executable, os.path.join(TESTS, "kit", "box_reporter.py"),
              str(port), os.path.dirname(st.root)], str(tmp_path / f"{name}.log"))
    p.readline_until("published", timeout=60)
    return p


def test_boxes_page_shows_versions_deferrals_drift_rollbacks_and_a_dead_box(tmp_path, browser):
    repo = SiteRepo(tmp_path / "site", None)
    for b in ("b1", "b2", "b3"):
        repo.box(b, tmp_path / b / "records")
    repo.station("b1", "busy", {"meter": "/dev/m1", "stm32": "/dev/s1"})
    repo.station("b2", "s1", {"meter": "/dev/m2", "stm32": "/dev/s2"})
    repo.station("b3", "x", {"meter": "/dev/m3", "stm32": "/dev/s3"})
    v1, v2, bad = "1" * 40, "2" * 40, "b" * 40
    s1 = _state(tmp_path, repo, "b1", [v1, v2], {"stations": {"busy": {
        "version": v1, "pending": v2, "in_test": True, "running": True, "refused": None}}})
    s2 = _state(tmp_path, repo, "b2", [v2], {"stations": {"s1": {
        "version": v2, "pending": None, "in_test": False, "running": True, "refused": None}}},
        rollback=(bad, v2, "health gate (15 s): s1: no meter reading " + HTML))
    s3 = _state(tmp_path, repo, "b3", [v2], {"stations": {}, "drift_files": ["stations/x.yaml"]})
    lt = LoopThread()
    procs: list[Proc] = []
    srv = out = None
    with Broker(tmp_path) as broker:
        try:
            procs += [_reporter(tmp_path, broker.port, s, n) for s, n in ((s1, "b1"), (s2, "b2"), (s3, "b3"))]
            srv, url, _outs, _dirs = start_console(tmp_path)
            base = mqtt_schema.base_topic("hookwatch", "lab", "hall-1", "line-1", "loom-a")
            out = MqttOutput(MqttSettings(station_id="loom-a", base_topic=base, port=broker.port,
                                          outbox_path=str(tmp_path / "a.sqlite"),
                                          reconnect_min_s=0.2, reconnect_max_s=1.0))
            assert srv.attach_site("loom-a", base, out.pump.add_site_feed)
            lt.call(out.start())
            ctx = browser.new_context(viewport={"width": 1500, "height": 900}, bypass_csp=True)
            page = ctx.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url + "/#/boxes")
            wait_js(page, "window.hw.boxes && window.hw.boxes.length === 3")
            assert page.evaluate("window.hw.boxes") == ["b1", "b2", "b3"]

            def cell(box, cls):
                return page.locator(f'#boxes tr[data-box="{box}"] td.{cls}').inner_text()
            assert cell("b1", "version") == v2[:12] and cell("b1", "deferred") == "busy"
            assert cell("b1", "pending") == "busy" and cell("b1", "drift") == "no"
            assert cell("b2", "deferred") == "none"
            rb = cell("b2", "rollback")
            assert rb.startswith(f"{bad[:12]} → {v2[:12]}: health gate (15 s): s1: no meter reading"), rb
            assert "<img" in rb and page.locator("#boxes img").count() == 0        # text, never HTML
            assert page.evaluate("window.pwned === undefined")
            assert cell("b3", "drift") == "yes: stations/x.yaml"
            assert all(cell(b, "online") == "online" for b in ("b1", "b2", "b3"))
            page.screenshot(path=str(tmp_path / "boxes.png"), full_page=True)
            # box b3 dies: its Will
            procs[2].p.send_signal(signal.SIGKILL)
            procs[2].p.wait(10)
            wait_js(page, "document.querySelector('#boxes tr[data-box=\"b3\"] td.online')"
                          ".textContent === 'offline'")
            assert cell("b3", "drift") == "yes: stations/x.yaml"       # the Will keeps what was said
            assert cell("b1", "online") == "online"
            assert not errors, errors
            assert srv.site is not None and srv.site.boxes.counters["refused"] == 0
            ctx.close()
        finally:
            for p in procs:
                p.stop()
            if out is not None:
                lt.call(out.stop())
            closer = threading.Thread(target=lt.close)
            closer.start()
            closer.join(30)
            if srv is not None:
                srv.stop()
