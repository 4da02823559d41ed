"""The output registry: one row per output (:class:`OutputRow`), everything the rest of hookwatch
asks of an output, said once.

A row says its configuration section, how it is built (for a station in the station's own
process; in a fleet, what the worker keeps and what the supervisor serves for the station's
proxy), whether it needs every slot record, the doors it listens on, whether a change of its
section rebuilds it on SIGHUP, what the commissioning probe checks of it and what the metrics
show of it. The composition root (``gateway/compose.py``) builds every output from the rows —
in one process, in a fleet's worker and in its supervisor — and the supervisor (the worker's
``--served-by-supervisor``, the rows it streams, the reload key), the probe and the loader's
clash checks read them; nothing else names an output. Every field of a row is required: a row
that leaves one out fails at import.

Plug-in outputs (a historian, a test fixture) are rows too: a module named in
``$HOOKWATCH_OUTPUTS`` calls :func:`register` with its row, whose ``schema`` is its own section
(``gateway/config/plugins.py``: the loader accepts and checks it, the output reads it with
:func:`~gateway.config.plugins.plugin_config`). docs/architecture.md, "Adding an output".
"""
from __future__ import annotations

import logging
import os
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from ..config import plugins as P
from ..config.sections import BrokerConfig, StationConfig
from ..core.ports import Output, StationLinks, StationView
from ..plumbing.doors import DoorLimits
from .broker.settings import broker_kwargs
from .console.app import ConsoleServer
from .mqtt import schema as mqtt_schema
from .mqtt.output import MqttOutput, MqttSettings
from .plc.server import ModbusOutput, ModbusSettings
from .prometheus import MetricsOutput, MetricsRelay
from .sparkplug.device import SparkplugDevice
from .sparkplug.output import SparkplugOutput, settings_from_config

log = logging.getLogger("hookwatch.northbound")

Door = P.Door       # (configuration key, host, port) an output listens on


# ------------------------------------------------------------------------------------------------
# what a row's factories get


@dataclass(frozen=True)
class Host:
    """What the process that builds a station's outputs offers them: its operator console (one per
    process: ``hookwatch run``'s, a fleet supervisor's; a fleet's worker has none), and whether the
    northbound outputs run at all (``--no-northbound``)."""
    console: ConsoleServer | None
    northbound: bool


@dataclass(frozen=True)
class StationBuild:
    """A station's outputs being built in its own process (``hookwatch run`` in one process, a
    fleet's worker): its configuration, the station, its outputs so far (the metrics read the
    MQTT and PLC outputs'), the process."""
    cfg: StationConfig
    station: StationLinks
    outputs: list[Output]
    host: Host


@dataclass(frozen=True)
class BoxBuild:
    """A station's outputs being built in a fleet's supervisor, for the station's proxy
    (``gateway.supervisor.remote.RemoteStation``, fed by the worker's IPC stream)."""
    cfg: StationConfig
    station: StationView
    outputs: list[Output]
    host: Host


class Switch(Protocol):
    """An output's configuration section, as far as the registry reads it: its switch."""

    @property
    def enabled(self) -> bool: ...


Build = Callable[[StationBuild], list[Output]]
Serve = Callable[[BoxBuild], list[Output]]


@dataclass(frozen=True)
class OutputRow:
    """One output (no defaults: every row says every fact, or fails at import)."""
    name: str                   # the word of ``--served-by-supervisor`` and ``served_by_supervisor``
    section: str                # its configuration section
    schema: type | None         # a plug-in's own section (a dataclass of config keys); None: a built-in one
    config: Callable[[StationConfig], Switch]   # its section in a station's configuration
    wanted: Callable[[StationConfig, Host], bool]   # the station has it in this process (its switch)
    northbound: bool            # ``--no-northbound`` leaves it out
    box: bool                   # a fleet's supervisor serves it for the station (else the worker runs it)
    slot_rows: bool             # served by a supervisor, it needs every slot record: the worker streams them
    reload: bool                # served by a supervisor: a change of its section rebuilds it on SIGHUP
    build: Build | None         # built for a station in its own process (in a fleet's worker: when not served)
    feed: Build | None          # in a fleet's worker when the supervisor serves it: what feeds the served one
    serve: Serve | None         # built in a fleet's supervisor for the station's proxy (``box``)
    broker: Callable[[StationConfig], BrokerConfig | None]   # the broker it connects to (the probe connects)
    doors: Callable[[StationConfig], list[Door]]   # the ports it listens on, when on (the probe checks each is free)
    metrics: str                # what the metrics output shows of it

    def __post_init__(self) -> None:
        if self.box and self.serve is None:
            raise TypeError(f"output {self.name!r}: served by the box (box=True) but no `serve` factory")
        if not self.box and self.build is None:
            raise TypeError(f"output {self.name!r}: runs in the station's process (box=False) but no "
                            "`build` factory")


# ------------------------------------------------------------------------------------------------
# the settings of the built-in outputs from configuration


def outbox_path(cfg: StationConfig) -> str | None:
    """The station's MQTT outbox file (None when MQTT is off: no result waits in one)."""
    if not cfg.mqtt.enabled:
        return None
    return cfg.mqtt.outbox.path or os.path.join(cfg.recorder.dir, cfg.station.id, "outbox.sqlite")


def mqtt_settings(cfg: StationConfig) -> MqttSettings:
    m = cfg.mqtt
    st = cfg.station
    path = m.outbox.path or os.path.join(cfg.recorder.dir, st.id, "outbox.sqlite")
    return MqttSettings(
        station_id=st.id,
        base_topic=mqtt_schema.base_topic(m.prefix, st.site, st.area, st.line, st.id),
        protocol=m.protocol, **broker_kwargs(m),
        telemetry_interval_s=float(m.telemetry_interval_s), outbox_path=path,
        telemetry_budget_bytes=int(float(m.outbox.telemetry_budget_mb) * 1024 * 1024),
        reply_prefix=m.reply_prefix, share_lives=bool(m.share_lives),
        records_dir=os.path.join(cfg.recorder.dir, st.id), command_doors=tuple(m.command_doors),
    )


def modbus_settings(cfg: StationConfig) -> ModbusSettings:
    mb = cfg.modbus_tcp
    return ModbusSettings(
        station_id=cfg.station.id, host=mb.host, port=int(mb.port), unit_id=int(mb.unit_id),
        word_order=mb.word_order, writes_enabled=bool(mb.writes.enabled),
        allowed_clients=tuple(str(a) for a in (mb.writes.allowed_clients or ())),
        grades=tuple(cfg.grades), door=DoorLimits.from_config(mb.connections),
    )


# ------------------------------------------------------------------------------------------------
# the factories of the built-in outputs


def _mqtt(b: StationBuild) -> list[Output]:
    ms = mqtt_settings(b.cfg)
    try:
        out = MqttOutput(ms, b.station)
    except (OSError, sqlite3.Error) as e:
        # the measurement goes on (it is recorded on disk); the PLC sees mqtt_connected = 0
        log.error("station %s: MQTT disabled: cannot open the outbox mqtt.outbox.path %r: %s",
                  b.cfg.station.id, ms.outbox_path, e)
        return []
    return [out]


def _modbus(b: StationBuild) -> list[Output]:
    # the MQTT link reaches the PLC through the station's state (StationState.mqtt_ok)
    return [ModbusOutput(modbus_settings(b.cfg), b.station)]


def _modbus_box(b: BoxBuild) -> list[Output]:
    return [ModbusOutput(modbus_settings(b.cfg), b.station)]


def _sparkplug(b: StationBuild) -> list[Output]:
    return [SparkplugOutput(settings_from_config(b.cfg), b.station)]


def _sparkplug_box(b: BoxBuild) -> list[Output]:
    # the supervisor's device follows its worker (up at HELLO, DDEATH when it goes)
    return [SparkplugDevice(settings_from_config(b.cfg), b.station)]


def _console(b: StationBuild) -> list[Output]:
    console = b.host.console
    if console is None or b.station.id not in console.feeds:
        return []
    # the console's site view rides on this station's MQTT session (the first that has one)
    mq = next((o for o in b.outputs if isinstance(o, MqttOutput)), None)
    if mq is not None:
        console.attach_site(b.station.id, mq.s.base_topic, mq.pump.add_site_feed)
    return [console.output_for(b.station)]


def _console_box(b: BoxBuild) -> list[Output]:
    console = b.host.console
    return [console.output_for(b.station)] if console is not None and b.station.id in console.feeds else []


def _metrics(b: StationBuild, serve: bool = True) -> list[Output]:
    m = b.cfg.metrics
    mqtt = next((o for o in b.outputs if isinstance(o, MqttOutput)), None)
    modbus = next((o for o in b.outputs if isinstance(o, ModbusOutput)), None)
    return [MetricsOutput(b.station, m.host, int(m.port), mqtt=mqtt, modbus=modbus, serve=serve,
                          limits=DoorLimits.from_config(m.connections))]


def _metrics_feed(b: StationBuild) -> list[Output]:
    # counts in the worker but opens no endpoint: its snapshots go to the supervisor over IPC
    return _metrics(b, serve=False)


def _metrics_box(b: BoxBuild) -> list[Output]:
    m = b.cfg.metrics
    modbus = next((o for o in b.outputs if isinstance(o, ModbusOutput)), None)
    return [MetricsRelay(b.station.id, m.host, int(m.port), ts=b.station.ts, modbus=modbus,
                         limits=DoorLimits.from_config(m.connections))]


def no_doors(cfg: StationConfig) -> list[Door]:
    """A row's ``doors`` when its output listens on none."""
    return []


def no_broker(cfg: StationConfig) -> BrokerConfig | None:
    """A row's ``broker`` when its output connects to none."""
    return None


def _modbus_doors(cfg: StationConfig) -> list[Door]:
    mb = cfg.modbus_tcp
    return [("modbus_tcp", mb.host, int(mb.port))] if mb.enabled else []


def _console_doors(cfg: StationConfig) -> list[Door]:
    out: list[Door] = []
    if not cfg.console.enabled:
        return out
    for addr in cfg.console.listen:
        host, _, p = str(addr).rpartition(":")
        if p.isdigit():
            out.append(("console.listen", host.strip("[]") or "0.0.0.0", int(p)))
    return out


def _metrics_doors(cfg: StationConfig) -> list[Door]:
    m = cfg.metrics
    return [("metrics", m.host, int(m.port))] if m.enabled else []


BUILTIN: tuple[OutputRow, ...] = (
    OutputRow("mqtt", "mqtt", schema=None, config=lambda c: c.mqtt, wanted=lambda c, h: c.mqtt.enabled,
              northbound=True, box=False, slot_rows=False, reload=False, build=_mqtt, feed=None, serve=None,
              broker=lambda c: c.mqtt if c.mqtt.enabled else None, doors=no_doors,
              metrics="the MQTT link, the outbox and what waits in it"),
    OutputRow("modbus", "modbus_tcp", schema=None, config=lambda c: c.modbus_tcp,
              wanted=lambda c, h: c.modbus_tcp.enabled, northbound=True, box=True, slot_rows=True,
              reload=True, build=_modbus, feed=None, serve=_modbus_box, broker=no_broker,
              doors=_modbus_doors, metrics="the PLC server's requests, refusals and connections"),
    OutputRow("sparkplug", "sparkplug", schema=None, config=lambda c: c.sparkplug,
              wanted=lambda c, h: c.sparkplug.enabled, northbound=True, box=True, slot_rows=True,
              reload=True, build=_sparkplug, feed=None, serve=_sparkplug_box,
              broker=lambda c: c.sparkplug if c.sparkplug.enabled else None, doors=no_doors,
              metrics="none of its own (its edge node logs its link)"),
    # the metrics read the outputs built before them (MQTT link, outbox, PLC server) at scrape time
    OutputRow("metrics", "metrics", schema=None, config=lambda c: c.metrics,
              wanted=lambda c, h: c.metrics.enabled, northbound=False, box=True, slot_rows=False,
              reload=True, build=_metrics, feed=_metrics_feed, serve=_metrics_box, broker=no_broker,
              doors=_metrics_doors, metrics="itself: the station's figures on its endpoint"),
    # one console per process (the first station's `console:`), fed by every station of it
    OutputRow("console", "console", schema=None, config=lambda c: c.console,
              wanted=lambda c, h: h.console is not None, northbound=False, box=True, slot_rows=True,
              reload=False, build=_console, feed=None, serve=_console_box, broker=no_broker,
              doors=_console_doors, metrics="none of its own"),
)
#: the built-in rows built before the plug-in outputs (the others read them, or come last)
_HEAD = 3

_PLUGINS: list[OutputRow] = []


# ------------------------------------------------------------------------------------------------
# the registry


def register(row: OutputRow) -> None:
    """Add a plug-in output (its module, named in ``$HOOKWATCH_OUTPUTS``, calls this at import):
    its section (``row.schema``) becomes a section of every station file, its doors join the
    clash checks between stations; it is built like the built-in outputs, in one process and in
    a fleet. A name or section already taken is refused (ValueError)."""
    if row.schema is None:
        raise ValueError(f"output {row.name!r}: a plug-in output's row names its section's schema")
    if any(r.name == row.name or r.section == row.section for r in (*BUILTIN, *_PLUGINS)):
        raise ValueError(f"output {row.name!r} (section {row.section!r}) is registered already")
    P.add_section(row.section, row.schema, f"the plug-in output {row.name}", row.doors, shared=row.box)
    _PLUGINS.append(row)


def plugin_row(name: str, schema: type[Switch], *, northbound: bool, box: bool, slot_rows: bool, reload: bool,
               build: Build | None, feed: Build | None, serve: Serve | None,
               broker: Callable[[StationConfig], BrokerConfig | None],
               doors: Callable[[StationConfig], list[Door]], metrics: str) -> OutputRow:
    """The row of a plug-in output whose section ``name:`` is ``schema`` (switched by its
    ``enabled`` key): every other fact as :class:`OutputRow` says it (no defaults)."""
    def config(cfg: StationConfig) -> Switch:
        return P.plugin_config(cfg, name, schema)

    return OutputRow(name, name, schema=schema, config=config, wanted=lambda c, h: config(c).enabled,
                     northbound=northbound, box=box, slot_rows=slot_rows, reload=reload, build=build,
                     feed=feed, serve=serve, broker=broker, doors=doors, metrics=metrics)


def rows() -> tuple[OutputRow, ...]:
    """Every output, in the order a station's outputs are built (MQTT, Modbus TCP, Sparkplug, the
    plug-in outputs, then the metrics, which read the others, and the console)."""
    P.load_plugins()
    return (*BUILTIN[:_HEAD], *_PLUGINS, *BUILTIN[_HEAD:])


def box_served() -> tuple[str, ...]:
    """What a fleet's supervisor may serve for its workers' stations."""
    return tuple(r.name for r in rows() if r.box)


def row_served() -> frozenset[str]:
    """Served things that need every slot record (the others live on the summaries and snapshots)."""
    return frozenset(r.name for r in rows() if r.box and r.slot_rows)


def wanted(cfg: StationConfig, row: OutputRow, host: Host) -> bool:
    """The station of ``cfg`` has the output of ``row`` in a process offering ``host``."""
    return (host.northbound or not row.northbound) and row.wanted(cfg, host)


def served_by_box(cfg: StationConfig, host: Host) -> frozenset[str]:
    """What a fleet's supervisor (offering ``host``) serves for the station of ``cfg``."""
    return frozenset(r.name for r in rows() if r.box and wanted(cfg, r, host))


def reload_key(cfg: StationConfig) -> tuple[Switch, ...]:
    """The sections whose change rebuilds a station's outputs in a fleet's supervisor (SIGHUP)."""
    return tuple(r.config(cfg) for r in rows() if r.box and r.reload)


def listen_doors(cfg: StationConfig) -> list[Door]:
    """(key, host, port) the station's enabled outputs listen on."""
    return [d for r in rows() for d in r.doors(cfg)]


def brokers(cfg: StationConfig) -> list[tuple[str, BrokerConfig]]:
    """(section, its broker settings) of the station's enabled outputs that connect to a broker."""
    out: list[tuple[str, BrokerConfig]] = []
    for r in rows():
        b = r.broker(cfg)
        if b is not None:
            out.append((r.section, b))
    return out
