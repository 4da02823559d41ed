"""The operator console: an aiohttp server on its own thread and loop (:class:`ConsoleServer`).

Pages (static, shipped in ``static/``; uPlot vendored, nothing from the internet):
``/`` fleet, ``/#/station/<id>`` station, ``/#/history/<id>`` history.

JSON API (reading: open from the loopback address, else a login — ``console.read_without_login``)::

    GET  /api/fleet[?site=1]                fleet cards (site=1: with the site's other boxes)
    GET  /api/station/<id>                  snapshot: decimated series from slot 0, markers, events
    GET  /api/station/<id>/stream           Server-Sent Events: snapshot, then changes (~4/s)
    GET  /api/station/<id>/tests            recorded tests
    GET  /api/station/<id>/hooks            the successive hooks and their lives (hooks.jsonl)
    GET  /api/station/<id>/journal          the ISA-18.2 alarm journal (every transition, who, when)
    GET  /api/due[?line=&area=&site=1]      the planner's due list (every station, soonest first;
                                            site=1: the stations of the site's other boxes too)
    GET  /api/due.csv[?line=&area=&site=1]  the same as CSV (cells defused against formulas)
    GET  /api/station/<id>/tests/<test>/fig7.png        the report's Fig. 7 of a test
    GET  /api/station/<id>/tests/<test>/files/<name>    log.csv.gz, log.meta.yaml, events.jsonl, result.json
    GET  /api/session                       who is logged in (+ CSRF token)
    POST /api/login  {user, password}       → session cookie + CSRF token
    POST /api/logout
    POST /api/station/<id>/command {command, ...}   start | stop | ack | setpoint | hook_replaced |
                                            shelve | unshelve | out_of_service | in_service

Every POST other than login needs the session cookie and the ``X-CSRF-Token`` header; commands go
through the station's one validation (``Station.submit`` on the station's own loop) and are logged
with the user.
"""
from __future__ import annotations

import asyncio
import hmac
import ipaddress
import json
import logging
import math
import os
import re
import shutil
import socket
import ssl
import sys
import tempfile
import time
from collections.abc import Callable
from typing import Any

from aiohttp import web

from .. import safeout
from ..commandtypes import CODE, Rejection, reply_code
from ..doors import AiohttpDoor, DoorLimits, door_middleware, door_runner_kwargs
from ..northbound.cmdparse import intake, nesting_depth, rejected_event_data
from ..ports import StationView
from ..ratelog import RateLog
from ..records import CommandKind
from ..threadloop import ThreadLoop, call_soon_on, submit_to
from . import auth
from .feed import (
    DUE_COLUMNS,
    ConsoleOutput,
    StationFeed,
    due_list,
    hook_history,
    journal_from_disk,
    series_from_log,
)
from .guard import Busy, HostAllow, LogLimit, RateBound, ReportPool, ServerLog
from .site import SiteView
from .site import filters as site_filters

log = logging.getLogger("hookwatch.console")


def _json(data: Any, **kw: Any) -> web.Response:
    """A JSON response, strict: never NaN/Infinity (a non-finite number is null; gateway.safeout)."""
    return web.json_response(data, dumps=safeout.dumps, **kw)


STATIC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "static")
#: largest request body accepted
MAX_BODY = 16 * 1024
#: messages queued per live client before it is dropped as too slow
CLIENT_QUEUE = 64
#: a client that cannot take one message within this long is dropped
WRITE_TIMEOUT_S = 10.0
#: kernel send buffer and transport high-water mark of a live client, bytes
SEND_BUFFER = 16 * 1024
#: most live (SSE) clients at once
MAX_CLIENTS = 64
#: deepest JSON nesting ([ and {) a request body may have
MAX_JSON_DEPTH = 16
#: how often the console drains the hand-overs and sends changes
TICK_S = 0.25
#: reads from disk (a station's hooks, the due list as CSV) a minute from one address
FILE_READS_PER_MIN = 60
#: longest line / area filter of the due list, characters
FILTER_MAX = 64
COOKIE = "hw_session"
TEST_ID_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.:+-]{0,127}$")
DOWNLOADS = {"log.csv.gz": "application/gzip", "log.meta.yaml": "text/yaml; charset=utf-8",
             "events.jsonl": "application/x-ndjson", "result.json": "application/json"}


class ConsoleSettings:
    def __init__(self, *, listen=("127.0.0.1:8080",), cert_file=None, key_file=None,
                 users_file: str, read_without_login="local", session_ttl_s=28800.0,
                 lockout_attempts=5, lockout_s=300.0, login_failures_per_address=20,
                 allowed_hosts=(), report_jobs=1, report_queue=8, stream_connects_per_address=30,
                 stream_connects_total=120, door: DoorLimits | None = None, site_view: bool = True,
                 login_hashes_per_s=4.0, login_hash_burst=10, login_hashes_per_user_per_s=1.0,
                 login_hash_burst_per_user=5):
        self.listen = tuple(listen)
        self.cert_file, self.key_file = cert_file, key_file
        self.users_file = users_file
        self.read_without_login = read_without_login
        self.session_ttl_s = float(session_ttl_s)
        self.lockout_attempts = int(lockout_attempts)
        self.lockout_s = float(lockout_s)
        self.login_failures_per_address = int(login_failures_per_address)
        self.allowed_hosts = tuple(allowed_hosts)
        self.report_jobs = int(report_jobs)
        self.report_queue = int(report_queue)
        self.stream_connects_per_address = int(stream_connects_per_address)
        self.stream_connects_total = int(stream_connects_total)
        #: the password-hashing budget (gateway/console/auth.py, Hasher)
        self.login_hashes_per_s = float(login_hashes_per_s)
        self.login_hash_burst = int(login_hash_burst)
        self.login_hashes_per_user_per_s = float(login_hashes_per_user_per_s)
        self.login_hash_burst_per_user = int(login_hash_burst_per_user)
        #: connection cap, request deadline, idle timeout (console.connections)
        self.door = door or DoorLimits(256, 10.0, 60.0, max_per_address=32)
        #: show the stations of the site's other boxes (console.site_view; gateway/console/site.py)
        self.site_view = bool(site_view)

    @classmethod
    def from_config(cls, cfg) -> ConsoleSettings:
        c = cfg.console
        users = c.users_file or os.path.join(cfg.recorder.dir, "console-users.json")
        return cls(listen=c.listen, cert_file=c.tls.cert_file, key_file=c.tls.key_file,
                   users_file=users, read_without_login=c.read_without_login,
                   session_ttl_s=c.session_ttl_s, lockout_attempts=c.lockout_attempts,
                   lockout_s=c.lockout_s, login_failures_per_address=c.login_failures_per_address,
                   allowed_hosts=c.allowed_hosts, report_jobs=c.report_jobs,
                   report_queue=c.report_queue,
                   stream_connects_per_address=c.stream_connects_per_address,
                   stream_connects_total=c.stream_connects_total,
                   door=DoorLimits.from_config(c.connections),
                   site_view=bool(c.site_view),
                   login_hashes_per_s=c.login_hashes_per_s, login_hash_burst=c.login_hash_burst,
                   login_hashes_per_user_per_s=c.login_hashes_per_user_per_s,
                   login_hash_burst_per_user=c.login_hash_burst_per_user)


def parse_listen(addr: str) -> tuple[str, int]:
    host, sep, port = str(addr).rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"console.listen {addr!r}: expected host:port")
    return host.strip("[]") or "0.0.0.0", int(port)


def _is_loopback(remote: str | None) -> bool:
    try:
        return ipaddress.ip_address(remote or "").is_loopback
    except ValueError:
        return False


class _Client:
    def __init__(self):
        self.q: asyncio.Queue = asyncio.Queue(CLIENT_QUEUE)
        self.dropped = False


class ConsoleServer:
    """One console per process: every station of the fleet, on its own thread and loop."""

    def __init__(self, settings: ConsoleSettings, stations: dict[str, str], ts: float = 0.02,
                 mqtt_enabled: dict[str, bool] | None = None,
                 places: dict[str, tuple[str, str]] | None = None):
        """``stations``: station id → its records folder (recorder.dir/<id>); ``mqtt_enabled``:
        stations that report over MQTT (the others show no MQTT link); ``places``: station id →
        (station.line, station.area) for the due list's columns and filters."""
        self.settings = settings
        self.ts = ts
        self.records = dict(stations)
        self.feeds = {name: StationFeed(name, ts) for name in stations}
        for name, on in (mqtt_enabled or {}).items():
            self.feeds[name].mqtt_enabled = bool(on)
        for name, (line, area) in (places or {}).items():
            if name in self.feeds:
                self.feeds[name].line, self.feeds[name].area = str(line or ""), str(area or "")
        #: the stations of the site's other boxes (fed by one MQTT session of this box: attach_site)
        self.site: SiteView | None = SiteView(set(stations)) if settings.site_view else None
        self._site_carrier: str | None = None
        self.tl = ThreadLoop("console")
        self.sessions = auth.Sessions(settings.session_ttl_s)
        self.lockout = auth.Lockout(settings.lockout_attempts, settings.lockout_s)
        self.hasher = auth.Hasher(settings.login_hashes_per_s, settings.login_hash_burst,
                                  settings.login_hashes_per_user_per_s,
                                  settings.login_hash_burst_per_user)
        self.hosts = HostAllow(settings.allowed_hosts, (parse_listen(a)[0] for a in settings.listen))
        self.reports = ReportPool(settings.report_jobs, settings.report_queue)
        self.stream_rate = RateBound(settings.stream_connects_per_address)
        self.stream_rate_all = RateBound(settings.stream_connects_total)
        self.file_rate = RateBound(FILE_READS_PER_MIN)
        self.refusals = LogLimit(log)
        self.clients: dict[str, set[_Client]] = {n: set() for n in stations}
        self.urls: list[str] = []
        self.dropped_clients = 0
        self.cpu_s = 0.0
        self._runner: web.AppRunner | None = None
        self.door: AiohttpDoor | None = None
        self._tick_task: asyncio.Task | None = None
        self._cache = tempfile.mkdtemp(prefix="hookwatch-console-")
        self._campaign_busy = False
        self._campaign_n = 0
        self._rebuilding: set[str] = set()
        self.error: str | None = None

    # ----------------------------------------------------------------- lifecycle (any thread)
    def output_for(self, station: StationView) -> ConsoleOutput:
        """The station output that feeds this console (one per Station object)."""
        return ConsoleOutput(self.feeds[station.id], station)

    def attach_site(self, station_id: str, base_topic: str,
                    add_feed: Callable[[tuple[str, ...], Callable[[str, bytes], object]], None]) -> bool:
        """Let the site view ride on the MQTT session of station ``station_id`` (``add_feed``: its
        pump's :meth:`~gateway.northbound.mqtt_pump.MqttPump.add_site_feed`): the first station
        with MQTT carries it, and carries it again when it is rebuilt. True when attached."""
        site = self.site
        if site is None or (self._site_carrier not in (None, station_id)):
            return False
        site.filters = site_filters(base_topic)
        self._site_carrier = station_id
        add_feed(site.filters, site.receive)
        log.info("console: the site view reads %s (on the MQTT session of %s)",
                 ", ".join(site.filters), station_id)
        return True

    def add_station(self, name: str, records_dir: str, mqtt_enabled: bool = False,
                    timeout: float = 10.0, line: str = "", area: str = "") -> None:
        """A station that joined while the console runs (a fleet's SIGHUP with a new station
        file): its feed is added on the console's loop, where every handler reads the feeds."""
        async def add() -> None:
            if name in self.feeds:
                return
            feed = StationFeed(name, self.ts)
            feed.mqtt_enabled = bool(mqtt_enabled)
            feed.line, feed.area = str(line or ""), str(area or "")
            self.records = {**self.records, name: records_dir}
            self.clients = {**self.clients, name: set()}
            self.feeds = {**self.feeds, name: feed}
        if self.site is not None:
            self.site.local.add(name)
        if self.tl.running:
            self.tl.submit(add()).result(timeout)

    def start(self, timeout: float = 10.0) -> list[str]:
        """Start the thread and listen; returns the URLs. A port in use is logged, not raised."""
        self.tl.start()
        try:
            self.urls = self.tl.submit(self._start()).result(timeout)
        except Exception as e:  # the stations run on without a console
            self.error = f"{type(e).__name__}: {e}"
            log.error("console not started: %s", self.error)
            self.urls = []
        return self.urls

    def stop(self, timeout: float = 5.0) -> None:
        try:
            self.tl.submit(self._stop()).result(timeout)
        except Exception as e:
            log.warning("console stop: %s", e)
        self.tl.stop(timeout)
        shutil.rmtree(self._cache, ignore_errors=True)

    # ----------------------------------------------------------------- on the console loop
    async def _start(self) -> list[str]:
        lim = self.settings.door
        app = self.make_app()
        # the door's middleware first: a request's body is read within its deadline (gateway/doors.py);
        # the console's own server logger (malformed requests: one rate-limited line, no traceback)
        app.middlewares.insert(0, door_middleware())
        self._runner = web.AppRunner(app, shutdown_timeout=1.0,
                                     **{**door_runner_kwargs(lim), "logger": ServerLog(log, self.refusals)})
        await self._runner.setup()
        ctx = None
        if self.settings.cert_file and self.settings.key_file:
            ctx = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            ctx.load_cert_chain(self.settings.cert_file, self.settings.key_file)
        # one door for every listen address: one connection cap, deadlines, accept-error pause
        self.door = AiohttpDoor("console", lim, self._runner, ssl_context=ctx, logger=log)
        urls = []
        for addr in self.settings.listen:
            host, port = parse_listen(addr)
            s = await self.door.listen(host, port)
            h, p = s.getsockname()[:2]
            shown = f"[{h}]" if ":" in h else h
            urls.append(f"{'https' if ctx else 'http'}://{shown}:{p}/")
        self._tick_task = asyncio.get_running_loop().create_task(self._ticker())
        for u in urls:
            log.info("console on %s", u)
        return urls

    async def _stop(self) -> None:
        if self._tick_task is not None:
            self._tick_task.cancel()
        self.reports.cancel_all()
        for cs in self.clients.values():
            for c in list(cs):
                c.dropped = True
                try:
                    c.q.put_nowait(None)
                except asyncio.QueueFull:
                    pass
        if self.door is not None:
            await self.door.close()
        if self._runner is not None:
            await self._runner.cleanup()
        self._refusal_log.close()       # the counts of the last window, and no timer after
        self.refusals.close()
        if self.site is not None:
            self.site.close()
        self.hasher.close()

    def make_app(self) -> web.Application:
        app = web.Application(client_max_size=MAX_BODY, middlewares=[self._guard])
        r = app.router
        r.add_get("/", self.h_index)
        r.add_get("/api/fleet", self.h_fleet)
        r.add_get("/api/session", self.h_session)
        r.add_post("/api/login", self.h_login)
        r.add_post("/api/logout", self.h_logout)
        r.add_get("/api/station/{sid}", self.h_station)
        r.add_get("/api/station/{sid}/stream", self.h_stream)
        r.add_post("/api/station/{sid}/command", self.h_command)
        r.add_get("/api/station/{sid}/tests", self.h_tests)
        r.add_get("/api/station/{sid}/hooks", self.h_hooks)
        r.add_get("/api/station/{sid}/journal", self.h_journal)
        r.add_get("/api/due", self.h_due)
        r.add_get("/api/due.csv", self.h_due_csv)
        r.add_get("/api/station/{sid}/tests/{tid}/fig7.png", self.h_fig7)
        r.add_get("/api/station/{sid}/tests/{tid}/files/{name}", self.h_file)
        r.add_post("/api/campaign", self.h_campaign_run)
        r.add_get("/api/campaign/{cid}/{path:.+}", self.h_campaign_file)
        r.add_static("/static/", STATIC, show_index=False, follow_symlinks=False)
        return app

    async def _ticker(self) -> None:
        while True:
            await asyncio.sleep(TICK_S)
            self.cpu_s = time.thread_time()      # CPU of the console's own thread (benchmarks)
            try:
                self.tick()
            except Exception:
                log.exception("console tick failed")

    def tick(self) -> None:
        for name, feed in self.feeds.items():
            gen = feed.series.gen
            changed = feed.drain()
            if feed.pending is not None and name not in self._rebuilding:
                self._rebuild(name, feed)
            clients = self.clients[name]
            if not clients or not changed:
                if changed:
                    feed.series.take_changes()
                continue
            if feed.series.gen != gen:
                feed.series.take_changes()
                msg = feed.snapshot()
            else:
                ch = feed.series.take_changes()
                msg = {"type": "update", "gen": feed.series.gen, "from": ch[0] if ch else None,
                       "rows": ch[1] if ch else [], "markers": feed.markers,
                       "summary": feed.summary(), "events": list(feed.events)[-20:]}
            data = ("data: " + safeout.dumps(msg) + "\n\n").encode()
            for c in list(clients):
                try:
                    c.q.put_nowait(data)
                except asyncio.QueueFull:      # a slow browser is dropped, never waited for
                    self._drop(name, c, "queue full")

    def _rebuild(self, name: str, feed: StationFeed) -> None:
        """The hand-over lost records of a running test: read the test so far from the recorder's
        log on disk (in a worker thread), then add the live tail kept meanwhile."""
        path = os.path.join(self.records[name], feed.test_id or "", "log.csv.gz")
        self._rebuilding.add(name)
        log.warning("console: %s: live data lost in the hand-over (%d items); rebuilding the curve "
                    "from %s", name, feed.dropped, path)

        def done(fut) -> None:
            self._rebuilding.discard(name)
            try:
                feed.rebuild_from(fut.result())
            except Exception as e:       # no log yet or unreadable: the live tail goes on alone
                log.error("console: %s: cannot read %s: %s", name, path, e)
                pending, feed.pending = feed.pending or [], None
                for rec in pending:
                    feed.series.add(rec)

        fut = asyncio.get_running_loop().run_in_executor(None, series_from_log, path, feed.series.ts)
        fut.add_done_callback(done)

    def _drop(self, name: str, c: _Client, why: str) -> None:
        if c.dropped:
            return
        c.dropped = True
        self.clients[name].discard(c)
        self.dropped_clients += 1
        log.info("console: live client of %s dropped (%s)", name, why)
        while True:   # make room for the end marker
            try:
                c.q.get_nowait()
            except asyncio.QueueEmpty:
                break
        c.q.put_nowait(None)

    # ----------------------------------------------------------------- security
    def _session(self, request) -> auth.Session | None:
        return self.sessions.get(request.cookies.get(COOKIE))

    def _may_read(self, request) -> bool:
        mode = self.settings.read_without_login
        if mode == "all" or (mode == "local" and _is_loopback(request.remote)):
            return True
        return self._session(request) is not None

    def _host_ok(self, request) -> bool:
        sock = request.transport.get_extra_info("sockname") if request.transport else None
        return self.hosts.allowed(request.headers.get("Host"), sock[0] if sock else None)

    def _refuse(self, request, status: int, kind: str, reason: str,
                headers: dict | None = None) -> web.Response:
        """A client error: a short answer, and one WARNING line per kind a minute (no traceback)."""
        self.refusals.warn(kind, "%s %s from %s refused (%d): %s", request.method,
                           _cut(request.path), request.remote, status, reason)
        return _err(status, reason, headers)

    @web.middleware
    async def _guard(self, request, handler):
        path = request.path
        if not self._host_ok(request):
            self.refusals.warn("host", "request for host %r from %s refused (421): not the console's "
                               "address nor in console.allowed_hosts", _cut(request.headers.get("Host", "")),
                               request.remote)
            return _err(421, "this console does not answer for that host name (console.allowed_hosts)")
        if request.method == "POST":
            if request.content_length is not None and request.content_length > MAX_BODY:
                return self._refuse(request, 413, "too large", f"request body larger than {MAX_BODY} bytes")
            origin = request.headers.get("Origin")
            if origin and origin.split("://", 1)[-1] != request.host:
                return _err(403, "cross-origin request refused")
            if path != "/api/login":
                s = self._session(request)
                if s is None:
                    return _err(401, "log in first")
                tok = request.headers.get("X-CSRF-Token", "")
                if not hmac.compare_digest(tok.encode(), s.csrf.encode()):
                    return _err(403, "missing or wrong CSRF token (X-CSRF-Token)")
        elif path.startswith("/api/") and path != "/api/session" and not self._may_read(request):
            return _err(401, "log in to read from this address")
        resp = await handler(request)
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        resp.headers.setdefault("X-Frame-Options", "DENY")
        resp.headers.setdefault("Content-Security-Policy",
                                "default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'")
        resp.headers.setdefault("Cache-Control", "no-store")
        return resp

    async def _json_body(self, request) -> dict:
        """The JSON object of a request; a client error (logged once a minute per kind) as
        :class:`_HttpError` with 400, 413 or 415 — never a 500."""
        def bad(status: int, kind: str, reason: str) -> _HttpError:
            self.refusals.warn(kind, "%s %s from %s refused (%d): %s", request.method,
                               _cut(request.path), request.remote, status, reason)
            return _HttpError(status, reason)
        if request.content_type != "application/json":
            raise bad(415, "content type", "request body must be application/json")
        try:
            body = await request.read()
        except web.HTTPRequestEntityTooLarge:
            raise bad(413, "too large", f"request body larger than {MAX_BODY} bytes") from None
        if nesting_depth(body, MAX_JSON_DEPTH) > MAX_JSON_DEPTH:
            raise bad(400, "deep JSON", f"JSON nested deeper than {MAX_JSON_DEPTH} levels")
        try:
            data = json.loads(body.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            raise bad(400, "bad JSON", "request body is not JSON") from None
        if not isinstance(data, dict):
            raise bad(400, "bad JSON", "request body must be a JSON object")
        return data

    # ----------------------------------------------------------------- handlers
    async def h_index(self, request):
        return web.FileResponse(os.path.join(STATIC, "index.html"))

    def _feed(self, request) -> StationFeed:
        f = self.feeds.get(request.match_info["sid"])
        if f is None:
            raise _HttpError(404, f"no station {request.match_info['sid']!r}")
        return f

    def _with_site(self, request) -> bool:
        return request.query.get("site") in ("1", "true") and self.site is not None

    def _cards(self, request) -> list[dict[str, Any]]:
        """This box's fleet cards (``remote`` false), and with ``?site=1`` the site view's
        cards of the site's other boxes (``remote`` true: read-only)."""
        cards = [{**f.summary(), "remote": False} for f in self.feeds.values()]
        if self._with_site(request):
            assert self.site is not None
            cards.extend(self.site.cards())
        return cards

    def _site_info(self) -> dict[str, Any]:
        site = self.site
        return {"enabled": site is not None, "fed": site is not None and site.filters is not None,
                "stations": site.stations() if site is not None else 0,
                "refused": site.counters["refused"] if site is not None else 0}

    async def h_fleet(self, request):
        return _json({"stations": self._cards(request), "site": self._site_info(),
                      "time": time.time(),
                      "console": {"cpu_s": self.cpu_s, "dropped_clients": self.dropped_clients,
                                  "live_clients": sum(len(c) for c in self.clients.values())}})

    async def h_session(self, request):
        s = self._session(request)
        if s is None:
            return _json({"user": None, "read": self._may_read(request)})
        return _json({"user": s.user, "csrf": s.csrf, "read": True})

    async def h_login(self, request):
        try:
            data = await self._json_body(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        user, pw = data.get("user"), data.get("password")
        if not isinstance(user, str) or not isinstance(pw, str) or not auth.USER_RE.match(user) \
                or len(pw) > auth.PASSWORD_MAX:
            return _err(400, "user and password required")
        remote = request.remote or "?"
        # checked and counted in one step (no await in between): a burst gets no more tries
        pair, addr = f"ua:{remote} {user}", f"a:{remote}"
        left = self.lockout.attempt({pair: self.settings.lockout_attempts,
                                     addr: self.settings.login_failures_per_address})
        if left > 0:
            self.refusals.warn("locked out " + remote, "login of %r from %s refused: locked out "
                               "(%.0f s left)", user, remote, left)
            return _err(429, f"too many failed logins; try again in {left:.0f} s",
                        headers={"Retry-After": str(int(left) + 1)})
        # the hashing budget (after the lockout, which costs no hash): none beyond it; checked
        # here and taken below, with no await in between. Not a try: the attempt is taken back
        wait = self.hasher.wait(user)
        if wait > 0:
            self.lockout.forgive(one=(pair, addr))
            self.hasher.refused += 1
            self.refusals.warn("hash budget", "login of %r from %s refused: over the password-"
                               "hashing budget (%d refused so far)", user, remote, self.hasher.refused)
            return _err(429, "too many logins right now; try again shortly",
                        headers={"Retry-After": str(max(1, math.ceil(wait)))})
        try:
            users = auth.load_users(self.settings.users_file)
        except auth.UsersError as e:
            self.lockout.forgive(one=(pair, addr))
            log.error("console: %s", e)
            return _err(500, "users file unreadable; see the gateway log")
        # an unknown user name: the same work as a real check, so the answer time does not tell
        # which users exist; one hash of the budget either way
        self.hasher.take(user)
        ok = await self.hasher.verify(pw, users.get(user))
        if not ok:
            self.refusals.warn("failed login " + remote, "failed login of %r from %s", user, remote)
            return _err(401, "wrong user or password")
        self.lockout.forgive(clear=(pair,), one=(addr,))
        self.sessions.drop(request.cookies.get(COOKIE))
        token, s = self.sessions.create(user, remote)
        log.info("console: %s logged in from %s", user, remote)
        resp = _json({"user": user, "csrf": s.csrf})
        resp.set_cookie(COOKIE, token, httponly=True, samesite="Strict", path="/",
                        secure=bool(self.settings.cert_file), max_age=int(self.settings.session_ttl_s))
        return resp

    async def h_logout(self, request):
        self.sessions.drop(request.cookies.get(COOKIE))
        resp = _json({"user": None})
        resp.del_cookie(COOKIE, path="/")
        return resp

    async def h_station(self, request):
        try:
            f = self._feed(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        return _json(f.snapshot())

    async def h_stream(self, request):
        try:
            f = self._feed(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        # connect churn is bounded per address and in all: each connect costs a snapshot
        wait = self.stream_rate.take(request.remote or "?") or self.stream_rate_all.take()
        if wait > 0:
            return self._refuse(request, 429, "stream rate", "too many live-stream connects; "
                                f"try again in {math.ceil(wait)} s",
                                headers={"Retry-After": str(math.ceil(wait))})
        if sum(len(c) for c in self.clients.values()) >= MAX_CLIENTS:
            return _err(503, f"too many live clients (at most {MAX_CLIENTS})")
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                           "Cache-Control": "no-store", "X-Accel-Buffering": "no"})
        await resp.prepare(request)
        _small_send_buffer(request.transport)
        c = _Client()
        f.drain()
        first = ("data: " + safeout.dumps(f.snapshot()) + "\n\n").encode()
        self.clients[f.name].add(c)
        try:
            await asyncio.wait_for(resp.write(first), WRITE_TIMEOUT_S)
            while True:
                data = await c.q.get()
                if data is None:
                    break
                await asyncio.wait_for(resp.write(data), WRITE_TIMEOUT_S)
        except TimeoutError:
            self._drop(f.name, c, "write timed out")
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            self.clients[f.name].discard(c)
            if c.dropped and request.transport is not None:
                request.transport.close()
        return resp

    #: refused commands: one log line per kind per minute, with the count (gateway/ratelog.py)
    _refusal_log = RateLog(log)

    async def h_command(self, request):
        """A command from the console: the body through the one bounded intake
        (gateway/northbound/cmdparse.py: size, depth, strict types, bounded strings), then the
        station's validation through its refusal gate (bounded ``command_rejected`` events)."""
        try:
            f = self._feed(request)
            body = await request.read()
        except _HttpError as e:
            return _err(e.status, e.reason)
        except web.HTTPRequestEntityTooLarge:
            return _err(413, f"request body larger than {MAX_BODY} bytes")
        s = self._session(request)
        if s is None:
            return _err(401, "log in first")
        source = f"console:{s.user}"
        cmd = intake(None, body, source)
        st, loop = f.station, f.loop
        if isinstance(cmd, Rejection):
            if st is not None and loop is not None:
                name = cmd.reason.split(":", 1)[0]
                call_soon_on(loop, st.refused, rejected_event_data(name, cmd, source))
            return self._reply(f, s, "command", cmd, status=400)
        kind = cmd.kind.value
        hook = cmd.kind == CommandKind.HOOK_REPLACED
        if st is None or loop is None:
            return self._reply(f, s, kind, Rejection(False, f"station {f.name} is not running", None,
                                                     CODE["NO_STATION"]))
        try:
            fut = submit_to(loop, st.submit(cmd))   # the one hand-over (gateway/threadloop.py)
            if fut is None:
                raise RuntimeError("its loop is closed")
            reply = await asyncio.wait_for(asyncio.wrap_future(fut), 5.0)
        except (TimeoutError, RuntimeError) as e:
            reply = Rejection(False, f"the station did not answer ({type(e).__name__})", None,
                              CODE["NO_STATION"])
        if hook and reply.ok:
            log.info("console: %s: hook replaced by %s (new hook %s)", f.name, s.user,
                     _cut(str(cmd.args.get("sample_id", "(derived)"))))
        return self._reply(f, s, kind, reply)

    def _reply(self, f: StationFeed, s: auth.Session, kind: str, reply, status: int = 409) -> web.Response:
        """The answer: 200 accepted; 409 refused by the station; 400 refused by the intake (the
        request itself is malformed); ``reason`` and ``code`` as over MQTT and the PLC."""
        code = reply_code(reply)
        if reply.ok:
            log.info("console: command %s on %s by %s: accepted", kind, f.name, s.user)
        else:
            self._refusal_log.warning(("command", kind, int(code)), "console: command %s on %s by %s: refused: %s",
                                      kind, f.name, s.user, reply.reason)
        return _json({"ok": bool(reply.ok), "reason": reply.reason, "code": code},
                                 status=200 if reply.ok else status)

    # ----------------------------------------------------------------- campaign
    async def h_campaign_run(self, request):
        """Run the report (Tables 3–6, Figs. 7–9) over the ended tests of the chosen stations."""
        try:
            data = await self._json_body(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        stations = data.get("stations")
        if not isinstance(stations, list) or not stations or len(stations) > len(self.records) \
                or not all(isinstance(x, str) and x in self.records for x in stations):
            return _err(400, f"stations: a list of station names from {sorted(self.records)}")
        if self._campaign_busy:
            return _err(429, "a campaign report is already being made; try again when it is done")
        self._campaign_busy = True
        self._campaign_n += 1
        cid = f"c{self._campaign_n}"
        base = os.path.join(self._cache, cid)
        loop = asyncio.get_running_loop()
        try:
            n = await loop.run_in_executor(None, _campaign_inputs, self.records, sorted(set(stations)),
                                           os.path.join(base, "in"))
            if n == 0:
                return _err(409, "no ended tests in the chosen stations")
            try:
                rc, err = await self.reports.run("campaign:" + cid, lambda: _report_process(
                    [os.path.join(base, "in"), "--out", os.path.join(base, "out")], 600))
            except Busy as e:
                return self._refuse(request, 503, "report queue", "too many reports being made; "
                                    f"try again in {e.retry_after} s",
                                    headers={"Retry-After": str(e.retry_after)})
            if rc is None:
                return _err(504, "the report took longer than 10 minutes")
            if not os.path.isfile(os.path.join(base, "out", "report.html")):
                return _err(500, "no report: " + err)
        finally:
            self._campaign_busy = False
        log.info("console: campaign report %s over %s (%d tests) by %s", cid, ", ".join(stations), n,
                 getattr(self._session(request), "user", "?"))
        return _json({"ok": True, "tests": n, "url": f"/api/campaign/{cid}/report.html"})

    async def h_campaign_file(self, request):
        cid, path = request.match_info["cid"], request.match_info["path"]
        if not re.match(r"^c[0-9]{1,6}$", cid) or not CAMPAIGN_FILE_RE.match(path):
            return _err(404, "no such file")
        f = os.path.join(self._cache, cid, "out", path)
        if not os.path.isfile(f):
            return _err(404, "no such file")
        return web.FileResponse(f, headers={"Content-Type": CAMPAIGN_TYPES[os.path.splitext(f)[1]]})

    # ----------------------------------------------------------------- history
    def _station_dir(self, request) -> str:
        sid = request.match_info["sid"]
        d = self.records.get(sid)
        if d is None:
            raise _HttpError(404, f"no station {sid!r}")
        return d

    def _test_dir(self, request) -> str:
        d = self._station_dir(request)
        tid = request.match_info["tid"]
        if not TEST_ID_RE.match(tid) or not os.path.isdir(os.path.join(d, tid)):
            raise _HttpError(404, f"no test {tid!r}")
        return os.path.join(d, tid)

    async def h_tests(self, request):
        try:
            d = self._station_dir(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        tests = await asyncio.get_running_loop().run_in_executor(None, list_tests, d)
        return _json({"station": request.match_info["sid"], "tests": tests})

    def _file_rate(self, request) -> web.Response | None:
        """Disk reads (hooks, the CSV) are bounded per client address: 429 + Retry-After."""
        wait = self.file_rate.take(request.remote or "?")
        if wait > 0:
            return self._refuse(request, 429, "file rate", "too many reads from disk; "
                                f"try again in {math.ceil(wait)} s",
                                headers={"Retry-After": str(math.ceil(wait))})
        return None

    async def h_hooks(self, request):
        """The station's successive hooks with their lives, newest first (hooks.jsonl, bounded)."""
        try:
            d = self._station_dir(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        refused = self._file_rate(request)
        if refused is not None:
            return refused
        hooks = await asyncio.get_running_loop().run_in_executor(None, hook_history, d)
        return _json({"station": request.match_info["sid"], "hooks": hooks})

    async def h_journal(self, request):
        """The alarm journal of a station: every ISA-18.2 transition with who and when, oldest
        first (what the recorded tests hold, then what the console saw live; bounded)."""
        try:
            f = self._feed(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        f.drain()
        if not f.journal_seeded:
            f.journal_seeded = True
            try:
                old = await asyncio.get_running_loop().run_in_executor(
                    None, journal_from_disk, self.records[f.name])
            except OSError as e:
                log.warning("console: %s: recorded alarm journal unreadable: %s", f.name, e)
                old = []
            f.drain()
            f.seed_journal(old)
        return _json({"station": f.name, "journal": list(f.journal)})

    def _due_filters(self, request) -> tuple[str | None, str | None]:
        out = []
        for name in ("line", "area"):
            v = request.query.get(name)
            if v is not None and (len(v) > FILTER_MAX or not v.isprintable()):
                raise _HttpError(400, f"{name}: at most {FILTER_MAX} printable characters")
            out.append(v if v else None)
        return out[0], out[1]

    def _due(self, request) -> list[dict[str, Any]]:
        line, area = self._due_filters(request)
        for f in self.feeds.values():
            f.drain()
        return due_list(self._cards(request), line, area)

    async def h_due(self, request):
        """The planner's due list: every station, the soonest due first (docs/console.md)."""
        try:
            rows = self._due(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        cards = self._cards(request)
        return _json({"time": time.time(), "columns": list(DUE_COLUMNS), "stations": rows,
                      "lines": sorted({c["line"] for c in cards if c.get("line")}),
                      "areas": sorted({c["area"] for c in cards if c.get("area")}),
                      "site": self._site_info()})

    async def h_due_csv(self, request):
        """The due list as CSV (RFC 4180; every cell defused against formulas in any locale:
        gateway.safeout.csv_text)."""
        try:
            rows = self._due(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        refused = self._file_rate(request)
        if refused is not None:
            return refused
        text = safeout.csv_text([DUE_COLUMNS, *([r.get(c) for c in DUE_COLUMNS] for r in rows)])
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        return web.Response(body=text.encode("utf-8"), headers={
            "Content-Type": "text/csv; charset=utf-8",
            "Content-Disposition": f'attachment; filename="due-{stamp}.csv"'})

    async def h_file(self, request):
        try:
            td = self._test_dir(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        name = request.match_info["name"]
        if name not in DOWNLOADS or not os.path.isfile(os.path.join(td, name)):
            return _err(404, f"no file {name!r}")
        tid = os.path.basename(td)
        return web.FileResponse(os.path.join(td, name), headers={
            "Content-Type": DOWNLOADS[name],
            "Content-Disposition": f'attachment; filename="{tid}-{name}"'})

    async def _fig7_job(self, td: str, out: str) -> tuple[str | None, str]:
        png = _find_png(out)
        if png is not None:
            return png, ""
        rc, err = await _report_process([td, "--out", out], 120)
        png = _find_png(out)
        return png, ("timeout" if rc is None else err)

    async def h_fig7(self, request):
        try:
            td = self._test_dir(request)
        except _HttpError as e:
            return _err(e.status, e.reason)
        if not os.path.isfile(os.path.join(td, "result.json")):
            return _err(409, "the test is still running; its figure comes when it has ended")
        key = request.match_info["sid"] + "__" + os.path.basename(td)
        out = os.path.join(self._cache, key)
        png = _find_png(out)
        if png is None:
            # the report runs as its own process at low priority (no figure delays a slot), at
            # most console.report_jobs at once; requests for the same figure share its process
            try:
                png, why = await self.reports.run("fig7:" + key, lambda: self._fig7_job(td, out))
            except Busy as e:
                return self._refuse(request, 503, "report queue", "too many reports being made; "
                                    f"try again in {e.retry_after} s",
                                    headers={"Retry-After": str(e.retry_after)})
            if png is None:
                return _err(504 if why == "timeout" else 500, "the figure took too long"
                            if why == "timeout" else "no figure: " + why)
        return web.FileResponse(png, headers={"Content-Type": "image/png"})


async def _report_process(args: list[str], timeout_s: float) -> tuple[int | None, str]:
    """Run ``hookwatch report`` as a child at low priority: (exit code or None on timeout, the
    end of its stderr). The child is killed when it runs too long or the caller is cancelled."""
    p = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "gateway.cli", "report", *args, "-q", "--jobs", "1",
        stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
        preexec_fn=lambda: os.nice(10))
    try:
        _, err = await asyncio.wait_for(p.communicate(), timeout_s)
    except (TimeoutError, asyncio.CancelledError) as e:
        p.kill()
        await asyncio.shield(p.wait())
        if isinstance(e, asyncio.CancelledError):
            raise
        return None, ""
    return p.returncode, err.decode(errors="replace")[-300:]


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _campaign_inputs(records: dict[str, str], stations: list[str], into: str) -> int:
    """Hard-link (or copy) the ended tests of ``stations`` under ``into``; the count of tests."""
    n = 0
    for sid in stations:
        d = records[sid]
        for t in list_tests(d):
            if "result.json" not in t["files"] or "log.csv.gz" not in t["files"]:
                continue      # a running or broken test is not part of a campaign
            src = os.path.join(d, t["test_id"])
            dst = os.path.join(into, sid, t["test_id"])
            os.makedirs(dst, exist_ok=True)
            for name in ("log.csv.gz", "log.meta.yaml", "result.json"):
                if os.path.isfile(os.path.join(src, name)):
                    _link_or_copy(os.path.join(src, name), os.path.join(dst, name))
            n += 1
    return n


def _small_send_buffer(transport) -> None:
    """Bound what the kernel and the transport hold for one live client: a client that stops
    reading fills them within seconds, its queue fills, and it is dropped."""
    if transport is None:
        return
    sock = transport.get_extra_info("socket")
    try:
        if sock is not None:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SEND_BUFFER)
        transport.set_write_buffer_limits(high=SEND_BUFFER)
    except (OSError, AttributeError, NotImplementedError):
        pass


CAMPAIGN_FILE_RE = re.compile(r"^(report\.html|report\.md|problems\.txt|[A-Za-z0-9_.-]+\.csv|"
                              r"figures/[A-Za-z0-9_.-]+\.png)$")
CAMPAIGN_TYPES = {".html": "text/html; charset=utf-8", ".md": "text/markdown; charset=utf-8",
                  ".txt": "text/plain; charset=utf-8", ".csv": "text/csv; charset=utf-8",
                  ".png": "image/png"}


def _find_png(out: str) -> str | None:
    d = os.path.join(out, "figures")
    try:
        names = sorted(n for n in os.listdir(d) if n.startswith("fig7") and n.endswith(".png"))
    except OSError:
        return None
    return os.path.join(d, names[0]) if names else None


def list_tests(station_dir: str, limit: int = 500) -> list[dict[str, Any]]:
    """The recorded tests of a station folder, newest first."""
    try:
        names = sorted((n for n in os.listdir(station_dir)
                        if TEST_ID_RE.match(n) and os.path.isdir(os.path.join(station_dir, n))),
                       reverse=True)[:limit]
    except OSError:
        return []
    out = []
    for n in names:
        td = os.path.join(station_dir, n)
        item: dict[str, Any] = {"test_id": n, "files": [f for f in DOWNLOADS if os.path.isfile(os.path.join(td, f))]}
        try:
            with open(os.path.join(td, "result.json"), encoding="utf-8") as fh:
                r = json.load(fh)
            m = r.get("method", r) if isinstance(r, dict) else {}
            item.update(status=m.get("status"), t_life=m.get("t_life"), mu_ss=m.get("mu_ss"),
                        mu_th=m.get("mu_th"), headroom=m.get("headroom"),
                        test_status=r.get("test_status"), end_reason=r.get("end_reason"),
                        sample_id=r.get("sample_id"), grade=r.get("grade"))
        except (OSError, ValueError, AttributeError):
            item.update(status=None, test_status="running" if "result.json" not in item["files"] else "unreadable")
        out.append(item)
    return out


class _HttpError(Exception):
    def __init__(self, status: int, reason: str):
        super().__init__(reason)
        self.status, self.reason = status, reason


def _cut(text: str, n: int = 60) -> str:
    """Client text quoted in a log line: at most ``n`` characters, no control characters."""
    t = "".join(ch if ch.isprintable() else "?" for ch in str(text)[:n])
    return t if len(text) <= n else f"{t}… ({len(text)} chars)"


def _err(status: int, reason: str, headers: dict | None = None) -> web.Response:
    return _json({"ok": False, "reason": reason}, status=status, headers=headers)
