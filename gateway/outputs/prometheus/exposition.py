"""Metrics, part 2: the renderer — snapshots as Prometheus metric families (pure: no I/O, no
clock), and the prometheus_client collector that pulls every source's snapshot at scrape time."""
from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

from prometheus_client import CollectorRegistry
from prometheus_client.exposition import generate_latest
from prometheus_client.metrics_core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric

from ... import __version__
from ...core import catalog
from ..sparkplug.runtime import node_figures
from .figures import _PROCESS, GAUGES, OPERATION_KINDS, SLOT_GAUGES

log = logging.getLogger("hookwatch.metrics")

PREFIX = "hookwatch"
#: the classic text format (what generate_latest writes; every Prometheus 2.x reads it)
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"


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


def families(snapshots: list[dict], *, console_clients: int | None = None,
             sparkplug: list[dict[str, Any]] | None = None,
             config: dict[str, Any] | None = None) -> list[Metric]:
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

    events = CounterMetricFamily(f"{p}_events", "station events by type", labels=["station", "type"])
    for s in snapshots:
        for t, v in sorted(s["events"].items()):
            events.add_metric([s["station"], t], float(v))
    out.append(events)

    pr_tests = CounterMetricFamily(f"{p}_records_pruned_tests", "completed tests removed by record "
                                   "retention (recorder.retention)", labels=["station"])
    pr_bytes = CounterMetricFamily(f"{p}_records_pruned_bytes", "bytes freed by record retention "
                                   "(recorder.retention)", labels=["station"])
    for s in snapshots:
        rp = s.get("records_pruned") or {"tests": 0, "bytes": 0}
        pr_tests.add_metric([s["station"]], float(rp["tests"]))
        pr_bytes.add_metric([s["station"]], float(rp["bytes"]))
    out += [pr_tests, pr_bytes]

    sup = GaugeMetricFamily(f"{p}_station_up", "1 while the station's loop runs and reports (a "
                            "fleet: its worker process is up)", labels=["station"])
    restarts = CounterMetricFamily(f"{p}_worker_restarts", "restarts of the station's worker "
                                   "process by the fleet supervisor", labels=["station"])
    for s in snapshots:
        sup.add_metric([s["station"]], 1.0 if s.get("up", True) else 0.0)
        if "restarts" in s:
            restarts.add_metric([s["station"]], float(s["restarts"]))
    out += [sup, restarts]

    mu = GaugeMetricFamily(f"{p}_mu", "last valid friction coefficient μ of the running test",
                           labels=["station"])
    for s in snapshots:
        v = s.get("mu")
        if v is not None and math.isfinite(v):
            mu.add_metric([s["station"]], float(v))
    out.append(mu)
    out += state_families(p, snapshots)
    if SLOT_GAUGES:
        out += state_families(p, snapshots, SLOT_GAUGES)

    if console_clients is not None:
        out.append(GaugeMetricFamily(f"{p}_console_clients", "clients connected to the web console",
                                     value=float(console_clients)))
    out += sparkplug_families(p, sparkplug or [])
    if config is not None:
        out += config_families(p, config)
    return out


def config_families(p: str, c: dict[str, Any]) -> list[Any]:
    """A site-managed box (issue 37): which version of the site's configuration it runs, whether
    its tree was edited by hand, how many stations wait for their test to end."""
    box = str(c.get("box") or "")
    info = GaugeMetricFamily(f"{p}_config_info", "always 1: the site configuration version this box "
                             "runs (a Git commit), the sha256 of its effective tree and the last "
                             "verified version", labels=["box", "site", "version", "sha256", "verified"])
    info.add_metric([box, str(c.get("site") or ""), str(c.get("version") or ""),
                     str(c.get("sha256") or ""), str(c.get("verified") or "")], 1.0)
    drift = GaugeMetricFamily(f"{p}_config_drift", "1 while a file of the box's effective tree "
                              "differs from what was staged (a hand edit)", labels=["box"])
    drift.add_metric([box], 1.0 if c.get("drift") else 0.0)
    deferred = GaugeMetricFamily(f"{p}_config_deferred_stations", "stations whose new configuration "
                                 "waits for their running test to end", labels=["box"])
    deferred.add_metric([box], float(c.get("deferred") or 0))
    return [info, drift, deferred]


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
        config = None
        if _PROCESS.config is not None:
            try:
                config = _PROCESS.config()
            except Exception:  # the configuration figures must not hide the stations'
                log.exception("metrics: the configuration figures failed")
        yield from families(snaps, console_clients=_PROCESS.console_clients, sparkplug=node_figures(),
                            config=config)



def render(registry: CollectorRegistry) -> bytes:
    """The text exposition of ``registry`` (CONTENT_TYPE)."""
    return generate_latest(registry)


def state_families(p: str, snapshots: list[dict[str, Any]],
                   values: tuple[catalog.Value | catalog.SlotValue, ...] = GAUGES) -> list[Metric]:
    """A gauge per catalog row with one (gateway/core/catalog.py: a value of the state, or the
    latest slot's reading of a slot records' row), from the snapshots' values: a flag 1 or 0; a
    number when there is one (absent while it is null or not finite); an enumeration one gauge
    per choice, labelled, 1 for the current one."""
    out: list[Metric] = []
    for v in values:
        g = v.prometheus
        assert g is not None
        fam = GaugeMetricFamily(f"{p}_{g.name}", g.help, labels=["station", g.label] if g.label else ["station"])
        for s in snapshots:
            x = s.get(v.name)
            if g.label and isinstance(v, catalog.Value):
                for c in v.choices:
                    fam.add_metric([s["station"], c], 1.0 if x == c else 0.0)
            elif v.base_type == "bool":
                fam.add_metric([s["station"]], 1.0 if x else 0.0)
            elif isinstance(x, (int, float)) and math.isfinite(x):
                fam.add_metric([s["station"]], float(x))
        out.append(fam)
    return out


def sparkplug_families(p: str, nodes: list[dict[str, Any]]) -> list[Any]:
    """The Sparkplug edge nodes of this process (docs/sparkplug.md): session up, bad inbound
    payloads by kind (STATE, NCMD, DCMD … refused within bounds and ignored), and the node's other
    counters (births, rebirths, published, connect errors, crashes …) as events."""
    if not nodes:
        return []
    labels = ["group", "node"]
    up = GaugeMetricFamily(f"{p}_sparkplug_connected", "1 while the edge node's MQTT session is up",
                           labels=labels)
    bad = CounterMetricFamily(f"{p}_sparkplug_bad_payloads", "inbound Sparkplug payloads refused "
                              "within bounds and ignored, by kind (the session goes on)",
                              labels=labels + ["kind"])
    ev = CounterMetricFamily(f"{p}_sparkplug_events", "the edge node's counted events (births, "
                             "rebirths, published messages, connect errors, crashes …)",
                             labels=labels + ["event"])
    for n in nodes:
        key = [str(n["group"]), str(n["node"])]
        up.add_metric(key, 1.0 if n["connected"] else 0.0)
        for name, v in sorted(n["counters"].items()):
            if name.startswith("bad_"):
                bad.add_metric(key + [name[4:]], float(v))
            else:
                ev.add_metric(key + [name], float(v))
    return [up, bad, ev]
