"""A station as the supervisor sees it: the proxy that drives the shared outputs of a fleet.

In ``hookwatch run FLEET_DIR`` every station runs in its own worker process, but the things a
fleet shares stay in the supervisor: the Modbus TCP port with one unit per station, the Sparkplug
edge nodes with a device per station, the operator console, the metrics endpoint. A
:class:`RemoteStation` per station stands in for the
:class:`~gateway.station.station.Station` those outputs were written for. It rebuilds the
station's stream from its worker's IPC frames (:mod:`.ipc`: every
:class:`~gateway.core.records.SlotRecord` from the SLOTS frames' ``rows``, every
:class:`~gateway.core.records.Event`, every :class:`~gateway.core.records.StationState`, the METRICS
snapshots) and calls the SAME output classes the in-process runtime uses, built by the rows of
the output registry (gateway/outputs/registry.py: ``ModbusOutput``, ``SparkplugOutput`` as
``SparkplugDevice``, ``ConsoleOutput``, ``MetricsRelay``, a plug-in's), so register map, Sparkplug
metric set, console and metrics have one definition in both modes.

Threads: frames arrive on the hub's reader thread (one per worker, as a station has one loop)
and the outputs' ``on_record``/``on_event``/``on_state`` run there (they are O(1), never
blocking). The outputs' coroutines — ``start``/``stop`` and :meth:`RemoteStation.submit`, where
their commands go (a PLC write, a console button, a Sparkplug DCMD from its node's thread) — run
on one supervisor loop (:class:`~gateway.plumbing.threadloop.ThreadLoop`
``fleet-outputs``); :meth:`submit` waits for the worker's REPLY in an executor thread
(``StationHub.command`` blocks up to its timeout), so neither a server's loop nor a reader thread
ever waits for a worker.

A worker that is down (crashed, killed, restarting) is shown as down, not with stale values:
its outputs get a state with every link down (PLC status bits ``meter_ok``, ``stm32_ok``,
``mqtt_connected`` 0; the heartbeat register stops), ``on_worker(False)`` where an output has it
(console: the station is offline; metrics: ``hookwatch_station_up`` 0; Sparkplug: a DDEATH of
its device, a DBIRTH when its worker is back), and commands are refused with ``NO_STATION``.
"""
from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
from typing import Any

from ..compose import shared_outputs, station_facts
from ..core.command_rules import CODE, Rejection
from ..core.ports import Output, PlanView, StationLimits
from ..core.records import Command, CommandReply, Event, EventType, SlotRecord, StationState
from ..outputs.console.app import ConsoleServer
from ..outputs.registry import reload_key
from ..plumbing.threadloop import ThreadLoop
from ..station.alarm_store import KIND_OF, MODEL_NAME
from ..station.fanout import Fanout
from .fleetcfg import apply_overrides
from .ipc import FrameType, event_from_dict, slot_from_row, state_from_dict

__all__ = ["COMMAND_TIMEOUT_S", "RemoteFleet", "RemoteStation"]

log = logging.getLogger("hookwatch.supervisor")

#: how long a command waits for its worker's reply (the PLC server waits 5 s for the station)
COMMAND_TIMEOUT_S = 4.5


class RemoteAlarms:
    """What the supervisor knows of a station's alarm store beyond its :class:`StationState`: when
    each alarm's shelving expires (from the station's ``alarm_shelved`` events). The worker's store
    stays the truth: readers show the expiry only while the state says ``shelved``."""

    def __init__(self) -> None:
        self._until: dict[str, float] = {}

    def on_event(self, ev: Event) -> None:
        if ev.type != EventType.ALARM_SHELVED:
            return
        until = ev.data.get("until")
        if until is None:
            return
        name = ev.data.get("alarm")
        for n in ([name] if isinstance(name, str) else list(MODEL_NAME.values())):
            self._until[KIND_OF.get(n, n)] = float(until)

    def shelved_until(self, name: str) -> float | None:
        """The expiry of the last shelving of alarm ``name`` (a model or kind name), s since the epoch."""
        return self._until.get(KIND_OF.get(name, name))


class RemoteStation:
    """The supervisor's stand-in of one station for the outputs it serves (see the module doc):
    a :class:`~gateway.core.ports.StationView` like the station itself (``id``, ``ts``, ``limits``,
    ``default_plan``, ``state``: the latest :class:`StationState`, ``alarms``:
    :class:`RemoteAlarms`, ``outputs``; ``submit(cmd)`` is the command sink). Its outputs are fed
    through the station's own :class:`~gateway.station.fanout.Fanout`."""

    def __init__(self, hub: Any, *, ts: float = 0.02, limits: StationLimits | None = None,
                 default_plan: PlanView | None = None) -> None:
        self.hub = hub
        self.id: str = hub.name
        self.ts = float(ts)
        self.limits = limits if limits is not None else StationLimits()
        self.default_plan = default_plan
        self.state = StationState(station=self.id)
        self.alarms = RemoteAlarms()
        self.fanout = Fanout(self.id, [])
        self.loop: asyncio.AbstractEventLoop | None = None
        self.up = False
        self.last_k: int | None = None
        #: slot records the IPC lost (frames dropped by a stalled supervisor), counted
        self.lost = 0
        #: requests the supervisor's doors refused before they became commands
        self.intake_refusals = 0
        self._failed: set[tuple[str, str]] = set()

    @property
    def outputs(self) -> list[Output]:
        return self.fanout.outputs

    @outputs.setter
    def outputs(self, outs: list[Output]) -> None:
        self.fanout.outputs = outs

    # ------------------------------------------------------------ lifecycle (the outputs' loop)
    async def start(self) -> None:
        self.loop = asyncio.get_running_loop()
        for o in self.outputs:
            try:
                await o.start()
            except Exception:  # one output that cannot start must not keep the others away
                log.exception("%s: shared output %s did not start", self.id, type(o).__name__)
        self.on_worker(False)           # down until its worker says HELLO
        self.hub.sink = self

    async def stop(self) -> None:
        if self.hub.sink is self:
            self.hub.sink = None
        for o in self.outputs:
            try:
                await o.stop()
            except Exception:
                log.exception("%s: shared output %s did not stop cleanly", self.id, type(o).__name__)

    # ------------------------------------------------------------ the command sink
    async def submit(self, cmd: Command) -> CommandReply:
        """A command for the station: to its worker (``StationHub.command``, off this loop)."""
        if not self.up:
            return Rejection(False, f"station {self.id} is not running (its worker is down)",
                             cmd.request_id, CODE["NO_STATION"])
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(
            None, lambda: self.hub.command(cmd.kind.value, dict(cmd.args), source=cmd.source,
                                           request_id=cmd.request_id, timeout=COMMAND_TIMEOUT_S))

    def refused(self, data: dict[str, Any]) -> None:
        """A door of the supervisor refused a request before it became a command: counted here
        (the door logs it once a minute with the count); the worker's station never saw it."""
        self.intake_refusals += 1

    # ------------------------------------------------------------ frames (the hub's reader thread)
    def on_frame(self, ftype: FrameType, body: dict[str, Any]) -> None:
        if ftype == FrameType.SLOTS:
            rows = body.get("rows")
            if not isinstance(rows, list):
                return
            for row in rows:
                try:
                    rec = slot_from_row(row)
                except (TypeError, ValueError) as e:
                    self._bad("slot row", e)
                    continue
                self._record(rec)
        elif ftype == FrameType.EVENT:
            try:
                ev = event_from_dict(body)
            except (KeyError, TypeError, ValueError) as e:
                self._bad("event", e)
                return
            self.alarms.on_event(ev)
            self.fanout.event(ev)
        elif ftype == FrameType.STATE:
            try:
                st = state_from_dict(body)
            except (TypeError, ValueError) as e:
                self._bad("state", e)
                return
            self.state = st
            self.fanout.state(st)
        elif ftype == FrameType.METRICS:
            self.fanout.metrics(body)

    def _record(self, rec: SlotRecord) -> None:
        last = self.last_k
        if last is not None and rec.k > last + 1:
            # frames were dropped between the worker and here: say so to outputs that can mend it
            # (the console reads the test so far from the recorder's log)
            n = rec.k - last - 1
            self.lost += n
            self.fanout.lost(n)
        self.last_k = rec.k
        self.fanout.record(rec)

    def on_worker(self, up: bool, restarts: int = 0) -> None:
        """The worker came up (HELLO) or went down (its link closed)."""
        self.up = bool(up)
        self.last_k = None
        if not up:
            down = dataclasses.replace(self.state, meter_ok=False, stm32_ok=False, mqtt_ok=False)
            self.state = down
            self.fanout.state(down)
        self.fanout.worker(self.up, restarts)

    def _bad(self, what: str, e: Exception) -> None:
        key = ("frame", what)
        if key not in self._failed:
            self._failed.add(key)
            log.error("%s: a %s from the worker could not be read: %s", self.id, what, e)


class RemoteFleet:
    """The station proxies of one supervisor and the loop their outputs' coroutines run on: the
    supervisor's shared outputs (``Supervisor.shared``), attached at its start and after each
    reload; which outputs a proxy gets is the composition root's
    (:func:`gateway.compose.shared_outputs`)."""

    def __init__(self, console: ConsoleServer | None = None, *, with_northbound: bool = True) -> None:
        self.tl = ThreadLoop("fleet-outputs")
        self.console = console
        self.with_northbound = with_northbound
        self.stations: dict[str, RemoteStation] = {}
        #: per station, what its outputs were built from (rebuilt when it changes on SIGHUP)
        self.keys: dict[str, str] = {}

    def attach(self, sup: Any) -> None:
        """A station proxy with its shared outputs per running station of ``sup`` (a
        :class:`~gateway.supervisor.supervisor.Supervisor`; at start, and after a SIGHUP: new
        stations get one, a station whose reload key changed — the sections of the registry's
        rows served here with ``reload`` (Modbus TCP, Sparkplug, metrics, a plug-in's) — gets a
        new one, a removed station's is stopped)."""
        with_nb, console = self.with_northbound, self.console
        cfgs = {c.station.id: c for c in (apply_overrides(c, sup.opts) for _, c in sup.plan.accepted)}
        for name, hub in sup.hubs.items():
            cfg = cfgs.get(name)
            if cfg is None or hub.worker is None or hub.worker.path not in sup.workers:
                if name in self.stations and (hub.worker is None or hub.worker.path not in sup.workers):
                    self.remove(name)
                continue
            key = repr((reload_key(cfg), with_nb))     # the registry's rows (gateway/outputs/registry.py)
            if self.keys.get(name) == key:
                continue
            if console is not None and name not in console.feeds:
                console.add_station(name, os.path.join(cfg.recorder.dir, name), bool(cfg.mqtt.enabled),
                                    line=cfg.station.line, area=cfg.station.area)
            st = RemoteStation(hub, **station_facts(cfg))
            st.outputs = shared_outputs(cfg, st, console, with_northbound=with_nb)
            self.add(st, key)

    def add(self, st: RemoteStation, key: str = "", timeout: float = 15.0) -> None:
        """Start ``st``'s outputs and attach it to its hub (replacing an earlier proxy)."""
        self.tl.start()
        old = self.stations.pop(st.id, None)
        if old is not None:
            self.tl.submit(old.stop()).result(timeout)
        self.stations[st.id] = st
        self.keys[st.id] = key
        self.tl.submit(st.start()).result(timeout)
        w = st.hub.worker
        if w is not None and w.hello and w.running:     # a worker already up (a rebuilt proxy)
            st.on_worker(True, w.restarts)

    def remove(self, name: str, timeout: float = 15.0) -> None:
        st = self.stations.pop(name, None)
        self.keys.pop(name, None)
        if st is not None:
            self.tl.submit(st.stop()).result(timeout)

    def stop(self, timeout: float = 15.0) -> None:
        for name in list(self.stations):
            try:
                self.remove(name, timeout)
            except Exception as e:  # stopping goes on for the others
                log.warning("%s: shared outputs did not stop: %s", name, e)
        self.tl.stop(timeout)
