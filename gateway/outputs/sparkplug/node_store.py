"""The edge node's SQLite store: its bdSeq and its store-and-forward rows (the outbox's public API).

One store per edge node (``sparkplug.store_path``, :mod:`gateway.outputs.broker.outbox`): the bdSeq of
the coming CONNECT is written to it before each CONNECT (a WAL commit: a restart after kill -9
continues from it), and the DDATA held while no primary host listens wait in it
(:class:`OutboxBuffer`, the node's :class:`~.replay.Buffer`). A store that cannot be opened is a
state, not a crash: the data is then held in memory only and bdSeq restarts at 0 (logged once).
"""
from __future__ import annotations

import collections
import logging
import sqlite3
import time

from ..broker.outbox import Outbox, Row
from .bdseq import BdSeq
from .node_settings import SparkplugSettings
from .replay import Buffer, MemoryBuffer

log = logging.getLogger("hookwatch.sparkplug")


class OutboxBuffer:
    """The node's store-and-forward buffer on the SQLite outbox (its public API only).

    A store that cannot be written (disk full, I/O error) is a state, not a crash: rows wait in
    memory (at most ``memory_max``; beyond, the oldest measured values are dropped, counted) and
    are written to disk as soon as it accepts them again; the replay takes disk rows, then these.
    """

    def __init__(self, outbox: Outbox, memory_max: int = 20_000):
        self.ob = outbox
        self.memory: collections.deque = collections.deque()    # (key, Row, telemetry)
        self.memory_max = memory_max
        self.store_errors = 0
        self.dropped = 0

    def _flush_memory(self) -> bool:
        if not self.memory:
            return True
        try:
            self.ob.add([r for _k, r, _t in self.memory])
        except sqlite3.Error:
            return False
        self.memory.clear()
        log.warning("sparkplug store %s writable again; held rows written", self.ob.path)
        return True

    def put(self, topic: str, payload: bytes, telemetry: bool) -> None:
        row = Row(self.ob.next_seq(), "telemetry" if telemetry else "event", topic, payload, 0, False,
                  time.time())
        if self._flush_memory():
            try:
                self.ob.add([row])
                return
            except sqlite3.Error as e:
                self.store_errors += 1
                if self.store_errors == 1 or self.store_errors % 1000 == 0:
                    log.error("sparkplug store %s not writable (%s): data held in memory (%d errors so "
                              "far)", self.ob.path, e, self.store_errors)
        self.memory.append((row.seq, row, telemetry))
        if len(self.memory) > self.memory_max:
            for i, (_k, _r, tel) in enumerate(self.memory):
                if tel:
                    del self.memory[i]
                    break
            else:
                self.memory.popleft()
            self.dropped += 1

    def peek(self, n: int) -> list[tuple[int, str, bytes]]:
        self._flush_memory()
        try:
            rows = [(r.seq, r.topic, r.payload) for r in self.ob.pending(0, n)]
        except sqlite3.Error:
            rows = []
        for k, r, _t in self.memory:
            if len(rows) >= n:
                break
            rows.append((k, r.topic, r.payload))
        return rows

    def remove(self, keys: list[int]) -> None:
        ks = set(keys)
        if self.memory:
            self.memory = collections.deque(x for x in self.memory if x[0] not in ks)
        try:
            self.ob.confirm(keys)
        except sqlite3.Error as e:
            # they were published: a resend after a restart is flagged historical, harmless
            log.error("sparkplug store %s: cannot delete replayed rows: %s", self.ob.path, e)

    def __len__(self) -> int:
        try:
            n = self.ob.count()
        except sqlite3.Error:
            n = 0
        return n + len(self.memory)


class NodeStore:
    """The node's store, opened by the node thread's owner and closed when the thread ends."""

    def __init__(self, s: SparkplugSettings, counters: collections.Counter[str]) -> None:
        self.counters = counters
        self.outbox: Outbox | None = None
        #: the bdSeq persisted by the last process (None: none, or no store)
        self.last_bdseq: int | None = None
        try:
            self.outbox = Outbox(s.store_path, s.history_budget_bytes)
            self.last_bdseq = self.outbox.meta_int("bdseq")
        except (OSError, sqlite3.Error) as e:
            log.error("sparkplug %s/%s: store %s unusable (%s): data is held in memory only and bdSeq "
                      "restarts at 0", s.group_id, s.edge_node_id, s.store_path, e)

    def buffer(self) -> Buffer:
        """The node's store-and-forward buffer: on the outbox, or in memory without one."""
        return OutboxBuffer(self.outbox) if self.outbox is not None else MemoryBuffer()

    def persist_bdseq(self, bdseq: BdSeq) -> None:
        """The bdSeq of the coming CONNECT, or the last one used, kept for the next process."""
        if self.outbox is None:
            return
        last = bdseq.last_used()
        try:
            self.outbox.add([], meta={"bdseq": last})
        except sqlite3.Error as e:
            self.counters["bdseq_store_errors"] += 1
            log.error("sparkplug: cannot persist bdSeq %s: %s", last, e)

    def close(self) -> None:
        if self.outbox is not None:
            self.outbox.close()
