"""The method's parameters: one definition of every name, default, unit and allowed range.

These names (METHOD.md §10) are the keys of a station's ``method:`` section, of a log's metadata
sidecar and of ``hookwatch analyze --set``. Docs and CLI help are generated from ``PARAMS``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any, Mapping

from ..validation import MISSING, Problem, ValidationError, did_you_mean


@dataclass(frozen=True)
class ParamSpec:
    name: str
    default: float | None
    unit: str
    doc: str
    required: bool = False
    optional: bool = False  # may be None (e.g. t_end)


PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("ts", 0.02, "s", "sampling period"),
    ParamSpec("theta_deg", 105.0, "deg", "wrap angle θ of the yarn around the hook"),
    ParamSpec("t_set", None, "N", "regulated mean tension T_set", required=True),
    ParamSpec("full_scale", 5.0, "N", "sensor full scale"),
    ParamSpec("sat_ratio", 0.98, "1", "T_sat = sat_ratio · full_scale"),
    ParamSpec("t_min_ratio", 0.05, "1", "T_min = t_min_ratio · t_set"),
    ParamSpec("jump_ratio", 0.5, "1", "J_max = jump_ratio · t_set"),
    ParamSpec("r_min", 1.01, "1", "lower bound of R = T2/T1"),
    ParamSpec("r_max", 4.2, "1", "upper bound of R = T2/T1"),
    ParamSpec("stop_after", 1.0, "s", "protection stop after this long unsafe"),
    ParamSpec("w_ss", 60.0, "s", "baseline window length"),
    ParamSpec("valid_ratio_min", 0.9, "1", "N_eff / N_ss needed in a steady window"),
    ParamSpec("sigma_max", 0.01, "1", "robust σ bound in a steady window"),
    ParamSpec("g_max", 0.02, "1", "range bound (max − min of μ) in a steady window"),
    ParamSpec("w_hold", 3600.0, "s", "steady duration needed for the baseline"),
    ParamSpec("delta", 0.25, "1", "relative threshold increment δ"),
    ParamSpec("tau", 60.0, "s", "persistence time τ"),
    ParamSpec("tau_g", 1.0, "s", "tolerated interruption τ_g"),
    ParamSpec("t_end", None, "s", "planned test duration (none: open-ended)", optional=True),
)
PARAM_NAMES: tuple[str, ...] = tuple(p.name for p in PARAMS)
SPEC = {p.name: p for p in PARAMS}

RESULT_KEYS: tuple[str, ...] = (
    "status", "mu_ss", "mu_th", "k_b", "stable_first", "stable_last", "k_life", "t_life",
    "n_slots", "n_valid", "reasons", "interrupted", "stop_slot", "stop_reasons",
)


class ParamError(ValidationError):
    """A parameter name or value that the method cannot use. The message says what is allowed;
    ``problem`` holds the same as data: the parameter (``problem.path == (name,)``; a rule
    between two parameters names the other in ``problem.related``), the value and what is allowed."""


def _err(prefix: str, name: str, message: str, value: Any = MISSING, allowed: str | None = None,
         related: tuple[str, ...] = (), text: str | None = None,
         suggestion: str | None = None) -> ParamError:
    """A ParamError on parameter ``name``: ``{prefix}{name}: {message}`` unless ``text`` is given."""
    return ParamError(Problem((name,), message, value=value, allowed=allowed, suggestion=suggestion,
                              related=tuple((r,) for r in related)),
                      text=text if text is not None else f"{prefix}{name}: {message}")


@dataclass(frozen=True)
class MethodParams:
    t_set: float
    ts: float = 0.02
    theta_deg: float = 105.0
    full_scale: float = 5.0
    sat_ratio: float = 0.98
    t_min_ratio: float = 0.05
    jump_ratio: float = 0.5
    r_min: float = 1.01
    r_max: float = 4.2
    stop_after: float = 1.0
    w_ss: float = 60.0
    valid_ratio_min: float = 0.9
    sigma_max: float = 0.01
    g_max: float = 0.02
    w_hold: float = 3600.0
    delta: float = 0.25
    tau: float = 60.0
    tau_g: float = 1.0
    t_end: float | None = None

    # ---- derived quantities (one place) ----
    @property
    def theta(self) -> float:
        return math.radians(self.theta_deg)

    @property
    def t_sat(self) -> float:
        return self.sat_ratio * self.full_scale

    @property
    def t_min(self) -> float:
        return self.t_min_ratio * self.t_set

    @property
    def j_max(self) -> float:
        return self.jump_ratio * self.t_set

    @property
    def n_ss(self) -> int:
        return int(round(self.w_ss / self.ts))

    @property
    def n_eff_min(self) -> float:
        return self.valid_ratio_min * self.n_ss

    @property
    def m_windows(self) -> int:
        # ceil(W_hold / W_ss), robust to float noise (3600/60 must be exactly 60)
        q = self.w_hold / self.w_ss
        return max(1, int(math.ceil(q - 1e-9)))

    @property
    def n_tau(self) -> int:
        return int(round(self.tau / self.ts))

    @property
    def n_g(self) -> int:
        return int(round(self.tau_g / self.ts))

    @property
    def n_stop(self) -> int:
        """Number of consecutive unsafe slots that is still tolerated (50 at 50 Hz);
        the next one (the 51st) triggers the protection stop."""
        return int(round(self.stop_after / self.ts))

    @property
    def end_slot(self) -> int | None:
        """Number of slots in a planned test (slots 0 .. end_slot-1), or None."""
        if self.t_end is None:
            return None
        return int(round(self.t_end / self.ts))

    def with_delta(self, delta: float) -> "MethodParams":
        return replace(self, delta=delta)

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def _num(name: str, value: Any, source: str) -> float | None:
    spec = SPEC[name]
    what = f"a number ({spec.doc}, {spec.unit})"
    if value is None:
        if spec.optional:
            return None
        raise _err(source, name, f"a number is required ({spec.doc}, {spec.unit})", value, what)
    if isinstance(value, bool):
        raise _err(source, name, f"{value!r} is not a number ({spec.doc}, {spec.unit})", value, what)
    if isinstance(value, str):
        v = value.strip().lower()
        if spec.optional and v in ("", "none", "null"):
            return None
        try:
            value = float(v)
        except ValueError:
            raise _err(source, name, f"{value!r} is not a number ({spec.doc}, {spec.unit})",
                       value, what) from None
    try:
        f = float(value)
    except (TypeError, ValueError, OverflowError):
        raise _err(source, name, f"{value!r} is not a number ({spec.doc}, {spec.unit})",
                   value, what) from None
    if not math.isfinite(f):
        raise _err(source, name, f"{value!r} is not a finite number", value, "a finite number")
    return f


def build_params(values: Mapping[str, Any], source: str = "") -> MethodParams:
    """Make MethodParams from a mapping of §10 names. Unknown names and impossible values raise
    ParamError with a message that names the key, the value and what is allowed."""
    prefix = f"{source}: " if source else ""
    unknown = [k for k in values if k not in SPEC]
    if unknown:
        k = unknown[0]
        raise _err(prefix, k, "unknown parameter", allowed=", ".join(PARAM_NAMES),
                   suggestion=did_you_mean(k, PARAM_NAMES),
                   text=f"{prefix}unknown parameter {k!r}; valid names: {', '.join(PARAM_NAMES)}")
    kw: dict[str, Any] = {}
    for k, v in values.items():
        kw[k] = _num(k, v, prefix)
    if kw.get("t_set") is None:
        raise _err(prefix, "t_set", "missing; the regulated mean tension T_set (N) is required",
                   allowed=f"a number ({SPEC['t_set'].doc}, N)")
    p = MethodParams(**kw)
    validate(p, prefix)
    return p


def validate(p: MethodParams, prefix: str = "") -> None:
    def bad(name: str, rule: str) -> None:
        v = getattr(p, name)
        raise _err(prefix, name, f"{v!r} is impossible; allowed: {rule}", v, rule)

    for name in ("ts", "t_set", "full_scale", "w_ss", "w_hold", "tau", "delta", "sigma_max", "g_max"):
        if not getattr(p, name) > 0:
            bad(name, "> 0")
    if not 0 < p.theta_deg < 360 * 10:
        bad("theta_deg", "0 < theta_deg < 3600")
    if not 0 < p.sat_ratio <= 1:
        bad("sat_ratio", "0 < sat_ratio ≤ 1")
    if not 0 <= p.t_min_ratio < 1:
        bad("t_min_ratio", "0 ≤ t_min_ratio < 1")
    if not p.jump_ratio > 0:
        bad("jump_ratio", "> 0")
    if not p.r_min > 0:
        bad("r_min", "> 0")
    if not p.r_min < p.r_max:
        msg = f"r_min {p.r_min!r} must be smaller than r_max {p.r_max!r}"
        raise _err(prefix, "r_max", msg, p.r_max, f"> r_min ({p.r_min!r})", related=("r_min",),
                   text=prefix + msg)
    if not p.stop_after >= 0:
        bad("stop_after", "≥ 0")
    if not 0 < p.valid_ratio_min <= 1:
        bad("valid_ratio_min", "0 < valid_ratio_min ≤ 1")
    if not p.tau_g >= 0:
        bad("tau_g", "≥ 0")
    if p.w_ss < p.ts:
        bad("w_ss", f"≥ ts ({p.ts})")
    if p.tau < p.ts:
        bad("tau", f"≥ ts ({p.ts})")
    if p.t_end is not None and not p.t_end > 0:
        bad("t_end", "> 0, or none")
