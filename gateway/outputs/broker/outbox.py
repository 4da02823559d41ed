"""On-disk outbox (SQLite, WAL) of one station's MQTT messages: kept until the broker confirms.

Used from a single thread (the MQTT pump), except :meth:`Outbox.next_seq`, which any thread may
call. Rows carry the per-station sequence number ``seq`` (also inside their JSON payload); the
counter is persisted, so it keeps increasing across restarts.

Retention rules (see docs/mqtt.md, Delivery):
- events, alarms, results and replies stay until confirmed;
- telemetry stays within a byte budget; over it the oldest unsent telemetry is dropped;
- a ``state`` row not yet handed to the client is dropped when a newer state arrives.

A full or read-only disk (``database or disk is full``, ``readonly database``, I/O error) is a
*state*, never an exception past the outbox: ``disk_ok`` turns False, ``on_disk_state(False, info)``
is called and one error line is logged (then at most one a minute, with counts). While it lasts,
new telemetry is refused (counted in ``refused_telemetry``); every other row (events, alarms,
results, replies, status, state) is kept in an in-memory reserve (at most
:data:`.outbox_reserve.RESERVE_MAX_ROWS` rows) that :meth:`pending` serves like stored rows, so
the broker still gets them in seq order; confirmations that cannot be deleted are remembered.
Every :data:`.outbox_reserve.RETRY_S` the reserve is written again; when that succeeds
``disk_ok`` turns True and ``on_disk_state(True, info)`` is called. What the reserve still holds
at :meth:`close` is lost (logged with its count).

The outbox is three rooms: this module (the seq counter, and what the engines call: store,
confirm, read in seq order), :mod:`.outbox_table` (the SQLite file: rows, retention rules, meta)
and :mod:`.outbox_reserve` (the disk state and its in-memory reserve).
"""
from __future__ import annotations

import logging
import sqlite3
import threading
import time

from .outbox_reserve import DiskFullReserve, DiskStateCallback
from .outbox_table import Meta, OutboxTable, Row

__all__ = ["Outbox", "Row"]

log = logging.getLogger("hookwatch.outbox")


class Outbox:
    """One station's outbox at ``path`` (see the module docstring): the file
    (:attr:`table`) and, while the disk refuses writes, the reserve (:attr:`reserve`)."""

    def __init__(self, path: str, telemetry_budget_bytes: int = 50 * 1024 * 1024):
        self.path = path
        self.budget = int(telemetry_budget_bytes)
        self.table = OutboxTable(path, self.budget)
        self.reserve = DiskFullReserve(path)
        self._last_seq = self.table.last_seq
        self._seq_lock = threading.Lock()
        self.confirmed = 0
        self._closed = False
        self._sent_hint = 0

    # -- any thread
    def next_seq(self) -> int:
        with self._seq_lock:
            self._last_seq += 1
            return self._last_seq

    @property
    def last_seq(self) -> int:
        return self._last_seq

    # -- the figures (of the file and of the disk state)
    @property
    def telemetry_bytes(self) -> int:
        return self.table.telemetry_bytes

    @property
    def dropped_telemetry(self) -> int:
        return self.table.dropped_telemetry

    @property
    def superseded_states(self) -> int:
        return self.table.superseded_states + self.reserve.superseded_states

    @property
    def disk_ok(self) -> bool:
        return self.reserve.disk_ok

    @property
    def refused_telemetry(self) -> int:
        return self.reserve.refused_telemetry

    @property
    def lost_rows(self) -> int:
        return self.reserve.lost_rows

    @property
    def write_errors(self) -> int:
        return self.reserve.write_errors

    @property
    def on_disk_state(self) -> DiskStateCallback | None:
        """Called (owner thread) with ``(ok, info)`` when the disk state changes."""
        return self.reserve.on_disk_state

    @on_disk_state.setter
    def on_disk_state(self, callback: DiskStateCallback | None) -> None:
        self.reserve.on_disk_state = callback

    # -- the owner thread
    def meta_get(self, key: str) -> object:
        """The value kept under ``key`` in the meta table (None: none)."""
        return self.table.meta_get(key)

    def meta_int(self, key: str) -> int | None:
        """The integer kept under ``key`` in the meta table (None: none, or not an integer)."""
        return self.table.meta_int(key)

    def add(self, rows: list[Row], sent_upto: int = 0, meta: Meta | None = None) -> None:
        """Store rows (one transaction). Rows with seq <= ``sent_upto`` are already handed to the
        client and are never dropped by the retention rules. Never raises for a full or
        read-only disk (see the module doc)."""
        if not rows and not meta:
            return
        self._sent_hint = max(self._sent_hint, sent_upto)
        if not self.reserve.disk_ok:
            self._hold(rows, meta, sent_upto)
            self.retry(sent_upto)
            return
        try:
            self.table.insert(rows, sent_upto, meta, self._last_seq)
        except sqlite3.DatabaseError as e:
            self.reserve.failed(e)
            self._hold(rows, meta, sent_upto)

    def _hold(self, rows: list[Row], meta: Meta | None, sent_upto: int) -> None:
        """Into the reserve; the counter stays above every held row (it is written with them)."""
        self.reserve.hold(rows, meta, sent_upto)
        held = [r.seq for r in rows if r.kind != "telemetry"]
        if held:
            with self._seq_lock:
                self._last_seq = max(self._last_seq, *held)

    def retry(self, sent_upto: int | None = None, force: bool = False) -> bool:
        """Write the reserve (and remembered confirmations) if the disk takes it again; at most
        once per :data:`.outbox_reserve.RETRY_S` unless ``force``. True when the disk state is ok."""
        r = self.reserve
        if r.disk_ok:
            return True
        if not r.due(force):
            return False
        sent_upto = self._sent_hint if sent_upto is None else sent_upto
        rows = list(r.rows.values())
        try:
            if r.confirms:
                self.table.delete(sorted(r.confirms))
                r.confirms.clear()
            # a real write proves the disk takes data again (also when nothing is held)
            self.table.insert(rows, sent_upto, r.meta or {"disk_probe": time.time()}, self._last_seq)
        except sqlite3.DatabaseError as e:
            r.failed(e)
            return False
        r.recovered(len(rows))
        return True

    def confirm(self, seqs: list[int]) -> None:
        """The broker confirmed these: delete them (one transaction). Never raises for a full or
        read-only disk: held rows are dropped from memory, the rest remembered and deleted later."""
        if not seqs:
            return
        rest = self.reserve.take_confirmed(seqs)
        self.confirmed += len(seqs)
        if not rest:
            return
        if not self.reserve.disk_ok:
            self.reserve.confirms.update(rest)
            return
        try:
            self.table.delete(rest)
        except sqlite3.DatabaseError as e:
            self.reserve.failed(e)
            self.reserve.confirms.update(rest)

    def pending(self, after_seq: int, limit: int) -> list[Row]:
        """Stored rows (and rows held in memory) with seq > after_seq, oldest first."""
        if not self.reserve.disk_ok:
            self.retry()
        rows = self.table.select(after_seq, limit, self.reserve.confirms)
        held = self.reserve.after(after_seq)
        if held:
            rows += held
            rows.sort(key=lambda r: r.seq)
        return rows[: int(limit)]

    def count(self, kind: str | None = None) -> int:
        """Rows not yet confirmed (stored and held in memory)."""
        if kind is None:
            return self.table.count() + self.reserve.count() - len(self.reserve.confirms)
        return self.table.count(kind) + self.reserve.count(kind)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if not self.retry(force=True) and self.reserve.rows:
                log.error("outbox %s: closing on a disk that refuses writes: %d held messages lost",
                          self.path, len(self.reserve.rows))
            self.table.close()
