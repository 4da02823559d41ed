"""A fleet folder read station by station: the stations that can run, and the ones refused.

``load_fleet`` (gateway.config) refuses the whole fleet when one file is broken; a supervisor
refuses only that station (its own errors, or a clash with a station that comes earlier in
file-name order) and runs the others. :func:`apply_overrides` applies ``hookwatch run``'s options
(``--sample``, ``--records-dir``, …) to a configuration, in the supervisor and in each worker alike.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from typing import Any

from ..config import Issue, cross_issues, validate_fleet
from ..plumbing.ratelog import safe

__all__ = ["FleetPlan", "Refused", "RunOptions", "apply_overrides", "fingerprint", "plan_fleet"]


@dataclass
class RunOptions:
    """The options of ``hookwatch run`` that change a station's configuration or its outputs."""
    sample: str | None = None
    grade: str | None = None
    t_set: float | None = None
    t_end: float | None = None
    start: bool = False
    records_dir: str | None = None
    no_northbound: bool = False
    log_level: str | None = None
    #: SCHED_FIFO priority of each station's slot-loop thread (None: normal scheduling)
    realtime: int | None = None

    @classmethod
    def from_args(cls, args: Any) -> RunOptions:
        kw: dict[str, Any] = {f.name: getattr(args, f.name, None) or (False if f.type == "bool" else None)
                              for f in dataclasses.fields(cls)}
        return cls(**kw)

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def apply_overrides(cfg: Any, opt: RunOptions) -> Any:
    test = cfg.test
    changes: dict[str, Any] = {}
    if opt.sample:
        changes["sample_id"] = opt.sample
    if opt.grade:
        changes["grade"] = opt.grade
    if opt.t_set is not None:
        changes["t_set_n"] = opt.t_set
    if opt.t_end is not None:
        changes["t_end_s"] = opt.t_end
    if opt.start:
        changes["autostart"] = True
    if changes:
        cfg = dataclasses.replace(cfg, test=dataclasses.replace(test, **changes))
    if opt.records_dir:
        cfg = dataclasses.replace(cfg, recorder=dataclasses.replace(cfg.recorder, dir=opt.records_dir))
    return cfg


def fingerprint(cfg: Any) -> str:
    """Equal for two loads of an unchanged station (file and fleet defaults): what SIGHUP compares."""
    return repr(cfg)


@dataclass
class Refused:
    path: str
    name: str                       # station.id as written, else the file's stem
    issues: list[Issue]

    def message(self) -> str:
        return "; ".join(str(i) for i in self.issues)


@dataclass
class FleetPlan:
    fleet_file: str | None
    accepted: list[tuple[str, Any]] = field(default_factory=list)     # (station file, config)
    refused: list[Refused] = field(default_factory=list)


def plan_fleet(folder: str) -> FleetPlan:
    """Validate a fleet folder; each station with an error (or clashing with an earlier station)
    is refused alone. Raises FileNotFoundError for a missing folder."""
    loaded = validate_fleet(folder)
    ff = os.path.join(folder, "fleet.yaml")
    plan = FleetPlan(ff if os.path.isfile(ff) else None)
    bad: dict[int, list[Issue]] = {}
    for i, ld in enumerate(loaded):
        if ld.errors:
            bad[i] = list(ld.errors)
    for i, issue in cross_issues(loaded):
        if issue.severity == "error" and i not in bad:
            bad.setdefault(i, []).append(issue)
    # a clash is reported on the later station (file-name order): the first one runs
    for i, ld in enumerate(loaded):
        if i in bad:
            name = ld.name or os.path.splitext(os.path.basename(ld.path))[0]
            plan.refused.append(Refused(ld.path, safe(name, 64), bad[i]))
        else:
            plan.accepted.append((ld.path, ld.cfg))
    return plan
