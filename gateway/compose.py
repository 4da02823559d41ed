"""The composition root: drivers, stations and outputs built from configuration, in one place.

Nothing else in hookwatch wires parts together: the station knows its ports and outputs only by
their contracts (``gateway/ports.py``), the drivers know nothing of the station, the northbound
outputs know the station only as a command sink and a state source. ``hookwatch run`` and
``hookwatch demo`` call :func:`build_station`; a new output or meter type is added here.
"""
from __future__ import annotations

import importlib
import os

from drivers.stm32 import Stm32Link
from drivers.zns import ZnsMeter

from .console.server import ConsoleServer, ConsoleSettings
from .northbound.wiring import metrics_outputs, outputs_for
from .ports import MeterPort, Output, Stm32Port
from .station.build import control_params, default_plan, method_values, records_dir_ok, station_limits
from .station.station import Station

__all__ = ["build_console", "build_meter", "build_stm32", "build_station", "northbound_outputs", "records_dir_ok"]


def build_meter(cfg) -> MeterPort:
    """The tension meter of the ``meter:`` section (a ZN-S over Modbus RTU)."""
    return ZnsMeter.from_config(cfg.meter)


def build_stm32(cfg) -> Stm32Port:
    """The take-up motor controller of the ``stm32:`` section."""
    return Stm32Link.from_config(cfg.stm32)


def northbound_outputs(cfg, station: Station) -> list[Output]:
    """MQTT and Modbus TCP, as the ``mqtt:`` and ``modbus_tcp:`` sections enable them."""
    return list(outputs_for(cfg, station))


def build_station(cfg, *, outputs: list[Output] | None = None, with_northbound: bool = True) -> Station:
    """One station from its configuration: drivers, method, control, limits and outputs."""
    mv = method_values(cfg)
    ts = float(mv.get("ts", 0.02))
    st = Station(
        station_id=cfg.station.id, method=mv, control=control_params(cfg, ts),
        meter=build_meter(cfg), stm32=build_stm32(cfg), records_dir=cfg.recorder.dir,
        swap_channels=bool(cfg.meter.swap_channels), outputs=list(outputs or []),
        flush_interval_s=float(cfg.recorder.flush_interval_s), default_plan=default_plan(cfg),
        autostart=bool(cfg.test.autostart), limits=station_limits(cfg, mv),
        identity={"site": cfg.station.site, "area": cfg.station.area, "line": cfg.station.line},
    )
    if with_northbound:
        st.outputs.extend(northbound_outputs(cfg, st))
    st.outputs.extend(plugin_outputs(cfg, st))
    # last: the metrics read the other outputs' figures (MQTT link, outbox, PLC server) at scrape time
    st.outputs.extend(metrics_outputs(cfg, st, st.outputs))
    return st


#: extra outputs of a site (a historian, a test fixture): ``module:callable[,module:callable]``;
#: each callable gets (cfg, station) and returns the outputs to add (``gateway.ports.Output``)
PLUGINS_ENV = "HOOKWATCH_OUTPUTS"


def plugin_outputs(cfg, station: Station) -> list[Output]:
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
    return ConsoleServer(ConsoleSettings.from_config(cfgs[0]),
                         {c.station.id: os.path.join(c.recorder.dir, c.station.id) for c in cfgs},
                         mqtt_enabled={c.station.id: bool(c.mqtt.enabled) for c in cfgs})
