"""The composition root: drivers, stations and outputs built from configuration, in one place.

Nothing else in hookwatch wires parts together: the station knows its ports and outputs only by
their contracts (``gateway/core/ports.py``), the drivers know nothing of the station, the northbound
outputs know the station only as a command sink and a state source. ``hookwatch run`` and
``hookwatch demo`` call :func:`build_station` and run it in :func:`in_process_runtime`; a new
output or meter type is added here.
"""
from __future__ import annotations

import importlib
import os
from collections.abc import Callable

from drivers.meter.driver import ZnsMeter
from drivers.stm32.driver import Stm32Link

from .core.ports import MeterPort, Output, StationLinks, StationView, Stm32Port
from .core.records import EventType
from .outputs.console.app import ConsoleServer
from .outputs.console.settings import ConsoleSettings
from .outputs.mqtt.output import MqttOutput
from .outputs.plc.server import ModbusOutput
from .outputs.prometheus import MetricsRelay
from .outputs.sparkplug.output import SparkplugOutput
from .outputs.sparkplug.output import settings_from_config as sparkplug_settings
from .outputs.wiring import metrics_outputs, modbus_settings, outbox_path, outputs_for
from .plumbing.doors import Budget, DoorLimits, budget
from .station.build import control_params, default_plan, method_values, records_dir_ok, station_limits
from .station.fleet import Fleet, StationRunner
from .station.retention import Policy, Pruned, RetentionOutput
from .station.station import Station

__all__ = ["build_console", "build_meter", "build_stm32", "build_station", "in_process_runtime",
           "northbound_outputs", "records_dir_ok", "served_by_supervisor", "shared_outputs",
           "shared_sparkplug_nodes", "station_facts"]


def build_meter(cfg) -> MeterPort:
    """The tension meter of the ``meter:`` section (a ZN-S over Modbus RTU)."""
    return ZnsMeter.from_config(cfg.meter)


def build_stm32(cfg) -> Stm32Port:
    """The take-up motor controller of the ``stm32:`` section."""
    return Stm32Link.from_config(cfg.stm32, watchdog_s=cfg.stm32_watchdog_s())


def northbound_outputs(cfg, station: StationLinks, *, modbus: bool = True, sparkplug: bool = True) -> list[Output]:
    """MQTT, Modbus TCP and Sparkplug, as the ``mqtt:``, ``modbus_tcp:`` and ``sparkplug:``
    sections enable them (Modbus TCP not when ``modbus`` is False, the Sparkplug device not when
    ``sparkplug`` is False: a fleet's supervisor serves them)."""
    return list(outputs_for(cfg, station, modbus=modbus, sparkplug=sparkplug))


def build_station(cfg, *, outputs: list[Output] | None = None, with_northbound: bool = True,
                  served_by_supervisor: frozenset[str] = frozenset(),
                  console: ConsoleServer | None = None, slot_phase: float = 0.0) -> Station:
    """One station from its configuration: drivers, method, control, limits and outputs.

    ``console``: the process's console (``hookwatch run`` in one process), which gets the
    station's feed; ``slot_phase``: where in the slot this station's deadlines fall (stations of
    one process are spread over it).

    ``served_by_supervisor`` (a worker of ``hookwatch run FLEET_DIR``): ``"modbus"`` — no Modbus
    TCP output here (the supervisor serves the station's unit from the IPC stream); ``"sparkplug"``
    — no Sparkplug device here (the supervisor hosts the edge node); ``"metrics"`` — the metrics
    output counts here but opens no endpoint (its snapshot goes over IPC)."""
    process_budget(cfg)
    mv = method_values(cfg)
    ts = float(mv.get("ts", 0.02))
    st = Station(
        station_id=cfg.station.id, method=mv, control=control_params(cfg, ts),
        meter=build_meter(cfg), stm32=build_stm32(cfg), records_dir=cfg.recorder.dir,
        swap_channels=bool(cfg.meter.swap_channels), outputs=list(outputs or []),
        flush_interval_s=float(cfg.recorder.flush_interval_s), default_plan=default_plan(cfg),
        autostart=bool(cfg.test.autostart), limits=station_limits(cfg, mv),
        identity={"site": cfg.station.site, "area": cfg.station.area, "line": cfg.station.line},
        priors=cfg.forecast.priors, restart_on_replace=bool(cfg.test.restart_on_replace),
    )
    if with_northbound:
        st.outputs.extend(northbound_outputs(cfg, st, modbus="modbus" not in served_by_supervisor,
                                             sparkplug="sparkplug" not in served_by_supervisor))
    st.outputs.extend(plugin_outputs(cfg, st))
    # first of the outputs: a pass still running at the station's stop finishes (and its event
    # leaves) before MQTT and the metrics stop
    st.outputs.insert(0, retention_output(cfg, st))
    # last: the metrics read the other outputs' figures (MQTT link, outbox, PLC server) at scrape time
    st.outputs.extend(metrics_outputs(cfg, st, st.outputs, serve="metrics" not in served_by_supervisor))
    if console is not None and st.id in console.feeds:
        st.outputs.append(console.output_for(st))
        # the console's site view rides on this station's MQTT session (the first that has one)
        mq = next((o for o in st.outputs if isinstance(o, MqttOutput)), None)
        if mq is not None:
            console.attach_site(st.id, mq.s.base_topic, mq.pump.add_site_feed)
    st.slot_phase = slot_phase
    return st


def in_process_runtime(factories: dict[str, Callable[[], Station]], *, rt_priority: int = 0,
                       rt_optional: bool = False,
                       reloader: Callable[[], dict[str, Callable[[], Station]]] | None = None) -> Fleet:
    """The stations of this process, each on its own thread (``hookwatch run STATION.yaml``, a
    fleet with ``--in-process``, ``hookwatch demo``): the ``Runtime`` that ``drive()`` runs.
    ``factories`` builds each station by name (again after a crash); ``rt_priority``: SCHED_FIFO of
    the slot threads (0: normal scheduling), ``rt_optional``: only where permitted, a refusal said
    at info level (the demo), not as a warning (``--realtime`` asked for it); ``reloader``: the
    new factories on SIGHUP."""
    return Fleet([StationRunner(name, f, rt_priority=rt_priority, rt_optional=rt_optional)
                  for name, f in factories.items()], reloader=reloader)


def process_budget(cfg) -> Budget:
    """The process's descriptor budget (gateway/plumbing/doors.py): the soft RLIMIT_NOFILE raised to the
    hard limit, ``process.fd_reserve`` kept from the listening ports (the first call sets it)."""
    p = getattr(cfg, "process", None)
    return budget(int(p.fd_reserve) if p is not None else None)


def retention_output(cfg, st: Station) -> RetentionOutput:
    """The station's record retention (``recorder.retention``): passes off the slot loop, never the
    running test nor a result still in the MQTT outbox; each pruning a ``records_pruned`` event
    (the metrics count it)."""
    rc = cfg.recorder.retention

    def pruned(p: Pruned) -> None:
        st.board.emit(EventType.RECORDS_PRUNED, tests=list(p.tests), bytes=p.bytes, rules=list(p.rules))

    return RetentionOutput(st.id, st.station_dir, Policy.from_config(rc), float(rc.interval_s),
                           lambda: st.test_id, outbox_path(cfg), pruned)


#: extra outputs of a site (a historian, a test fixture): ``module:callable[,module:callable]``;
#: each callable gets (cfg, station) and returns the outputs to add (``gateway.core.ports.Output``)
PLUGINS_ENV = "HOOKWATCH_OUTPUTS"


def plugin_outputs(cfg, station: StationLinks) -> list[Output]:
    """The outputs named in ``$HOOKWATCH_OUTPUTS`` (none when it is unset). A name that does not
    import is an error at start-up, not a silently missing output."""
    out: list[Output] = []
    for spec in filter(None, (x.strip() for x in os.environ.get(PLUGINS_ENV, "").split(","))):
        mod, _, attr = spec.partition(":")
        if not mod or not attr:
            raise ValueError(f"{PLUGINS_ENV}: {spec!r} is not module:callable")
        factory = getattr(importlib.import_module(mod), attr)
        out.extend(factory(cfg, station))
    return out


def build_console(cfgs: list) -> ConsoleServer | None:
    """The operator console of one process (the ``console:`` section of its first station; put it
    in the fleet defaults), serving every station of ``cfgs``; None when it is not enabled."""
    if not cfgs or not cfgs[0].console.enabled:
        return None
    process_budget(cfgs[0])
    return ConsoleServer(ConsoleSettings.from_config(cfgs[0]),
                         {c.station.id: os.path.join(c.recorder.dir, c.station.id) for c in cfgs},
                         mqtt_enabled={c.station.id: bool(c.mqtt.enabled) for c in cfgs},
                         places={c.station.id: (c.station.line, c.station.area) for c in cfgs})


# ------------------------------------------------------------------------------------------------
# a fleet's supervisor (``hookwatch run FLEET_DIR``): the shared outputs, fed over IPC


def served_by_supervisor(cfg, *, console: bool, with_northbound: bool = True) -> frozenset[str]:
    """What a fleet's supervisor serves for the station of ``cfg`` (its worker then streams what
    those outputs need and serves none of them): its Modbus TCP unit, its Sparkplug device (every
    edge node lives in the supervisor, shared by several stations or not), the console, its
    metrics."""
    out = set()
    if with_northbound and cfg.modbus_tcp.enabled:
        out.add("modbus")
    if with_northbound and getattr(cfg, "sparkplug", None) is not None and cfg.sparkplug.enabled:
        out.add("sparkplug")
    if console:
        out.add("console")
    if cfg.metrics.enabled:
        out.add("metrics")
    return frozenset(out)


def station_facts(cfg) -> dict:
    """What a station proxy in the supervisor knows of a station without running it: the slot
    period, the command limits and the default test plan (``RemoteStation``'s keywords)."""
    mv = method_values(cfg)
    return {"ts": float(mv.get("ts", 0.02)), "limits": station_limits(cfg, mv),
            "default_plan": default_plan(cfg)}


def shared_outputs(cfg, station: StationView, console: ConsoleServer | None = None, *,
                   with_northbound: bool = True, sparkplug_device=None) -> list[Output]:
    """The outputs a fleet's supervisor runs for one station proxy (``station``: a
    ``gateway.supervisor.remote.RemoteStation``): the same classes as in one process — the
    station's unit on its Modbus TCP port (shared by every station that names it), its Sparkplug
    device on its edge node (shared by every station that names the same broker, group and node;
    ``sparkplug_device``: the ``SparkplugOutput`` class to build, the supervisor's own whose device
    follows its worker), its console feed, and its metrics (the worker's snapshots on the
    supervisor's endpoint)."""
    process_budget(cfg)
    outs: list[Output] = []
    modbus = None
    if with_northbound and cfg.modbus_tcp.enabled:
        modbus = ModbusOutput(modbus_settings(cfg), station)
        outs.append(modbus)
    if with_northbound and cfg.sparkplug.enabled:
        outs.append((sparkplug_device or SparkplugOutput)(sparkplug_settings(cfg), station))
    if console is not None and station.id in console.feeds:
        outs.append(console.output_for(station))
    m = cfg.metrics
    if m.enabled:
        outs.append(MetricsRelay(station.id, m.host, int(m.port), ts=station.ts, modbus=modbus,
                                 limits=DoorLimits.from_config(m.connections)))
    return outs


def shared_sparkplug_nodes(cfgs: list) -> list[str]:
    """Sparkplug edge nodes that several stations of ``cfgs`` share (same broker, group and edge
    node: one MQTT session for all of them), as ``group/node`` names. In a fleet's supervisor such
    a node is one session with a device per station (``hookwatch run`` names them at start)."""
    seen: dict[tuple, list[str]] = {}
    for c in cfgs:
        if getattr(c, "sparkplug", None) is None or not c.sparkplug.enabled:
            continue
        s = sparkplug_settings(c)
        seen.setdefault((tuple(s.servers), s.group_id, s.edge_node_id), []).append(c.station.id)
    return sorted(f"{g}/{n}" for (_, g, n), ids in seen.items() if len(ids) > 1)
