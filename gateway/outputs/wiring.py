"""The outputs of a station: one row per output (:data:`OUTPUTS`), and their settings from the
configuration (``cfg.mqtt``, ``cfg.modbus_tcp``, ``cfg.sparkplug``, ``cfg.metrics``).

The rows say, once per output, what the rest of hookwatch asks of it: the worker of a fleet
(``--served-by-supervisor``: which outputs a supervisor may serve, which of them need every slot
record), the supervisor's reload key (a change of which sections rebuilds a station's shared
outputs on SIGHUP), the commissioning probe (the broker an output connects to, the doors it
listens on). Every field of a row is required: a row that leaves one out fails at import.
"""
from __future__ import annotations

import logging
import os
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..core.ports import StationLinks
from ..plumbing.doors import DoorLimits
from .broker.settings import broker_kwargs
from .mqtt import schema as mqtt_schema
from .mqtt.output import MqttOutput, MqttSettings
from .plc.server import ModbusOutput, ModbusSettings
from .prometheus import MetricsOutput
from .sparkplug.output import SparkplugOutput, settings_from_config

log = logging.getLogger("hookwatch.northbound")


def outbox_path(cfg) -> str | None:
    """The station's MQTT outbox file (None when MQTT is off: no result waits in one)."""
    if getattr(cfg, "mqtt", None) is None or not cfg.mqtt.enabled:
        return None
    return cfg.mqtt.outbox.path or os.path.join(cfg.recorder.dir, cfg.station.id, "outbox.sqlite")


def mqtt_settings(cfg):

    m = cfg.mqtt
    sid = cfg.station.id
    st = cfg.station
    ob = m.outbox
    path = ob.path or os.path.join(cfg.recorder.dir, sid, "outbox.sqlite")
    return MqttSettings(
        station_id=sid,
        base_topic=mqtt_schema.base_topic(m.prefix, getattr(st, "site", ""), getattr(st, "area", ""),
                                     getattr(st, "line", ""), sid),
        protocol=m.protocol, **broker_kwargs(m),
        telemetry_interval_s=float(m.telemetry_interval_s), outbox_path=path,
        telemetry_budget_bytes=int(float(ob.telemetry_budget_mb) * 1024 * 1024),
        reply_prefix=getattr(m, "reply_prefix", None),
        share_lives=bool(getattr(m, "share_lives", True)), records_dir=os.path.join(cfg.recorder.dir, sid),
        command_doors=tuple(getattr(m, "command_doors", ())),
    )


def modbus_settings(cfg):

    mb = cfg.modbus_tcp
    return ModbusSettings(
        station_id=cfg.station.id, host=mb.host, port=int(mb.port), unit_id=int(mb.unit_id),
        word_order=mb.word_order, writes_enabled=bool(mb.writes.enabled),
        allowed_clients=tuple(str(a) for a in (mb.writes.allowed_clients or ())),
        grades=tuple(getattr(cfg, "grades", ("I", "II"))),
        door=DoorLimits.from_config(mb.connections),
    )


def outputs_for(cfg, station: StationLinks, *, modbus: bool = True, sparkplug: bool = True) -> list:
    """The northbound outputs of one station (MQTT, then Modbus TCP unless ``modbus`` is False,
    then its Sparkplug device unless ``sparkplug`` is False: a fleet's supervisor hosts it)."""
    outs: list = []
    mqtt_out = None
    if getattr(cfg, "mqtt", None) is not None and cfg.mqtt.enabled:
        ms = mqtt_settings(cfg)
        try:
            mqtt_out = MqttOutput(ms, station)
        except (OSError, sqlite3.Error) as e:
            # the measurement goes on (it is recorded on disk); the PLC sees mqtt_connected = 0
            log.error("station %s: MQTT disabled: cannot open the outbox mqtt.outbox.path %r: %s",
                      cfg.station.id, ms.outbox_path, e)
        else:
            outs.append(mqtt_out)
    if modbus and getattr(cfg, "modbus_tcp", None) is not None and cfg.modbus_tcp.enabled:

        # the MQTT link reaches the PLC through the station's state (StationState.mqtt_ok)
        outs.append(ModbusOutput(modbus_settings(cfg), station))
    if sparkplug and getattr(cfg, "sparkplug", None) is not None and cfg.sparkplug.enabled:
        outs.append(SparkplugOutput(settings_from_config(cfg), station))
    return outs


def metrics_outputs(cfg, station: StationLinks, outputs: list, *, serve: bool = True) -> list:
    """The metrics output of a station (``metrics.enabled``), reading the MQTT outbox and the
    PLC server counters of the station's other ``outputs``; with ``serve`` False it opens no
    endpoint (a fleet worker: the supervisor serves its snapshots)."""
    m = getattr(cfg, "metrics", None)
    if m is None or not m.enabled:
        return []

    mqtt = next((o for o in outputs if isinstance(o, MqttOutput)), None)
    modbus = next((o for o in outputs if isinstance(o, ModbusOutput)), None)
    return [MetricsOutput(station, m.host, int(m.port), mqtt=mqtt, modbus=modbus, serve=serve,
                          limits=DoorLimits.from_config(m.connections))]


# ------------------------------------------------------------------------------------------------
# the output registry

Door = tuple[str, str, int]     # (configuration key, host, port) an output listens on


@dataclass(frozen=True)
class OutputRow:
    """One output (no defaults: every row says every fact, or fails at import)."""
    name: str                   # the word of ``--served-by-supervisor`` and ``served_by_supervisor``
    section: str                # its configuration section (``enabled`` switches it)
    box: bool                   # a fleet's supervisor serves it for the station (else the worker runs it)
    slot_rows: bool             # needs every slot record: served by a supervisor, the worker streams them
    reload: bool                # served by a supervisor: a change of ``section`` rebuilds it on SIGHUP
    broker: bool                # connects to a broker (the probe connects to each of its servers)
    doors: Callable[[Any], list[Door]]   # the ports it listens on (the probe checks each is free)
    metrics: str                # what the metrics output shows of it


def _no_doors(cfg: Any) -> list[Door]:
    return []


def _modbus_doors(cfg: Any) -> list[Door]:
    return [("modbus_tcp", cfg.modbus_tcp.host, int(cfg.modbus_tcp.port))]


def _console_doors(cfg: Any) -> list[Door]:
    out = []
    for addr in cfg.console.listen:
        host, _, p = str(addr).rpartition(":")
        if p.isdigit():
            out.append(("console.listen", host.strip("[]") or "0.0.0.0", int(p)))
    return out


def _metrics_doors(cfg: Any) -> list[Door]:
    return [("metrics", cfg.metrics.host, int(cfg.metrics.port))]


OUTPUTS: tuple[OutputRow, ...] = (
    OutputRow("mqtt", "mqtt", box=False, slot_rows=False, reload=False, broker=True, doors=_no_doors,
              metrics="the MQTT link, the outbox and what waits in it"),
    OutputRow("modbus", "modbus_tcp", box=True, slot_rows=True, reload=True, broker=False,
              doors=_modbus_doors, metrics="the PLC server's requests, refusals and connections"),
    OutputRow("sparkplug", "sparkplug", box=True, slot_rows=True, reload=True, broker=True,
              doors=_no_doors, metrics="none of its own (its edge node logs its link)"),
    OutputRow("console", "console", box=True, slot_rows=True, reload=False, broker=False,
              doors=_console_doors, metrics="none of its own"),
    OutputRow("metrics", "metrics", box=True, slot_rows=False, reload=True, broker=False,
              doors=_metrics_doors, metrics="itself: the station's figures on its endpoint"),
)
OUTPUT = {r.name: r for r in OUTPUTS}
#: what a fleet's supervisor may serve for its workers' stations
BOX_SERVED: tuple[str, ...] = tuple(r.name for r in OUTPUTS if r.box)
#: served things that need every slot record (the others live on the summaries and snapshots)
ROW_SERVED: frozenset[str] = frozenset(r.name for r in OUTPUTS if r.box and r.slot_rows)


def enabled(cfg: Any, row: OutputRow) -> bool:
    """The output of ``row`` is switched on in ``cfg``."""
    sec = getattr(cfg, row.section, None)
    return sec is not None and bool(sec.enabled)


def reload_key(cfg: Any) -> tuple[Any, ...]:
    """The sections whose change rebuilds a station's outputs in a fleet's supervisor (SIGHUP)."""
    return tuple(getattr(cfg, r.section, None) for r in OUTPUTS if r.box and r.reload)


def listen_doors(cfg: Any) -> list[Door]:
    """(key, host, port) the station's enabled outputs listen on."""
    return [d for r in OUTPUTS if enabled(cfg, r) for d in r.doors(cfg)]


def broker_sections(cfg: Any) -> list[str]:
    """The enabled sections that connect to a broker."""
    return [r.section for r in OUTPUTS if r.broker and enabled(cfg, r)]
