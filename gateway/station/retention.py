"""Record retention: which completed tests of a station are pruned so that the disk never fills.

A station records about 4.6 MB per hour of test (log, sidecar, events, result); nothing else ever
removes them, so a box would fill its disk within months. ``recorder.retention`` (configuration)
bounds them:

- ``max_age_days``: completed tests closed longer ago than this are pruned;
- ``max_total_mb``: the station's records take at most this much; beyond it the oldest go first;
- ``min_free_percent``: while the file system holding the records has less free space than this,
  the oldest go first (the default, 10 %, is what keeps a box that nobody configured from filling);
- ``keep_last``: the newest K completed tests are never pruned, whatever the limits say.

Never pruned, whatever the policy: the running test (and any folder without ``result.json``: a
test being closed, or one cut off that the next start closes), and a test whose result has not yet
left the MQTT outbox (a ``result`` row still in ``outbox.sqlite``, read through its own read-only
SQLite connection). A test is pruned whole (its folder), oldest first by closing time. Each pruning
is one log line, an event (``records_pruned`` with the test ids, bytes and the rule) and the
Prometheus counters ``hookwatch_records_pruned_tests_total`` / ``…_bytes_total``.

:func:`select` is pure (the policy on a list of folders); :func:`scan` and :func:`prune` do the I/O
and never raise: a folder that cannot be read or removed is skipped and logged once per pass.
:class:`RetentionOutput` runs the passes of one station (at start, after every test end and every
``interval_s``; in a worker thread, one at a time), wired in ``gateway.compose``.
"""
from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shutil
import sqlite3
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from ..core.records import Event, EventType, SlotRecord, StationState

log = logging.getLogger("hookwatch.retention")

#: at most this many folders are looked at per station and pass (a bound on the work of a pass)
MAX_FOLDERS = 100_000
#: a station's stop waits at most this long for a pass in progress (its thread then finishes alone)
STOP_WAIT_S = 30.0
#: a result.json larger than this is not read for its closing time (the folder's mtime is used)
MAX_RESULT_BYTES = 4 * 1024 * 1024


@dataclass(frozen=True, slots=True)
class Policy:
    max_age_days: float | None = None
    max_total_mb: float | None = None
    min_free_percent: float = 10.0
    keep_last: int = 20

    @classmethod
    def from_config(cls, rc: object) -> Policy:
        return cls(max_age_days=getattr(rc, "max_age_days", None), max_total_mb=getattr(rc, "max_total_mb", None),
                   min_free_percent=float(getattr(rc, "min_free_percent", 10.0)),
                   keep_last=int(getattr(rc, "keep_last", 20)))


@dataclass(frozen=True, slots=True)
class Folder:
    """One test folder of a station."""
    test_id: str
    path: str
    closed: float          # closing time (epoch s); folders without a result: their mtime
    size: int              # bytes
    completed: bool        # has a result.json (closed)


@dataclass(frozen=True, slots=True)
class Disk:
    total: int
    free: int


@dataclass(slots=True)
class Plan:
    prune: list[tuple[Folder, str]] = field(default_factory=list)    # (folder, rule)

    @property
    def bytes(self) -> int:
        return sum(f.size for f, _ in self.prune)


def select(folders: Iterable[Folder], policy: Policy, now: float, protected: set[str],
           disk: Disk | None = None) -> Plan:
    """The folders to prune, oldest first, with the rule that selects each (pure).

    Eligible: completed, not protected, not among the newest ``keep_last`` completed ones. Then
    by rule: age, then the size budget, then the free-space floor (each counting what the rules
    before it already freed)."""
    done = sorted((f for f in folders if f.completed), key=lambda f: (f.closed, f.test_id))
    keep = {f.test_id for f in done[-policy.keep_last:]} if policy.keep_last > 0 else set()
    eligible = [f for f in done if f.test_id not in keep and f.test_id not in protected]
    plan = Plan()
    chosen: set[str] = set()

    def take(f: Folder, rule: str) -> None:
        plan.prune.append((f, rule))
        chosen.add(f.test_id)

    if policy.max_age_days is not None:
        cutoff = now - policy.max_age_days * 86400.0
        for f in eligible:
            if f.closed < cutoff:
                take(f, "max_age_days")
    if policy.max_total_mb is not None:
        total = sum(f.size for f in folders) - plan.bytes
        budget = policy.max_total_mb * 1e6
        for f in eligible:
            if total <= budget:
                break
            if f.test_id not in chosen:
                take(f, "max_total_mb")
                total -= f.size
    if disk is not None and disk.total > 0 and policy.min_free_percent > 0:
        free = disk.free + plan.bytes
        floor = disk.total * policy.min_free_percent / 100.0
        for f in eligible:
            if free >= floor:
                break
            if f.test_id not in chosen:
                take(f, "min_free_percent")
                free += f.size
    return plan


def _size(path: str) -> int:
    n = 0
    for dp, _dn, fns in os.walk(path):
        for fn in fns:
            try:
                n += os.lstat(os.path.join(dp, fn)).st_size
            except OSError:
                pass
    return n


def _closed_time(path: str) -> tuple[bool, float]:
    res = os.path.join(path, "result.json")
    try:
        st = os.stat(res)
    except OSError:
        try:
            return False, os.stat(path).st_mtime
        except OSError:
            return False, 0.0
    return True, st.st_mtime


def scan(station_dir: str) -> list[Folder]:
    """The test folders of one station's records folder (never raises: unreadable → [])."""
    out: list[Folder] = []
    try:
        entries = sorted(os.scandir(station_dir), key=lambda e: e.name)[:MAX_FOLDERS]
    except FileNotFoundError:
        return out                  # no test recorded yet
    except OSError as e:
        log.warning("retention: cannot list %s: %s", station_dir, e.strerror or e)
        return out
    for ent in entries:
        try:
            if not ent.is_dir(follow_symlinks=False):
                continue
        except OSError:
            continue
        completed, closed = _closed_time(ent.path)
        out.append(Folder(test_id=ent.name, path=ent.path, closed=closed, size=_size(ent.path),
                          completed=completed))
    return out


def pending_results(outbox_path: str | None) -> set[str]:
    """Test ids whose result is still in the MQTT outbox (not yet confirmed by the broker). A
    missing outbox: none; an outbox that cannot be read: None is never returned — the error is
    logged and every test is treated as pending (nothing is pruned that might not have left)."""
    if not outbox_path or not os.path.exists(outbox_path):
        return set()
    try:
        db = sqlite3.connect(f"file:{outbox_path}?mode=ro", uri=True, timeout=5.0)
        try:
            rows = db.execute("SELECT payload FROM messages WHERE kind='result'").fetchall()
        finally:
            db.close()
    except sqlite3.Error as e:
        log.warning("retention: cannot read the outbox %s (%s): nothing pruned this pass", outbox_path, e)
        return {"*"}
    out: set[str] = set()
    for (payload,) in rows:
        try:
            d = json.loads(payload)
        except (ValueError, TypeError, UnicodeDecodeError):
            continue
        tid = d.get("test_id") if isinstance(d, dict) else None
        if isinstance(tid, str):
            out.add(tid)
    return out


def disk_of(path: str) -> Disk | None:
    try:
        st = os.statvfs(path)
    except OSError:
        return None
    return Disk(total=st.f_blocks * st.f_frsize, free=st.f_bavail * st.f_frsize)


@dataclass(frozen=True, slots=True)
class Pruned:
    """What one pass removed (for the log line, the event and the metrics)."""
    station: str
    tests: list[str]
    rules: list[str]
    bytes: int
    failed: list[str]


def prune(station: str, station_dir: str, policy: Policy, now: float, running: str | None,
          outbox_path: str | None) -> Pruned | None:
    """One pass over one station: select and remove. Never raises. None when nothing was pruned."""
    folders = scan(station_dir)
    protected = pending_results(outbox_path)
    if "*" in protected:
        return None
    if running:
        protected.add(running)
    plan = select(folders, policy, now, protected, disk_of(station_dir))
    if not plan.prune:
        return None
    gone: list[str] = []
    rules: list[str] = []
    failed: list[str] = []
    freed = 0
    for f, rule in plan.prune:
        try:
            shutil.rmtree(f.path)
        except OSError as e:
            failed.append(f.test_id)
            log.warning("retention: %s: cannot remove %s: %s", station, f.path, e.strerror or e)
            continue
        gone.append(f.test_id)
        rules.append(rule)
        freed += f.size
    if not gone and not failed:
        return None
    if gone:
        log.info("retention: %s: pruned %d test(s), %.1f MB (%s): %s", station, len(gone), freed / 1e6,
                 ", ".join(sorted(set(rules))), ", ".join(gone[:5]) + (" …" if len(gone) > 5 else ""))
    return Pruned(station=station, tests=gone, rules=rules, bytes=freed, failed=failed)


class RetentionOutput:
    """The retention passes of one station, as one of its outputs (wired in ``gateway.compose``):
    a pass at start, after every test end (``test_ended``) and every ``interval_s``, each in a
    worker thread (``asyncio.to_thread``: never on the slot loop), at most one at a time (a pass
    asked for during one runs once more after it). The running test is read when a pass begins;
    ``on_pruned`` gets what a pass removed (the station's ``records_pruned`` event). A failing pass
    is logged and counted, never raised."""

    def __init__(self, station: str, station_dir: str, policy: Policy, interval_s: float,
                 running: Callable[[], str | None], outbox_path: str | None,
                 on_pruned: Callable[[Pruned], None], clock: Callable[[], float] = time.time) -> None:
        self.station, self.station_dir, self.policy = station, station_dir, policy
        self.interval_s = float(interval_s)
        self._running, self.outbox_path, self._on_pruned, self._clock = running, outbox_path, on_pruned, clock
        self._ticker: asyncio.Task[None] | None = None
        self._pass: asyncio.Task[None] | None = None
        self._again = False
        self._stopping = False
        #: passes done, passes that failed, tests and bytes pruned by this output
        self.passes = self.failures = self.pruned_tests = self.pruned_bytes = 0

    # -- output protocol (the station's loop)
    async def start(self) -> None:
        self._stopping = False
        self._ticker = asyncio.get_running_loop().create_task(self._tick())

    def on_record(self, rec: SlotRecord) -> None:
        pass

    def on_event(self, ev: Event) -> None:
        if ev.type is EventType.TEST_ENDED:
            self.request()

    def on_state(self, st: StationState) -> None:
        pass

    async def stop(self) -> None:
        self._stopping = True
        if self._ticker is not None:
            self._ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._ticker
            self._ticker = None
        if self._pass is not None:      # a pass in its thread cannot be cancelled: let it finish
            await asyncio.wait({self._pass}, timeout=STOP_WAIT_S)

    # -- passes
    def request(self) -> None:
        """Ask for a pass (on the station's loop); joins the one running, if any."""
        if self._stopping:
            return
        if self._pass is not None and not self._pass.done():
            self._again = True
            return
        self._pass = asyncio.get_running_loop().create_task(self._passes())

    async def _tick(self) -> None:
        while True:
            self.request()
            await asyncio.sleep(self.interval_s)

    async def _passes(self) -> None:
        while True:
            self._again = False
            running = self._running()
            try:
                res = await asyncio.to_thread(prune, self.station, self.station_dir, self.policy,
                                              self._clock(), running, self.outbox_path)
            except Exception:       # prune never raises by design; a bug must not end the station
                self.failures += 1
                if self.failures == 1:
                    log.exception("retention: %s: a pass failed (further failures are counted)", self.station)
                res = None
            self.passes += 1
            if res is not None and res.tests:
                self.pruned_tests += len(res.tests)
                self.pruned_bytes += res.bytes
                try:
                    self._on_pruned(res)
                except Exception:
                    log.exception("retention: %s: reporting a pruning failed", self.station)
            if not self._again or self._stopping:
                return
