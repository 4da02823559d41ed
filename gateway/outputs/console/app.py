"""The operator console: an aiohttp server on its own thread and loop (:class:`ConsoleServer`).

Pages (static, shipped in ``static/``; uPlot vendored, nothing from the internet):
``/`` fleet, ``/#/station/<id>`` station, ``/#/history/<id>`` history.

This module is the app and its lifecycle: the thread and loop, the listening door, the guard
middleware every request passes, the ticker that sends the live changes. The routes live in
rooms by subject, each given the console's shared :class:`~gateway.outputs.console.context.ConsoleContext`:
``routes_fleet.py`` (the page, fleet cards, the due list), ``routes_session.py`` (login, logout,
session), ``routes_station.py`` (a station live, its commands and history), ``routes_campaign.py``
(campaign reports).

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
    GET  /api/boxes                         the site's boxes by their config reports
    GET  /api/values                        the station values the page shows, with their labels
    GET  /api/station/<id>/tests/<test>/fig7.png        the report's Fig. 7 of a test
    GET  /api/station/<id>/tests/<test>/files/<name>    log.csv.gz, log.meta.yaml, events.jsonl, result.json
    GET  /api/session                       who is logged in (+ CSRF token)
    POST /api/login  {user, password}       → session cookie + CSRF token
    POST /api/logout
    POST /api/station/<id>/command {command, ...}   start | stop | ack | setpoint | hook_replaced |
                                            shelve | unshelve | out_of_service | in_service
    POST /api/campaign {stations: [...]}    a campaign report over the ended tests of the stations
    GET  /api/campaign/<cid>/<path>         its files

Every POST other than login needs the session cookie and the ``X-CSRF-Token`` header; commands go
through the station's one validation (``Station.submit`` on the station's own loop) and are logged
with the user.
"""
from __future__ import annotations

import asyncio
import hmac
import logging
import os
import shutil
import ssl
import time
from collections.abc import Callable

from aiohttp import web

from ...core.ports import StationView
from ...plumbing import safeout
from ...plumbing.doors import AiohttpDoor, door_middleware, door_runner_kwargs
from ...plumbing.threadloop import ThreadLoop
from . import auth
from .common import MAX_BODY, STATIC, TICK_S, cut, err
from .context import ConsoleContext
from .feed import ConsoleOutput, StationFeed, series_from_log
from .guard import ServerLog
from .routes_campaign import CampaignRoutes
from .routes_fleet import FleetRoutes
from .routes_session import SessionRoutes
from .routes_station import StationRoutes
from .settings import ConsoleSettings, parse_listen
from .site import SiteView
from .site import filters as site_filters

log = logging.getLogger("hookwatch.console")


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
        #: what the route modules share (feeds, records, clients, sessions, bounds)
        self.ctx = ctx = ConsoleContext(settings, stations, ts, mqtt_enabled, places)
        self._site_carrier: str | None = None
        self.tl = ThreadLoop("console")
        self.station_routes = StationRoutes(ctx)
        self.routes = (FleetRoutes(ctx), SessionRoutes(ctx), self.station_routes, CampaignRoutes(ctx))
        self.urls: list[str] = []
        self._runner: web.AppRunner | None = None
        self.door: AiohttpDoor | None = None
        self._tick_task: asyncio.Task | None = None
        self._rebuilding: set[str] = set()
        self.error: str | None = None

    # the context's members under their old names (compose.py, the supervisor, tests)
    @property
    def feeds(self) -> dict[str, StationFeed]:
        return self.ctx.feeds

    @property
    def records(self) -> dict[str, str]:
        return self.ctx.records

    @property
    def site(self) -> SiteView | None:
        return self.ctx.site

    @property
    def hasher(self) -> auth.Hasher:
        return self.ctx.hasher

    @property
    def _cache(self) -> str:
        return self.ctx.cache

    # ----------------------------------------------------------------- lifecycle (any thread)
    def output_for(self, station: StationView) -> ConsoleOutput:
        """The station output that feeds this console (one per Station object)."""
        return ConsoleOutput(self.feeds[station.id], station)

    def attach_site(self, station_id: str, base_topic: str,
                    add_feed: Callable[[tuple[str, ...], Callable[[str, bytes], object]], None]) -> bool:
        """Let the site view ride on the MQTT session of station ``station_id`` (``add_feed``: its
        pump's :meth:`~gateway.outputs.mqtt.pump.MqttPump.add_site_feed`): the first station
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
        ctx = self.ctx

        async def add() -> None:
            if name in ctx.feeds:
                return
            feed = StationFeed(name, self.ts)
            feed.mqtt_enabled = bool(mqtt_enabled)
            feed.line, feed.area = str(line or ""), str(area or "")
            ctx.records = {**ctx.records, name: records_dir}
            ctx.clients = {**ctx.clients, name: set()}
            ctx.feeds = {**ctx.feeds, name: feed}
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
        # the door's middleware first: a request's body is read within its deadline (gateway/plumbing/doors.py);
        # the console's own server logger (malformed requests: one rate-limited line, no traceback)
        app.middlewares.insert(0, door_middleware())
        self._runner = web.AppRunner(app, shutdown_timeout=1.0,
                                     **{**door_runner_kwargs(lim), "logger": ServerLog(log, self.ctx.refusals)})
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
        ctx = self.ctx
        if self._tick_task is not None:
            self._tick_task.cancel()
        ctx.reports.cancel_all()
        for cs in ctx.clients.values():
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
        self.station_routes.refusal_log.close()       # the counts of the last window, and no timer after
        ctx.refusals.close()
        if self.site is not None:
            self.site.close()
        ctx.hasher.close()

    def make_app(self) -> web.Application:
        app = web.Application(client_max_size=MAX_BODY, middlewares=[self._guard])
        for room in self.routes:
            room.add_to(app.router)
        app.router.add_static("/static/", STATIC, show_index=False, follow_symlinks=False)
        return app

    async def _ticker(self) -> None:
        while True:
            await asyncio.sleep(TICK_S)
            self.ctx.cpu_s = time.thread_time()      # CPU of the console's own thread (benchmarks)
            try:
                self.tick()
            except Exception:
                log.exception("console tick failed")

    def tick(self) -> None:
        ctx = self.ctx
        for name, feed in ctx.feeds.items():
            gen = feed.series.gen
            changed = feed.drain()
            if feed.pending is not None and name not in self._rebuilding:
                self._rebuild(name, feed)
            clients = ctx.clients[name]
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
                       "summary": feed.summary(values=True), "events": list(feed.events)[-20:]}
            data = ("data: " + safeout.dumps(msg) + "\n\n").encode()
            for c in list(clients):
                try:
                    c.q.put_nowait(data)
                except asyncio.QueueFull:      # a slow browser is dropped, never waited for
                    ctx.drop(name, c, "queue full")

    def _rebuild(self, name: str, feed: StationFeed) -> None:
        """The hand-over lost records of a running test: read the test so far from the recorder's
        log on disk (in a worker thread), then add the live tail kept meanwhile."""
        path = os.path.join(self.ctx.records[name], feed.test_id or "", "log.csv.gz")
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

    # ----------------------------------------------------------------- the guard of every request
    @web.middleware
    async def _guard(self, request, handler):
        ctx = self.ctx
        path = request.path
        if not ctx.host_ok(request):
            ctx.refusals.warn("host", "request for host %r from %s refused (421): not the console's "
                              "address nor in console.allowed_hosts", cut(request.headers.get("Host", "")),
                              request.remote)
            return err(421, "this console does not answer for that host name (console.allowed_hosts)")
        if request.method == "POST":
            if request.content_length is not None and request.content_length > MAX_BODY:
                return ctx.refuse(request, 413, "too large", f"request body larger than {MAX_BODY} bytes")
            origin = request.headers.get("Origin")
            if origin and origin.split("://", 1)[-1] != request.host:
                return err(403, "cross-origin request refused")
            if path != "/api/login":
                s = ctx.session(request)
                if s is None:
                    return err(401, "log in first")
                tok = request.headers.get("X-CSRF-Token", "")
                if not hmac.compare_digest(tok.encode(), s.csrf.encode()):
                    return err(403, "missing or wrong CSRF token (X-CSRF-Token)")
        elif path.startswith("/api/") and path != "/api/session" and not ctx.may_read(request):
            return err(401, "log in to read from this address")
        resp = await handler(request)
        resp.headers.setdefault("X-Content-Type-Options", "nosniff")
        resp.headers.setdefault("X-Frame-Options", "DENY")
        resp.headers.setdefault("Content-Security-Policy",
                                "default-src 'self'; img-src 'self' data:; style-src 'self' 'unsafe-inline'")
        resp.headers.setdefault("Cache-Control", "no-store")
        return resp
