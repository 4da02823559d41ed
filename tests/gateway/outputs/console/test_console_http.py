"""The console over real HTTP against `hookwatch run` with the console on: reading, login, CSRF,
the one command validation, lockout, bad input and a slow live client being dropped."""
from __future__ import annotations

import json
import socket
import time

from kit.console_helpers import Client, console_fleet
from kit.e2e import wait_log

PW = "correct horse battery"


def _wait(fn, timeout=30.0, every=0.3):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        v = fn()
        if v:
            return v
        time.sleep(every)
    raise AssertionError("condition not met in time")


def test_console_http_auth_csrf_commands_lockout(tmp_path):
    with console_fleet(tmp_path, ("loom-a", "loom-b"), users={"alice": PW}) as (url, gw, _sims):
        c = Client(url)
        # reading is open on the local host: the fleet lists both stations, the series grows
        st, fleet, hdr = c.get("/api/fleet")
        assert st == 200 and sorted(s["station"] for s in fleet["stations"]) == ["loom-a", "loom-b"]
        assert "default-src 'self'" in hdr["Content-Security-Policy"]
        assert all(s["mqtt_ok"] is None for s in fleet["stations"])   # MQTT not configured
        snap = _wait(lambda: (lambda s: s if len(s[1]["rows"]) > 20 else None)(c.get("/api/station/loom-a")))
        rows = snap[1]["rows"]
        assert rows[0][0] == 0.0 and rows[-1][0] > rows[0][0]
        assert c.get("/api/station/nope")[0] == 404
        # a command without a login is refused, also with a made-up CSRF token
        st, r, _ = c.post("/api/station/loom-a/command", {"command": "stop"})
        assert st == 401, r
        st, r, _ = c.request("POST", "/api/station/loom-a/command", {"command": "stop"},
                             headers={"X-CSRF-Token": "x"})
        assert st == 401
        # wrong password, then the right one
        assert c.login("alice", "wrong password")[0] == 401
        st, who = c.login("alice", PW)
        assert st == 200 and who["user"] == "alice"
        cookie = next(iter(c.jar))
        assert cookie.name == "hw_session" and cookie.has_nonstandard_attr("HttpOnly")
        # logged in, but no CSRF token → refused
        st, r, _ = c.post("/api/station/loom-a/command", {"command": "stop"}, csrf=False)
        assert st == 403 and "CSRF" in r["reason"]
        # with the token: the station's own validation answers, with the reason MQTT and PLC give
        st, r, _ = c.post("/api/station/loom-a/command", {"command": "ack"})
        assert st == 409 and r["reason"] == "no unacknowledged alarm (end of life or wear warning)" and r["code"] == 3
        st, r, _ = c.post("/api/station/loom-a/command", {"command": "start", "sample_id": "X", "t_set": 0.5})
        assert st == 409 and r["code"] == 1 and "already running" in r["reason"]
        st, r, _ = c.post("/api/station/loom-a/command", {"command": "setpoint", "t_set": 99})
        assert st == 409 and r["code"] in (5, 8)
        st, r, _ = c.post("/api/station/loom-a/command", {"command": "fly"})
        assert st == 400 and "unknown" in r["reason"] and r["code"] == 9     # refused by the intake
        st, r, _ = c.post("/api/station/loom-a/command", {"command": "stop", "evil": 1})
        assert st == 400 and "unknown key" in r["reason"]
        # bad input: not JSON, not an object, too large
        assert c.post("/api/station/loom-a/command", raw=b"{not json")[0] == 400
        assert c.post("/api/station/loom-a/command", raw=b"[1,2]")[0] == 400
        assert c.post("/api/station/loom-a/command", raw=b"{" + b" " * 20000 + b"}")[0] == 413
        # a good command works and is logged with the user
        st, r, _ = c.post("/api/station/loom-b/command", {"command": "stop"})
        assert st == 200 and r["ok"], r
        wait_log(gw, "command stop on loom-b by alice: accepted")
        wait_log(gw, "console:alice")    # the station's own event log names the source
        # lockout: 3 failures lock the user out, even for the right password
        for _ in range(3):
            assert Client(url).login("alice", "nope nope")[0] == 401
        st, r = Client(url).login("alice", PW)
        assert st == 429 and "too many failed logins" in r["reason"]
        # the existing session goes on working; logout ends it
        assert c.get("/api/session")[1]["user"] == "alice"
        assert c.post("/api/logout", {})[0] == 200
        assert c.post("/api/station/loom-a/command", {"command": "stop"})[0] == 401


def _sse_socket(url: str, path: str, rcvbuf: int | None = None) -> socket.socket:
    host, port = url.split("//")[1].split(":")
    s = socket.socket()
    if rcvbuf:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.connect((host, int(port)))
    s.sendall(f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nAccept: text/event-stream\r\n\r\n".encode())
    return s


def test_console_slow_client_dropped_fast_client_served(tmp_path):
    with console_fleet(tmp_path, ("loom-a",)) as (url, gw, _sims):
        slow = _sse_socket(url, "/api/station/loom-a/stream", rcvbuf=2048)   # never reads
        fast = _sse_socket(url, "/api/station/loom-a/stream")
        fast.settimeout(5)
        buf = b""
        t_end = time.monotonic() + 90
        dropped = False
        while time.monotonic() < t_end and not dropped:
            buf += fast.recv(65536)
            dropped = "live client of loom-a dropped" in gw.log_all()
        assert dropped, gw.log()
        # the fast client still gets updates after the slow one was dropped
        n0 = buf.count(b"data: {")
        t_end = time.monotonic() + 5
        while time.monotonic() < t_end:
            buf += fast.recv(65536)
        assert buf.count(b"data: {") > n0 + 3
        # (chunked transfer: each event is "data: {json}\n\n" inside a chunk)
        msgs = [json.loads(x.split(b"\n\n")[0]) for x in buf.split(b"data: ")[1:-1]]
        assert msgs[0]["type"] == "snapshot" and any(m["type"] == "update" for m in msgs)
        # the slow client's connection was closed by the server
        slow.setblocking(False)
        slow.close()
        fast.close()


def test_console_history_fig7_downloads_and_campaign(tmp_path):
    with console_fleet(tmp_path, ("loom-a", "loom-b"), users={"alice": PW},
                       test={"t_end_s": 15}) as (url, gw, _sims):
        c = Client(url)

        def ended():
            st, r, _ = c.get("/api/station/loom-a/tests")
            return r if st == 200 and r["tests"] and "result.json" in r["tests"][0]["files"] else None

        tests = _wait(ended, timeout=60)["tests"]
        t = tests[0]
        assert t["test_status"] == "completed" and t["sample_id"] == "S-loom-a"
        assert t["status"] in ("no_failure", "no_baseline", "failure")
        base = f"/api/station/loom-a/tests/{t['test_id']}"
        # downloads: the recorded files, nothing else
        req = c.opener.open(url + base + "/files/result.json", timeout=30)
        assert json.loads(req.read())["test_id"] == t["test_id"]
        assert c.get(base + "/files/alarm.json")[0] == 404
        assert c.get("/api/station/loom-a/tests/..%2F..%2Fetc/files/result.json")[0] == 404
        # the Fig. 7 PNG, made by the report code in its own process
        with c.opener.open(url + base + "/fig7.png", timeout=120) as r:
            png = r.read()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10000
        # campaign: needs a login; then a report over both stations
        assert c.post("/api/campaign", {"stations": ["loom-a", "loom-b"]})[0] == 401
        c.login("alice", PW)
        _wait(lambda: c.get("/api/station/loom-b/tests")[1]["tests"][:1]
              and "result.json" in c.get("/api/station/loom-b/tests")[1]["tests"][0]["files"], 30)
        assert c.post("/api/campaign", {"stations": ["nope"]})[0] == 400
        st, r, _ = c.post("/api/campaign", {"stations": ["loom-a", "loom-b"]})
        assert st == 200 and r["tests"] == 2, r
        with c.opener.open(url + r["url"], timeout=30) as resp:
            html = resp.read().decode()
        assert "Table" in html and "fig7_" in html
        assert c.get(r["url"].replace("report.html", "../../etc/passwd"))[0] == 404
