"""The SQLite file of an outbox (WAL): its rows, the retention rules, the meta table.

:class:`OutboxTable` is what reached the disk: the ``messages`` table (one :class:`Row` per
message, keyed by its ``seq``) and the ``meta`` table (``last_seq``, and what an engine keeps
there: the ``status`` session number, Sparkplug's bdSeq). Each write is one transaction and
applies the retention rules of :mod:`.outbox` (a newer ``state`` drops the unsent older ones;
telemetry over its byte budget loses its oldest unsent rows); a failed transaction is rolled
back and leaves the running figures as they were. Every method may raise
:class:`sqlite3.DatabaseError` (a full or read-only disk): :class:`.outbox.Outbox` turns that
into the disk state (:mod:`.outbox_reserve`), so what reached the disk always reads back.

Used from the outbox's owner thread only.
"""
from __future__ import annotations

import json
import logging
import os
import sqlite3
import time
from dataclasses import dataclass

from ...plumbing import safeout

log = logging.getLogger("hookwatch.outbox")

#: bytes counted per row on top of topic and payload (index, row header)
ROW_OVERHEAD = 64

KINDS = ("status", "state", "telemetry", "event", "alarm", "result", "reply")

#: what the meta table holds: key → any value gateway/plumbing/safeout.py writes as JSON (read back as
#: JSON: :meth:`OutboxTable.meta_get`; an integer kept there, typed: :meth:`OutboxTable.meta_int`)
Meta = dict[str, object]


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


class OutboxTable:
    """The outbox file (see the module docstring): open (and create or upgrade) it at ``path``;
    ``budget`` bytes of telemetry at most."""

    def __init__(self, path: str, budget: int) -> None:
        self.path = path
        self.budget = int(budget)
        os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
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
        #: the highest seq the file knows (its counter, or its newest row)
        self.last_seq = max(int(r[0]) if r else 0, int(m or 0))
        #: bytes of the stored telemetry (as ROW_OVERHEAD counts them), kept with every write
        self.telemetry_bytes = int(self.db.execute(
            "SELECT COALESCE(SUM(LENGTH(payload) + LENGTH(topic) + ?), 0) FROM messages WHERE kind='telemetry'",
            (ROW_OVERHEAD,)).fetchone()[0])
        self.dropped_telemetry = 0
        self.superseded_states = 0

    def meta_get(self, key: str) -> object:
        """The value kept under ``key`` (as JSON reads it back); None when there is none."""
        r = self.db.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        value: object = json.loads(r[0]) if r else None
        return value

    def meta_int(self, key: str) -> int | None:
        """The integer kept under ``key`` (the engines' counters: the ``status`` session, Sparkplug's
        bdSeq); None when there is none, or what is there is not an integer."""
        v = self.meta_get(key)
        return v if isinstance(v, int) and not isinstance(v, bool) else None

    # -- writes (one transaction each; raise sqlite3.DatabaseError on a full or read-only disk)
    def insert(self, rows: list[Row], sent_upto: int, meta: Meta | None, last_seq: int) -> None:
        """Store ``rows`` and ``meta`` and raise the stored counter to ``last_seq``, with the
        retention rules (rows with seq <= ``sent_upto`` are in flight: never dropped)."""
        if not rows and not meta:
            return
        before = (self.telemetry_bytes, self.dropped_telemetry)
        try:
            self._insert_tx(rows, sent_upto, meta, last_seq)
        except BaseException:
            self.telemetry_bytes, self.dropped_telemetry = before
            raise

    def _insert_tx(self, rows: list[Row], sent_upto: int, meta: Meta | None, last_seq: int) -> None:
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
                        (str(max(max_seq, last_seq)),))
            for k, v in (meta or {}).items():
                cur.execute("INSERT INTO meta (key, value) VALUES (?, ?) ON CONFLICT(key) DO UPDATE "
                            "SET value=excluded.value", (k, safeout.dumps(v)))
            cur.execute("COMMIT")
        except BaseException:
            _rollback(cur)
            raise

    def _trim_telemetry(self, cur: sqlite3.Cursor, sent_upto: int) -> None:
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

    def delete(self, seqs: list[int]) -> None:
        """Delete the rows of ``seqs`` (confirmed by the broker); an unknown seq is skipped."""
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

    # -- reads
    def select(self, after_seq: int, limit: int, skip: set[int]) -> list[Row]:
        """Stored rows with seq > ``after_seq``, oldest first, at most ``limit`` of them once the
        seqs in ``skip`` (confirmed, their delete not written yet) are left out."""
        cur = self.db.execute("SELECT seq, kind, topic, payload, qos, retain, created, correlation FROM "
                              "messages WHERE seq > ? ORDER BY seq LIMIT ?",
                              (after_seq, int(limit) + len(skip)))
        return [Row(s, k, t, bytes(p), q, bool(r), c, None if cd is None else bytes(cd))
                for s, k, t, p, q, r, c, cd in cur.fetchall() if s not in skip][: int(limit)]

    def count(self, kind: str | None = None) -> int:
        """Stored rows (of ``kind``)."""
        if kind is None:
            n: int = self.db.execute("SELECT COUNT(*) FROM messages").fetchone()[0]
        else:
            n = self.db.execute("SELECT COUNT(*) FROM messages WHERE kind=?", (kind,)).fetchone()[0]
        return n

    def close(self) -> None:
        try:
            self.db.execute("PRAGMA wal_checkpoint(PASSIVE)")
        except sqlite3.Error:
            pass
        self.db.close()


def _rollback(cur: sqlite3.Cursor) -> None:
    try:
        cur.execute("ROLLBACK")
    except sqlite3.Error:
        pass      # no transaction left (SQLite rolled it back itself on a full disk)
