"""The composition root: drivers, stations and outputs built from configuration, in one place.

Nothing else in hookwatch wires parts together: the station knows its ports and outputs only by
their contracts (``gateway/core/ports.py``), the drivers know nothing of the station, the northbound
outputs know the station only as a command sink and a state source. ``hookwatch run`` and
``hookwatch demo`` call :func:`build_station` and run it in :func:`in_process_runtime`; a fleet's
supervisor calls :func:`shared_outputs` per station. The outputs are built from the rows of the
output registry (``gateway/outputs/registry.py``): a new output is a row there (or a plug-in's),
not a change here; a new meter type is added here.
"""
from __future__ import annotations

import os
from collections.abc import Callable

from drivers.meter.driver import ZnsMeter
from drivers.stm32.driver import Stm32Link

from .core.ports import MeterPort, Output, StationLinks, StationView, Stm32Port
from .core.records import EventType
from .outputs.console.app import ConsoleServer
from .outputs.console.settings import ConsoleSettings
from .outputs.registry import BoxBuild, Host, StationBuild, outbox_path, rows, served_by_box, wanted
from .outputs.sparkplug.output import settings_from_config as sparkplug_settings
from .plumbing.doors import Budget, budget
from .station.build import control_params, default_plan, method_values, records_dir_ok, station_limits
from .station.fleet import Fleet, StationRunner
from .station.retention import Policy, Pruned, RetentionOutput
from .station.station import Station

__all__ = ["build_console", "build_meter", "build_stm32", "build_station", "in_process_runtime",
           "records_dir_ok", "served_by_supervisor", "shared_outputs", "shared_sparkplug_nodes",
           "station_facts", "station_outputs"]


def build_meter(cfg) -> MeterPort:
    """The tension meter of the ``meter:`` section (a ZN-S over Modbus RTU)."""
    return ZnsMeter.from_config(cfg.meter)


def build_stm32(cfg) -> Stm32Port:
    """The take-up motor controller of the ``stm32:`` section."""
    return Stm32Link.from_config(cfg.stm32, watchdog_s=cfg.stm32_watchdog_s())


def build_station(cfg, *, outputs: list[Output] | None = None, with_northbound: bool = True,
                  served_by_supervisor: frozenset[str] = frozenset(),
                  console: ConsoleServer | None = None, slot_phase: float = 0.0) -> Station:
    """One station from its configuration: drivers, method, control, limits and outputs.

    ``console``: the process's console (``hookwatch run`` in one process), which gets the
    station's feed; ``slot_phase``: where in the slot this station's deadlines fall (stations of
    one process are spread over it).

    ``served_by_supervisor`` (a worker of ``hookwatch run FLEET_DIR``): the rows a fleet's
    supervisor serves for this station from the IPC stream; here each gets its row's ``feed``
    instead of its ``build`` (``"modbus"``, ``"sparkplug"``: nothing here; ``"metrics"``: the
    metrics output counts here but opens no endpoint, its snapshot goes over IPC)."""
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
    # first of the outputs: a pass still running at the station's stop finishes (and its event
    # leaves) before MQTT and the metrics stop
    st.outputs.insert(0, retention_output(cfg, st))
    station_outputs(cfg, st, st.outputs, Host(console, with_northbound), served_by_supervisor)
    st.slot_phase = slot_phase
    return st


def station_outputs(cfg, station: StationLinks, outputs: list[Output], host: Host,
                    served_by_supervisor: frozenset[str] = frozenset()) -> list[Output]:
    """The outputs of the registry's rows the station of ``cfg`` has in a process offering
    ``host``, added to ``outputs`` (the station's list: the metrics read those before them) in the
    registry's order; a row the supervisor serves gets its ``feed`` instead of its ``build``."""
    b = StationBuild(cfg, station, outputs, host)
    for row in rows():
        make = row.feed if row.name in served_by_supervisor else row.build
        if make is not None and wanted(cfg, row, host):
            outputs.extend(make(b))
    return outputs


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


def served_by_supervisor(cfg, console: ConsoleServer | None, *, with_northbound: bool = True) -> frozenset[str]:
    """What a fleet's supervisor (its ``console``, its ``--no-northbound``) serves for the station
    of ``cfg`` (its worker then streams what those outputs need and serves none of them): the
    registry's rows served by the box that the station has — its Modbus TCP unit, its Sparkplug
    device (every edge node lives in the supervisor, shared by several stations or not), the
    console, its metrics, a plug-in's."""
    return served_by_box(cfg, Host(console, with_northbound))


def station_facts(cfg) -> dict:
    """What a station proxy in the supervisor knows of a station without running it: the slot
    period, the command limits and the default test plan (``RemoteStation``'s keywords)."""
    mv = method_values(cfg)
    return {"ts": float(mv.get("ts", 0.02)), "limits": station_limits(cfg, mv),
            "default_plan": default_plan(cfg)}


def shared_outputs(cfg, station: StationView, console: ConsoleServer | None = None, *,
                   with_northbound: bool = True) -> list[Output]:
    """The outputs a fleet's supervisor runs for one station proxy (``station``: a
    ``gateway.supervisor.remote.RemoteStation``): the registry's rows it serves
    (:func:`served_by_supervisor`), each built by its row's ``serve`` — the same classes as in one
    process: the station's unit on its Modbus TCP port (shared by every station that names it),
    its Sparkplug device on its edge node (shared by every station that names the same broker,
    group and node; the device follows its worker), its metrics (the worker's snapshots on the
    supervisor's endpoint), its console feed, a plug-in's output."""
    process_budget(cfg)
    outs: list[Output] = []
    host = Host(console, with_northbound)
    b = BoxBuild(cfg, station, outs, host)
    for row in rows():
        if row.box and row.serve is not None and wanted(cfg, row, host):
            outs.extend(row.serve(b))
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
