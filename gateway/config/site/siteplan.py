"""``hookwatch config plan``: what an apply of a candidate tree would do on this box, per station.

The candidate is checked first (:func:`.sitecheck.check_box`: a plan of a broken tree is an
error). Each station's effective configuration (its file merged with fleet.yaml, as the loader
builds it) is compared key by key with the one the box's ``current`` tree gives:

- ``new`` / ``removed`` — the station file appears / goes;
- ``unchanged`` — no key differs: the apply leaves it alone (its worker is not even told);
- ``apply-now`` — keys differ and the station is idle: it restarts with them at the apply;
- ``deferred`` — keys differ and a test runs: it keeps its parameters and restarts with the new
  configuration when the test ends (never sooner, unless ``--interrupt-tests``).

Whether a station is in a test comes from its supervisor: ``STATE/config/supervisor.json``, which
the running supervisor writes from its workers' heartbeats (``in_test``) — the station's own state
as the supervisor knows it, not a guess. Values of secret-looking keys are masked.
"""
from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass, field
from typing import Any

from ..loader import validate_fleet
from .boxreport import supervisor_alive
from .repository import Effective, read_tree
from .sitecheck import check_box
from .versions import StateDir, read_json

__all__ = ["Plan", "StationPlan", "flatten", "make_plan", "plan_text"]

#: keys whose values are never shown (the key name's last part)
SECRET_RE = re.compile(r"pass(word)?|secret|token|private|credential", re.I)
MASK = "***"
#: keys of a configuration that say where it was read from, not what it is
WHERE_KEYS = ("source", "fleet_file")


@dataclass
class StationPlan:
    station: str
    status: str                        # unchanged | apply-now | deferred | new | removed
    keys: list[str] = field(default_factory=list)
    diff: list[tuple[str, Any, Any]] = field(default_factory=list)
    in_test: bool = False

    def as_dict(self) -> dict[str, Any]:
        return {"station": self.station, "status": self.status, "keys": self.keys,
                "in_test": self.in_test, "diff": [{"key": k, "old": o, "new": n} for k, o, n in self.diff]}


@dataclass
class Plan:
    box: str
    version: str | None                # the candidate's commit (None: the working tree)
    current: str | None
    stations: list[StationPlan] = field(default_factory=list)
    files: list[str] = field(default_factory=list)       # files of the tree that differ
    errors: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    sha256: str | None = None
    eff: Effective | None = None

    @property
    def changed(self) -> bool:
        return bool(self.files or any(s.status != "unchanged" for s in self.stations)
                    or (self.version is not None and self.version != self.current))

    def as_dict(self) -> dict[str, Any]:
        return {"box": self.box, "version": self.version, "current": self.current,
                "changed": self.changed, "sha256": self.sha256, "files": self.files,
                "stations": [s.as_dict() for s in self.stations], "errors": self.errors}


def _plain(v: Any) -> Any:
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        return {f.name: _plain(getattr(v, f.name)) for f in dataclasses.fields(v)}
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


def flatten(cfg: Any, root: str) -> dict[str, Any]:
    """A station configuration as ``{dotted key: value}``, its tree's folder written ``<tree>``."""
    out: dict[str, Any] = {}

    def walk(prefix: str, v: Any) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                walk(f"{prefix}.{k}" if prefix else k, x)
            return
        if isinstance(v, str) and root:
            v = v.replace(root, "<tree>")
        elif isinstance(v, list):
            v = [x.replace(root, "<tree>") if isinstance(x, str) else x for x in v]
        out[prefix] = v
    walk("", {k: x for k, x in _plain(cfg).items() if k not in WHERE_KEYS})
    return out


def _masked(key: str, v: Any) -> Any:
    return MASK if v is not None and SECRET_RE.search(key.rsplit(".", 1)[-1]) else v


def _current(state: StateDir) -> dict[str, dict[str, Any]]:
    """The stations of the box's current tree, flattened (as its supervisor reads them)."""
    cur = state.current()
    if not cur or not state.complete(cur):
        return {}
    out = {}
    for ld in validate_fleet(state.current_link):
        if ld.cfg is not None:
            out[ld.cfg.station.id] = flatten(ld.cfg, state.current_link)
    return out


def _in_test(state: StateDir) -> dict[str, bool]:
    if supervisor_alive(state) is None:
        return {}
    st = read_json(state.path("supervisor.json")) or {}
    raw = st.get("stations")
    stations: dict[str, Any] = raw if isinstance(raw, dict) else {}
    return {str(n): bool(s.get("in_test")) for n, s in stations.items() if isinstance(s, dict)}


def make_plan(checkout: str, box: str, state: StateDir, version: str | None) -> Plan:
    """The plan of the candidate at ``checkout`` (a repository's files) for ``box``."""
    chk = check_box(checkout, box)
    plan = Plan(box, version, state.current(), errors=chk.errors, warnings=chk.warnings)
    if chk.errors:
        return plan
    plan.sha256, plan.eff = chk.eff.digest, chk.eff
    cur_files = read_tree(state.current_link) if plan.current else {}
    plan.files = sorted(p for p in set(cur_files) | set(chk.eff.files)
                        if cur_files.get(p) != chk.eff.files.get(p))
    old = _current(state)
    in_test = _in_test(state)
    new = {sid: flatten(cfg, os.path.dirname(os.path.dirname(cfg.source)))
           for sid, (cfg, _) in chk.stations.items()}
    for sid in sorted(set(old) | set(new)):
        t = in_test.get(sid, False)
        if sid not in old:
            plan.stations.append(StationPlan(sid, "new"))
            continue
        if sid not in new:
            plan.stations.append(StationPlan(sid, "removed", in_test=t))
            continue
        a, b = old[sid], new[sid]
        keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
        status = "unchanged" if not keys else ("deferred" if t else "apply-now")
        plan.stations.append(StationPlan(sid, status, keys, [(k, _masked(k, a.get(k)), _masked(k, b.get(k)))
                                                             for k in keys], t))
    return plan


def plan_text(plan: Plan) -> str:
    """The plan as a person reads it (and ``ansible-playbook --check`` shows)."""
    cur = (plan.current or "none")[:12]
    to = (plan.version or "the working tree")[:12] if plan.version else "the working tree"
    lines = [f"box {plan.box}: {cur} → {to}: " + ("changes" if plan.changed else "nothing to change")]
    words = {"unchanged": "unchanged", "apply-now": "applies now (idle; restart)",
             "deferred": "deferred: a test runs, applies when it ends", "new": "new station",
             "removed": "removed"}
    for s in plan.stations:
        extra = f" — keys: {', '.join(s.keys)}" if s.keys else ""
        if s.status == "removed" and s.in_test:
            extra += " (stops when its test ends)"
        lines.append(f"  {s.station}: {words[s.status]}{extra}")
        for k, o, n in s.diff:
            lines.append(f"      {k}: {o!r} → {n!r}")
    if plan.files:
        lines.append("  files: " + ", ".join(plan.files))
    return "\n".join(lines)
