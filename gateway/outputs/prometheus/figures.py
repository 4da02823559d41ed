"""Metrics, part 1: the figures — what the stations count, and their snapshots.

:class:`StationFigures` are plain ints and floats that a station's loop updates in O(1) per slot
(no lock, no prometheus_client call on the slot path), kept per station id for the life of the
process; :func:`figures_snapshot` makes the plain, JSON-serializable **snapshot** (the shape in
gateway/outputs/prometheus/__init__.py) that the renderer (exposition.py) turns into metric
families and a fleet worker sends to its supervisor.
"""
from __future__ import annotations

import os
import sqlite3
import threading
import time
import urllib.parse
from bisect import bisect_left
from collections.abc import Callable
from typing import Any

from ...core import catalog
from ...core.records import SlotRecord, StationState, TestState
from ...core.slotwindow import SlotWindow
from ..plc.server import ModbusOutput

SNAPSHOT_VERSION = 2     # 2: the state's values under their catalog names (test_state, wear_warning, …)
#: the catalog's rows a station's snapshot carries and the exposition shows (a gauge each)
GAUGES = tuple(v for v in catalog.CATALOG if v.prometheus is not None)
#: the catalog's slot records' rows with a gauge (of the latest slot's reading): none today
SLOT_GAUGES = tuple(s for s in catalog.SLOT_CATALOG if s.prometheus is not None)

#: slot lateness buckets, s: a poll that starts > 10 ms (ts/2 at 50 Hz) late is an overrun
LATENESS_BUCKETS_S = (0.0001, 0.00025, 0.0005, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.010)
#: meter round-trip buckets, s: the 4-register reply takes ~5 ms at 115200, ~16 ms at 19200,
#: ~32 ms at 9600; the gateway's read timeout is 15 ms by default
RTT_BUCKETS_S = (0.0025, 0.005, 0.0075, 0.010, 0.0125, 0.015, 0.0175, 0.020, 0.025, 0.030,
                 0.035, 0.040, 0.050, 0.100)

#: driver counter kinds that count traffic, not failures (every other kind is an error kind)
OPERATION_KINDS = {
    "meter": frozenset({"reads", "reads_ok", "reopened"}),
    "stm32": frozenset({"sent", "acked", "keepalives", "reopened"}),
    "mqtt": frozenset({"sent", "confirmed", "commands", "connects", "lives_checked", "lives_saves"}),
}
LINKS = ("meter", "stm32", "mqtt")
_RUNNING = (TestState.BASELINE_SEARCH, TestState.MONITORING, TestState.END_OF_LIFE)


class Histogram:
    """Bucket counts (not cumulative) and a sum; ``observe`` is one C bisect and two adds."""
    __slots__ = ("le", "counts", "sum")

    def __init__(self, le: tuple[float, ...]):
        self.le = tuple(float(b) for b in le)
        self.counts = [0] * (len(self.le) + 1)      # last: above the largest bound (+Inf)
        self.sum = 0.0

    def observe(self, v: float) -> None:
        # bisect_left: v == bound falls in that bound's bucket (Prometheus' "le")
        self.counts[bisect_left(self.le, v)] += 1
        self.sum += v

    def snapshot(self) -> dict[str, Any]:
        counts = list(self.counts)      # one atomic copy under the GIL; count = sum(counts)
        return {"le": list(self.le), "counts": counts, "sum": self.sum}


class StationFigures:
    """What a station's loop counts, as plain attributes (written by one thread only)."""
    __slots__ = ("station", "life", "overruns", "lateness", "rtt", "mu", "events",
                 "pruned_tests", "pruned_bytes", "values", "latest")

    def __init__(self, station: str):
        self.station = station
        #: every slot of the station's life in this process (Prometheus counters never reset)
        self.life = SlotWindow()
        self.overruns = 0
        self.lateness = Histogram(LATENESS_BUCKETS_S)
        self.rtt = Histogram(RTT_BUCKETS_S)
        self.mu: float | None = None
        self.events: dict[str, int] = {}
        self.pruned_tests = self.pruned_bytes = 0     # record retention (records_pruned events)
        #: the catalog's values with a gauge as the station's state last had them
        self.values: dict[str, catalog.Reading] = state_figures(StationState(station=station))
        #: the latest slot record (its readings: the gauges of SLOT_GAUGES, read at scrape time)
        self.latest: SlotRecord | None = None


_FIGURES: dict[str, StationFigures] = {}
_FIGURES_LOCK = threading.Lock()


def figures_for(station: str) -> StationFigures:
    """The figures of ``station`` in this process (the same object across station rebuilds)."""
    with _FIGURES_LOCK:
        f = _FIGURES.get(station)
        if f is None:
            f = _FIGURES[station] = StationFigures(station)
        return f


def _counters(d: Any) -> dict[str, int]:
    if not d:
        return {}
    for _ in range(3):
        try:
            return {str(k): int(v) for k, v in dict(d).items()}
        except RuntimeError:     # changed size while copied by another thread: try again
            continue
    return {}


class OutboxGauge:
    """Depth and oldest-message age of an MQTT outbox, read on its own read-only connection."""

    def __init__(self, path: str):
        self.path = path
        self._db: sqlite3.Connection | None = None
        self._lock = threading.Lock()

    def read(self) -> tuple[int | None, float | None]:
        """(messages, age of the oldest in s); (None, None) while the file cannot be read."""
        with self._lock:
            try:
                if self._db is None:
                    uri = "file:" + urllib.parse.quote(os.path.abspath(self.path)) + "?mode=ro"
                    self._db = sqlite3.connect(uri, uri=True, timeout=0.5, check_same_thread=False)
                (n,) = self._db.execute("SELECT COUNT(*) FROM messages").fetchone()
                row = self._db.execute("SELECT created FROM messages ORDER BY seq LIMIT 1").fetchone()
                oldest = row[0] if row else None
            except sqlite3.Error:
                self.close_locked()
                return None, None
        return int(n), (max(0.0, time.time() - float(oldest)) if oldest is not None else None)

    def close_locked(self) -> None:
        if self._db is not None:
            try:
                self._db.close()
            except sqlite3.Error:
                pass
            self._db = None

    def close(self) -> None:
        with self._lock:
            self.close_locked()

def plc_figures(modbus: ModbusOutput | None) -> dict[str, Any] | None:
    """The ``plc`` part of a snapshot: the Modbus TCP server a ``ModbusOutput`` serves on."""
    if modbus is None:
        return None
    srv = modbus.server
    return {"listen": f"{modbus.s.host}:{modbus.s.port}",
            "listening": bool(srv is not None and srv.listening.is_set()),
            "counters": _counters(srv.store.counters if srv is not None else None)}


def figures_snapshot(f: StationFigures, station_id: str, ts: float, *, links: dict[str, Any],
                     outbox: dict[str, Any] | None, plc: dict[str, Any] | None) -> dict[str, Any]:
    """A snapshot (the shape in the module docstring) of ``f`` and the given link figures."""
    return {
        "v": SNAPSHOT_VERSION, "station": station_id, "time": time.time(), "ts": ts,
        "slots": f.life.n, "filled": f.life.n_present, "overruns": f.overruns,
        "lateness_s": f.lateness.snapshot(), "rtt_s": f.rtt.snapshot(),
        "links": links, "outbox": outbox, "plc": plc,
        "mu": f.mu, "events": dict(f.events),
        "records_pruned": {"tests": f.pruned_tests, "bytes": f.pruned_bytes}, **f.values,
        **catalog.read_latest(SLOT_GAUGES, f.latest),
    }


class _Process:
    console_clients: int | None = None
    #: the site configuration of this box (its supervisor's BoxAgent.figures), or None
    config: Callable[[], dict[str, Any]] | None = None


_PROCESS = _Process()


def set_console_clients(n: int | None) -> None:
    """The web console reports how many clients it serves (None: no console in this process)."""
    _PROCESS.console_clients = None if n is None else max(0, int(n))


def set_config_source(fn: Callable[[], dict[str, Any]] | None) -> None:
    """A site-managed box's supervisor names where its configuration figures come from
    (``hookwatch_config_info``, ``hookwatch_config_drift``; None: none in this process)."""
    _PROCESS.config = fn


def state_figures(st: StationState, values: tuple[catalog.Value, ...] = GAUGES) -> dict[str, catalog.Reading]:
    """The snapshot's values of the station's state: every catalog row with a gauge
    (gateway/core/catalog.py), as its source reads ``st``."""
    return catalog.read(values, st)
