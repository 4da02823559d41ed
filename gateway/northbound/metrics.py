"""Metrics for Prometheus: the gateway's own health, one endpoint per gateway process.

Three parts, one job each (docs/metrics.md lists every metric):

* :class:`StationFigures` — plain ints and floats that a station's loop updates in O(1) per slot
  (no lock, no prometheus_client call on the slot path), kept per station id for the life of the
  process, so a station rebuilt by a reload keeps counting.
* :class:`MetricsOutput` — an ordinary station output (``start``/``on_record``/``on_event``/
  ``on_state``/``stop``) that feeds the figures and, at scrape time, builds the station's
  **snapshot**: a plain, JSON-serializable dict (shape below) that also pulls the drivers'
  ``counters``, link states and the MQTT outbox depth. The snapshot is the unit of hand-over: a
  supervisor of per-station worker processes can receive it over IPC and serve it unchanged.
* :class:`Endpoint` — the HTTP server on its own thread, shared by the stations of a process that
  name the same ``metrics.host:port``; :func:`families` renders snapshots as Prometheus metric
  families at scrape time (a custom collector). Bounded: at most :data:`MAX_CONNECTIONS` requests
  at once (more are closed at once), :data:`REQUEST_TIMEOUT_S` per request, GET/HEAD without a
  body only, request line and headers at most :data:`MAX_LINE` bytes each. A port in use is a
  state (one log line, retried every :data:`RETRY_S`), never a crash; the slot loop never waits
  for a scrape.

Snapshot shape (``SNAPSHOT_VERSION`` 1; every value a JSON number, string, bool, null, list or
object)::

    {"v": 1, "station": "loom-01", "time": 1764000000.0,         # wall clock of the snapshot
     "ts": 0.02,                                                 # the slot period, s
     "slots": 123456, "filled": 123400, "overruns": 3,           # counters since process start
     "lateness_s": {"le": [0.0001, ...], "counts": [...], "sum": 1.23},   # histogram: counts
     "rtt_s": {"le": [...], "counts": [...], "sum": 2.34},       #   per bucket, not cumulative,
                                                                 #   len(counts) == len(le) + 1
     "links": {"meter": {"up": true, "counters": {"timeouts": 2, ...}},
               "stm32": {"up": true, "counters": {...}},
               "mqtt": {"up": false, "counters": {...}}},        # only links the station has
     "outbox": {"messages": 12 | null, "oldest_age_s": 3.5 | null,   # null: file unreadable
                "dropped_telemetry": 0} | null,
     "plc": {"listen": "127.0.0.1:5020", "listening": true, "counters": {"reads": 9, ...}} | null,
     "state": "monitoring", "test_running": true, "alarm": "normal",
     "mu": 0.21 | null, "mu_ss": 0.2 | null, "mu_th": 0.25 | null,
     "headroom": 0.4 | null, "t_cross": 5400.0 | null, "warning": false,    # METHOD.md §5a
     "end_p10_left": 900.0 | null, "end_p50_left": ..., "end_p90_left": ...,   # §5b, s remaining
     "p_end": 0.2 | null, "due": false, "lead_s": 3600.0 | null,
     "events": {"port_lost": 1, ...}}

Process-wide figures (not per station): :func:`set_console_clients` (the console sets it) and
the PLC server counters (a Modbus TCP server may serve several stations; labelled by ``listen``).
"""
from __future__ import annotations

import http.server
import io
import logging
import math
import os
import socket
import socketserver
import sqlite3
import sys
import threading
import time
import urllib.parse
from bisect import bisect_left
from collections.abc import Callable
from typing import Any, cast

from prometheus_client import CollectorRegistry, PlatformCollector, ProcessCollector
from prometheus_client.exposition import generate_latest
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric

from .. import __version__
from ..ports import StationView
from ..records import AlarmState, Event, SlotRecord, StationState, TestState

log = logging.getLogger("hookwatch.metrics")

SNAPSHOT_VERSION = 1
PREFIX = "hookwatch"

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
    "mqtt": frozenset({"sent", "confirmed", "commands", "connects"}),
}
LINKS = ("meter", "stm32", "mqtt")

MAX_CONNECTIONS = 4
REQUEST_TIMEOUT_S = 5.0
MAX_LINE = 8192
RETRY_S = 5.0
#: niceness added to the threads that answer scrapes
SCRAPE_NICE = 5
#: the classic text format (what generate_latest writes; every Prometheus 2.x reads it)
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
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
    __slots__ = ("station", "slots", "filled", "overruns", "lateness", "rtt", "mu", "mu_ss",
                 "mu_th", "headroom", "t_cross", "warning", "state", "alarm", "events", "disk_ok",
                 "forecast")

    def __init__(self, station: str):
        self.station = station
        self.slots = self.filled = self.overruns = 0
        self.lateness = Histogram(LATENESS_BUCKETS_S)
        self.rtt = Histogram(RTT_BUCKETS_S)
        self.mu: float | None = None
        self.mu_ss: float | None = None
        self.mu_th: float | None = None
        self.headroom: float | None = None
        self.t_cross: float | None = None
        self.warning = False
        self.disk_ok = True
        self.state = TestState.IDLE
        self.alarm = "normal"
        self.events: dict[str, int] = {}
        #: the §5b forecast as the state last had it (forecast_figures)
        self.forecast: dict[str, Any] = {}


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


class _EndpointSource:
    """A station's snapshot source on the endpoint of (``host``, ``port``) while started."""
    station_id: str
    host: str
    port: int
    endpoint: Endpoint | None

    def snapshot(self) -> dict[str, Any]:
        raise NotImplementedError

    async def start(self) -> None:
        self.endpoint = endpoint(self.host, self.port)
        self.endpoint.add_source(self.station_id, self.snapshot)

    async def stop(self) -> None:
        if self.endpoint is not None:
            ep, self.endpoint = self.endpoint, None
            ep.remove_source(self.station_id, self.snapshot)


class MetricsOutput(_EndpointSource):
    """Station output feeding :class:`StationFigures`; registers the station on its endpoint."""

    def __init__(self, station: StationView, host: str = "127.0.0.1", port: int = 9620, *,
                 mqtt=None, modbus=None, serve: bool = True):
        self.station = station
        self.station_id = station.id
        self.host, self.port = host, int(port)
        self.ts = float(getattr(station, "ts", 0.02))
        self.f = figures_for(self.station_id)
        self._late_max = self.ts / 2
        self.mqtt = mqtt
        self.modbus = modbus
        self._outbox = OutboxGauge(mqtt.outbox.path) if mqtt is not None else None
        #: False in a fleet worker: :meth:`snapshot` goes to the supervisor, which serves it
        self.serve = serve
        self.endpoint: Endpoint | None = None

    # -- output protocol (station loop)
    async def start(self) -> None:
        if self.serve:
            await super().start()

    async def stop(self) -> None:
        await super().stop()
        if self._outbox is not None:
            self._outbox.close()

    def on_record(self, rec: SlotRecord) -> None:
        # O(1), a few hundred ns: plain attribute updates and C bisects, nothing else
        f = self.f
        f.slots += 1
        lat = rec.lateness_s
        if lat > self._late_max:        # a slot lost to an overrun (recorded as MISSING)
            f.overruns += 1
            return
        h = f.lateness
        h.counts[bisect_left(h.le, lat)] += 1
        h.sum += lat
        if rec.present:
            f.filled += 1
            rtt = rec.rtt_s
            if rtt == rtt:              # not NaN
                h = f.rtt
                h.counts[bisect_left(h.le, rtt)] += 1
                h.sum += rtt
            if rec.q:
                f.mu = rec.mu

    def on_event(self, ev: Event) -> None:
        ev_counts = self.f.events
        t = ev.type.value
        ev_counts[t] = ev_counts.get(t, 0) + 1

    def on_state(self, st: StationState) -> None:
        f = self.f
        f.state, f.alarm = st.state, st.alarm
        f.mu_ss, f.mu_th = st.mu_ss, st.mu_th
        # METHOD.md §5a figures, once the station state carries them
        f.headroom = getattr(st, "headroom", None)
        f.t_cross = getattr(st, "t_cross", None)
        f.warning = bool(st.wear_warning)
        f.forecast = forecast_figures(st)
        f.disk_ok = bool(getattr(st, "disk_ok", True))
        if st.state not in _RUNNING:
            f.mu = None

    # -- scrape time (any thread)
    def snapshot(self) -> dict[str, Any]:
        """This station's figures as a plain dict (the shape in the module docstring)."""
        f = self.f
        st = self.station
        links: dict[str, Any] = {}
        for name, drv in (("meter", getattr(st, "meter", None)), ("stm32", getattr(st, "stm32", None))):
            if drv is not None:
                links[name] = {"up": bool(getattr(drv, "connected", False)),
                               "counters": _counters(getattr(drv, "counters", None))}
        outbox = None
        if self.mqtt is not None and self._outbox is not None:     # set together in __init__
            links["mqtt"] = {"up": bool(self.mqtt.connected), "counters": _counters(self.mqtt.counters)}
            n, age = self._outbox.read()
            ob = getattr(self.mqtt, "outbox", None)
            outbox = {"messages": n, "oldest_age_s": age,
                      "dropped_telemetry": int(getattr(ob, "dropped_telemetry", 0))}
        return figures_snapshot(f, self.station_id, self.ts, links=links, outbox=outbox,
                                plc=plc_figures(self.modbus))


def plc_figures(modbus) -> dict[str, Any] | None:
    """The ``plc`` part of a snapshot: the Modbus TCP server a ``ModbusOutput`` serves on."""
    if modbus is None:
        return None
    srv = getattr(modbus, "server", None)
    store = getattr(srv, "store", None)
    return {"listen": f"{modbus.s.host}:{modbus.s.port}",
            "listening": bool(srv is not None and srv.listening.is_set()),
            "counters": _counters(getattr(store, "counters", None))}


def figures_snapshot(f: StationFigures, station_id: str, ts: float, *, links: dict[str, Any],
                     outbox: dict[str, Any] | None, plc: dict[str, Any] | None) -> dict[str, Any]:
    """A snapshot (the shape in the module docstring) of ``f`` and the given link figures."""
    state = f.state
    return {
        "v": SNAPSHOT_VERSION, "station": station_id, "time": time.time(), "ts": ts,
        "slots": f.slots, "filled": f.filled, "overruns": f.overruns,
        "lateness_s": f.lateness.snapshot(), "rtt_s": f.rtt.snapshot(),
        "links": links, "outbox": outbox, "plc": plc,
        "state": state.name.lower(), "test_running": state in _RUNNING, "alarm": f.alarm,
        "mu": f.mu, "mu_ss": f.mu_ss, "mu_th": f.mu_th, "headroom": f.headroom,
        "t_cross": f.t_cross, "warning": f.warning,
        "events": dict(f.events), "disk_ok": f.disk_ok, **f.forecast,
    }


def forecast_figures(st: StationState) -> dict[str, Any]:
    """The §5b figures of a snapshot (METHOD.md): the remaining time to each end quantile of the
    last forecast time (s, at least 0; null without one), P, the due flag and the lead."""
    el = float(st.elapsed_s)
    out: dict[str, Any] = {f"end_p{q}_left": (max(0.0, e - el) if e is not None else None)
                           for q, e in ((10, st.end_p10), (50, st.end_p50), (90, st.end_p90))}
    out.update(p_end=st.p_end, due=bool(st.due), lead_s=st.lead_s)
    return out


class MetricsRelay(_EndpointSource):
    """The supervisor's side of a fleet (``hookwatch run FLEET_DIR``): an output of a station
    proxy (gateway/supervisor/remote.py) that serves the snapshots its worker sends (METRICS
    frames, one a second) on this process' endpoint, with the counters of the Modbus TCP server
    the supervisor runs for the station (``modbus``) and the worker's health:
    ``hookwatch_station_up`` 0 and every link down while the worker is down or restarting, and
    ``hookwatch_worker_restarts_total``. Counters start again with a restarted worker (a reset
    that ``rate()`` handles)."""

    def __init__(self, station_id: str, host: str = "127.0.0.1", port: int = 9620, *,
                 ts: float = 0.02, modbus=None):
        self.station_id = station_id
        self.host, self.port = host, int(port)
        self.ts = float(ts)
        self.modbus = modbus
        self.latest: dict[str, Any] | None = None
        self.up = False
        self.restarts = 0
        self.endpoint: Endpoint | None = None

    def on_record(self, rec: SlotRecord) -> None:
        pass        # the worker counts its slots; its snapshot carries them

    def on_event(self, ev: Event) -> None:
        pass

    def on_state(self, st: StationState) -> None:
        pass

    def on_metrics(self, snap: dict[str, Any]) -> None:
        """A worker's snapshot (the reader thread of its IPC link)."""
        self.latest = snap

    def on_worker(self, up: bool, restarts: int = 0) -> None:
        self.up = bool(up)
        self.restarts = int(restarts)

    def snapshot(self) -> dict[str, Any]:
        snap = self.latest
        if snap is None or snap.get("v") != SNAPSHOT_VERSION:
            s = figures_snapshot(StationFigures(self.station_id), self.station_id, self.ts,
                                 links={}, outbox=None, plc=None)
        else:
            s = dict(snap)
        s["station"] = self.station_id
        if not self.up:
            s["links"] = {k: {**v, "up": False} for k, v in (s.get("links") or {}).items()}
        s["up"] = self.up
        s["restarts"] = self.restarts
        if self.modbus is not None:
            s["plc"] = plc_figures(self.modbus)
        return s


# ------------------------------------------------------------------------------------------------
# rendering: snapshots -> metric families


class _Process:
    console_clients: int | None = None


_PROCESS = _Process()


def set_console_clients(n: int | None) -> None:
    """The web console reports how many clients it serves (None: no console in this process)."""
    _PROCESS.console_clients = None if n is None else max(0, int(n))


def _hist(name: str, doc: str, snaps: list[dict], key: str) -> HistogramMetricFamily:
    fam = HistogramMetricFamily(name, doc, labels=["station"])
    for s in snaps:
        h = s[key]
        cum, buckets = 0, []
        for le, c in zip(list(h["le"]) + [math.inf], h["counts"]):
            cum += c
            buckets.append(("+Inf" if le == math.inf else repr(float(le)), cum))
        fam.add_metric([s["station"]], buckets, float(h["sum"]))
    return fam


def families(snapshots: list[dict], *, console_clients: int | None = None) -> list[Metric]:
    """Prometheus metric families of station snapshots (pure: no I/O, no clock)."""
    p = PREFIX
    out: list[Metric] = []
    info = GaugeMetricFamily(f"{p}_build_info", "hookwatch version of this gateway", labels=["version"])
    info.add_metric([__version__], 1.0)
    out.append(info)

    def counter(name, doc, key):
        fam = CounterMetricFamily(f"{p}_{name}", doc, labels=["station"])
        for s in snapshots:
            fam.add_metric([s["station"]], float(s[key]))
        out.append(fam)

    counter("slots", "slots (20 ms at 50 Hz) the station's loop has passed", "slots")
    counter("slots_filled", "slots with a valid meter reading", "filled")
    counter("slot_overruns", "slots lost because the loop started them more than ts/2 late "
            "(recorded as MISSING)", "overruns")
    out.append(_hist(f"{p}_slot_lateness_seconds", "how late each slot's poll started after its "
                     "deadline (slots not lost to an overrun)", snapshots, "lateness_s"))
    out.append(_hist(f"{p}_meter_rtt_seconds", "meter request-to-reply time of filled slots",
                     snapshots, "rtt_s"))

    errors = CounterMetricFamily(f"{p}_link_errors",
                                 "link failures by kind (the drivers' counters)",
                                 labels=["station", "link", "kind"])
    ops = CounterMetricFamily(f"{p}_link_operations", "link traffic by kind (requests, replies, "
                              "reconnects; the drivers' counters)", labels=["station", "link", "kind"])
    up = GaugeMetricFamily(f"{p}_link_up", "1 when the link is up: meter and STM32 serial port open "
                           "(a silent device shows as timeouts), MQTT connected to the broker",
                           labels=["station", "link"])
    for s in snapshots:
        for link, d in s["links"].items():
            up.add_metric([s["station"], link], 1.0 if d["up"] else 0.0)
            op_kinds = OPERATION_KINDS.get(link, frozenset())
            for kind, v in sorted(d["counters"].items()):
                (ops if kind in op_kinds else errors).add_metric([s["station"], link, kind], float(v))
    out += [errors, ops, up]

    depth = GaugeMetricFamily(f"{p}_outbox_messages", "MQTT messages stored and not yet confirmed "
                              "by the broker", labels=["station"])
    age = GaugeMetricFamily(f"{p}_outbox_oldest_age_seconds", "age of the oldest unconfirmed MQTT "
                            "message (0 when the outbox is empty)", labels=["station"])
    dropped = CounterMetricFamily(f"{p}_outbox_dropped_telemetry", "telemetry messages dropped "
                                  "over the outbox budget (events and results are never dropped)",
                                  labels=["station"])
    for s in snapshots:
        ob = s.get("outbox")
        if ob is not None and ob["messages"] is not None:
            depth.add_metric([s["station"]], float(ob["messages"]))
            age.add_metric([s["station"]], float(ob["oldest_age_s"] or 0.0))
            dropped.add_metric([s["station"]], float(ob["dropped_telemetry"]))
    out += [depth, age, dropped]

    plc_req = CounterMetricFamily(f"{p}_plc_requests", "Modbus TCP requests by result (reads and "
                                  "writes served, refused writes, bad values, unknown unit IDs)",
                                  labels=["listen", "result"])
    plc_up = GaugeMetricFamily(f"{p}_plc_listening", "1 when the Modbus TCP server listens",
                               labels=["listen"])
    seen: set[str] = set()
    for s in snapshots:
        pl = s.get("plc")
        if pl is None or pl["listen"] in seen:
            continue
        seen.add(pl["listen"])
        plc_up.add_metric([pl["listen"]], 1.0 if pl["listening"] else 0.0)
        for kind, v in sorted(pl["counters"].items()):
            plc_req.add_metric([pl["listen"], kind], float(v))
    out += [plc_req, plc_up]

    state = GaugeMetricFamily(f"{p}_station_state", "the station's test state (1 for the current "
                              "one)", labels=["station", "state"])
    running = GaugeMetricFamily(f"{p}_test_running", "1 while a test runs", labels=["station"])
    warning = GaugeMetricFamily(f"{p}_wear_warning", "1 once the test's early wear warning fired "
                                "(METHOD.md §5a)", labels=["station"])
    alarm = GaugeMetricFamily(f"{p}_alarm", "end-of-life alarm state (1 for the current one)",
                              labels=["station", "alarm"])
    events = CounterMetricFamily(f"{p}_events", "station events by type", labels=["station", "type"])
    disk = GaugeMetricFamily(f"{p}_disk_ok", "1 when the test records and the MQTT outbox can be "
                             "written (0: a full or read-only disk)", labels=["station"])
    for s in snapshots:
        for ts_ in TestState:
            state.add_metric([s["station"], ts_.name.lower()], 1.0 if s["state"] == ts_.name.lower() else 0.0)
        running.add_metric([s["station"]], 1.0 if s["test_running"] else 0.0)
        warning.add_metric([s["station"]], 1.0 if s.get("warning") else 0.0)
        for a in (x.value for x in AlarmState):
            alarm.add_metric([s["station"], a], 1.0 if s["alarm"] == a else 0.0)
        for t, v in sorted(s["events"].items()):
            events.add_metric([s["station"], t], float(v))
        disk.add_metric([s["station"]], 1.0 if s.get("disk_ok", True) else 0.0)
    out += [state, running, warning, alarm, events, disk]

    sup = GaugeMetricFamily(f"{p}_station_up", "1 while the station's loop runs and reports (a "
                            "fleet: its worker process is up)", labels=["station"])
    restarts = CounterMetricFamily(f"{p}_worker_restarts", "restarts of the station's worker "
                                   "process by the fleet supervisor", labels=["station"])
    for s in snapshots:
        sup.add_metric([s["station"]], 1.0 if s.get("up", True) else 0.0)
        if "restarts" in s:
            restarts.add_metric([s["station"]], float(s["restarts"]))
    out += [sup, restarts]

    for key, name, doc in (("mu", "mu", "last valid friction coefficient μ of the running test"),
                           ("mu_ss", "mu_ss", "steady baseline μ_ss of the running test"),
                           ("mu_th", "mu_threshold", "end-of-life threshold (1+δ)·μ_ss"),
                           ("headroom", "wear_headroom", "wear headroom h of the last window "
                            "(METHOD.md §5a): 1 at the baseline, 0 at the threshold"),
                           ("t_cross", "wear_projected_end_seconds", "test time at which the recent "
                            "μ trend reaches the threshold (METHOD.md §5a projection)")):
        g = GaugeMetricFamily(f"{p}_{name}", doc, labels=["station"])
        for s in snapshots:
            v = s.get(key)
            if v is not None and math.isfinite(v):
                g.add_metric([s["station"]], float(v))
        out.append(g)

    out += forecast_families(p, snapshots)

    if console_clients is not None:
        out.append(GaugeMetricFamily(f"{p}_console_clients", "clients connected to the web console",
                                     value=float(console_clients)))
    return out


def forecast_families(p: str, snapshots: list[dict[str, Any]]) -> list[Any]:
    """The §5b remaining-life metrics (METHOD.md): remaining seconds to each end quantile, P, the
    lead and a due gauge (the alerting rule in deploy/prometheus/ fires on it)."""
    out: list[Any] = []
    for q in (10, 50, 90):
        g = GaugeMetricFamily(f"{p}_end_p{q}_seconds", f"remaining time to the {q} % end quantile "
                              "of the hook's life forecast at its last forecast time (METHOD.md "
                              "§5b); absent without a prior, outside a test and once the end of "
                              "life was detected", labels=["station"])
        for s in snapshots:
            v = s.get(f"end_p{q}_left")
            if v is not None and math.isfinite(v):
                g.add_metric([s["station"]], float(v))
        out.append(g)
    pe = GaugeMetricFamily(f"{p}_end_within_lead_probability", "chance that the hook's end comes "
                           "within the lead (METHOD.md §5b P)", labels=["station"])
    lead = GaugeMetricFamily(f"{p}_lead_seconds", "the planner's lead the hook is judged against "
                             "(METHOD.md §5b)", labels=["station"])
    due = GaugeMetricFamily(f"{p}_hook_due", "1 while the last forecast window of the running test "
                            "is due (METHOD.md §5b: P ≥ p_due, a headroom run or a projected "
                            "crossing within the lead)", labels=["station"])
    for s in snapshots:
        if s.get("p_end") is not None and math.isfinite(s["p_end"]):
            pe.add_metric([s["station"]], float(s["p_end"]))
        if s.get("lead_s") is not None:
            lead.add_metric([s["station"]], float(s["lead_s"]))
        due.add_metric([s["station"]], 1.0 if s.get("due") else 0.0)
    return out + [pe, lead, due]


class SnapshotCollector:
    """prometheus_client collector: pulls every source's snapshot at scrape time."""

    def __init__(self, sources: Callable[[], list[Callable[[], dict]]]):
        self._sources = sources

    def collect(self):
        snaps = []
        for src in self._sources():
            try:
                snaps.append(src())
            except Exception:  # one broken source must not hide the others
                log.exception("metrics: a station snapshot failed")
        snaps.sort(key=lambda s: s["station"])
        yield from families(snaps, console_clients=_PROCESS.console_clients)


# ------------------------------------------------------------------------------------------------
# the HTTP endpoint


class _Handler(http.server.BaseHTTPRequestHandler):
    server_version = "hookwatch-metrics"
    timeout = REQUEST_TIMEOUT_S
    protocol_version = "HTTP/1.0"
    default_request_version = "HTTP/1.0"      # garbage gets a status line too, never HTTP/0.9
    server: _Server                           # the one server class that uses this handler
    raw_requestline: bytes                    # set by handle_one_request() (not in typeshed)

    def setup(self) -> None:
        # a scrape yields the CPU to the stations' slot threads (Linux: nice is per thread)
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(),
                           os.getpriority(os.PRIO_PROCESS, 0) + SCRAPE_NICE)
        except (OSError, AttributeError):
            pass
        super().setup()
        self._lines = _LimitedReader(self.rfile)
        # http.server reads the request line and the headers with readline() only
        self.rfile = cast(io.BufferedIOBase, self._lines)

    def parse_request(self) -> bool:
        if len(self.raw_requestline) > MAX_LINE:
            self.requestline, self.request_version, self.command = "", "HTTP/1.0", ""
            self.close_connection = True
            self.send_error(414)
            return False
        if not super().parse_request():
            return False
        if self._lines.too_long:
            self.close_connection = True
            self.send_error(431, "header line too long")
            return False
        return True

    def do_GET(self) -> None:
        self._serve(body=True)

    def do_HEAD(self) -> None:
        self._serve(body=False)

    def _serve(self, body: bool) -> None:
        if self.headers.get("Content-Length", "0") not in ("", "0"):
            self.send_error(413, "no request body accepted")
            return
        path = self.path.split("?", 1)[0]
        if path == "/":
            data, ctype = (b"<html><body><a href=\"/metrics\">hookwatch metrics</a></body></html>\n",
                           "text/html; charset=utf-8")
        elif path == "/metrics":
            try:
                data, ctype = generate_latest(self.server.registry), CONTENT_TYPE
            except Exception:
                log.exception("metrics: rendering failed")
                self.send_error(500)
                return
        else:
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        if body:
            self.wfile.write(data)

    def do_POST(self) -> None:
        self.send_error(405)

    do_PUT = do_DELETE = do_PATCH = do_POST

    def log_message(self, format: str, *args) -> None:   # noqa: A002 (http.server's signature)
        log.debug("metrics %s: " + format, self.address_string(), *args)


class _LimitedReader:
    """Lines of at most MAX_LINE bytes (http.server allows 64 KiB per line)."""

    def __init__(self, raw):
        self._raw = raw
        self.too_long = False

    def readline(self, limit: int = -1) -> bytes:
        lim = MAX_LINE + 1 if limit < 0 else min(limit, MAX_LINE + 1)
        line = self._raw.readline(lim)
        if len(line) > MAX_LINE:
            self.too_long = True
        return line

    def __getattr__(self, name):
        return getattr(self._raw, name)


class _Server(socketserver.ThreadingMixIn, http.server.HTTPServer):
    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 8
    block_on_close = False

    def __init__(self, addr, registry: CollectorRegistry):
        self.registry = registry
        self.slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self.refused = 0
        self.address_family = socket.AF_INET6 if ":" in addr[0] else socket.AF_INET
        super().__init__(addr, _Handler)

    def process_request(self, request, client_address) -> None:
        if not self.slots.acquire(blocking=False):
            self.refused += 1
            self.shutdown_request(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self.slots.release()
            raise

    def handle_error(self, request, client_address) -> None:
        # a client that hangs up or times out is its own business: one debug line, no traceback
        # on stderr (socketserver's default); anything else is a bug worth a log entry
        exc = sys.exc_info()[1]
        if isinstance(exc, OSError):
            log.debug("metrics: request from %s ended: %s", client_address, exc)
        else:
            log.exception("metrics: request from %s failed", client_address)

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self.slots.release()


class Endpoint:
    """``/metrics`` on (host, port), served by its own thread; stations add snapshot sources."""

    def __init__(self, host: str, port: int):
        self.host, self.port = host, int(port)
        self._sources: dict[str, Callable[[], dict]] = {}
        self._lock = threading.Lock()
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(SnapshotCollector(self.sources))
        ProcessCollector(registry=self.registry)
        PlatformCollector(registry=self.registry)
        self.server: _Server | None = None
        self.error: str | None = None
        self.listening = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._main, name=f"metrics-{host}:{port}", daemon=True)
        self._thread.start()

    @property
    def address(self) -> tuple[str, int]:
        srv = self.server
        return (self.host, srv.server_address[1]) if srv is not None else (self.host, self.port)

    def sources(self) -> list[Callable[[], dict]]:
        with self._lock:
            return list(self._sources.values())

    def add_source(self, name: str, fn: Callable[[], dict]) -> None:
        with self._lock:
            self._sources[name] = fn

    def remove_source(self, name: str, fn: Callable[[], dict] | None = None) -> None:
        """Remove a source (only ``fn`` if given: a rebuilt station may have replaced it)."""
        with self._lock:
            if fn is None or self._sources.get(name) == fn:
                self._sources.pop(name, None)

    def _main(self) -> None:
        logged = False
        while not self._stop.is_set():
            try:
                srv = _Server((self.host, self.port), self.registry)
            except OSError as e:   # address in use, permission, no such address: a state
                self.error = f"metrics {self.host}:{self.port}: cannot listen: {e.strerror or e}"
                if not logged:
                    log.error("%s; retrying every %.0f s", self.error, RETRY_S)
                    logged = True
                self._stop.wait(RETRY_S)
                continue
            self.server, self.error = srv, None
            self.listening.set()
            log.info("metrics for Prometheus on http://%s:%d/metrics", self.host, srv.server_address[1])
            try:
                srv.serve_forever(poll_interval=0.5)
            finally:
                srv.server_close()
                self.listening.clear()
            return

    def shutdown(self, timeout: float = 5.0) -> None:
        self._stop.set()
        srv = self.server
        if srv is not None:
            srv.shutdown()
        self._thread.join(timeout)


_ENDPOINTS: dict[tuple[str, int], Endpoint] = {}
_ENDPOINTS_LOCK = threading.Lock()


def endpoint(host: str, port: int) -> Endpoint:
    """The process' endpoint on (host, port), started on first use; it runs until process exit
    (a station rebuilt by a reload re-registers without the port ever closing)."""
    key = (host, int(port))
    with _ENDPOINTS_LOCK:
        ep = _ENDPOINTS.get(key)
        if ep is None:
            ep = _ENDPOINTS[key] = Endpoint(host, int(port))
        return ep


def shutdown_all() -> None:
    """Stop every endpoint of this process (tests; the process exit does it otherwise)."""
    with _ENDPOINTS_LOCK:
        eps = list(_ENDPOINTS.values())
        _ENDPOINTS.clear()
    for ep in eps:
        ep.shutdown()
