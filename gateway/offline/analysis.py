"""Offline analysis: a recorded log + its sidecar + overrides → the method's result."""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from ..core.method.core import Result, SlotArrays, analyze_slots, mark_lost, to_slots
from ..core.method.params import PARAM_NAMES, PRIOR_NAMES, MethodParams, ParamError, build_params, validate_prior
from .logio import Log, LogError, read_log


class AnalysisError(ValueError):
    pass


def parse_overrides(items: Iterable[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for it in items:
        name, sep, value = it.partition("=")
        name = name.strip()
        if not sep or not name:
            raise AnalysisError(f"--set {it!r}: expected NAME=VALUE")
        if name not in PARAM_NAMES:
            raise AnalysisError(f"--set {name}: unknown parameter; valid names: {', '.join(PARAM_NAMES)}")
        out[name] = value
    return out


def params_for(meta: Mapping[str, Any], overrides: Mapping[str, Any], source: str) -> MethodParams:
    """The parameters of a log: its sidecar's ``method:`` section, then the overrides.

    A prior from the sidecar with ``prior_sd`` ≤ 0 (or only half of one) means "no prior"
    (METHOD.md §5b: the prior parts are null); a prior given with ``--set`` must be a real one."""
    values = dict(meta.get("method") or {})
    values.update(overrides)
    try:
        p = build_params(values, source, prior_from_log=True)
        if any(k in overrides for k in PRIOR_NAMES):
            validate_prior(p.prior_mean, p.prior_sd, f"{source}: --set ")
        return p
    except ParamError as e:
        raise AnalysisError(str(e)) from None


def log_slots(log: Log, p: MethodParams) -> SlotArrays:
    """A log on the slot grid, with the sidecar's ``lost_spans`` (slots whose rows the recorder
    could not write during a disk outage) as LOST slots, exactly as the live station fed them to
    the method (``gateway.core.method.rules.LOST``)."""
    s = to_slots(log.t, log.t1, log.t2, p)
    spans = log.meta.get("lost_spans")
    if spans is None:
        return s
    if not isinstance(spans, list):
        raise AnalysisError(f"{log.path}: lost_spans: expected a list of [first, last] slots")
    try:
        return mark_lost(s, spans)
    except ValueError as e:
        raise AnalysisError(f"{log.path}: {e}") from None


def analyze_log(path: str, overrides: Mapping[str, Any] | None = None) -> tuple[Result, MethodParams]:
    """The result of a recorded log and the parameters it was analysed with."""
    try:
        log = read_log(path)
    except LogError as e:
        raise AnalysisError(str(e)) from None
    p = params_for(log.meta, overrides or {}, path)
    return analyze_slots(log_slots(log, p), p), p


def analyze_file(path: str, overrides: Mapping[str, Any] | None = None) -> Result:
    return analyze_log(path, overrides)[0]
