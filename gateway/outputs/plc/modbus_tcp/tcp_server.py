"""The asyncio Modbus TCP server: connections, limits, pacing, dispatch to the units.

- connections: a :class:`~gateway.plumbing.doors.Door` (the one mechanism of every listening port): at most
  ``max_connections`` per server (:data:`MAX_CONNECTIONS`, within the process's descriptor
  budget) and :data:`MAX_PER_CLIENT` per client address (the door's per-address cap and
  eviction, as on every door). The PLC always finds room: clients in
  the stations' ``allowed_clients`` (the allow-list) have :data:`RESERVED_FOR_ALLOWED` slots no
  other address may take, and at the cap an allowed client's connection closes the oldest
  connection of the address holding the most (busy or idle). Any other client at a cap closes
  that address's (or anyone's) connection idle longest if it has been idle ≥ :data:`EVICT_IDLE_S`,
  else it is closed at once (counted, one log line a minute);
- a connection that does not complete a whole Modbus request within ``idle_timeout_s`` of its
  accept or of its previous reply is closed, however many single bytes it trickles; a request
  begun must be complete within ``request_timeout_s``; a reply not read for ``idle_timeout_s``
  closes the connection;
- frames: :class:`~.framer.Framer` (several requests per segment, requests split over segments);
  requests of one connection are answered one after the other, in order; a header that is not
  Modbus closes that connection (counted, one log line a minute, no traceback);
- every request waits for the server-wide :class:`Pacer` (requests per second);
- requests go to the unit (one per station) by unit id; an unknown unit id answers 0x0B.

The units are duck-typed: ``input_image()`` (the input registers), ``hr`` (the holding registers),
``lock``, ``may_write(peer)``, ``allowed(peer)`` (in the allow-list, writes enabled or not) and
``owner.handle_write(unit, address, values, peer)`` (an awaitable giving ``None`` or an
:class:`~.pdu.Exc`).
"""
from __future__ import annotations

import asyncio
import dataclasses
import logging
import socket
import time
from typing import Any

from ....plumbing.doors import EVICT_IDLE_S, Conn, Door, DoorLimits, RateLog
from . import pdu as P
from .framer import FrameError, Framer, encode

log = logging.getLogger("hookwatch.modbus")

MAX_CONNECTIONS = 64
MAX_PER_CLIENT = 16
IDLE_TIMEOUT_S = 60.0
REQUEST_TIMEOUT_S = 10.0
#: slots only clients of the allow-list may take
RESERVED_FOR_ALLOWED = 4
READ_CHUNK = 4096
LOG_INTERVAL_S = 60.0

__all__ = ["EVICT_IDLE_S", "ModbusTcpServer", "Pacer", "RateLog", "Store"]


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
            "connections": 0, "failed": 0, "evicted": 0, "request_timeouts": 0,
            "accept_errors": 0}


class ModbusTcpServer:
    def __init__(self, store: Store, pacer: Pacer | None = None, *, max_connections: int | None = None,
                 max_per_client: int | None = None, idle_timeout_s: float | None = None,
                 limits: DoorLimits | None = None):
        self.store = store
        self.pacer = pacer
        lim = limits or DoorLimits(MAX_CONNECTIONS, REQUEST_TIMEOUT_S, IDLE_TIMEOUT_S,
                                   max_per_address=MAX_PER_CLIENT)
        if max_connections is not None:
            lim = dataclasses.replace(lim, max_connections=max_connections)
        if idle_timeout_s is not None:
            lim = dataclasses.replace(lim, request_timeout_s=min(lim.request_timeout_s, idle_timeout_s),
                                      idle_timeout_s=idle_timeout_s)
        if max_per_client is not None:
            lim = dataclasses.replace(lim, max_per_address=max_per_client)
        self.limits = lim
        self.max_per_client = lim.max_per_address
        self.idle_timeout_s = lim.idle_timeout_s
        self.rlog = RateLog(log)
        self.door: Door | None = None
        self._tasks: set[asyncio.Task] = set()
        self._writers: dict[Conn, asyncio.StreamWriter] = {}

    @property
    def max_connections(self) -> int:
        return self.door.cap if self.door is not None else self.limits.max_connections

    async def start(self, host: str, port: int) -> None:
        """Listen (a :class:`~gateway.plumbing.doors.Door`: connections are accepted one at a time by our
        own loop, and one over a cap is closed before the next is accepted)."""
        door = Door(f"Modbus TCP {host}:{port}", self.limits, self._serve_conn,
                    make_room=self._make_room, logger=log, counters=self.store.counters)
        await door.listen(host, port)
        self.door = door

    async def close(self) -> None:
        if self.door is not None:
            await self.door.close()
        for t in list(self._tasks):
            t.cancel()
        if self._tasks:
            await asyncio.gather(*self._tasks, return_exceptions=True)
        self.rlog.close()               # the counts of the last window, and no timer after

    @property
    def connections(self) -> int:
        return self.door.connections if self.door is not None else 0

    def _allowed(self, peer: str) -> bool:
        for u in list(self.store.units.values()):
            fn = getattr(u, "allowed", None)
            if fn is not None and fn(peer):
                return True
        return False

    # -- admission (the door calls it at its cap; the per-address cap is the door's, the
    #    allow-list's reserve is ours)
    def _make_room(self, peer: str) -> bool:
        door = self.door
        if door is None:
            return False
        if self._allowed(peer):
            return door.evict_busiest(peer, exclude=self._allowed, fair=False)
        return door.evict_idle(exclude=self._allowed)

    def _admit(self, door: Door, peer: str) -> bool:
        """Room for a connection ``peer`` the door has accepted (within its caps)."""
        if not self._allowed(peer):
            others = sum(1 for c in door.conns if not self._allowed(c.peer))
            # ``others`` counts this connection too (the door registered it)
            if others > max(1, door.cap - RESERVED_FOR_ALLOWED) and not door.evict_idle(exclude=self._allowed):
                return False
        return True

    # -- connections
    async def _serve_conn(self, sock: socket.socket, conn: Conn) -> None:
        door = self.door
        c = self.store.counters
        if door is None or not self._admit(door, conn.peer):
            c["refused_connections"] += 1
            self.rlog(logging.WARNING, "cap", "Modbus TCP: connection from %s refused (%d open, at most "
                      "%d; at most %d per client address)", conn.peer, door.connections if door else 0,
                      self.max_connections, self.max_per_client)
            if door is not None:
                door.gone(conn)
            sock.close()
            return
        reader, writer = await asyncio.open_connection(sock=sock, limit=READ_CHUNK)
        conn.transport = writer.transport
        conn.close = writer.transport.abort
        self._writers[conn] = writer
        t = asyncio.get_running_loop().create_task(self._connection(reader, writer, conn))
        self._tasks.add(t)
        t.add_done_callback(self._tasks.discard)

    async def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                          conn: Conn) -> None:
        c = self.store.counters
        peer = conn.peer
        door = self.door
        c["connections"] += 1
        framer = Framer()
        try:
            while True:
                data = await reader.read(READ_CHUNK)
                if not data:
                    break
                conn.data()
                try:
                    frames = framer.feed(data)
                except FrameError as e:
                    c["malformed"] += 1
                    self.rlog(logging.WARNING, "malformed", "Modbus TCP: malformed frame from %s (%s); "
                              "connection closed", peer, e)
                    break
                if not frames:
                    continue
                conn.begin()
                for f in frames:
                    reply = await self.handle(f.unit, f.pdu, peer)
                    writer.write(encode(f.tid, f.unit, reply))
                try:
                    await asyncio.wait_for(writer.drain(), self.idle_timeout_s)
                except TimeoutError:
                    c["idle_closed"] += 1
                    break
                conn.end()
                if framer.pending:
                    conn.data()          # the next request has begun
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            if door is not None:
                door.gone(conn)
            self._writers.pop(conn, None)
            writer.transport.abort()

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
