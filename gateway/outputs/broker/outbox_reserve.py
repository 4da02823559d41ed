"""The disk state of an outbox: a full or read-only disk is a state, never a crash.

:class:`DiskFullReserve` is what an :class:`.outbox.Outbox` holds while its file
(:class:`.outbox_table.OutboxTable`) refuses writes (``database or disk is full``, ``readonly
database``, an I/O error): the state itself (``disk_ok``, reported through ``on_disk_state(ok,
info)``, the station's status bit and event), its log lines (one when it starts, then at most one
a minute with the counts; one when the disk takes data again) and its in-memory reserve:

- new telemetry is refused (counted in ``refused_telemetry``);
- every other row (events, alarms, results, replies, status, state) waits in the reserve, at most
  :data:`RESERVE_MAX_ROWS` rows (beyond, the oldest are dropped, counted in ``lost_rows``); a newer
  ``state`` supersedes the unsent older ones there as on disk;
- ``meta`` values wait beside them, and confirmations whose delete could not be written are
  remembered (the reads leave those rows out);
- every :data:`RETRY_S` the outbox writes all of it again (:meth:`due`); when that succeeds
  :meth:`recovered` turns the state back to ok.

It touches no file: the outbox does the writes and tells it how they went. Used from the outbox's
owner thread only.
"""
from __future__ import annotations

import logging
import time
from collections import OrderedDict
from collections.abc import Callable

from .outbox_table import Meta, Row

log = logging.getLogger("hookwatch.outbox")

#: rows (not telemetry) kept in memory while the disk refuses writes
RESERVE_MAX_ROWS = 20_000
#: seconds between attempts to write the reserve to a disk that refused writes
RETRY_S = 1.0
#: at most one "still cannot write" log line per this many seconds
LOG_INTERVAL_S = 60.0

#: what the disk state reports with each change (``reason``; on recovery also ``duration_s``,
#: ``refused_telemetry``, ``rows_written``, ``lost_rows``)
DiskInfo = dict[str, str | int | float]
#: ``on_disk_state(ok, info)``
DiskStateCallback = Callable[[bool, DiskInfo], None]


class DiskFullReserve:
    """The disk state and in-memory reserve of the outbox at ``path`` (see the module docstring)."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.disk_ok = True
        self.on_disk_state: DiskStateCallback | None = None
        self.refused_telemetry = 0
        self.lost_rows = 0
        self.write_errors = 0
        self.superseded_states = 0
        #: rows waiting for the disk, by seq (oldest first)
        self.rows: OrderedDict[int, Row] = OrderedDict()
        #: meta values waiting for the disk
        self.meta: Meta = {}
        #: confirmed seqs whose delete waits for the disk
        self.confirms: set[int] = set()
        self._last_try = 0.0
        self._last_log = 0.0
        self._errors_unlogged = 0
        self._fail_reason = ""
        self._fail_since = 0.0
        self._last_ok_log = 0.0

    # -- the state
    def failed(self, e: Exception) -> None:
        """A write failed: the state turns FAILED (reported once), or stays so (counted)."""
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
                          self._errors_unlogged, self.refused_telemetry, len(self.rows))
                self._last_log = now
                self._errors_unlogged = 0

    def due(self, force: bool = False) -> bool:
        """Whether the outbox should try to write the reserve now (at most once per
        :data:`RETRY_S` unless ``force``); the attempt is counted from now."""
        now = time.monotonic()
        if not force and now - self._last_try < RETRY_S:
            return False
        self._last_try = now
        return True

    def recovered(self, rows_written: int) -> None:
        """The reserve (``rows_written`` rows) reached the disk: the state is ok again."""
        now = time.monotonic()
        self.rows.clear()
        self.meta = {}
        self.disk_ok = True
        info: DiskInfo = {"reason": self._fail_reason, "duration_s": round(now - self._fail_since, 3),
                          "refused_telemetry": self.refused_telemetry, "rows_written": rows_written,
                          "lost_rows": self.lost_rows}
        if now - self._last_ok_log >= LOG_INTERVAL_S:
            self._last_ok_log = now
            log.warning("outbox %s: writing again after %.1f s; %d held rows stored, %d telemetry messages "
                        "refused so far", self.path, info["duration_s"], rows_written, self.refused_telemetry)
        self._notify(True, info)

    def _notify(self, ok: bool, info: DiskInfo) -> None:
        if self.on_disk_state is not None:
            try:
                self.on_disk_state(ok, info)
            except Exception:
                log.exception("outbox %s: disk state callback failed", self.path)

    # -- the reserve
    def hold(self, rows: list[Row], meta: Meta | None, sent_upto: int) -> None:
        """Keep ``rows`` (not telemetry: refused, counted) and ``meta`` until the disk takes them."""
        for r in rows:
            if r.kind == "telemetry":
                self.refused_telemetry += 1
                continue
            if r.kind == "state":       # a newer state supersedes unsent ones, as on disk
                old = [s for s, x in self.rows.items() if x.kind == "state" and sent_upto < s < r.seq]
                for s in old:
                    del self.rows[s]
                self.superseded_states += len(old)
            self.rows[r.seq] = r
        over = len(self.rows) - RESERVE_MAX_ROWS
        if over > 0:
            for _ in range(over):
                self.rows.popitem(last=False)
            self.lost_rows += over
            log.error("outbox %s: in-memory reserve full: %d oldest rows dropped (%d so far)", self.path,
                      over, self.lost_rows)
        if meta:
            self.meta.update(meta)

    def take_confirmed(self, seqs: list[int]) -> list[int]:
        """Drop the held rows of ``seqs`` (confirmed); the others (on disk) are returned."""
        return [s for s in seqs if self.rows.pop(s, None) is None]

    def after(self, after_seq: int) -> list[Row]:
        """Held rows with seq > ``after_seq``, oldest first."""
        return [r for s, r in self.rows.items() if s > after_seq]

    def count(self, kind: str | None = None) -> int:
        """Held rows (of ``kind``)."""
        if kind is None:
            return len(self.rows)
        return sum(1 for r in self.rows.values() if r.kind == kind)
