"""Build a running station from its configuration: drivers, control, method, outputs."""
from __future__ import annotations

import logging
import os
from dataclasses import fields
from typing import Any

from ..control import ControlParams, NotchParams
from .station import Station, TestPlan

log = logging.getLogger("hookwatch.build")

#: method values the station takes from its test plan, not from the method section
PLAN_KEYS = ("t_set", "t_end")


def control_params(cfg, ts: float) -> ControlParams:
    c = cfg.control
    notch_src = c.notch
    nkw = {f.name: getattr(notch_src, f.name) for f in fields(NotchParams) if hasattr(notch_src, f.name)}
    kw: dict[str, Any] = {}
    for f in fields(ControlParams):
        if f.name in ("notch", "ts"):
            continue
        if hasattr(c, f.name):
            kw[f.name] = getattr(c, f.name)
    return ControlParams(ts=ts, notch=NotchParams(**nkw), **kw)


def method_values(cfg) -> dict[str, Any]:
    m = cfg.method
    values = dict(m) if isinstance(m, dict) else {k: v for k, v in vars(m).items()}
    return {k: v for k, v in values.items() if k not in PLAN_KEYS and v is not None}


def build_station(cfg, *, outputs: list | None = None, with_northbound: bool = True) -> Station:
    from drivers.stm32 import Stm32Link
    from drivers.zns import ZnsMeter

    mv = method_values(cfg)
    ts = float(mv.get("ts", 0.02))
    meter = ZnsMeter.from_config(cfg.meter)
    stm32 = Stm32Link.from_config(cfg.stm32)
    t = cfg.test
    plan = TestPlan(sample_id=t.sample_id or f"{cfg.station.id}-sample", grade=t.grade,
                    t_set=float(t.t_set_n), t_end=float(t.t_end_s))
    outs = list(outputs or [])
    st = Station(
        station_id=cfg.station.id, method=mv, control=control_params(cfg, ts), meter=meter,
        stm32=stm32, records_dir=cfg.recorder.dir, swap_channels=bool(cfg.meter.swap_channels),
        outputs=outs, flush_interval_s=float(cfg.recorder.flush_interval_s), default_plan=plan,
        autostart=bool(t.autostart), grades=tuple(getattr(cfg, "grades", ("I", "II"))),
        identity={"site": cfg.station.site, "area": cfg.station.area, "line": cfg.station.line},
    )
    if with_northbound:
        st.outputs.extend(northbound_outputs(cfg, st))
    from ..northbound.wiring import metrics_outputs

    st.outputs.extend(metrics_outputs(cfg, st, st.outputs))
    return st


def northbound_outputs(cfg, station: Station) -> list:
    outs = []
    try:
        from ..northbound.wiring import outputs_for
    except ImportError:
        return outs
    outs.extend(outputs_for(cfg, station))
    return outs


def records_dir_ok(path: str) -> str | None:
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        return f"recorder.dir {path!r}: cannot create: {e.strerror}"
    if not os.access(path, os.W_OK):
        return f"recorder.dir {path!r}: not writable"
    return None
