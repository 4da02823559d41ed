"""Metrics for Prometheus: the gateway's own health, one endpoint per gateway process.

Four modules, one job each (docs/metrics.md lists every metric):

* ``figures`` — :class:`StationFigures`: plain ints and floats that a station's loop updates in O(1) per slot
  (no lock, no prometheus_client call on the slot path), kept per station id for the life of the
  process, so a station rebuilt by a reload keeps counting.
* ``outputs`` — :class:`MetricsOutput`: an ordinary station output (``start``/``on_record``/``on_event``/
  ``on_state``/``stop``) that feeds the figures and, at scrape time, builds the station's
  **snapshot**: a plain, JSON-serializable dict (shape below) that also pulls the drivers'
  ``counters``, link states and the MQTT outbox depth. The snapshot is the unit of hand-over: a
  supervisor of per-station worker processes can receive it over IPC and serve it unchanged.
* ``exposition`` — :func:`families` renders snapshots as Prometheus metric families at scrape time
  (a custom collector, :class:`SnapshotCollector`); pure.
* ``http`` — :class:`Endpoint`: the HTTP server (aiohttp, the gateway's one HTTP stack) on its
  own thread, shared by the stations of a process that name the same ``metrics.host:port``,
  behind a door (gateway/plumbing/doors.py: connection cap, whole-request deadline, idle timeout,
  ``metrics.connections``). A port in use is a state (one log line, retried every
  :data:`RETRY_S`), never a crash; the slot loop never waits for a scrape.

Snapshot shape (``SNAPSHOT_VERSION`` 2; every value a JSON number, string, bool, null, list or
object; the values of the station's state are the catalog's rows with a gauge, by their names:
gateway/core/catalog.py)::

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
     "mu": 0.21 | null,                                          # the last valid slot's μ
     "events": {"port_lost": 1, ...}, "records_pruned": {"tests": 0, "bytes": 0},
     "test_state": "monitoring", "test_running": true, "alarm": "normal",   # the catalog's rows
     "mu_ss": 0.2 | null, "mu_th": 0.25 | null, "headroom": 0.4 | null,
     "t_cross": 5400.0 | null, "wear_warning": false, "p_end": 0.2 | null, "due": false,
     "lead_s": 600.0 | null, "disk_ok": true, "end_p10_left": 120.0 | null, ...}

Process-wide figures (not per station): :func:`set_console_clients` (the console sets it) and
the PLC server counters (a Modbus TCP server may serve several stations; labelled by ``listen``).
"""
from __future__ import annotations

from ... import __version__
from .exposition import CONTENT_TYPE, PREFIX, SnapshotCollector, families, render
from .figures import (
                      LATENESS_BUCKETS_S,
                      LINKS,
                      OPERATION_KINDS,
                      RTT_BUCKETS_S,
                      SNAPSHOT_VERSION,
                      Histogram,
                      OutboxGauge,
                      StationFigures,
                      figures_for,
                      figures_snapshot,
                      plc_figures,
                      set_console_clients,
)
from .http import (
                      MAX_CONNECTIONS,
                      MAX_LINE,
                      REQUEST_TIMEOUT_S,
                      RETRY_S,
                      Endpoint,
                      EndpointSource,
                      endpoint,
                      shutdown_all,
)
from .outputs import MetricsOutput, MetricsRelay

__all__ = ["__version__", "CONTENT_TYPE",
           "LATENESS_BUCKETS_S", "LINKS", "MAX_CONNECTIONS", "MAX_LINE", "OPERATION_KINDS",
           "PREFIX", "REQUEST_TIMEOUT_S", "RETRY_S", "RTT_BUCKETS_S", "SNAPSHOT_VERSION", "Endpoint",
           "EndpointSource", "Histogram", "MetricsOutput", "MetricsRelay", "OutboxGauge",
           "SnapshotCollector", "StationFigures", "endpoint", "families", "figures_for",
           "figures_snapshot", "plc_figures", "render", "set_console_clients", "shutdown_all"]
