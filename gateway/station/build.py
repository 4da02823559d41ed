"""A station's parameters from its configuration: control, method values, limits, default plan.

Pure translation of the configuration; the drivers and outputs are built by the composition root
(``gateway/compose.py``)."""
from __future__ import annotations

import logging
import os
from dataclasses import fields
from typing import Any

from ..core.control import ControlParams, NotchParams
from ..core.ports import StationLimits
from .session import TestPlan

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


def station_limits(cfg, values: dict[str, Any]) -> StationLimits:
    """What commands to this station are checked against: built once, from its configuration."""
    return StationLimits.from_values(values, grades=tuple(cfg.grades),
                                     t_end_default_s=float(cfg.test.t_end_s))


def default_plan(cfg) -> TestPlan:
    """The test a start without arguments runs (the ``test:`` section)."""
    t = cfg.test
    return TestPlan(sample_id=t.sample_id or f"{cfg.station.id}-sample", grade=t.grade,
                    t_set=float(t.t_set_n), t_end=float(t.t_end_s))


def records_dir_ok(path: str) -> str | None:
    try:
        os.makedirs(path, exist_ok=True)
    except OSError as e:
        return f"recorder.dir {path!r}: cannot create: {e.strerror}"
    if not os.access(path, os.W_OK):
        return f"recorder.dir {path!r}: not writable"
    return None
