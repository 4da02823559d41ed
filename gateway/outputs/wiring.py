"""Build a station's northbound outputs from its configuration (``cfg.mqtt``, ``cfg.modbus_tcp``)."""
from __future__ import annotations

import logging
import os
import sqlite3

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
