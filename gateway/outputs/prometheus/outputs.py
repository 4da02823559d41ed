"""Metrics, part 3: the station outputs — :class:`MetricsOutput` feeds a station's figures and
offers its snapshot on the process's endpoint; :class:`MetricsRelay` serves a fleet worker's
snapshots in the supervisor."""
from __future__ import annotations

from bisect import bisect_left
from typing import Any

from ...core.ports import StationLinks
from ...core.records import Event, EventType, SlotRecord, StationState
from ...plumbing.doors import DoorLimits
from .figures import (
    _RUNNING,
    SNAPSHOT_VERSION,
    OutboxGauge,
    StationFigures,
    _counters,
    figures_for,
    figures_snapshot,
    plc_figures,
    state_figures,
)
from .http import Endpoint, EndpointSource

__all__ = ["MetricsOutput", "MetricsRelay"]


class MetricsOutput(EndpointSource):
    """Station output feeding :class:`StationFigures`; registers the station on its endpoint."""

    def __init__(self, station: StationLinks, host: str = "127.0.0.1", port: int = 9620, *,
                 mqtt=None, modbus=None, serve: bool = True, limits: DoorLimits | None = None):
        self.station = station
        self.limits = limits
        self.station_id = station.id
        self.host, self.port = host, int(port)
        self.ts = float(station.ts)
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
        # O(1), under a microsecond: the slot window's attribute updates and C bisects, nothing else
        f = self.f
        f.life.add(rec)                 # slots, and those with a reading
        f.latest = rec                  # the catalog's gauges of the latest slot (SLOT_GAUGES)
        lat = rec.lateness_s
        if lat > self._late_max:        # a slot lost to an overrun (recorded as MISSING)
            f.overruns += 1
            return
        h = f.lateness
        h.counts[bisect_left(h.le, lat)] += 1
        h.sum += lat
        if rec.present:
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
        if ev.type is EventType.RECORDS_PRUNED:
            self.f.pruned_tests += len(ev.data.get("tests") or ())
            self.f.pruned_bytes += int(ev.data.get("bytes") or 0)

    def on_state(self, st: StationState) -> None:
        f = self.f
        f.values = state_figures(st)
        if st.state not in _RUNNING:
            f.mu = None

    # -- scrape time (any thread)
    def snapshot(self) -> dict[str, Any]:
        """This station's figures as a plain dict (the shape in the module docstring)."""
        f = self.f
        st = self.station
        links: dict[str, Any] = {}
        for name, port in (("meter", st.meter), ("stm32", st.stm32)):
            links[name] = {"up": bool(port.connected), "counters": _counters(port.counters)}
        outbox = None
        if self.mqtt is not None and self._outbox is not None:     # set together in __init__
            links["mqtt"] = {"up": bool(self.mqtt.connected), "counters": _counters(self.mqtt.counters)}
            n, age = self._outbox.read()
            ob = getattr(self.mqtt, "outbox", None)
            outbox = {"messages": n, "oldest_age_s": age,
                      "dropped_telemetry": int(getattr(ob, "dropped_telemetry", 0))}
        return figures_snapshot(f, self.station_id, self.ts, links=links, outbox=outbox,
                                plc=plc_figures(self.modbus))

class MetricsRelay(EndpointSource):
    """The supervisor's side of a fleet (``hookwatch run FLEET_DIR``): an output of a station
    proxy (gateway/supervisor/remote.py) that serves the snapshots its worker sends (METRICS
    frames, one a second) on this process' endpoint, with the counters of the Modbus TCP server
    the supervisor runs for the station (``modbus``) and the worker's health:
    ``hookwatch_station_up`` 0 and every link down while the worker is down or restarting, and
    ``hookwatch_worker_restarts_total``. Counters start again with a restarted worker (a reset
    that ``rate()`` handles)."""

    def __init__(self, station_id: str, host: str = "127.0.0.1", port: int = 9620, *,
                 ts: float = 0.02, modbus=None, limits: DoorLimits | None = None):
        self.station_id = station_id
        self.limits = limits
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

    def on_lost(self, n: int) -> None:
        pass        # the worker's snapshot counts its slots, those the hand-over lost included

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

