"""Listening doors and the process's descriptor budget: one mechanism for every TCP server.

Every port the gateway listens on (the console, the metrics endpoint, each Modbus TCP port, and
anything added later) is a :class:`Door`: our own accept loop on a non-blocking listening socket
with

- a **connection cap** (:attr:`DoorLimits.max_connections`): at the cap a newcomer whose address
  holds at least two fewer connections than the busiest other address closes that address's oldest connection
  not serving a request (:meth:`Door.evict_busiest`: one client cannot starve another by holding
  the door's room); else the newcomer is closed at once (a door's ``make_room`` hook replaces the
  rule: the Modbus door keeps room for the PLC's allow-list);
- a **per-address cap** (:attr:`DoorLimits.max_per_address`): a newcomer from an address that
  holds as many closes that address's connection idle longest if it has been idle ≥
  :data:`EVICT_IDLE_S` (a client that re-connects instead of re-using), else it is closed at once
  (counted ``refused_per_address``, one log line a minute with the count);
- a **request deadline** (:attr:`DoorLimits.request_timeout_s`): a request must be complete (for
  HTTP: the request line, the headers and the body; for Modbus: the whole frame) within this long
  of its first byte, however the bytes trickle in (a deadline, not a per-``recv`` timeout);
- an **idle timeout** (:attr:`DoorLimits.idle_timeout_s`): a connection that does not begin a new
  request this long after its last reply (Modbus: after its accept too; HTTP: the first request
  must be complete within the request deadline of the accept) is closed; a reply that does not
  move for as long (a client that does not read) is closed too;
- an **accept rate** (:attr:`DoorLimits.accepts_per_s`, a token bucket): beyond it the door waits
  before its next accept and further connects queue in the kernel's backlog, so that a connect
  flood (e.g. live-stream churn answered 429) costs the process — and the slot loop sharing its
  interpreter — a bounded amount of work per second, whatever the flood's rate; a connection
  refused at once costs a tenth of an accept (:data:`REFUSAL_COST`), so the backlog (:data:`BACKLOG`)
  a re-opening client fills drains fast and another client's connect does not wait behind it long;
- **accept errors** (``EMFILE``, ``ENFILE``, ``ENOBUFS`` …) are a *state*: counted, one log line
  (then at most one a minute, with the count), and the door stops accepting for
  :attr:`DoorLimits.accept_pause_s` instead of spinning; the pending connections wait in the
  kernel's backlog.

The :class:`Budget` is per process: at the first use it raises the soft ``RLIMIT_NOFILE`` to the
hard limit and keeps a **reserve** of descriptors (``budget.reserve``: the slot loops, the
recorder's files, serial ports, the MQTT outbox, the supervisor's socketpairs for worker restarts)
that no door takes: the doors' caps are granted out of ``soft limit − reserve − the descriptors
open at start`` (a door asks for its configured cap and gets at most half of what is left, with
one log line, when the limit is too small), and a connection accepted while fewer than ``reserve`` descriptors are free
(the new descriptor's number tells: Linux gives the lowest free one) is closed at once.

A door's protocol side marks a connection's requests: :meth:`Conn.data` (bytes of a request came
in), :meth:`Conn.begin` (a complete request: no deadline while it is served) and :meth:`Conn.end`
(the reply is written: the idle time starts). One sweeper task per door checks the deadlines
twice a second. :func:`aiohttp_door` puts an aiohttp ``AppRunner`` behind a door.
"""
from __future__ import annotations

import asyncio
import errno
import logging
import os
import resource
import socket
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from aiohttp import web
from aiohttp.abc import AbstractAccessLogger

from . import ratelog as _ratelog

log = logging.getLogger("hookwatch.doors")

#: descriptors no door may take (the process's own work: files, ports, pipes, worker restarts)
FD_RESERVE = 128
#: how often a door checks its connections' deadlines
SWEEP_S = 0.5
#: one log line per kind and door this often at most (the lines not written are counted)
LOG_INTERVAL_S = 60.0
#: the smallest cap a door is granted, whatever the budget (it can still serve someone)
MIN_CAP = 2
#: an address at its per-address cap replaces its connection idle at least this long
EVICT_IDLE_S = 1.0
#: a connection refused at once (a cap, the reserve) costs this share of an accept of the accept
#: rate: a client re-opening what the door closes drains the kernel's backlog ten times as fast
#: as served connections do, so that another client's connect waits behind fewer of its
REFUSAL_COST = 0.1
#: the listening backlog of a door (the kernel caps it at net.core.somaxconn): room for a
#: re-opening client's connects and the others' behind them
BACKLOG = 512
_GONE = object()


@dataclass(frozen=True)
class DoorLimits:
    max_connections: int = 64
    request_timeout_s: float = 10.0
    idle_timeout_s: float = 60.0
    accept_pause_s: float = 0.5
    #: new connections accepted per second at most (a token bucket with a burst of as many)
    accepts_per_s: float = 100.0
    #: connections of one client address at once
    max_per_address: int = 16

    @classmethod
    def from_config(cls, c: Any) -> DoorLimits:
        """From a configuration section with the door keys (``max_connections``,
        ``request_timeout_s``, ``idle_timeout_s``, ``accept_pause_s``, ``accepts_per_s``,
        ``max_per_address``)."""
        return cls(int(c.max_connections), float(c.request_timeout_s), float(c.idle_timeout_s),
                   float(c.accept_pause_s), float(c.accepts_per_s), int(c.max_per_address))


class RateLog(_ratelog.RateLog):
    """The project's one rate-limited logger (:class:`gateway.plumbing.ratelog.RateLog`: the first line of a
    kind at once, the rest of the window as one line with the count), called as
    ``rlog(level, key, msg, *args)`` by the doors."""

    def __call__(self, level: int, key: str, msg: str, *args: Any) -> None:
        self.log(key, level, msg, *args)


# ================================================================================ the budget


class Budget:
    """The process's descriptor budget (one per process: :func:`budget`)."""

    def __init__(self, reserve: int = FD_RESERVE):
        self.reserve = int(reserve)
        self.soft, self.hard = self._raise()
        self.base = _open_fds()
        self._lock = threading.Lock()
        self.claims: dict[str, int] = {}
        self.refused_low = 0

    @staticmethod
    def _raise() -> tuple[int, int]:
        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if hard != resource.RLIM_INFINITY and soft != hard:
            try:
                resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
                soft = hard
            except (OSError, ValueError) as e:
                log.warning("cannot raise the descriptor limit from %d to %d: %s", soft, hard, e)
        if soft == resource.RLIM_INFINITY:
            soft = 1 << 20
        return int(soft), int(hard)

    @property
    def for_doors(self) -> int:
        """Descriptors the doors may hold together."""
        return max(0, self.soft - self.reserve - self.base)

    def set_reserve(self, reserve: int) -> None:
        with self._lock:
            self.reserve = max(16, int(reserve))

    def claim(self, name: str, wanted: int) -> int:
        """A door's cap: ``wanted``, or half of what is left of :attr:`for_doors` when that is
        less (no door takes all: the doors started later still get room), at least MIN_CAP."""
        with self._lock:
            self.claims.pop(name, None)
            left = self.for_doors - sum(self.claims.values())
            got = max(MIN_CAP, min(int(wanted), left // 2))
            self.claims[name] = got
        if got < wanted:
            log.warning("%s: at most %d connections, not %d: the descriptor limit is %d and %d are "
                        "kept for the stations (raise LimitNOFILE)", name, got, wanted, self.soft,
                        self.reserve)
        return got

    def release(self, name: str) -> None:
        with self._lock:
            self.claims.pop(name, None)

    def low(self, fd: int) -> bool:
        """True when descriptor ``fd`` (just opened) leaves fewer than ``reserve`` free: Linux
        hands out the lowest free number, so at least ``fd`` descriptors are in use."""
        return fd >= self.soft - self.reserve


_BUDGET: Budget | None = None
_BUDGET_LOCK = threading.Lock()


def budget(reserve: int | None = None) -> Budget:
    """The process's budget; made (and the soft limit raised) at the first call."""
    global _BUDGET
    with _BUDGET_LOCK:
        if _BUDGET is None:
            _BUDGET = Budget(FD_RESERVE if reserve is None else reserve)
        elif reserve is not None:
            _BUDGET.set_reserve(reserve)
        return _BUDGET


def _open_fds() -> int:
    try:
        return len(os.listdir("/proc/self/fd"))
    except OSError:
        return 16


def is_exhausted(e: BaseException) -> bool:
    """An error that says the process or the system is out of descriptors or buffers."""
    return isinstance(e, OSError) and e.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS,
                                                    errno.ENOMEM)


# ================================================================================ the door


class Conn:
    """One accepted connection's request state (see the module docstring)."""
    __slots__ = ("peer", "accepted", "idle_since", "first_byte", "busy", "close", "wbuf", "wbuf_t",
                 "transport", "requests", "door")

    def __init__(self, peer: str, close: Callable[[], None], door: Door | None = None,
                 first_request_deadline: bool = False):
        now = time.monotonic()
        self.peer = peer
        self.door = door
        self.accepted = self.idle_since = now
        #: the request deadline runs from the accept when the first request is due at once (HTTP)
        self.first_byte: float | None = now if first_request_deadline else None
        self.busy = False
        self.close = close
        self.transport: Any = None
        self.wbuf = 0
        self.wbuf_t = now
        self.requests = 0

    def data(self) -> None:
        if self.first_byte is None and not self.busy:
            self.first_byte = time.monotonic()

    def begin(self) -> None:
        self.busy = True
        self.first_byte = None

    def end(self) -> None:
        self.busy = False
        self.first_byte = None
        self.requests += 1
        self.idle_since = time.monotonic()


class Door:
    """One listening socket with its accept loop, caps and deadlines (see the module docstring).

    ``serve(sock, conn)`` takes an accepted socket over (it must set ``conn.close`` to something
    that closes the connection at once and call :meth:`gone` when it ends). ``make_room(peer)``
    may close a connection to admit ``peer`` at the cap (True: room was made); a door without it
    closes the newcomer.
    """

    #: a new connection's first request must be complete within the request deadline of the
    #: accept (HTTP: a client connects to send a request); else the idle timeout applies first
    first_request_deadline = False

    def __init__(self, name: str, limits: DoorLimits,
                 serve: Callable[[socket.socket, Conn], Awaitable[None] | None], *,
                 make_room: Callable[[str], bool] | None = None, logger: logging.Logger | None = None,
                 counters: dict[str, int] | None = None):
        self.name = name
        self.limits = limits
        self.serve = serve
        self.make_room = make_room
        self.log = logger or log
        self.rlog = RateLog(self.log)
        self.cap = limits.max_connections
        self.conns: dict[Conn, None] = {}
        #: open connections per client address (the keys of :attr:`conns`, counted)
        self.per_address: dict[str, int] = {}
        #: counted here (a server may pass its own dict: the door's keys are added to it)
        self.counters = counters if counters is not None else {}
        for k in ("accepted", "accepts_paced", "refused_connections", "refused_per_address",
                  "refused_reserve", "accept_errors", "request_timeouts", "idle_closed", "evicted"):
            self.counters.setdefault(k, 0)
        self.paused_until = 0.0
        self.sockets: list[socket.socket] = []
        self._tasks: list[asyncio.Task] = []

    # -- life
    async def listen(self, host: str, port: int, backlog: int = BACKLOG) -> socket.socket:
        fam = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.create_server((host, port), family=fam, backlog=backlog)
        sock.setblocking(False)
        return await self.listen_on(sock)

    async def listen_on(self, sock: socket.socket) -> socket.socket:
        """Serve on a listening socket (several per door: one cap over all of them)."""
        if not self.sockets:
            self.cap = budget().claim(self.name, self.limits.max_connections)
            self._tasks.append(asyncio.get_running_loop().create_task(self._sweep()))
        self.sockets.append(sock)
        self._tasks.append(asyncio.get_running_loop().create_task(self._accept(sock)))
        return sock

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except (asyncio.CancelledError, Exception):
                pass
        self._tasks.clear()
        for s in self.sockets:
            s.close()
        if self.sockets:
            budget().release(self.name)
        self.sockets.clear()
        for c in list(self.conns):
            self._close(c)
        self.rlog.close()               # the counts of the last window, and no timer after

    @property
    def connections(self) -> int:
        return len(self.conns)

    @property
    def addresses(self) -> list[tuple[str, int]]:
        return [s.getsockname()[:2] for s in self.sockets]

    def gone(self, conn: Conn) -> None:
        """The connection ended (the protocol side calls it once)."""
        self._forget(conn)

    def evict(self, conn: Conn) -> None:
        self.counters["evicted"] += 1
        self._close(conn)

    def _add(self, conn: Conn) -> None:
        self.conns[conn] = None
        self.per_address[conn.peer] = self.per_address.get(conn.peer, 0) + 1

    def _forget(self, conn: Conn) -> None:
        if self.conns.pop(conn, _GONE) is _GONE:
            return
        n = self.per_address.get(conn.peer, 1) - 1
        if n > 0:
            self.per_address[conn.peer] = n
        else:
            self.per_address.pop(conn.peer, None)

    def _close(self, conn: Conn) -> None:
        self._forget(conn)
        try:
            conn.close()
        except Exception:  # already closed
            pass

    # -- room (at a cap)
    def evict_idle(self, peer: str | None = None, exclude: Callable[[str], bool] | None = None,
                   min_idle_s: float = EVICT_IDLE_S) -> bool:
        """Close the connection (of ``peer``, or of any address ``exclude`` does not name) idle
        longest — between requests, not mid-request — if idle ≥ ``min_idle_s``; True if closed."""
        cands = [c for c in self.conns if not c.busy and c.first_byte is None
                 and (peer is None or c.peer == peer) and not (exclude is not None and exclude(c.peer))]
        if not cands:
            return False
        c = min(cands, key=lambda x: x.idle_since)
        if time.monotonic() - c.idle_since < min_idle_s:
            return False
        self.evict(c)
        return True

    def evict_busiest(self, peer: str, exclude: Callable[[str], bool] | None = None,
                      fair: bool = True) -> bool:
        """Room for ``peer``: close the oldest connection of the other address holding the most
        (one not serving a request if it has one). ``fair``: only when that address holds at
        least two more than ``peer`` does (so that two clients do not take turns closing each
        other's connections). Addresses ``exclude`` names are never chosen. True if one was closed."""
        counts = {a: n for a, n in self.per_address.items()
                  if a != peer and not (exclude is not None and exclude(a))}
        if not counts:
            return False
        busiest = max(counts, key=lambda a: counts[a])
        if fair and counts[busiest] <= self.per_address.get(peer, 0) + 1:
            return False
        mine = [c for c in self.conns if c.peer == busiest]
        if not mine:
            return False
        quiet = [c for c in mine if not c.busy]
        self.evict(min(quiet or mine, key=lambda c: c.accepted))
        return True

    # -- accepting
    async def _accept(self, lsock: socket.socket) -> None:
        loop = asyncio.get_running_loop()
        c = self.counters
        b = budget()
        rate = max(1.0, float(self.limits.accepts_per_s))
        tokens, t_last = rate, time.monotonic()
        while True:
            now = time.monotonic()
            tokens = min(rate, tokens + (now - t_last) * rate)
            t_last = now
            if tokens < 1.0:              # over the accept rate: the backlog holds the rest
                c["accepts_paced"] += 1
                await asyncio.sleep((1.0 - tokens) / rate)
                continue
            tokens -= 1.0
            try:
                sock, addr = await loop.sock_accept(lsock)
            except asyncio.CancelledError:
                raise
            except OSError as e:      # EMFILE, ENFILE, ENOBUFS, ECONNABORTED: a state
                c["accept_errors"] += 1
                self.rlog(logging.ERROR, "accept", "%s: cannot accept a connection (%s); pausing "
                          "%.1f s (%d accept errors so far)", self.name, e.strerror or e,
                          self.limits.accept_pause_s, c["accept_errors"])
                self.paused_until = time.monotonic() + self.limits.accept_pause_s
                await asyncio.sleep(self.limits.accept_pause_s)
                continue
            peer = str(addr[0]) if addr else "?"
            if b.low(sock.fileno()):
                sock.close()
                c["refused_reserve"] += 1
                b.refused_low += 1
                self.rlog(logging.ERROR, "reserve", "%s: connection from %s refused: the process's "
                          "free descriptors are down to the reserve (%d of %d in use; %d refused)",
                          self.name, peer, b.soft - b.reserve, b.soft, c["refused_reserve"])
                tokens += 1.0 - REFUSAL_COST
                continue
            if self.per_address.get(peer, 0) >= self.limits.max_per_address \
                    and not self.evict_idle(peer):
                sock.close()
                c["refused_connections"] += 1
                c["refused_per_address"] += 1
                self.rlog(logging.WARNING, "per address", "%s: connection from %s refused (it holds "
                          "%d, at most %d per address; %d refused)", self.name, peer,
                          self.per_address.get(peer, 0), self.limits.max_per_address,
                          c["refused_per_address"])
                tokens += 1.0 - REFUSAL_COST
                continue
            if len(self.conns) >= self.cap and not self._make_room(peer):
                sock.close()
                c["refused_connections"] += 1
                self.rlog(logging.WARNING, "cap", "%s: connection from %s refused (%d open, at most "
                          "%d; %d refused)", self.name, peer, len(self.conns), self.cap, c["refused_connections"])
                tokens += 1.0 - REFUSAL_COST
                continue
            c["accepted"] += 1
            conn = Conn(peer, sock.close, self, self.first_request_deadline)
            self._add(conn)
            try:
                r = self.serve(sock, conn)
                if r is not None:
                    await r
            except OSError as e:
                self._forget(conn)
                sock.close()
                self.rlog(logging.ERROR, "serve", "%s: cannot serve a connection from %s: %s",
                          self.name, peer, e)

    def _make_room(self, peer: str) -> bool:
        if self.make_room is not None:
            return self.make_room(peer)
        return self.evict_busiest(peer)

    # -- deadlines
    async def _sweep(self) -> None:
        while True:
            await asyncio.sleep(SWEEP_S)
            self.sweep(time.monotonic())

    def sweep(self, now: float) -> None:
        lim = self.limits
        c = self.counters
        for conn in list(self.conns):
            if conn.busy:
                continue
            t = conn.transport
            if t is not None:
                try:
                    w = t.get_write_buffer_size()
                except Exception:
                    w = 0
                if w:
                    if w != conn.wbuf:          # the reply moves: not idle
                        conn.wbuf, conn.wbuf_t = w, now
                    elif now - conn.wbuf_t > lim.idle_timeout_s:
                        c["idle_closed"] += 1
                        self._close(conn)
                    continue
                conn.wbuf = 0
            if conn.first_byte is not None:
                if now - conn.first_byte > lim.request_timeout_s:
                    c["request_timeouts"] += 1
                    self.rlog(logging.INFO, "deadline", "%s: %s did not complete a request within "
                              "%.0f s; closed", self.name, conn.peer, lim.request_timeout_s)
                    self._close(conn)
            elif now - conn.idle_since > lim.idle_timeout_s:
                c["idle_closed"] += 1
                self._close(conn)


# ================================================================================ aiohttp


class _Tap(asyncio.Protocol):
    """Between the transport and aiohttp's protocol: marks the first byte of each request."""

    def __init__(self, inner: Any, conn: Conn, door: Door):
        self.inner, self.conn, self.door = inner, conn, door

    def connection_made(self, transport) -> None:
        self.conn.transport = transport
        self.conn.close = transport.abort
        _BY_TRANSPORT[transport] = self.conn
        self.inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        self.conn.data()
        self.inner.data_received(data)

    def eof_received(self):
        return self.inner.eof_received()

    def connection_lost(self, exc) -> None:
        self.door.gone(self.conn)
        self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        self.inner.pause_writing()

    def resume_writing(self) -> None:
        self.inner.resume_writing()


_BY_TRANSPORT: dict[Any, Conn] = {}


class AiohttpDoor(Door):
    """A door in front of an aiohttp ``AppRunner`` (set up with :func:`door_runner_kwargs` and
    the :func:`door_middleware` first among the app's middlewares)."""
    first_request_deadline = True

    def __init__(self, name: str, limits: DoorLimits, runner, *, ssl_context=None,
                 logger: logging.Logger | None = None):
        super().__init__(name, limits, self._serve_http, logger=logger)
        self.runner = runner
        self.ssl_context = ssl_context

    async def _serve_http(self, sock: socket.socket, conn: Conn) -> None:
        loop = asyncio.get_running_loop()
        factory = self.runner.server
        conn.close = sock.close

        def proto():
            return _Tap(factory(), conn, self)
        sock.setblocking(False)
        if self.ssl_context is None:
            await loop.connect_accepted_socket(proto, sock)
        else:
            # the TLS handshake is part of the first request's deadline
            conn.data()
            task = loop.create_task(loop.connect_accepted_socket(
                proto, sock, ssl=self.ssl_context, ssl_handshake_timeout=self.limits.request_timeout_s))
            task.add_done_callback(lambda t: None if t.cancelled() or t.exception() is None else sock.close())

    def gone(self, conn: Conn) -> None:
        super().gone(conn)
        if conn.transport is not None:
            _BY_TRANSPORT.pop(conn.transport, None)


def door_middleware():
    """The aiohttp middleware of a door: a request is *complete* when its body is read (within
    what is left of the request deadline), then it is served without a deadline; the reply's
    end starts the idle time (:class:`DoorAccessLog`)."""
    @web.middleware
    async def door_mw(request, handler):
        conn = _BY_TRANSPORT.get(request.transport) if request.transport is not None else None
        if conn is not None and request.body_exists and conn.first_byte is not None:
            door = conn.door
            left = (door.limits.request_timeout_s if door else 10.0) - (time.monotonic() - conn.first_byte)
            try:
                await asyncio.wait_for(request.read(), max(0.05, left))
            except TimeoutError:
                if door is not None:
                    door.counters["request_timeouts"] += 1
                conn.close()
                raise web.HTTPRequestTimeout() from None
        if conn is not None:
            conn.begin()
        return await handler(request)
    return door_mw


class DoorAccessLog(AbstractAccessLogger):
    """aiohttp's access logger is called once the reply is written: the request has ended."""

    def log(self, request, response, time) -> None:  # noqa: A002 (aiohttp's signature)
        conn = _BY_TRANSPORT.get(request.transport) if request.transport is not None else None
        if conn is not None:
            conn.end()


class _BadRequestLines(logging.Filter):
    """aiohttp logs every unparsable request with its traceback: input from the network is not a
    bug of ours. One line a minute (a warning, no traceback, with the count of those not shown)."""

    def __init__(self) -> None:
        super().__init__()
        self.last = -1e18
        self.skipped = 0

    def filter(self, record: logging.LogRecord) -> bool:
        now = time.monotonic()
        if now - self.last < LOG_INTERVAL_S:
            self.skipped += 1
            return False
        exc = record.exc_info[1] if record.exc_info else None
        record.msg = str(record.getMessage()) + (f": {exc}" if exc is not None else "")
        if self.skipped:
            record.msg += f" ({self.skipped} more since the last such line)"
        record.args = None
        record.exc_info = record.exc_text = None
        record.levelno, record.levelname = logging.WARNING, "WARNING"
        self.last, self.skipped = now, 0
        return True


#: aiohttp's server log of the doors (bad requests: rate-limited, no tracebacks)
http_log = logging.getLogger("hookwatch.doors.http")
http_log.addFilter(_BadRequestLines())


def door_runner_kwargs(limits: DoorLimits) -> dict[str, Any]:
    """``AppRunner`` keyword arguments of a door's aiohttp server."""
    return {"access_log_class": DoorAccessLog, "access_log": log, "logger": http_log,
            "keepalive_timeout": limits.idle_timeout_s}
