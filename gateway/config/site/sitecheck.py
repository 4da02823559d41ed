"""``hookwatch config check``: a box's whole candidate tree, or the whole site.

There is one validation: the effective tree is written to a temporary fleet folder and read by
the loader every station file goes through (:func:`gateway.config.validate_fleet`), with the
machine-independent feasibility checks (:func:`gateway.config.checks.feasibility`, as
``hookwatch check --skip-local``), the clashes between the stations of one box
(:func:`gateway.config.cross_issues`: ids, serial ports, Modbus TCP units, MQTT client ids,
outboxes) and the site's one name (:func:`site_issues`: ``station.site`` and the MQTT topic
prefix are site.yaml's). Each message is then located in the repository (``FILE:LINE: message``): a station
file's lines are its own, a line of the merged fleet.yaml is the line of the box.yaml or
defaults/fleet.yaml it came from. ``--site`` adds the rule across boxes: station ids are unique
in the site.
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from typing import Any

from ..checks import feasibility
from ..loader import Issue, Loaded, cross_issues, validate_fleet
from .repository import Effective, boxes, build, write_tree

__all__ = ["BoxCheck", "check_box", "check_site", "located", "site_issues"]


@dataclass
class BoxCheck:
    """What checking one box found: its tree, its errors and warnings as ``FILE:LINE: message``
    lines, and its stations (id → (config, where in the repository))."""
    eff: Effective
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    stations: dict[str, tuple[Any, str]] = field(default_factory=dict)
    #: every station id as written (broken files too) → where in the repository
    ids: dict[str, str] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.errors


def located(issue: Issue, tmp: str, eff: Effective) -> str:
    """An issue of the temporary tree as ``FILE:LINE: key: message`` of the repository."""
    rel = os.path.relpath(issue.file, tmp) if issue.file else ""
    where = eff.origin.get(rel, rel or "?")
    if rel == "fleet.yaml" and issue.line:
        where = eff.fleet_lines.get(issue.line, f"{where}:1")
    else:
        where = f"{where}:{issue.line or 1}"
    text = ": ".join(p for p in (issue.key, issue.message) if p)
    for path, origin in eff.origin.items():       # file names inside the message, as in the repository
        text = text.replace(os.path.join(tmp, path), origin)
    return f"{where}: {text.replace(tmp + os.sep, '')}"


def _validate(eff: Effective, out: BoxCheck) -> None:
    with tempfile.TemporaryDirectory(prefix=f"hookwatch-check-{eff.box}-") as tmp:
        write_tree(eff.files, os.path.join(tmp, "t"))
        root = os.path.join(tmp, "t")
        loaded: list[Loaded] = validate_fleet(root)
        per: list[list[Issue]] = [list(ld.issues) for ld in loaded]
        for i, ld in enumerate(loaded):
            if ld.cfg is not None:
                per[i].extend(feasibility(ld, local=False))
        for i, issue in cross_issues(loaded):
            per[i].append(issue)
        for i, ld in enumerate(loaded):
            per[i].extend(site_issues(ld, eff.site))
        seen: set[str] = set()
        for i, ld in enumerate(loaded):
            for issue in per[i]:
                line = located(issue, root, eff)
                if line in seen:             # a fleet default's problem, once for all stations
                    continue
                seen.add(line)
                (out.errors if issue.severity == "error" else out.warnings).append(line)
            rel = os.path.relpath(ld.path, root)
            p = ld.locate(("station", "id"))
            where = f"{eff.origin.get(rel, rel)}:{p.line if p else 1}"
            if ld.name:
                out.ids.setdefault(ld.name, where)
            if ld.cfg is not None and not any(x.severity == "error" for x in per[i]):
                out.stations[ld.cfg.station.id] = (ld.cfg, where)


def site_issues(ld: Loaded, site: dict[str, Any]) -> list[Issue]:
    """One name for the site: a station's ``station.site`` is the ``site:`` of site.yaml (its
    results, lives and commands are the site's: ``<prefix>/<site>/…``), and a station that
    publishes over MQTT does so under the site's topic prefix (site.yaml ``broker.prefix``, where
    the box's config report goes): the site's stations, lives and boxes under one
    ``<prefix>/<site>/``. The key is located where its value comes from (the station file, the
    box's box.yaml or defaults/fleet.yaml)."""
    cfg, name = ld.cfg, site.get("site")
    if cfg is None or not isinstance(name, str):
        return []
    out = []
    if cfg.station.site != name:
        out.append(ld.issue("error", ("station", "site"),
                            f"{cfg.station.site!r} is not the site {name!r} (site.yaml site:); every "
                            "station of the site names it (its topics <prefix>/<site>/…)"))
    broker = site.get("broker") if isinstance(site.get("broker"), dict) else {}
    prefix = str((broker or {}).get("prefix") or "hookwatch").strip("/")
    if cfg.mqtt.enabled and cfg.mqtt.prefix.strip("/") != prefix:
        out.append(ld.issue("error", ("mqtt", "prefix"),
                            f"{cfg.mqtt.prefix!r}: the station would publish under "
                            f"{cfg.mqtt.prefix}/{name}/…, the site is {prefix}/{name}/… "
                            "(site.yaml broker.prefix)"))
    return out


def check_box(root: str, box: str) -> BoxCheck:
    """Check one box's candidate tree from a repository checkout at ``root``."""
    eff = build(root, box)
    out = BoxCheck(eff, errors=list(eff.problems))
    if not eff.problems:
        _validate(eff, out)
    return out


def check_site(root: str) -> tuple[dict[str, BoxCheck], list[str]]:
    """Every box of the site, and the rules across boxes (station ids unique in the site):
    (checks per box, the errors across boxes)."""
    names = boxes(root)
    across: list[str] = []
    if not names:
        across.append("boxes:1: no boxes in the site repository (boxes/<box>/…)")
    checks = {b: check_box(root, b) for b in names}
    first: dict[str, tuple[str, str]] = {}
    for b in names:
        for sid, where in sorted(checks[b].ids.items()):
            if sid in first:
                ob, owhere = first[sid]
                across.append(f"{where}: station.id: {sid!r} is also a station of box {ob} ({owhere}); "
                              "station ids are unique across the site")
            else:
                first[sid] = (b, where)
    return checks, across
