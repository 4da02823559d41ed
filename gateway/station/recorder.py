"""Per-test recording: the log (METHOD.md §9 + extra columns) as .csv.gz, the metadata sidecar,
the events file (JSON Lines) and the result.

Flushed at least once a second, each flush one complete gzip member written in one call (a failed
write is truncated back): `kill -9` at any moment loses at most the last second, and what reached
the disk always reads back (``gateway.offline.logio`` reads every member; a full or read-only disk is a
state, see :class:`TestRecorder`). A test folder without ``result.json`` is a test that was cut off; on
restart :func:`recover_incomplete` closes it as ``aborted`` (reason: gateway restart).
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import gzip
import logging
import math
import os
import re
import threading
import time
from array import array
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import yaml

from ..core.method.rules import LOST
from ..core.records import Event, SlotRecord
from ..offline import logio
from ..offline.analysis import AnalysisError, analyze_file
from ..plumbing import safeout

log = logging.getLogger("hookwatch.recorder")

LOG_COLUMNS = ("t", "T1", "T2", "speed_cmd", "speed_act", "saturated", "q", "mask", "mu", "mean_filt")
LOG_NAME = "log.csv.gz"
META_NAME = "log.meta.yaml"
EVENTS_NAME = "events.jsonl"
RESULT_NAME = "result.json"


def floor_ms(ts: float) -> tuple[int, int]:
    """(whole seconds, milliseconds) of a Unix time, both floored: a time is never written as
    later (or, wrapping, earlier) than it was — hh:mm:30.9996 is 30.999, not 31.000 or 30.000."""
    total = math.floor(ts * 1000.0)
    if total / 1000.0 > ts:          # ts * 1000 rounded up in the last bit
        total -= 1
    return total // 1000, total % 1000


def utc_iso(ts: float | None = None) -> str:
    """UTC ISO 8601 to the millisecond, floored (:func:`floor_ms`)."""
    s, ms = floor_ms(time.time() if ts is None else ts)
    return (_dt.datetime.fromtimestamp(s, _dt.UTC).strftime("%Y-%m-%dT%H:%M:%S") + f".{ms:03d}Z")


def _f(x: float | None) -> str:
    """Exact round trip for values the method uses (repr is the shortest exact form)."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "nan"
    return repr(float(x))


#: one log row (LOG_COLUMNS), formatted once per flush for all rows of the interval: ``%r`` of a
#: float is its repr (the shortest exact form; ``nan`` for NaN, as :func:`_f`), ``%.3f`` of NaN is
#: ``nan``; q and mask as ``str()``, saturated as 0/1 — byte for byte the per-row form before
ROW_FORMAT = "%.4f,%r,%r,%.3f,%.3f,%d,%s,%s,%r,%r\n"
_NAN = math.nan


def _num(x: Any) -> float:
    try:
        return float(x)
    except (TypeError, ValueError, OverflowError):
        return _NAN


class _Columns:
    """The rows of one flush interval, kept as columns (floats in ``array('d')``): per slot only
    appends; the text is made once per flush (:meth:`take`)."""

    __slots__ = ("k", "t", "t1", "t2", "speed_cmd", "speed_act", "saturated", "q", "mask", "mu",
                 "mean_filt")

    def __init__(self) -> None:
        self.clear()

    def clear(self) -> None:
        """Empty columns (new objects: the taken ones stay with the caller)."""
        self.k: list[int] = []
        self.t, self.t1, self.t2 = array("d"), array("d"), array("d")
        self.speed_cmd, self.speed_act = array("d"), array("d")
        self.saturated: list[Any] = []
        self.q: list[Any] = []
        self.mask: list[Any] = []
        self.mu, self.mean_filt = array("d"), array("d")

    def __len__(self) -> int:
        return len(self.k)

    def add(self, rec: SlotRecord) -> None:
        n = len(self.k)
        try:
            self.t.append(rec.t)
            self.t1.append(rec.t1)
            self.t2.append(rec.t2)
            self.speed_cmd.append(rec.speed_cmd)
            self.speed_act.append(rec.speed_act)
            mu = rec.mu
            self.mu.append(_NAN if mu is None else mu)
            mf = rec.mean_filt
            self.mean_filt.append(_NAN if mf is None else mf)
        except (TypeError, ValueError, OverflowError):
            # a value that is no float (None where a number belongs): the row is kept with NaN
            self._cut(n)
            for name in ("t", "t1", "t2", "speed_cmd", "speed_act", "mu", "mean_filt"):
                getattr(self, name).append(_num(getattr(rec, name)))
        self.saturated.append(rec.saturated)
        self.q.append(rec.q)
        self.mask.append(rec.mask)
        self.k.append(rec.k)        # last: len(k) counts the complete rows

    def _cut(self, n: int) -> None:
        for name in ("t", "t1", "t2", "speed_cmd", "speed_act", "mu", "mean_filt"):
            del getattr(self, name)[n:]

    def take(self) -> tuple[list[str], list[int]]:
        """(rows as text, their slots); the columns are empty afterwards."""
        fmt = ROW_FORMAT
        rows = [fmt % r for r in zip(self.t, self.t1, self.t2, self.speed_cmd, self.speed_act,
                                     self.saturated, self.q, self.mask, self.mu, self.mean_filt)]
        ks = self.k
        self.clear()
        return rows, ks


_fsync_pool = None
_fsync_lock = threading.Lock()


def _fsync_dup(fd: int) -> None:
    try:
        os.fsync(fd)
    except OSError as e:
        log.warning("background fsync failed: %s", e)
    finally:
        os.close(fd)


def disk_thread() -> ThreadPoolExecutor:
    """The process's one thread for disk syncs off the slot loop (one: what it is given is done
    in order): the recorder's fsyncs, the hooks.jsonl appends (gateway/station/hook_log.py)."""
    global _fsync_pool
    with _fsync_lock:
        if _fsync_pool is None:
            _fsync_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fsync")
        return _fsync_pool


def _fsync_in_background(fd: int) -> None:
    disk_thread().submit(_fsync_dup, os.dup(fd))


#: rows kept in memory while the disk refuses writes (5 minutes at 50 Hz, about 1 MB): the
#: recorder's reserve. Once it is full the recorder refuses further slots (:meth:`TestRecorder.accepts`
#: is False): the station feeds them to the method as LOST (``gateway.core.method.rules.LOST``) and the
#: recorder notes them as ``lost_spans`` in the sidecar, which the offline analysis reads the same
#: way (online == offline after any disk outage)
MAX_PENDING_ROWS = 15_000
#: the reserve can be lowered (tests, a box short of memory) through this environment variable
RESERVE_ENV = "HOOKWATCH_RECORDER_RESERVE_ROWS"
#: events kept in memory while the disk refuses writes
MAX_PENDING_EVENTS = 1_000
#: at most one "still cannot write" log line per this many seconds
DISK_LOG_INTERVAL_S = 60.0


class DiskError(OSError):
    pass


def reserve_rows() -> int:
    """The recorder's reserve in rows: :data:`RESERVE_ENV` when set to a whole number in
    1 … :data:`MAX_PENDING_ROWS`, else :data:`MAX_PENDING_ROWS` (a bad value is logged, not used)."""
    raw = os.environ.get(RESERVE_ENV, "").strip()
    if not raw:
        return MAX_PENDING_ROWS
    try:
        n = int(raw)
    except ValueError:
        n = 0
    if not 1 <= n <= MAX_PENDING_ROWS:
        log.warning("%s=%r: not a whole number in 1 … %d; the reserve is %d rows", RESERVE_ENV, raw,
                    MAX_PENDING_ROWS, MAX_PENDING_ROWS)
        return MAX_PENDING_ROWS
    return n


def _write_block(fd: int, data: bytes, good_offset: int) -> int:
    """Write ``data`` at ``good_offset`` completely or not at all. On a short write or an error the
    file is truncated back to ``good_offset`` (so it never ends in half a gzip member / half a
    line) and the error is raised. Returns the new end offset."""
    view = memoryview(data)
    pos = good_offset
    try:
        while view:
            n = os.pwrite(fd, view, pos)
            if n <= 0:
                raise OSError(28, "short write")
            view = view[n:]
            pos += n
    except OSError:
        with contextlib.suppress(OSError):
            os.ftruncate(fd, good_offset)
        raise
    return pos


def new_test_dir(station_dir: str, sample_id: str, start_wall: float | None = None) -> tuple[str, str]:
    """A test id that cannot collide and its folder, created exclusively: UTC time to the
    millisecond (floored: an id is never earlier, nor later, than the start it names) + the sample
    name; if that folder exists (two starts in one millisecond, a clock step back), ``-2``, ``-3``,
    … is appended. Returns (test_id, path)."""
    s, ms = floor_ms(time.time() if start_wall is None else start_wall)
    base = (time.strftime("%Y%m%dT%H%M%S", time.gmtime(s)) + f".{ms:03d}Z-"
            + safe_name(sample_id))
    os.makedirs(station_dir, exist_ok=True)
    for n in range(1, 10_000):
        tid = base if n == 1 else f"{base}-{n}"
        path = os.path.join(station_dir, tid)
        try:
            os.mkdir(path)           # exclusive: never shares another test's folder
        except FileExistsError:
            continue
        return tid, path
    raise FileExistsError(f"{station_dir}: no free test folder for {base}")


def safe_name(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", s)[:48] or "test"


class TestRecorder:
    """Writes one test. Not thread-safe; called from the station's loop only.

    The log is a sequence of complete gzip members, one per flush: each block is compressed in
    memory and written in one call at the last good offset; a failed or short write is truncated
    back, so what reached the disk always reads back (no CRC error, no half member).

    A disk that refuses writes (full, read-only, gone) is a *state*, not a crash:
    ``disk_ok`` turns False, ``on_disk_state(False, info)`` is called once, one error line is
    logged (then at most one a minute, with a count); rows are kept in memory up to the reserve
    (:func:`reserve_rows`). Once it is full :meth:`accepts` is False: the station asks before it
    feeds a slot to the method and feeds a refused slot as LOST (``gateway.core.method.rules.LOST``);
    its record (mask LOST) is not written but counted in ``lost_rows``/``lost_spans`` ([first,
    last] slot). No row the method analysed is ever dropped. When a write succeeds again
    ``disk_ok`` turns True, ``on_disk_state(True, info)`` is called, the events ``disk_full`` and
    ``disk_ok`` (with the lost spans) are appended to the events file and the sidecar gets
    ``lost_spans`` (again at close): the offline analysis feeds those slots as LOST, as the live
    station did.
    """

    __test__ = False  # not a pytest test class

    def __init__(self, test_dir: str, meta: dict[str, Any], flush_interval_s: float = 1.0,
                 fsync_interval_s: float = 10.0, clock=time.monotonic,
                 on_disk_state: Callable[[bool, dict[str, Any]], None] | None = None):
        self.dir = test_dir
        os.makedirs(test_dir, exist_ok=True)
        self.meta = meta
        self._clock = clock
        self._flush_every = flush_interval_s
        self._fsync_every = fsync_interval_s
        self.on_disk_state = on_disk_state
        self._fd = os.open(os.path.join(test_dir, LOG_NAME), os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._off = 0
        self._buf: list[str] = [",".join(LOG_COLUMNS) + "\n"]
        self._buf_k: list[int] = [-1]       # slot of each buffered row (-1: the header)
        self._cols = _Columns()             # rows since the last flush, not yet text
        self._ev_fd = os.open(os.path.join(test_dir, EVENTS_NAME), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        self._ev_off = os.fstat(self._ev_fd).st_size
        self._ev_pending: list[str] = []
        self._last_flush = clock()
        self._last_fsync = clock()
        self.rows = 0
        self.closed = False
        #: the disk state: False while writes fail (full, read-only); see the class doc
        self.disk_ok = True
        self.write_errors = 0
        self.lost_rows = 0
        self.lost_spans: list[list[int]] = []   # [first k, last k] of LOST slots (refused, never recorded)
        #: rows held in memory while the disk refuses writes, at most (see :meth:`accepts`)
        self.reserve = reserve_rows()
        self.dropped_events = 0
        self._fail_since: float | None = None
        self._fail_utc: str | None = None
        self._fail_reason = ""
        self._last_err_log = 0.0
        self._errors_unlogged = 0
        # on the slot loop at the test's slot 0: nothing here waits for the disk (an fsync on a
        # busy disk took ~0.2 s once: 9 slots MISSING and the STM32's watchdog stopped the motor);
        # the sidecar, the log's header and the events file are synced by the background thread
        try:
            self._write_meta(sync=False)
        except OSError as e:
            self._failed(e)
        self.flush(force=True, sync=False)
        if self.disk_ok:
            _fsync_in_background(self._fd)
            _fsync_in_background(self._ev_fd)

    # -- disk state
    def _failed(self, e: OSError) -> None:
        self.write_errors += 1
        now = self._clock()
        if self.disk_ok:
            self.disk_ok = False
            self._fail_since = now
            self._fail_utc = utc_iso()
            self._fail_reason = e.strerror or str(e)
            self._last_err_log = now
            self._errors_unlogged = 0
            log.error("%s: cannot write (%s): disk state FAILED; rows kept in memory (up to %d), "
                      "then further slots are LOST (not recorded, not analysed; lost_spans)",
                      self.dir, self._fail_reason, self.reserve)
            self._notify(False, {"reason": self._fail_reason, "utc": self._fail_utc})
        else:
            self._errors_unlogged += 1
            if now - self._last_err_log >= DISK_LOG_INTERVAL_S:
                log.error("%s: still cannot write (%s): %d failed writes since the last line, "
                          "%d rows lost so far", self.dir, e.strerror or e, self._errors_unlogged,
                          self.lost_rows)
                self._last_err_log = now
                self._errors_unlogged = 0

    def _recovered(self) -> None:
        if self.disk_ok:
            return
        self.disk_ok = True
        dur = self._clock() - (self._fail_since or self._clock())
        info = {"reason": self._fail_reason, "since_utc": self._fail_utc, "duration_s": round(dur, 3),
                "lost_rows": self.lost_rows, "lost_spans": [list(s) for s in self.lost_spans],
                "dropped_events": self.dropped_events}
        log.warning("%s: writing again after %.1f s (%s); %d slots LOST in %d span(s)", self.dir, dur,
                    self._fail_reason, self.lost_rows, len(self.lost_spans))
        if self.lost_spans:     # in the sidecar now: a crash before the close keeps them
            self.update_meta(["lost_spans"], [list(s) for s in self.lost_spans])
            self.update_meta(["lost_rows"], self.lost_rows)
        self._ev_pending[:0] = [
            safeout.dumps({"utc": self._fail_utc, "type": "disk_full", "station": self.meta.get("station"),
                           "test_id": self.meta.get("test_id"), "data": {"reason": self._fail_reason}},
                          compact=False) + "\n",
            safeout.dumps({"utc": utc_iso(), "type": "disk_ok", "station": self.meta.get("station"),
                           "test_id": self.meta.get("test_id"), "data": info}, compact=False) + "\n"]
        self._notify(True, info)

    def _notify(self, ok: bool, info: dict[str, Any]) -> None:
        if self.on_disk_state is not None:
            try:
                self.on_disk_state(ok, info)
            except Exception:
                log.exception("%s: disk state callback failed", self.dir)

    def accepts(self) -> bool:
        """Can the recorder take the next slot's row? False only while the disk refuses writes and
        the reserve is full: the station then feeds that slot to the method as LOST."""
        return self.disk_ok or len(self._buf) + len(self._cols) < self.reserve

    def _lose(self, k: int) -> None:
        self.lost_rows += 1
        if self.lost_spans and self.lost_spans[-1][1] == k - 1:
            self.lost_spans[-1][1] = k
        else:
            self.lost_spans.append([k, k])

    def _write_meta(self, sync: bool = True) -> None:
        _atomic_write(os.path.join(self.dir, META_NAME),
                      lambda f: yaml.safe_dump(self.meta, f, sort_keys=False, allow_unicode=True),
                      sync=sync)

    def update_meta(self, path: list[str], value: Any) -> None:
        """Set one key of the sidecar (``["method", "end_slot"]``) and rewrite it atomically."""
        d = self.meta
        for k in path[:-1]:
            d = d.setdefault(k, {})
        d[path[-1]] = value
        try:
            self._write_meta(sync=False)        # on the slot loop: synced in the background
        except OSError as e:
            self.write_errors += 1
            log.error("%s: cannot rewrite the sidecar: %s", self.dir, e)

    def on_record(self, rec: SlotRecord) -> None:
        if self.closed:
            return
        if rec.mask & LOST:
            self._lose(rec.k)       # refused (accepts() was False): a lost span, no row
        elif rec.present:           # §9: a slot without a row is MISSING
            self._cols.add(rec)     # formatted at the flush, all rows of the interval at once
            self.rows += 1
        if self._clock() - self._last_flush >= self._flush_every:
            self.flush()

    def on_event(self, ev: Event) -> None:
        if self.closed:
            return
        self._ev_pending.append(safeout.dumps({"utc": utc_iso(ev.wall_time), **ev.as_dict()}, compact=False) + "\n")
        self._flush_events()

    def _flush_events(self) -> bool:
        if not self._ev_pending:
            return True
        try:
            self._ev_off = _write_block(self._ev_fd, "".join(self._ev_pending).encode(), self._ev_off)
        except OSError as e:
            over = len(self._ev_pending) - MAX_PENDING_EVENTS
            if over > 0:
                del self._ev_pending[:over]
                self.dropped_events += over
            self._failed(e)
            return False
        self._ev_pending.clear()
        return True

    def flush(self, force: bool = False, sync: bool | None = None) -> None:
        """Write the buffered rows as one complete gzip member (and pending events); never raises.
        ``force``: now, whatever the flush interval; ``sync`` (default: ``force``): and fsync
        here (otherwise every ``fsync_interval_s`` in the background)."""
        sync = force if sync is None else sync
        now = self._clock()
        self._last_flush = now
        ok = True
        if self._cols:
            rows, ks = self._cols.take()
            self._buf += rows
            self._buf_k += ks
        if self._buf:
            block = gzip.compress("".join(self._buf).encode(), compresslevel=5, mtime=0)
            try:
                self._off = _write_block(self._fd, block, self._off)
                self._buf.clear()
                self._buf_k.clear()
            except OSError as e:
                ok = False
                self._failed(e)
        if ok and not self.disk_ok:
            self._recovered()
        if ok:
            ok = self._flush_events()
        if ok:
            try:
                if sync:
                    os.fsync(self._fd)
                    os.fsync(self._ev_fd)
                    self._last_fsync = now
                elif now - self._last_fsync >= self._fsync_every:
                    # never on the slot loop: an fsync on a busy disk can take longer than the STM32
                    # watchdog; a background thread syncs a duplicate of the descriptor
                    _fsync_in_background(self._fd)
                    self._last_fsync = now
            except OSError as e:
                self._failed(e)

    def close(self, result: dict[str, Any]) -> None:
        """Flush, close the files, add the lost spans to the sidecar and write the result. Never
        raises: a result that cannot be written is kept and retried in the background (so a
        completed test is not closed again as aborted after a restart)."""
        if self.closed:
            return
        self.flush(force=True)
        tail: tuple[int, bytes] | None = None
        if self._buf or self._ev_pending:
            n = sum(1 for k in self._buf_k if k >= 0)
            if n:
                # rows the method analysed: kept and written with the result when the disk takes
                # them again (the retry thread), so the log still gives the live result
                tail = (self._off, gzip.compress("".join(self._buf).encode(), compresslevel=5, mtime=0))
            self.dropped_events += len(self._ev_pending)
            log.error("%s: closing with %d rows (kept in memory, written with the result) and %d "
                      "events (dropped) that have not reached the disk", self.dir, n,
                      len(self._ev_pending))
        for fd in (self._fd, self._ev_fd):
            with contextlib.suppress(OSError):
                os.close(fd)
        if self.lost_rows or self.write_errors:
            result = {**result, "recorder": {"lost_rows": self.lost_rows, "lost_spans": self.lost_spans,
                                             "write_errors": self.write_errors,
                                             "dropped_events": self.dropped_events}}
            self.meta = {**self.meta, "lost_spans": self.lost_spans, "lost_rows": self.lost_rows}
            try:
                self._write_meta()
            except OSError as e:
                log.error("%s: cannot update the sidecar with the lost spans: %s", self.dir, e)
        write_result(self.dir, result, tail)
        self.closed = True
        # the log's compact columns, for a fast offline analysis: one background thread, never raises
        logio.write_companion_later(os.path.join(self.dir, LOG_NAME))


_pending_results: dict[str, dict[str, Any]] = {}
#: log rows not yet on disk when their test closed: test folder → (offset, gzip member)
_pending_tails: dict[str, tuple[int, bytes]] = {}
_pending_lock = threading.Lock()
_retry_thread: threading.Thread | None = None
#: seconds between attempts to write a result that could not be written
RESULT_RETRY_S = 5.0


def _atomic_write(path: str, dump: Callable[[Any], Any], sync: bool = True) -> None:
    """Write a text file through a temporary file and a rename; on failure the temporary file is
    removed and the error raised (the old file, if any, stays). ``sync``: the temporary file is
    synced before the rename; otherwise (on a slot loop) the file and its folder are synced by
    the background thread right after it."""
    tmp = path + ".tmp"
    try:
        with open(tmp, "w", encoding="utf-8") as f:
            dump(f)
            f.flush()
            if sync:
                os.fsync(f.fileno())
            else:
                _fsync_in_background(f.fileno())
        os.replace(tmp, path)
        if not sync:
            dfd = os.open(os.path.dirname(path) or ".", os.O_RDONLY)
            try:
                _fsync_in_background(dfd)
            finally:
                os.close(dfd)
    except OSError:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _write_result_file(test_dir: str, result: dict[str, Any]) -> None:
    tail = _pending_tails.get(test_dir)
    if tail is not None:        # the log's last rows first: a result never names rows not on disk
        fd = os.open(os.path.join(test_dir, LOG_NAME), os.O_WRONLY)
        try:
            _write_block(fd, tail[1], tail[0])
            os.fsync(fd)
        finally:
            os.close(fd)
        del _pending_tails[test_dir]
    _atomic_write(os.path.join(test_dir, RESULT_NAME), lambda f: safeout.dump(result, f, indent=1))


def _retry_results() -> None:
    global _retry_thread
    while True:
        time.sleep(RESULT_RETRY_S)
        with _pending_lock:
            for d, res in list(_pending_results.items()):
                try:
                    _write_result_file(d, res)
                except OSError:
                    continue
                del _pending_results[d]
                log.warning("%s: result written after an earlier failure", d)
            if not _pending_results:
                _retry_thread = None
                return


def write_result(test_dir: str, result: dict[str, Any], tail: tuple[int, bytes] | None = None) -> bool:
    """Write ``result.json`` atomically (after ``tail``, the log's last rows as (offset, gzip
    member), if any). Never raises: on failure both are kept in memory and retried every
    :data:`RESULT_RETRY_S` in a background thread (one error line). Returns whether it was
    written now."""
    global _retry_thread
    try:
        with _pending_lock:
            if tail is not None:
                _pending_tails[test_dir] = tail
            _write_result_file(test_dir, result)
            _pending_results.pop(test_dir, None)
        return True
    except OSError as e:
        log.error("%s: cannot write %s (%s); kept in memory, retried every %.0f s", test_dir,
                  RESULT_NAME, e.strerror or e, RESULT_RETRY_S)
        with _pending_lock:
            _pending_results[test_dir] = result
            if _retry_thread is None:
                _retry_thread = threading.Thread(target=_retry_results, name="result-retry", daemon=True)
                _retry_thread.start()
        return False


def pending_results() -> dict[str, dict[str, Any]]:
    """Results not yet on disk (test folder → result)."""
    with _pending_lock:
        return dict(_pending_results)


#: a sidecar larger than this is not read back (it is a few kB)
SIDECAR_MAX_BYTES = 1 << 20


def read_sidecar(test_dir: str) -> dict[str, Any]:
    """The sidecar of a test folder as a dict; {} when it is missing, too large or unreadable
    (a test cut off before its sidecar reached the disk)."""
    path = os.path.join(test_dir, META_NAME)
    try:
        if os.path.getsize(path) > SIDECAR_MAX_BYTES:
            return {}
        with open(path, encoding="utf-8") as f:
            meta = yaml.safe_load(f)
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        return {}
    if not isinstance(meta, dict):
        return {}
    return {k: v for k, v in meta.items() if isinstance(v, (str, int, float, bool, type(None)))}


def incomplete_tests(station_dir: str) -> list[str]:
    """Test folders of a station that have a log but no result (cut off by a crash or kill)."""
    out: list[str] = []
    if not os.path.isdir(station_dir):
        return out
    for name in sorted(os.listdir(station_dir)):
        d = os.path.join(station_dir, name)
        if (os.path.isdir(d) and os.path.exists(os.path.join(d, LOG_NAME))
                and not os.path.exists(os.path.join(d, RESULT_NAME))):
            out.append(d)
    return out


def recover_incomplete(station_dir: str, reason: str = "gateway restart") -> list[tuple[str, dict]]:
    """Close every cut-off test as ``aborted`` with its partial result (offline analysis of what
    was recorded). Returns [(test_dir, result)]."""

    closed = []
    pend = pending_results()
    for d in incomplete_tests(station_dir):
        if d in pend:               # closed by this process; its result is still being retried
            continue
        logp = os.path.join(d, LOG_NAME)
        # who the test was: its sidecar (written at slot 0) names it; the folder name is its id
        meta = read_sidecar(d)
        res: dict[str, Any] = {"test_id": str(meta.get("test_id") or os.path.basename(d)),
                               "sample_id": meta.get("sample_id"), "grade": meta.get("grade"),
                               "t_set": meta.get("t_set"), "test_status": "aborted",
                               "end_reason": reason, "closed_utc": utc_iso()}
        try:
            r = analyze_file(logp)
            res["method"] = r.as_dict()
        except AnalysisError as e:
            res["method"] = None
            res["analysis_error"] = str(e)
        write_result(d, res)
        try:
            with open(os.path.join(d, EVENTS_NAME), "a", encoding="utf-8") as f:
                f.write(safeout.dumps({"utc": utc_iso(), "type": "test_ended", "test_id": res["test_id"],
                                       "reason": reason, "status": "aborted"}, compact=False) + "\n")
        except OSError:
            pass
        log.warning("%s: test was cut off; closed as aborted (%s)", d, reason)
        closed.append((d, res))
    return closed
