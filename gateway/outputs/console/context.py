"""What the console's route modules share (:class:`ConsoleContext`): the stations' feeds and
records folders, the live clients, the sessions and login budget, the door bounds; and the request
helpers every room uses (who is logged in, may this address read, a refusal logged once a minute,
a bounded JSON body, the station or test a URL names).

The app (``app.py``) makes one context and hands it to each route module; a route module sees the
console only through it, never the app.
"""
from __future__ import annotations

import asyncio
import json
import logging
import math
import os
import tempfile

from aiohttp import web

from ...core.command_intake import nesting_depth
from . import auth
from .common import (
    CLIENT_QUEUE,
    COOKIE,
    FILE_READS_PER_MIN,
    MAX_BODY,
    MAX_JSON_DEPTH,
    HttpError,
    cut,
    err,
    is_loopback,
)
from .feed import StationFeed
from .guard import HostAllow, LogLimit, RateBound, ReportPool
from .recorded import TEST_ID_RE
from .settings import ConsoleSettings, parse_listen
from .site import SiteView

log = logging.getLogger("hookwatch.console")


class Client:
    """One live (SSE) client: its bounded queue of messages, and whether it was dropped."""

    def __init__(self):
        self.q: asyncio.Queue = asyncio.Queue(CLIENT_QUEUE)
        self.dropped = False


class ConsoleContext:
    """The console's shared state and request helpers (one per console, used on its loop)."""

    def __init__(self, settings: ConsoleSettings, stations: dict[str, str], ts: float,
                 mqtt_enabled: dict[str, bool] | None = None,
                 places: dict[str, tuple[str, str]] | None = None):
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
        self.clients: dict[str, set[Client]] = {n: set() for n in stations}
        self.dropped_clients = 0
        self.cpu_s = 0.0
        #: the console's scratch folder (figures, campaign reports); removed at stop
        self.cache = tempfile.mkdtemp(prefix="hookwatch-console-")

    # ----------------------------------------------------------------- live clients
    def drop(self, name: str, c: Client, why: str) -> None:
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
    def session(self, request) -> auth.Session | None:
        return self.sessions.get(request.cookies.get(COOKIE))

    def may_read(self, request) -> bool:
        mode = self.settings.read_without_login
        if mode == "all" or (mode == "local" and is_loopback(request.remote)):
            return True
        return self.session(request) is not None

    def host_ok(self, request) -> bool:
        sock = request.transport.get_extra_info("sockname") if request.transport else None
        return self.hosts.allowed(request.headers.get("Host"), sock[0] if sock else None)

    def refuse(self, request, status: int, kind: str, reason: str,
               headers: dict | None = None) -> web.Response:
        """A client error: a short answer, and one WARNING line per kind a minute (no traceback)."""
        self.refusals.warn(kind, "%s %s from %s refused (%d): %s", request.method,
                           cut(request.path), request.remote, status, reason)
        return err(status, reason, headers)

    async def json_body(self, request) -> dict:
        """The JSON object of a request; a client error (logged once a minute per kind) as
        :class:`HttpError` with 400, 413 or 415 — never a 500."""
        def bad(status: int, kind: str, reason: str) -> HttpError:
            self.refusals.warn(kind, "%s %s from %s refused (%d): %s", request.method,
                               cut(request.path), request.remote, status, reason)
            return HttpError(status, reason)
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

    def file_reads(self, request) -> web.Response | None:
        """Disk reads (hooks, the CSV) are bounded per client address: 429 + Retry-After."""
        wait = self.file_rate.take(request.remote or "?")
        if wait > 0:
            return self.refuse(request, 429, "file rate", "too many reads from disk; "
                               f"try again in {math.ceil(wait)} s",
                               headers={"Retry-After": str(math.ceil(wait))})
        return None

    # ----------------------------------------------------------------- what a URL names
    def feed(self, request) -> StationFeed:
        f = self.feeds.get(request.match_info["sid"])
        if f is None:
            raise HttpError(404, f"no station {request.match_info['sid']!r}")
        return f

    def station_dir(self, request) -> str:
        sid = request.match_info["sid"]
        d = self.records.get(sid)
        if d is None:
            raise HttpError(404, f"no station {sid!r}")
        return d

    def test_dir(self, request) -> str:
        d = self.station_dir(request)
        tid = request.match_info["tid"]
        if not TEST_ID_RE.match(tid) or not os.path.isdir(os.path.join(d, tid)):
            raise HttpError(404, f"no test {tid!r}")
        return os.path.join(d, tid)
