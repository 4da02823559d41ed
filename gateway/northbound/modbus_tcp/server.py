"""The asyncio Modbus TCP server: connections, limits, pacing, dispatch to the units.

- connections: at most :data:`MAX_CONNECTIONS` per server and :data:`MAX_PER_CLIENT` per client
  address. At a cap, the connection idle longest is closed to make room if it has been idle for
  :data:`EVICT_IDLE_S` (so idle sockets cannot lock a PLC out); else the new connection is closed
  at once (counted, one log line a minute);
- a connection that sends nothing for :data:`IDLE_TIMEOUT_S` (or does not read its replies for as
  long) is closed;
- frames: :class:`~.framer.Framer` (several requests per segment, requests split over segments);
  requests of one connection are answered one after the other, in order; a header that is not
  Modbus closes that connection (counted, one log line a minute, no traceback);
- every request waits for the server-wide :class:`Pacer` (requests per second);
- requests go to the unit (one per station) by unit id; an unknown unit id answers 0x0B.

The units are duck-typed: ``input_image()`` (the input registers), ``hr`` (the holding registers), ``lock``,
``may_write(peer)`` and ``owner.handle_write(unit, address, values, peer)`` (an awaitable giving
``None`` or an :class:`~.pdu.Exc`).
"""
from __future__ import annotations

import asyncio
import logging
import socket
import time
from typing import Any

from . import pdu as P
from .framer import FrameError, Framer, encode

log = logging.getLogger("hookwatch.modbus")

MAX_CONNECTIONS = 64
MAX_PER_CLIENT = 16
IDLE_TIMEOUT_S = 60.0
EVICT_IDLE_S = 1.0
READ_CHUNK = 4096
LOG_INTERVAL_S = 60.0


class RateLog:
    """One log line per key and interval; the lines not written are counted into the next one."""

    def __init__(self, logger: logging.Logger, interval_s: float = LOG_INTERVAL_S):
        self.log, self.interval = logger, interval_s
        self._s: dict[str, list[float]] = {}

    def __call__(self, level: int, key: str, msg: str, *args: Any) -> None:
        now = time.monotonic()
        st = self._s.setdefault(key, [-1e18, 0])
        if now - st[0] >= self.interval:
            n = int(st[1])
            st[0], st[1] = now, 0
            self.log.log(level, msg + (f" ({n} more since the last such line)" if n else ""), *args)
        else:
            st[1] += 1


class Pacer:
    """At most ``rate`` requests per second over the whole server: time is cut into windows of
    ``window_s``, each serving ``rate · window_s`` requests; a request beyond a window's share
    waits for the next window with room. A flood of PLC requests cannot take the CPU from the
    stations."""

    def __init__(self, rate: float, window_s: float = 0.005):
        self.q = window_s
        self.cap = max(1, int(round(rate * window_s)))
        self.w = 0
        self.n = 0
        self.delayed = 0

    async def wait(self) -> None:
        now = time.monotonic()
        cur = int(now / self.q)
        if cur > self.w:
            self.w, self.n = cur, 0
        if self.n >= self.cap:
            self.w += 1
            self.n = 0
        self.n += 1
        delay = self.w * self.q - now
        if delay > 0:
            self.delayed += 1
            await asyncio.sleep(delay)


class Store:
    """The units of one server (unit id → unit) and its counters."""

    def __init__(self):
        self.units: dict[int, Any] = {}
        self.counters: dict[str, int] = {
            "reads": 0, "writes": 0, "refused": 0, "bad_value": 0, "unknown_unit": 0,
            "bad_request": 0, "malformed": 0, "refused_connections": 0, "idle_closed": 0,
            "connections": 0, "failed": 0, "evicted": 0,
            "accept_errors": 0}


class ModbusTcpServer:
    def __init__(self, store: Store, pacer: Pacer | None = None, *, max_connections: int | None = None,
                 max_per_client: int | None = None, idle_timeout_s: float | None = None):
        self.store = store
        self.pacer = pacer
        self.max_connections = MAX_CONNECTIONS if max_connections is None else max_connections
        self.max_per_client = MAX_PER_CLIENT if max_per_client is None else max_per_client
        self.idle_timeout_s = IDLE_TIMEOUT_S if idle_timeout_s is None else idle_timeout_s
        self.rlog = RateLog(log)
        self._lsock: socket.socket | None = None
        self._accept_task: asyncio.Task | None = None
        self._tasks: set[asyncio.Task] = set()
        self._conns: dict[asyncio.StreamWriter, list] = {}   # writer → [client, last activity]
        self._per_client: dict[str, int] = {}

    async def start(self, host: str, port: int) -> None:
        """Listen. Connections are accepted one at a time by our own loop, and one over a cap is
        closed before the next is accepted: the server never holds more than its caps + 1 file
        descriptors for clients, whatever arrives (no EMFILE bursts)."""
        fam = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.create_server((host, port), family=fam, backlog=128)
        sock.setblocking(False)
        self._lsock = sock
        self._accept_task = asyncio.get_running_loop().create_task(self._accept_loop())

    async def close(self) -> None:
        if self._accept_task is not None:
            self._accept_task.cancel()
            try:
                await self._accept_task
            except (asyncio.CancelledError, Exception):
                pass
            self._accept_task = None
        if self._lsock is not None:
            self._lsock.close()
            self._lsock = None
        for w in list(self._conns):
            w.transport.abort()
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)

    async def _accept_loop(self) -> None:
        loop = asyncio.get_running_loop()
        c = self.store.counters
        lsock = self._lsock     # started by start() once it listens
        if lsock is None:
            return
        while True:
            try:
                conn, addr = await loop.sock_accept(lsock)
            except asyncio.CancelledError:
                raise
            except OSError as e:      # EMFILE, ENFILE, ECONNABORTED: a state, not a crash
                c["accept_errors"] += 1
                self.rlog(logging.ERROR, "accept", "Modbus TCP: cannot accept a connection: %s", e)
                await asyncio.sleep(0.1)
                continue
            peer = addr[0] if addr else None
            key = peer or "?"
            if ((len(self._conns) >= self.max_connections and not self._evict(None))
                    or (self._per_client.get(key, 0) >= self.max_per_client and not self._evict(key))):
                c["refused_connections"] += 1
                self.rlog(logging.WARNING, "cap", "Modbus TCP: connection from %s refused (%d open, at most "
                          "%d; at most %d per client address)", peer, len(self._conns), self.max_connections,
                          self.max_per_client)
                conn.close()
                continue
            try:
                reader, writer = await asyncio.open_connection(sock=conn, limit=READ_CHUNK)
            except OSError:
                conn.close()
                continue
            self._conns[writer] = [key, time.monotonic()]
            self._per_client[key] = self._per_client.get(key, 0) + 1
            t = loop.create_task(self._connection(reader, writer, peer, key))
            self._tasks.add(t)
            t.add_done_callback(self._tasks.discard)

    @property
    def connections(self) -> int:
        return len(self._conns)

    # -- connections
    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                          peer: str | None, key: str) -> None:
        c = self.store.counters
        info = self._conns.get(writer) or [key, time.monotonic()]
        c["connections"] += 1
        framer = Framer()
        try:
            while True:
                try:
                    data = await asyncio.wait_for(reader.read(READ_CHUNK), self.idle_timeout_s)
                except TimeoutError:
                    c["idle_closed"] += 1
                    break
                if not data:
                    break
                info[1] = time.monotonic()
                try:
                    frames = framer.feed(data)
                except FrameError as e:
                    c["malformed"] += 1
                    self.rlog(logging.WARNING, "malformed", "Modbus TCP: malformed frame from %s (%s); "
                              "connection closed", peer, e)
                    break
                for f in frames:
                    reply = await self.handle(f.unit, f.pdu, peer)
                    writer.write(encode(f.tid, f.unit, reply))
                if frames:
                    try:
                        await asyncio.wait_for(writer.drain(), self.idle_timeout_s)
                    except TimeoutError:
                        c["idle_closed"] += 1
                        break
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            if self._conns.pop(writer, None) is not None:      # (an evicted one is counted off)
                self._release(key)
            writer.transport.abort()

    def _release(self, key: str) -> None:
        n = self._per_client.get(key, 1) - 1
        if n > 0:
            self._per_client[key] = n
        else:
            self._per_client.pop(key, None)

    def _evict(self, client: str | None) -> bool:
        """Close the connection (of ``client``, or any) idle longest, if idle ≥ EVICT_IDLE_S."""
        now = time.monotonic()
        cands = [(info[1], w) for w, info in self._conns.items() if client is None or info[0] == client]
        if not cands:
            return False
        last, w = min(cands, key=lambda x: x[0])
        if now - last < EVICT_IDLE_S:
            return False
        self.store.counters["evicted"] += 1
        self._release(self._conns.pop(w)[0])
        w.transport.abort()
        return True

    # -- requests
    async def handle(self, unit_id: int, raw: bytes, peer: str | None) -> bytes:
        """One request PDU from ``peer`` for ``unit_id`` → the reply PDU (never raises)."""
        fc = raw[0] if raw else 0
        c = self.store.counters
        if self.pacer is not None:
            await self.pacer.wait()
        u = self.store.units.get(unit_id)
        if u is None:
            c["unknown_unit"] += 1
            return P.exception(fc, P.Exc.GATEWAY_NO_RESPONSE)
        req = P.decode(raw)
        if isinstance(req, P.Exc):
            c["bad_request"] += 1
            return P.exception(fc, req)
        try:
            return await self._serve(u, req, peer)
        except Exception as e:  # a request must never take the server down
            c["failed"] += 1
            self.rlog(logging.ERROR, "failed", "Modbus TCP: request %d from %s failed: %s: %s", fc, peer,
                      type(e).__name__, e)
            log.debug("request failed", exc_info=True)
            return P.exception(fc, P.Exc.DEVICE_FAILURE)

    async def _serve(self, u, req: P.Request, peer: str | None) -> bytes:
        c = self.store.counters
        if req.writes:
            if not u.may_write(peer):
                c["refused"] += 1
                self.rlog(logging.INFO, f"refused:{peer}", "unit %d: write from %s refused (%s)", u.unit_id,
                          peer, u.write_policy())
                return P.exception(req.fc, P.Exc.ILLEGAL_FUNCTION)
            async with u.lock:
                rc = await u.owner.handle_write(u, req.write_addr, list(req.values), peer)
            if rc is not None:
                if rc == P.Exc.ILLEGAL_VALUE:
                    c["bad_value"] += 1
                return P.exception(req.fc, rc)
            c["writes"] += 1
            if not req.reads:
                return P.write_reply(req)
        c["reads"] += 1
        if req.fc == P.READ_INPUT:
            regs = P.read_range(u.input_image(), req.read_addr, req.read_count)
            if not isinstance(regs, P.Exc):
                regs = u.decorate_input(regs, req.read_addr, peer)
        else:
            regs = P.read_range(u.hr, req.read_addr, req.read_count)
        if isinstance(regs, P.Exc):
            return P.exception(req.fc, regs)
        return P.read_reply(req.fc, regs)
