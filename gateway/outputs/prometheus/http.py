"""Metrics, part 4: the HTTP endpoint — ``/metrics`` on aiohttp, behind a door.

One HTTP stack in the gateway (issue 23): the endpoint is an aiohttp server, like the console, on
its own thread and event loop (niced by :data:`SCRAPE_NICE`: a scrape yields the CPU to the
stations' slot threads), behind a :class:`~gateway.plumbing.doors.Door` like every listening port: at most
``metrics.connections.max_connections`` connections (within the process's descriptor budget; one
more is closed at once), a request must be complete within ``request_timeout_s`` of its first
byte (a trickling client is closed at that deadline, however it spreads its bytes: four or forty
trickling sockets cannot hold the endpoint), idle connections are closed after
``idle_timeout_s``, accept errors (EMFILE …) pause the door with one log line. GET/HEAD without a
body only (a body or a announced one: 413 at once), request line and each header at most
:data:`MAX_LINE` bytes (aiohttp's parser: 400). A port in use is a state (one log line, retried
every :data:`RETRY_S`), never a crash; the slot loop never waits for a scrape (the snapshots are
plain reads of the figures).
"""
from __future__ import annotations

import asyncio
import logging
import os
import threading
from collections.abc import Callable
from typing import Any

from aiohttp import web
from prometheus_client import CollectorRegistry, PlatformCollector, ProcessCollector

from ...plumbing.doors import AiohttpDoor, DoorLimits, door_middleware, door_runner_kwargs
from .exposition import CONTENT_TYPE, SnapshotCollector, render

log = logging.getLogger("hookwatch.metrics")

#: the endpoint's default connection cap (``metrics.connections.max_connections``)
MAX_CONNECTIONS = 8
#: a request must be complete this long after its first byte (``metrics.connections.request_timeout_s``)
REQUEST_TIMEOUT_S = 5.0
IDLE_TIMEOUT_S = 30.0
MAX_LINE = 8190
RETRY_S = 5.0
#: niceness added to the thread that answers scrapes
SCRAPE_NICE = 5
#: connections of one client address (``metrics.connections.max_per_address``)
MAX_PER_ADDRESS = 4
DEFAULT_LIMITS = DoorLimits(MAX_CONNECTIONS, REQUEST_TIMEOUT_S, IDLE_TIMEOUT_S,
                            max_per_address=MAX_PER_ADDRESS)


class EndpointSource:
    """A station's snapshot source on the endpoint of (``host``, ``port``) while started."""
    station_id: str
    host: str
    port: int
    endpoint: Endpoint | None
    #: the endpoint's door limits (the first source on a port sets them)
    limits: DoorLimits | None = None

    def snapshot(self) -> dict[str, Any]:
        raise NotImplementedError

    async def start(self) -> None:
        self.endpoint = endpoint(self.host, self.port, self.limits)
        self.endpoint.add_source(self.station_id, self.snapshot)

    async def stop(self) -> None:
        if self.endpoint is not None:
            ep, self.endpoint = self.endpoint, None
            ep.remove_source(self.station_id, self.snapshot)


class Endpoint:
    """``/metrics`` on (host, port), served by its own thread; stations add snapshot sources."""

    def __init__(self, host: str, port: int, limits: DoorLimits | None = None):
        self.host, self.port = host, int(port)
        self.limits = limits or DEFAULT_LIMITS
        self._sources: dict[str, Callable[[], dict]] = {}
        self._lock = threading.Lock()
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(SnapshotCollector(self.sources))
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)
        self.door: AiohttpDoor | None = None
        self.error: str | None = None
        self.listening = threading.Event()
        self.loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._bound: tuple[str, int] | None = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._main, name=f"metrics-{host}:{port}", daemon=True)
        self._thread.start()
        self._ready.wait(10)

    @property
    def address(self) -> tuple[str, int]:
        return self._bound or (self.host, self.port)

    @property
    def refused(self) -> int:
        d = self.door
        return d.counters["refused_connections"] if d is not None else 0

    def sources(self) -> list[Callable[[], dict]]:
        with self._lock:
            return list(self._sources.values())

    def add_source(self, name: str, fn: Callable[[], dict]) -> None:
        with self._lock:
            self._sources[name] = fn

    def remove_source(self, name: str, fn: Callable[[], dict] | None = None) -> None:
        """Remove a source (only ``fn`` if given: a rebuilt station may have replaced it)."""
        with self._lock:
            if fn is None or self._sources.get(name) == fn:
                self._sources.pop(name, None)

    # -- the endpoint's thread
    def _main(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                           os.getpriority(os.PRIO_PROCESS, 0) + SCRAPE_NICE)
        except (OSError, AttributeError):
            pass
        asyncio.run(self._serve())

    def make_app(self) -> web.Application:
        app = web.Application(client_max_size=1024, middlewares=[_no_body, door_middleware()])
        app.router.add_route("*", "/", self.h_index)
        app.router.add_route("*", "/metrics", self.h_metrics)
        return app

    async def _serve(self) -> None:
        self.loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        self._ready.set()
        runner = web.AppRunner(self.make_app(), handle_signals=False, shutdown_timeout=1.0,
                               max_line_size=MAX_LINE, max_field_size=MAX_LINE,
                               **door_runner_kwargs(self.limits))
        await runner.setup()
        logged = False
        try:
            while not self._stop.is_set():
                door = AiohttpDoor(f"metrics {self.host}:{self.port}", self.limits, runner, logger=log)
                try:
                    sock = await door.listen(self.host, self.port)
                except OSError as e:   # address in use, permission, no such address: a state
                    await door.close()
                    self.error = f"metrics {self.host}:{self.port}: cannot listen: {e.strerror or e}"
                    if not logged:
                        log.error("%s; retrying every %.0f s", self.error, RETRY_S)
                        logged = True
                    try:
                        await asyncio.wait_for(self._stop.wait(), RETRY_S)
                    except TimeoutError:
                        pass
                    continue
                self.door, self.error = door, None
                self._bound = (self.host, sock.getsockname()[1])
                self.listening.set()
                log.info("metrics for Prometheus on http://%s:%d/metrics", self.host, self._bound[1])
                await self._stop.wait()
        finally:
            if self.door is not None:
                await self.door.close()
            self.listening.clear()
            await runner.cleanup()

    async def h_index(self, request: web.Request) -> web.StreamResponse:
        if request.method not in ("GET", "HEAD"):
            return web.Response(status=405)
        return web.Response(body=b"<html><body><a href=\"/metrics\">hookwatch metrics</a></body></html>\n",
                            content_type="text/html", charset="utf-8")

    async def h_metrics(self, request: web.Request) -> web.StreamResponse:
        if request.method not in ("GET", "HEAD"):
            return web.Response(status=405)
        try:
            data = render(self.registry)
        except Exception:
            log.exception("metrics: rendering failed")
            return web.Response(status=500)
        return web.Response(body=data, headers={"Content-Type": CONTENT_TYPE})

    def shutdown(self, timeout: float = 5.0) -> None:
        loop, stop = self.loop, self._stop
        if loop is not None and stop is not None:
            try:
                loop.call_soon_threadsafe(stop.set)
            except RuntimeError:       # the loop has ended
                pass
        self._thread.join(timeout)


@web.middleware
async def _no_body(request: web.Request, handler):
    """A scrape has no body: one announced (or sent) is refused at once, never read."""
    if request.body_exists or (request.content_length or 0) > 0:
        return web.Response(status=413, text="no request body accepted")
    return await handler(request)


_ENDPOINTS: dict[tuple[str, int], Endpoint] = {}
_ENDPOINTS_LOCK = threading.Lock()


def endpoint(host: str, port: int, limits: DoorLimits | None = None) -> Endpoint:
    """The process' endpoint on (host, port), started on first use (with ``limits``); it runs
    until process exit (a station rebuilt by a reload re-registers without the port ever
    closing)."""
    key = (host, int(port))
    with _ENDPOINTS_LOCK:
        ep = _ENDPOINTS.get(key)
        if ep is None:
            ep = _ENDPOINTS[key] = Endpoint(host, int(port), limits)
        return ep


def shutdown_all() -> None:
    """Stop every endpoint of this process (tests; the process exit does it otherwise)."""
    with _ENDPOINTS_LOCK:
        eps = list(_ENDPOINTS.values())
        _ENDPOINTS.clear()
    for ep in eps:
        ep.shutdown()
