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
:data:`RESERVE_MAX_ROWS` rows) that :meth:`pending` serves like stored rows, so the broker still
gets them in seq order; confirmations that cannot be deleted are remembered. Every
:data:`RETRY_S` the reserve is written again; when that succeeds ``disk_ok`` turns True and
``on_disk_state(True, info)`` is called. What the reserve still holds at :meth:`close` is lost
(logged with its count).
"""
from __future__ import annotations

import json
import logging
import os
import sqlite3
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .. import safeout

log = logging.getLogger("hookwatch.outbox")

#: bytes counted per row on top of topic and payload (index, row header)
ROW_OVERHEAD = 64

KINDS = ("status", "state", "telemetry", "event", "alarm", "result", "reply")
#: rows (not telemetry) kept in memory while the disk refuses writes
RESERVE_MAX_ROWS = 20_000
#: seconds between attempts to write the reserve to a disk that refused writes
RETRY_S = 1.0
#: at most one "still cannot write" log line per this many seconds
LOG_INTERVAL_S = 60.0


@dataclass(slots=True)
class Row:
    seq: int
    kind: str
    topic: str
    payload: bytes
    qos: int = 1
    retain: bool = False
    created: float = 0.0
    #: MQTT 5 Correlation Data of a reply sent to a request's Response Topic (None: none)
    correlation: bytes | None = None

    @property
    def size(self) -> int:
        return len(self.payload) + len(self.topic) + ROW_OVERHEAD


class Outbox:
    def __init__(self, path: str, telemetry_budget_bytes: int = 50 * 1024 * 1024):
        self.path = path
        self.budget = int(telemetry_budget_bytes)
        d = os.path.dirname(os.path.abspath(path))
        os.makedirs(d, exist_ok=True)
        self.db = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=10.0)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=NORMAL")
        self.db.execute("CREATE TABLE IF NOT EXISTS messages (seq INTEGER PRIMARY KEY, kind TEXT NOT NULL, "
                        "topic TEXT NOT NULL, payload BLOB NOT NULL, qos INTEGER NOT NULL, "
                        "retain INTEGER NOT NULL, created REAL NOT NULL)")
        self.db.execute("CREATE INDEX IF NOT EXISTS messages_kind ON messages (kind, seq)")
        if "correlation" not in {r[1] for r in self.db.execute("PRAGMA table_info(messages)")}:
            self.db.execute("ALTER TABLE messages ADD COLUMN correlation BLOB")   # outbox of ≤ 0.1
        self.db.execute("CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
        r = self.db.execute("SELECT value FROM meta WHERE key='last_seq'").fetchone()
        m = self.db.execute("SELECT MAX(seq) FROM messages").fetchone()[0]
        self._last_seq = max(int(r[0]) if r else 0, int(m or 0))
        self._seq_lock = threading.Lock()
        self.telemetry_bytes = int(self.db.execute(
            "SELECT COALESCE(SUM(LENGTH(payload) + LENGTH(topic) + ?), 0) FROM messages WHERE kind='telemetry'",
            (ROW_OVERHEAD,)).fetchone()[0])
        self.dropped_telemetry = 0
        self.superseded_states = 0
        self.confirmed = 0
        self._closed = False
        # disk state (see the module doc)
        self.disk_ok = True
        self.on_disk_state: Callable[[bool, dict[str, Any]], None] | None = None
        self.refused_telemetry = 0
        self.lost_rows = 0
        self.write_errors = 0
        self._reserve: OrderedDict[int, Row] = OrderedDict()
        self._meta_pending: dict[str, Any] = {}
        self._confirm_pending: set[int] = set()
        self._last_try = 0.0
        self._last_log = 0.0
        self._errors_unlogged = 0
        self._fail_reason = ""
        self._fail_since = 0.0
        self._sent_hint = 0
        self._last_ok_log = 0.0

    # -- any thread
    def next_seq(self) -> int:
        with self._seq_lock:
            self._last_seq += 1
            return self._last_seq

    @property
    def last_seq(self) -> int:
        return self._last_seq

    # -- the owner thread
    def meta_get(self, key: str):
        r = self.db.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return json.loads(r[0]) if r else None

    def add(self, rows: list[Row], sent_upto: int = 0, meta: dict | None = None) -> None:
        """Store rows (one transaction). Rows with seq <= ``sent_upto`` are already handed to the
        client and are never dropped by the retention rules. Never raises for a full or
        read-only disk (see the module doc)."""
        if not rows and not meta:
            return
        self._sent_hint = max(self._sent_hint, sent_upto)
        if not self.disk_ok:
            self._hold(rows, meta, sent_upto)
            self.retry(sent_upto)
            return
        try:
            self._add_db(rows, sent_upto, meta)
        except sqlite3.DatabaseError as e:
            self._failed(e)
            self._hold(rows, meta, sent_upto)

    # -- disk state
    def _failed(self, e: Exception) -> None:
        self.write_errors += 1
        now = time.monotonic()
        self._last_try = now
        if self.disk_ok:
            self.disk_ok = False
            self._fail_reason = str(e)
            self._fail_since = now
            self._notify(False, {"reason": self._fail_reason})
            if self._last_log and now - self._last_log < LOG_INTERVAL_S:
                self._errors_unlogged += 1      # a disk at its limit flaps: one line a minute
                return
            self._last_log = now
            self._errors_unlogged = 0
            log.error("outbox %s: cannot write (%s): disk state FAILED; new telemetry refused, events, "
                      "alarms and results kept in memory (up to %d) and still sent", self.path, e,
                      RESERVE_MAX_ROWS)
        else:
            self._errors_unlogged += 1
            if now - self._last_log >= LOG_INTERVAL_S:
                log.error("outbox %s: still cannot write (%s): %d failed attempts since the last line; "
                          "%d telemetry messages refused, %d rows held in memory", self.path, e,
                          self._errors_unlogged, self.refused_telemetry, len(self._reserve))
                self._last_log = now
                self._errors_unlogged = 0

    def _notify(self, ok: bool, info: dict[str, Any]) -> None:
        if self.on_disk_state is not None:
            try:
                self.on_disk_state(ok, info)
            except Exception:
                log.exception("outbox %s: disk state callback failed", self.path)

    def _hold(self, rows: list[Row], meta: dict | None, sent_upto: int) -> None:
        for r in rows:
            if r.kind == "telemetry":
                self.refused_telemetry += 1
                continue
            if r.kind == "state":       # a newer state supersedes unsent ones, as on disk
                old = [s for s, x in self._reserve.items() if x.kind == "state" and sent_upto < s < r.seq]
                for s in old:
                    del self._reserve[s]
                self.superseded_states += len(old)
            self._reserve[r.seq] = r
            self._last_seq = max(self._last_seq, r.seq)
        over = len(self._reserve) - RESERVE_MAX_ROWS
        if over > 0:
            for _ in range(over):
                self._reserve.popitem(last=False)
            self.lost_rows += over
            log.error("outbox %s: in-memory reserve full: %d oldest rows dropped (%d so far)", self.path,
                      over, self.lost_rows)
        if meta:
            self._meta_pending.update(meta)

    def retry(self, sent_upto: int | None = None, force: bool = False) -> bool:
        """Write the reserve (and remembered confirmations) if the disk takes it again; at most
        once per :data:`RETRY_S` unless ``force``. True when the disk state is ok."""
        if self.disk_ok:
            return True
        now = time.monotonic()
        if not force and now - self._last_try < RETRY_S:
            return False
        self._last_try = now
        sent_upto = self._sent_hint if sent_upto is None else sent_upto
        rows = list(self._reserve.values())
        try:
            if self._confirm_pending:
                self._delete_db(sorted(self._confirm_pending))
                self._confirm_pending.clear()
            # a real write proves the disk takes data again (also when nothing is held)
            self._add_db(rows, sent_upto, self._meta_pending or {"disk_probe": time.time()})
        except sqlite3.DatabaseError as e:
            self._failed(e)
            return False
        self._reserve.clear()
        self._meta_pending = {}
        self.disk_ok = True
        info = {"reason": self._fail_reason, "duration_s": round(now - self._fail_since, 3),
                "refused_telemetry": self.refused_telemetry, "rows_written": len(rows),
                "lost_rows": self.lost_rows}
        if now - self._last_ok_log >= LOG_INTERVAL_S:
            self._last_ok_log = now
            log.warning("outbox %s: writing again after %.1f s; %d held rows stored, %d telemetry messages "
                        "refused so far", self.path, info["duration_s"], len(rows), self.refused_telemetry)
        self._notify(True, info)
        return True

    def _add_db(self, rows: list[Row], sent_upto: int, meta: dict | None) -> None:
        if not rows and not meta:
            return
        before = (self.telemetry_bytes, self.dropped_telemetry)
        try:
            self._add_tx(rows, sent_upto, meta)
        except BaseException:
            self.telemetry_bytes, self.dropped_telemetry = before
            raise

    def _add_tx(self, rows: list[Row], sent_upto: int, meta: dict | None) -> None:
        cur = self.db.cursor()
        cur.execute("BEGIN IMMEDIATE")
        try:
            max_seq = 0
            newest_state = None
            for r in rows:
                cur.execute("INSERT OR REPLACE INTO messages (seq, kind, topic, payload, qos, retain, created, "
                            "correlation) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                            (r.seq, r.kind, r.topic, r.payload, r.qos, int(r.retain), r.created or time.time(),
                             r.correlation))
                max_seq = max(max_seq, r.seq)
                if r.kind == "telemetry":
                    self.telemetry_bytes += r.size
                elif r.kind == "state":
                    newest_state = r.seq if newest_state is None else max(newest_state, r.seq)
            if newest_state is not None:
                n = cur.execute("DELETE FROM messages WHERE kind='state' AND seq < ? AND seq > ?",
                                (newest_state, sent_upto)).rowcount
                self.superseded_states += max(n, 0)
            if self.telemetry_bytes > self.budget:
                self._trim_telemetry(cur, sent_upto)
            cur.execute("INSERT INTO meta (key, value) VALUES ('last_seq', ?) ON CONFLICT(key) DO UPDATE "
                        "SET value=excluded.value WHERE CAST(value AS INTEGER) < CAST(excluded.value AS INTEGER)",
                        (str(max(max_seq, self._last_seq)),))
            for k, v in (meta or {}).items():
                cur.execute("INSERT INTO meta (key, value) VALUES (?, ?) ON CONFLICT(key) DO UPDATE "
                            "SET value=excluded.value", (k, safeout.dumps(v)))
            cur.execute("COMMIT")
        except BaseException:
            _rollback(cur)
            raise

    def _trim_telemetry(self, cur, sent_upto: int) -> None:
        """Drop the oldest unsent telemetry down to 90 % of the budget."""
        target = int(self.budget * 0.9)
        while self.telemetry_bytes > target:
            batch = cur.execute("SELECT seq, LENGTH(payload) + LENGTH(topic) + ? FROM messages "
                                "WHERE kind='telemetry' AND seq > ? ORDER BY seq LIMIT 500",
                                (ROW_OVERHEAD, sent_upto)).fetchall()
            if not batch:
                break
            upto, freed = None, 0
            for seq, size in batch:
                upto = seq
                freed += size
                if self.telemetry_bytes - freed <= target:
                    break
            n = cur.execute("DELETE FROM messages WHERE kind='telemetry' AND seq > ? AND seq <= ?",
                            (sent_upto, upto)).rowcount
            self.telemetry_bytes -= freed
            self.dropped_telemetry += max(n, 0)
        if self.dropped_telemetry:
            log.warning("outbox %s: telemetry over budget (%d bytes); %d oldest telemetry messages dropped "
                        "so far", self.path, self.budget, self.dropped_telemetry)

    def confirm(self, seqs: list[int]) -> None:
        """The broker confirmed these: delete them (one transaction). Never raises for a full or
        read-only disk: held rows are dropped from memory, the rest remembered and deleted later."""
        if not seqs:
            return
        rest = []
        for s in seqs:
            if self._reserve.pop(s, None) is None:
                rest.append(s)
        self.confirmed += len(seqs)
        if not rest:
            return
        if not self.disk_ok:
            self._confirm_pending.update(rest)
            return
        try:
            self._delete_db(rest)
        except sqlite3.DatabaseError as e:
            self._failed(e)
            self._confirm_pending.update(rest)

    def _delete_db(self, seqs: list[int]) -> None:
        cur = self.db.cursor()
        cur.execute("BEGIN IMMEDIATE")
        try:
            freed = 0
            for s in seqs:
                r = cur.execute("SELECT kind, LENGTH(payload) + LENGTH(topic) + ? FROM messages WHERE seq=?",
                                (ROW_OVERHEAD, s)).fetchone()
                if r is None:
                    continue
                if r[0] == "telemetry":
                    freed += r[1]
                cur.execute("DELETE FROM messages WHERE seq=?", (s,))
            cur.execute("COMMIT")
        except BaseException:
            _rollback(cur)
            raise
        self.telemetry_bytes -= freed

    def pending(self, after_seq: int, limit: int) -> list[Row]:
        """Stored rows (and rows held in memory) with seq > after_seq, oldest first."""
        if not self.disk_ok:
            self.retry()
        cur = self.db.execute("SELECT seq, kind, topic, payload, qos, retain, created, correlation FROM "
                              "messages WHERE seq > ? ORDER BY seq LIMIT ?",
                              (after_seq, int(limit) + len(self._confirm_pending)))
        rows = [Row(s, k, t, bytes(p), q, bool(r), c, None if cd is None else bytes(cd))
                for s, k, t, p, q, r, c, cd in cur.fetchall() if s not in self._confirm_pending]
        if self._reserve:
            rows += [r for s, r in self._reserve.items() if s > after_seq]
            rows.sort(key=lambda r: r.seq)
        return rows[: int(limit)]

    def count(self, kind: str | None = None) -> int:
        """Rows not yet confirmed (stored and held in memory)."""
        if kind is None:
            n = self.db.execute("SELECT COUNT(*) FROM messages").fetchone()[0]
            return n + len(self._reserve) - len(self._confirm_pending)
        n = self.db.execute("SELECT COUNT(*) FROM messages WHERE kind=?", (kind,)).fetchone()[0]
        return n + sum(1 for r in self._reserve.values() if r.kind == kind)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            if not self.retry(force=True) and self._reserve:
                log.error("outbox %s: closing on a disk that refuses writes: %d held messages lost",
                          self.path, len(self._reserve))
            try:
                self.db.execute("PRAGMA wal_checkpoint(PASSIVE)")
            except sqlite3.Error:
                pass
            self.db.close()


def _rollback(cur) -> None:
    try:
        cur.execute("ROLLBACK")
    except sqlite3.Error:
        pass      # no transaction left (SQLite rolled it back itself on a full disk)
