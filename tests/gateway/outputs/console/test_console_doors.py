"""The console's doors as a hostile outsider sees them, over real sockets (issue 21): the Host
allow-list (also against DNS rebinding in the real browser), the login lockout under a concurrent
burst and from a stranger's address, the bound on report processes (counted in /proc), malformed
requests answered 4xx with one log line and no traceback, and a storm of live-stream connects
refused while the connected clients keep receiving."""
from __future__ import annotations

import concurrent.futures as cf
import http.client
import json
import logging
import os
import shutil
import socket
import threading
import time

import pytest

from conftest import ROOT
from gateway.outputs.console import auth
from gateway.outputs.console.app import ConsoleServer
from gateway.outputs.console.settings import ConsoleSettings
from kit.console_helpers import Client, console_fleet

PW = "a long password"
CHROMIUM = "/usr/bin/chromium"
EXAMPLE = os.path.join(ROOT, "docs", "example-campaign", "virtual-bench")


def _server(tmp_path, stations=None, **kw):
    users = str(tmp_path / "u.json")
    if not os.path.exists(users):
        auth.add_user(users, "alice", PW)
    srv = ConsoleServer(ConsoleSettings(listen=("127.0.0.1:0",), users_file=users, **kw),
                        stations or {"s1": str(tmp_path / "s1")})
    url = srv.start()[0].rstrip("/")
    return srv, url, int(url.rsplit(":", 1)[1])


def _raw(port: int, data: bytes, source: str | None = None, timeout: float = 10.0) -> tuple[int, bytes]:
    """Send raw bytes, read the whole answer (Connection: close); (status, body)."""
    s = socket.create_connection(("127.0.0.1", port), timeout=timeout,
                                 source_address=(source, 0) if source else None)
    try:
        s.sendall(data)
        out = b""
        while True:
            b = s.recv(65536)
            if not b:
                break
            out += b
    finally:
        s.close()
    head, _, body = out.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), body


def _get(port: int, path: str, host: str, source: str | None = None) -> tuple[int, bytes]:
    return _raw(port, f"GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode(),
                source)


def _post(port: int, path: str, body: bytes, ctype="application/json", host=None, source=None,
          extra="") -> tuple[int, bytes]:
    host = host or f"127.0.0.1:{port}"
    return _raw(port, (f"POST {path} HTTP/1.1\r\nHost: {host}\r\nContent-Type: {ctype}\r\n"
                       f"Content-Length: {len(body)}\r\nConnection: close\r\n{extra}\r\n").encode() + body,
                source)


def _login(port: int, user: str, pw: str, source: str | None = None) -> int:
    return _post(port, "/api/login", json.dumps({"user": user, "password": pw}).encode(),
                 source=source)[0]


def _no_tracebacks(caplog) -> None:
    bad = [r for r in caplog.records if r.exc_info or r.levelno >= logging.ERROR]
    assert not bad, [(r.name, r.levelname, r.getMessage()[:120]) for r in bad]


# ------------------------------------------------------------------------------- Host allow-list

def test_host_allow_list_refuses_foreign_names_with_421(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    srv, url, port = _server(tmp_path, allowed_hosts=("console.plant.example",))
    try:
        for host in ("evil.example", f"evil.example:{port}", "127.0.0.1.evil.example",
                     "console.plant.example.evil.example", "localhost.evil.example", "", "10.9.9.9"):
            st, body = _get(port, "/api/fleet", host)
            assert st == 421, (host, st)
            assert json.loads(body)["ok"] is False and len(body) < 200
        # the login is behind the same door: a rebinding page cannot post it
        st, _ = _post(port, "/api/login", json.dumps({"user": "alice", "password": PW}).encode(),
                      host="evil.example")
        assert st == 421
        assert _get(port, "/", "evil.example")[0] == 421
        # the address the console listens on, localhost on a loopback address, the configured name
        for host in (f"127.0.0.1:{port}", "127.0.0.1", f"localhost:{port}", "LOCALHOST.", "localhost",
                     "console.plant.example", f"Console.Plant.Example:{port}"):
            st, body = _get(port, "/api/fleet", host)
            assert st == 200, (host, st, body[:100])
        assert _login(port, "alice", PW) == 200
        _no_tracebacks(caplog)
        lines = [r.getMessage() for r in caplog.records if "refused (421)" in r.getMessage()]  # a port may hold 421
        assert len(lines) == 1 and "evil.example" in lines[0]   # once a minute per kind
    finally:
        srv.stop()


@pytest.fixture
def rebinding_browser():
    """Chromium whose resolver maps rebind.example to 127.0.0.1 — what a DNS-rebinding attack
    achieves for a page of the attacker's name."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        missing: str | None = "playwright is not installed (pip install playwright)"
    else:
        missing = None if os.path.exists(CHROMIUM) else "Debian's chromium is not installed"
    if missing:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(missing)
        pytest.skip(missing)
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=[
            "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync",
            "--host-resolver-rules=MAP rebind.example 127.0.0.1"])
        try:
            yield b
        finally:
            b.close()


def test_dns_rebinding_page_in_the_browser_reads_nothing(tmp_path, rebinding_browser):
    srv, url, port = _server(tmp_path)
    try:
        ctx = rebinding_browser.new_context()
        page = ctx.new_page()
        # the attacker's page, served by the console's port under the attacker's name
        resp = page.goto(f"http://rebind.example:{port}/")
        assert resp is not None and resp.status == 421
        got = page.evaluate("""async () => {
            const f = await fetch('/api/fleet');
            const l = await fetch('/api/login', {method: 'POST', headers: {'Content-Type':
                'application/json'}, body: JSON.stringify({user: 'alice', password: 'x'})});
            return [f.status, await f.text(), l.status];
        }""")
        assert got[0] == 421 and "stations" not in got[1] and got[2] == 421
        # the same browser on the console's own address gets the fleet page and its data
        resp = page.goto(url + "/")
        assert resp is not None and resp.status == 200
        assert page.evaluate("async () => (await fetch('/api/fleet')).status") == 200
        ctx.close()
    finally:
        srv.stop()


# ------------------------------------------------------------------------------- login lockout

def test_lockout_is_atomic_and_per_address_and_user(tmp_path, caplog):
    caplog.set_level(logging.INFO)
    # (the lockout alone: the hashing budget is ample here; it has its own test,
    # test_console_login_budget.py)
    srv, url, port = _server(tmp_path, lockout_attempts=3, login_failures_per_address=8,
                             lockout_s=60, login_hashes_per_s=100.0, login_hash_burst=100,
                             login_hashes_per_user_per_s=100.0, login_hash_burst_per_user=100)
    try:
        # a concurrent burst of wrong passwords from a stranger's address: exactly 3 are checked
        with cf.ThreadPoolExecutor(24) as ex:
            codes = list(ex.map(lambda _: _login(port, "alice", "wrong wrong", "127.0.0.2"), range(24)))
        assert codes.count(401) == 3 and codes.count(429) == 21, codes
        assert _login(port, "alice", PW, "127.0.0.2") == 429      # that pair is locked
        # ... which does not lock the operator out at her own address
        assert _login(port, "alice", PW, "127.0.0.1") == 200
        # per address, any user: 8 failures lock the address (also for a right password)
        with cf.ThreadPoolExecutor(16) as ex:
            codes = list(ex.map(lambda i: _login(port, f"user{i % 5}", "wrong wrong", "127.0.0.3"),
                                range(16)))
        assert codes.count(401) == 8 and codes.count(429) == 8, codes
        assert _login(port, "alice", PW, "127.0.0.3") == 429
        assert _login(port, "alice", PW, "127.0.0.4") == 200
        # a right password takes its count back: the operator's own logins never lock her out
        for _ in range(6):
            assert _login(port, "alice", PW, "127.0.0.1") == 200
        _no_tracebacks(caplog)
    finally:
        srv.stop()


# ------------------------------------------------------------------------------- report processes

def _report_children(tag: str) -> set[int]:
    """Processes of `hookwatch report` started by this process whose command line holds ``tag``."""
    me = os.getpid()
    out = set()
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat", "rb") as f:
                ppid = int(f.read().rsplit(b")", 1)[1].split()[1])
            with open(f"/proc/{d}/cmdline", "rb") as f:
                cmd = f.read().split(b"\0")
        except (OSError, ValueError, IndexError):
            continue
        if ppid == me and b"gateway.cli" in cmd and b"report" in cmd and any(tag.encode() in c for c in cmd):
            out.add(int(d))
    return out


def test_report_processes_bounded_queued_and_coalesced(tmp_path):
    records = tmp_path / "records"
    shutil.copytree(EXAMPLE, records / "bench")
    tests = sorted(n for n in os.listdir(records / "bench") if (records / "bench" / n).is_dir())
    assert len(tests) >= 12
    srv, url, port = _server(tmp_path, {"bench": str(records / "bench")}, report_jobs=1,
                             report_queue=2)
    peak, seen, stop = [0], set(), threading.Event()

    def watch():
        while not stop.is_set():
            kids = _report_children(str(records))
            peak[0] = max(peak[0], len(kids))
            seen.update(kids)
            time.sleep(0.02)

    w = threading.Thread(target=watch, daemon=True)
    w.start()
    try:
        # a reader without a login (the loopback address reads freely): every test's Fig. 7,
        # each asked three times, all at once
        paths = [f"/api/station/bench/tests/{t}/fig7.png" for t in tests for _ in range(3)]

        def fetch(path):
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=300)
            try:
                conn.request("GET", path)
                r = conn.getresponse()
                return path, r.status, r.getheader("Retry-After"), r.read()
            finally:
                conn.close()

        with cf.ThreadPoolExecutor(len(paths)) as ex:
            answers = list(ex.map(fetch, paths))
        stop.set()
        w.join(5)
        assert len(answers) == len(paths)                       # every request got an answer
        assert {st for _, st, _, _ in answers} <= {200, 503}, [a[:3] for a in answers]
        ok = {p for p, st, _, _ in answers if st == 200}
        busy = [a for a in answers if a[1] == 503]
        assert ok and busy
        assert all(ra is not None and int(ra) >= 1 for _, _, ra, _ in busy)
        assert all(b[:8] == b"\x89PNG\r\n\x1a\n" for _, st, _, b in answers if st == 200)
        assert peak[0] <= 1, peak                            # never more than report_jobs at once
        # identical requests shared one process: at most one process per figure made
        assert 1 <= len(seen) <= len(ok)
        # later, a figure made once is served from the cache without a new process
        before = len(seen)
        p = next(iter(ok))
        assert fetch(p)[1] == 200 and not _report_children(str(records))
        assert len(seen) == before
    finally:
        stop.set()
        srv.stop()


# ------------------------------------------------------------------------------- malformed input

def test_malformed_requests_4xx_one_warning_line_per_kind_no_traceback(tmp_path, caplog):
    caplog.set_level(logging.DEBUG)
    srv, url, port = _server(tmp_path)
    try:
        deep = b"[" * 12000
        deep_obj = b'{"user": ' + b'{"a": ' * 2000 + b"1" + b"}" * 2000 + b"}"
        cases = [
            (lambda: _post(port, "/api/login", b"{not json"), 400),
            (lambda: _post(port, "/api/login", b"[1, 2]"), 400),
            (lambda: _post(port, "/api/login", b"\xff\xfe{}"), 400),
            (lambda: _post(port, "/api/login", deep), 400),
            (lambda: _post(port, "/api/login", deep_obj), 400),
            (lambda: _post(port, "/api/login", b'{"user": "alice"}', ctype="text/plain"), 415),
            (lambda: _post(port, "/api/login", b"{" + b" " * 20000 + b"}"), 413),
            (lambda: _raw(port, b"GARBAGE / HTTP/1.1\r\n\r\n"), 400),
            (lambda: _raw(port, b"GET / HTTP/1.1\r\nHost: a\x01b\r\n\r\n"), 400),
            (lambda: _raw(port, b"GET / HTTP/1.1\r\nHost: a\r\nX-Long: " + b"x" * 9000 + b"\r\n\r\n"), 400),
            (lambda: _raw(port, b"POST /api/login HTTP/1.1\r\nHost: a\r\nContent-Length: 5\r\n"
                                b"Transfer-Encoding: chunked\r\n\r\n"), 400),
        ]
        for _round in range(4):
            for i, (send, want) in enumerate(cases):
                st, body = send()
                assert st == want and st != 500, (i, st, body[:200])
                assert len(body) < 400
        # the server is fine afterwards
        assert _get(port, "/api/fleet", f"127.0.0.1:{port}")[0] == 200
        assert _login(port, "alice", PW) == 200
        _no_tracebacks(caplog)
        warn = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert warn and all(r.name == "hookwatch.console" for r in caplog.records
                            if r.levelno >= logging.WARNING)
        assert all("Traceback" not in m and "\n" not in m for m in warn)
        # 44 refused requests of 6 kinds: one line per kind within the minute
        assert len(warn) <= 6, warn
    finally:
        srv.stop()


# ------------------------------------------------------------------------------- live streams

def _sse(port: int, sid: str, source: str | None = None) -> tuple[socket.socket, int, bytes]:
    s = socket.create_connection(("127.0.0.1", port), timeout=10,
                                 source_address=(source, 0) if source else None)
    s.sendall(f"GET /api/station/{sid}/stream HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
              "Accept: text/event-stream\r\n\r\n".encode())
    buf = b""
    while b"\r\n\r\n" not in buf:
        b = s.recv(65536)
        if not b:
            break
        buf += b
    status = int(buf.split(b" ", 2)[1]) if buf else 0
    return s, status, buf


def test_stream_connect_storm_refused_while_clients_keep_receiving(tmp_path):
    with console_fleet(tmp_path, ("loom-a",), console={
            "stream_connects_per_address": 4, "stream_connects_total": 30}) as (url, gw, _sims):
        port = int(url.rsplit(":", 1)[1])
        t_keep = time.monotonic()
        keep, st, buf = _sse(port, "loom-a")
        assert st == 200
        keep.settimeout(5)

        def read_for(s, secs):
            data = b""
            t_end = time.monotonic() + secs
            while time.monotonic() < t_end:
                try:
                    data += s.recv(65536)
                except TimeoutError:
                    pass
            return data

        buf += read_for(keep, 2)
        n0 = buf.count(b"data: {")
        assert n0 >= 1
        # a storm of connects from one address: beyond the bound (4 a minute, the first of them
        # taken by `keep`), 429 with Retry-After
        t_storm = t_keep
        codes, retry = [], []
        for _ in range(40):
            s, code, head = _sse(port, "loom-a")
            codes.append(code)
            if code == 429:
                retry.append(b"Retry-After:" in head)
            s.close()
        refill = (time.monotonic() - t_storm) * 4 / 60          # tokens back during the storm
        assert set(codes) <= {200, 429} and codes.count(200) <= 3 + refill + 1, codes
        assert codes.count(429) >= 30 and all(retry)
        # another address still gets in (the bound is per address) ...
        other, st2, _ = _sse(port, "loom-a", "127.0.0.2")
        assert st2 == 200
        other.close()
        # ... until the global bound (30 a minute): a storm from many addresses is refused as well
        many = [_sse(port, "loom-a", f"127.0.1.{i}") for i in range(1, 41)]
        for s, _, _ in many:
            s.close()
        accepted = 1 + codes.count(200) + 1 + sum(1 for _, c, _ in many if c == 200)
        assert accepted <= 30 + (time.monotonic() - t_storm) * 30 / 60 + 1, accepted
        assert sum(1 for _, c, _ in many if c == 429) >= 1
        # the client connected before the storm kept receiving updates throughout
        buf += read_for(keep, 4)
        assert buf.count(b"data: {") > n0 + 3
        msgs = [json.loads(x.split(b"\n\n")[0]) for x in buf.split(b"data: ")[1:-1]]
        assert any(m["type"] == "update" for m in msgs)
        keep.close()
        assert "Traceback" not in gw.log_all()
        assert Client(url).get("/api/fleet")[0] == 200
