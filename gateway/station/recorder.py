"""Per-test recording: the log (METHOD.md §9 + extra columns) as .csv.gz, the metadata sidecar,
the events file (JSON Lines) and the result.

Flushed at least once a second (gzip sync flush): `kill -9` at any moment loses at most the last
second, and what was written still reads (``gateway.logio`` keeps every complete row of a gzip
stream without trailer). A test folder without ``result.json`` is a test that was cut off; on
restart :func:`recover_incomplete` closes it as ``aborted`` (reason: gateway restart).
"""
from __future__ import annotations

import datetime as _dt
import gzip
import json
import logging
import math
import os
import threading
import time
from typing import Any

import yaml

from ..records import Event, SlotRecord
from ..analysis import AnalysisError, analyze_file

log = logging.getLogger("hookwatch.recorder")

LOG_COLUMNS = ("t", "T1", "T2", "speed_cmd", "speed_act", "saturated", "q", "mask", "mu", "mean_filt")
LOG_NAME = "log.csv.gz"
META_NAME = "log.meta.yaml"
EVENTS_NAME = "events.jsonl"
RESULT_NAME = "result.json"


def utc_iso(ts: float | None = None) -> str:
    ts = time.time() if ts is None else ts
    return _dt.datetime.fromtimestamp(ts, _dt.timezone.utc).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _f(x: float | None) -> str:
    """Exact round trip for values the method uses (repr is the shortest exact form)."""
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "nan"
    return repr(float(x))


_fsync_pool = None
_fsync_lock = threading.Lock()


def _fsync_dup(fd: int) -> None:
    try:
        os.fsync(fd)
    except OSError as e:
        log.warning("background fsync failed: %s", e)
    finally:
        os.close(fd)


def _fsync_in_background(fd: int) -> None:
    global _fsync_pool
    with _fsync_lock:
        if _fsync_pool is None:
            from concurrent.futures import ThreadPoolExecutor
            _fsync_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fsync")
    _fsync_pool.submit(_fsync_dup, os.dup(fd))


class TestRecorder:
    """Writes one test. Not thread-safe; called from the station's loop only."""

    __test__ = False  # not a pytest test class

    def __init__(self, test_dir: str, meta: dict[str, Any], flush_interval_s: float = 1.0,
                 fsync_interval_s: float = 10.0, clock=time.monotonic):
        self.dir = test_dir
        os.makedirs(test_dir, exist_ok=True)
        self.meta = meta
        self._clock = clock
        self._flush_every = flush_interval_s
        self._fsync_every = fsync_interval_s
        self._raw = open(os.path.join(test_dir, LOG_NAME), "wb")
        self._gz = gzip.GzipFile(fileobj=self._raw, mode="wb", compresslevel=5,
                                 filename="", mtime=0)
        self._gz.write((",".join(LOG_COLUMNS) + "\n").encode())
        self._buf: list[str] = []
        self._events = open(os.path.join(test_dir, EVENTS_NAME), "a", encoding="utf-8")
        self._last_flush = clock()
        self._last_fsync = clock()
        self.rows = 0
        self.closed = False
        self.write_errors = 0
        self._write_meta()
        self.flush(force=True)

    def _write_meta(self) -> None:
        path = os.path.join(self.dir, META_NAME)
        tmp = path + ".tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            yaml.safe_dump(self.meta, f, sort_keys=False, allow_unicode=True)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)

    def update_meta(self, path: list[str], value: Any) -> None:
        """Set one key of the sidecar (``["method", "end_slot"]``) and rewrite it atomically."""
        d = self.meta
        for k in path[:-1]:
            d = d.setdefault(k, {})
        d[path[-1]] = value
        try:
            self._write_meta()
        except OSError as e:
            self.write_errors += 1
            log.error("%s: cannot rewrite the sidecar: %s", self.dir, e)

    def on_record(self, rec: SlotRecord) -> None:
        if not rec.present or self.closed:
            return  # §9: a slot without a row is MISSING
        self._buf.append(
            f"{rec.t:.4f},{_f(rec.t1)},{_f(rec.t2)},{rec.speed_cmd:.3f},"
            f"{'nan' if math.isnan(rec.speed_act) else format(rec.speed_act, '.3f')},"
            f"{int(rec.saturated)},{rec.q},{rec.mask},{_f(rec.mu)},{_f(rec.mean_filt)}\n")
        self.rows += 1
        if self._clock() - self._last_flush >= self._flush_every:
            self.flush()

    def on_event(self, ev: Event) -> None:
        if self.closed:
            return
        try:
            self._events.write(json.dumps({"utc": utc_iso(ev.wall_time), **ev.as_dict()}) + "\n")
            self._events.flush()
        except OSError as e:
            self.write_errors += 1
            log.error("%s: cannot write event: %s", self.dir, e)

    def flush(self, force: bool = False) -> None:
        try:
            if self._buf:
                self._gz.write("".join(self._buf).encode())
                self._buf.clear()
            self._gz.flush()            # zlib sync flush + write to the OS
            self._raw.flush()
            now = self._clock()
            self._last_flush = now
            if force:
                os.fsync(self._raw.fileno())
                self._last_fsync = now
            elif now - self._last_fsync >= self._fsync_every:
                # never on the slot loop: an fsync on a busy disk can take longer than the STM32
                # watchdog; a background thread syncs a duplicate of the descriptor
                _fsync_in_background(self._raw.fileno())
                self._last_fsync = now
        except OSError as e:
            self.write_errors += 1
            log.error("%s: cannot write the log: %s (rows kept in memory: %d)", self.dir, e, len(self._buf))

    def close(self, result: dict[str, Any]) -> None:
        if self.closed:
            return
        self.flush(force=True)
        try:
            self._gz.close()
            self._raw.close()
            self._events.close()
        except OSError as e:
            log.error("%s: closing files: %s", self.dir, e)
        write_result(self.dir, result)
        self.closed = True


def write_result(test_dir: str, result: dict[str, Any]) -> None:
    path = os.path.join(test_dir, RESULT_NAME)
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(result, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def incomplete_tests(station_dir: str) -> list[str]:
    """Test folders of a station that have a log but no result (cut off by a crash or kill)."""
    out = []
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
    for d in incomplete_tests(station_dir):
        logp = os.path.join(d, LOG_NAME)
        res: dict[str, Any] = {"test_status": "aborted", "end_reason": reason, "closed_utc": utc_iso()}
        try:
            r = analyze_file(logp)
            res["method"] = r.as_dict()
        except AnalysisError as e:
            res["method"] = None
            res["analysis_error"] = str(e)
        write_result(d, res)
        try:
            with open(os.path.join(d, EVENTS_NAME), "a", encoding="utf-8") as f:
                f.write(json.dumps({"utc": utc_iso(), "type": "test_ended", "reason": reason,
                                    "status": "aborted"}) + "\n")
        except OSError:
            pass
        log.warning("%s: test was cut off; closed as aborted (%s)", d, reason)
        closed.append((d, res))
    return closed
