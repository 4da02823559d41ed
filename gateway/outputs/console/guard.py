"""The console's door bounds: which Host names it answers, how often a client may open a live
stream, how many report processes run at once, and how often a refused request is logged.

All of it runs on the console's own loop (no locks); every table is bounded.
"""
from __future__ import annotations

import asyncio
import ipaddress
import logging
import math
import time
from collections.abc import Awaitable, Callable, Iterable
from typing import Any

from aiohttp.http_exceptions import HttpProcessingError

from ...plumbing.ratelog import RateBound, RateLog  # noqa: F401 - RateBound: the console's, now in ratelog

#: names a browser on the same host uses for a console bound to a loopback address
LOCAL_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback")
#: a refused-request log line of one kind at most this often; the lines not written are counted
LOG_EVERY_S = 60.0
#: most keys (client addresses) one rate table holds; beyond, the oldest are forgotten
MAX_KEYS = 4096


def host_name(host: str | None) -> str:
    """The name of a Host header without its port, lower case: ``[::1]:8080`` → ``::1``."""
    h = (host or "").strip().lower()
    if h.startswith("["):
        return h[1:].split("]", 1)[0]
    if h.count(":") == 1:
        h = h.split(":", 1)[0]
    return h.rstrip(".")


def _ip(text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        return ipaddress.ip_address(text.split("%", 1)[0])
    except ValueError:
        return None


class HostAllow:
    """The Host names the console answers (against DNS rebinding: a page of ``evil.example``
    whose name is made to resolve to the console gets a refusal, never the console's data).

    Allowed: the names in ``console.allowed_hosts``; the addresses the console listens on and
    the address the client connected to (an IP address in the Host header cannot be rebound);
    the localhost names when the connection came to a loopback address."""

    def __init__(self, names: Iterable[str], listen_hosts: Iterable[str]):
        self.names = {host_name(n) for n in names if str(n).strip()}
        self.listen = {ip for ip in (_ip(host_name(h)) for h in listen_hosts)
                       if ip is not None and not ip.is_unspecified}

    def allowed(self, host: str | None, local_addr: str | None) -> bool:
        name = host_name(host)
        if not name:
            return False
        if name in self.names:
            return True
        local = _ip(local_addr or "")
        ip = _ip(name)
        if ip is not None:
            if ip in self.listen or (local is not None and ip == local):
                return True
            # an IPv4 client on a dual-stack socket: ::ffff:a.b.c.d
            mapped = getattr(local, "ipv4_mapped", None)
            return mapped is not None and ip == mapped
        if name in LOCAL_NAMES or name.endswith(".localhost"):
            if local is None:
                return False
            mapped = getattr(local, "ipv4_mapped", None)
            return local.is_loopback or (mapped is not None and mapped.is_loopback)
        return False


class LogLimit(RateLog):
    """The console's log of refused requests: the project's one rate-limited log
    (:class:`gateway.plumbing.ratelog.RateLog`: the first line of a kind in a window at once, the rest of
    the window as one line with the count when it ends), every line a WARNING prefixed
    ``console:``, never with a traceback (refused requests are client input); ``counts`` keeps the
    refusals per kind (bounded: :data:`MAX_KEYS` kinds)."""

    def __init__(self, logger: logging.Logger, every_s: float = LOG_EVERY_S,
                 clock: Callable[[], float] = time.monotonic):
        super().__init__(logger, every_s, clock)
        self.counts: dict[str, int] = {}

    def warn(self, kind: str, msg: str, *args: Any) -> None:
        if kind not in self.counts and len(self.counts) >= MAX_KEYS:
            self.counts.clear()
        self.counts[kind] = self.counts.get(kind, 0) + 1
        self.warning(kind, "console: " + msg, *args)


class Busy(Exception):
    """The report queue is full: come back in ``retry_after`` seconds."""

    def __init__(self, retry_after: int):
        super().__init__(f"retry after {retry_after} s")
        self.retry_after = retry_after


class ReportPool:
    """Report processes (a test's Fig. 7, a campaign): at most ``jobs`` run at once, at most
    ``queue`` more wait; a request for a job already running or waiting waits for that job (no
    second process); beyond the queue :class:`Busy` is raised (HTTP 503 with Retry-After)."""

    def __init__(self, jobs: int, queue: int):
        self.jobs = max(1, int(jobs))
        self.queue = max(0, int(queue))
        self._sem: asyncio.Semaphore | None = None
        self._tasks: dict[str, asyncio.Task] = {}
        self.running = 0
        self.peak = 0
        self.refused = 0
        self._mean_s = 10.0        # a report's run time, smoothed (for Retry-After)

    @property
    def pending(self) -> int:
        return len(self._tasks)

    async def run(self, key: str, job: Callable[[], Awaitable[Any]]) -> Any:
        t = self._tasks.get(key)
        if t is None:
            if len(self._tasks) >= self.jobs + self.queue:
                self.refused += 1
                raise Busy(max(1, math.ceil(self._mean_s * (len(self._tasks) - self.jobs + 1)
                                            / self.jobs)))
            if self._sem is None:
                self._sem = asyncio.Semaphore(self.jobs)
            t = asyncio.get_running_loop().create_task(self._run(job))
            self._tasks[key] = t

            def done(_t: asyncio.Task, key: str = key) -> None:
                if self._tasks.get(key) is _t:
                    del self._tasks[key]
            t.add_done_callback(done)
        # a client that goes away does not cancel the job the others wait for
        return await asyncio.shield(t)

    async def _run(self, job: Callable[[], Awaitable[Any]]) -> Any:
        assert self._sem is not None
        async with self._sem:
            self.running += 1
            self.peak = max(self.peak, self.running)
            t0 = time.monotonic()
            try:
                return await job()
            finally:
                self.running -= 1
                self._mean_s = 0.7 * self._mean_s + 0.3 * max(1.0, time.monotonic() - t0)

    def cancel_all(self) -> None:
        for t in list(self._tasks.values()):
            t.cancel()


class ServerLog:
    """aiohttp's server logger for the console: a request the HTTP parser refuses (bad request
    line, bad header, header too long, …; aiohttp answers 400/413/431 itself) is client input —
    one rate-limited WARNING line without a traceback; any other error keeps its traceback."""

    def __init__(self, logger: logging.Logger, refusals: LogLimit):
        self._log = logger
        self._refusals = refusals

    def _client_error(self, exc: object) -> tuple[int, str] | None:
        if isinstance(exc, HttpProcessingError) and 400 <= int(exc.code or 0) < 500:
            first = str(exc.message).strip().splitlines()[0] if str(exc.message).strip() else ""
            return int(exc.code), first[:80]
        return None

    def exception(self, msg: str, *args: Any, exc_info: Any = None, **kw: Any) -> None:
        ce = self._client_error(exc_info)
        if ce is not None:
            remote = args[0] if args else "?"
            self._refusals.warn("malformed HTTP", "malformed HTTP request from %s refused (%d): %s",
                                remote, ce[0], ce[1])
            return
        self._log.error(msg, *args, exc_info=exc_info if exc_info is not None else True, **kw)

    def debug(self, msg: str, *args: Any, exc_info: Any = None, **kw: Any) -> None:
        ce = self._client_error(exc_info)
        if ce is not None:          # aiohttp's "not HTTP at all" (a bad method): the same line
            self.exception(msg, *args, exc_info=exc_info)
            return
        self._log.debug(msg, *args, exc_info=exc_info, **kw)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._log, name)
