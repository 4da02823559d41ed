"""On-disk outbox (SQLite, WAL) of one station's MQTT messages: kept until the broker confirms.

Used from a single thread (the MQTT pump), except :meth:`Outbox.next_seq`, which any thread may
call. Rows carry the per-station sequence number ``seq`` (also inside their JSON payload); the
counter is persisted, so it keeps increasing across restarts.

Retention rules (see docs/mqtt.md, Delivery):
- events, alarms, results and replies stay until confirmed;
- telemetry stays within a byte budget; over it the oldest unsent telemetry is dropped;
- a ``state`` row not yet handed to the client is dropped when a newer state arrives.
"""
from __future__ import annotations

import json
import logging
import os
import sqlite3
import threading
import time
from dataclasses import dataclass

log = logging.getLogger("hookwatch.outbox")

#: bytes counted per row on top of topic and payload (index, row header)
ROW_OVERHEAD = 64

KINDS = ("status", "state", "telemetry", "event", "alarm", "result", "reply")


@dataclass(slots=True)
class Row:
    seq: int
    kind: str
    topic: str
    payload: bytes
    qos: int = 1
    retain: bool = False
    created: float = 0.0

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
        client and are never dropped by the retention rules."""
        if not rows and not meta:
            return
        cur = self.db.cursor()
        cur.execute("BEGIN IMMEDIATE")
        try:
            max_seq = 0
            newest_state = None
            for r in rows:
                cur.execute("INSERT OR REPLACE INTO messages (seq, kind, topic, payload, qos, retain, created) "
                            "VALUES (?, ?, ?, ?, ?, ?, ?)",
                            (r.seq, r.kind, r.topic, r.payload, r.qos, int(r.retain), r.created or time.time()))
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
                            "SET value=excluded.value", (k, json.dumps(v)))
            cur.execute("COMMIT")
        except BaseException:
            cur.execute("ROLLBACK")
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
        """The broker confirmed these: delete them (one transaction)."""
        if not seqs:
            return
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
            cur.execute("ROLLBACK")
            raise
        self.telemetry_bytes -= freed
        self.confirmed += len(seqs)

    def pending(self, after_seq: int, limit: int) -> list[Row]:
        """Stored rows with seq > after_seq, oldest first."""
        cur = self.db.execute("SELECT seq, kind, topic, payload, qos, retain, created FROM messages "
                              "WHERE seq > ? ORDER BY seq LIMIT ?", (after_seq, int(limit)))
        return [Row(s, k, t, bytes(p), q, bool(r), c) for s, k, t, p, q, r, c in cur.fetchall()]

    def count(self, kind: str | None = None) -> int:
        if kind is None:
            return self.db.execute("SELECT COUNT(*) FROM messages").fetchone()[0]
        return self.db.execute("SELECT COUNT(*) FROM messages WHERE kind=?", (kind,)).fetchone()[0]

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self.db.execute("PRAGMA wal_checkpoint(PASSIVE)")
            except sqlite3.Error:
                pass
            self.db.close()
