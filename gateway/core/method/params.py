"""The method's parameters: one definition of every name, default, unit and allowed range.

These names (METHOD.md §10) are the keys of a station's ``method:`` section, of a log's metadata
sidecar and of ``hookwatch analyze --set``. Docs and CLI help are generated from ``PARAMS``.

Each default is written once, in the :class:`MethodParams` dataclass (the method's typed
parameters); a :class:`ParamSpec` row adds the unit, the doc, the parsing kind and the range, and
reads its default from the dataclass (as the ``control:`` keys read theirs from ControlParams).
A row without a field, or a field without a row, fails at import.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import MISSING as MISSING_FIELD
from dataclasses import dataclass, fields, replace
from typing import Any

from ..validation import MISSING, Problem, ValidationError, did_you_mean


@dataclass(frozen=True)
class ParamSpec:
    name: str
    unit: str
    doc: str
    optional: bool = False  # may be None (e.g. t_end)
    kind: str = "float"     # "float", "int" (a whole number) or "bool"
    hi: float | None = None  # the largest plausible value (inclusive); every value is finite too

    @property
    def default(self) -> float | int | bool | None:
        """The default of the MethodParams field (None for a required parameter)."""
        return _DEFAULTS[self.name]

    @property
    def required(self) -> bool:
        """The MethodParams field has no default (t_set)."""
        return self.name not in _HAS_DEFAULT

    def bound(self) -> str:
        """The upper bound as the docs and the error messages say it."""
        if self.hi is None:
            return ""
        if self.hi == TEN_YEARS:
            return f"≤ {TEN_YEARS:.0f} {self.unit} (10 years)"
        return f"≤ {self.hi:g}" + (f" {self.unit}" if self.unit not in ("1", "slot", "") else "")


#: the longest duration any parameter may have: 10 years of 365.25 days, in s. No needle hook
#: lives that long; a larger value (1e308) is a typing error, and would overflow the §5b quantiles
TEN_YEARS = 10 * 365.25 * 86400.0
#: the largest plausible tension, N (the ZN-S meter's largest range is far below)
MAX_TENSION = 1000.0

PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("ts", "s", "sampling period", hi=1.0),
    ParamSpec("theta_deg", "deg", "wrap angle θ of the yarn around the hook"),
    ParamSpec("t_set", "N", "regulated mean tension T_set", hi=MAX_TENSION),
    ParamSpec("full_scale", "N", "sensor full scale", hi=MAX_TENSION),
    ParamSpec("sat_ratio", "1", "T_sat = sat_ratio · full_scale"),
    ParamSpec("t_min_ratio", "1", "T_min = t_min_ratio · t_set"),
    ParamSpec("jump_ratio", "1", "J_max = jump_ratio · t_set", hi=100.0),
    ParamSpec("r_min", "1", "lower bound of R = T2/T1", hi=1e6),
    ParamSpec("r_max", "1", "upper bound of R = T2/T1", hi=1e6),
    ParamSpec("stop_after", "s", "protection stop after this long unsafe", hi=3600.0),
    ParamSpec("w_ss", "s", "baseline window length", hi=3600.0),
    ParamSpec("valid_ratio_min", "1", "N_eff / N_ss needed in a steady window"),
    ParamSpec("sigma_max", "1", "robust σ bound in a steady window", hi=10.0),
    ParamSpec("g_max", "1", "range bound (max − min of μ) in a steady window", hi=10.0),
    ParamSpec("w_hold", "s", "steady duration needed for the baseline", hi=TEN_YEARS),
    ParamSpec("delta", "1", "relative threshold increment δ", hi=100.0),
    ParamSpec("tau", "s", "persistence time τ", hi=86400.0),
    ParamSpec("tau_g", "s", "tolerated interruption τ_g", hi=3600.0),
    ParamSpec("t_end", "s", "planned test duration (none: open-ended)", optional=True, hi=TEN_YEARS),
    ParamSpec("end_slot", "slot", "first slot after a test ended on purpose (§3); written by "
              "the gateway into the sidecar, not set in a station file", optional=True, kind="int", hi=1e12),
    ParamSpec("h_warn", "1", "headroom below which windows count toward a headroom run "
              "(§5a, a reason of the early warning §5b)", hi=1.0),
    ParamSpec("n_warn", "1", "consecutive windows that make a headroom run (§5a)", kind="int", hi=10000),
    ParamSpec("trend_windows", "1", "windows used by the projection's Theil–Sen slope (§5a)",
              kind="int", hi=100000),
    ParamSpec("prior_mean", "s", "mean life of hooks of this grade at this T_set (§5b, §7a); "
              "written by the gateway into the sidecar at the start of a test", optional=True, hi=TEN_YEARS),
    ParamSpec("prior_sd", "s", "standard deviation of that life (§5b); without it, or ≤ 0 "
              "in a log's sidecar, the forecast from the prior is null", optional=True, hi=TEN_YEARS),
    ParamSpec("lead", "s", "the planner's lead time: a hook is due when its end may come "
              "within it (§5b)", hi=TEN_YEARS),
    ParamSpec("p_due", "1", "chance of the end within the lead that makes a hook due (§5b)"),
    ParamSpec("zero_check", "bool", "zero check before the motor starts (§3a)", kind="bool"),
    ParamSpec("zero_tol", "N", "allowed offset of each channel at zero (§3a)", hi=MAX_TENSION),
    ParamSpec("settle_band", "1", "slot 0 needs the mean tension within settle_band · t_set "
              "of t_set … (§3a)"),
    ParamSpec("settle_time", "s", "… for this long (§3a)", hi=3600.0),
    ParamSpec("start_timeout", "s", "no settled tension after this long: the start fails (§3a)", hi=3600.0),
)
PARAM_NAMES: tuple[str, ...] = tuple(p.name for p in PARAMS)
SPEC = {p.name: p for p in PARAMS}

RESULT_KEYS: tuple[str, ...] = (
    "status", "mu_ss", "mu_th", "k_b", "stable_first", "stable_last", "k_life", "t_life",
    "n_slots", "n_valid", "reasons", "interrupted", "stop_slot", "stop_reasons",
    "headroom", "t_cross", "warn_slot", "warn_reasons", "end_p10", "end_p50", "end_p90", "p_end",
)
#: the parameters of the life prior (§5b, §7a)
PRIOR_NAMES: tuple[str, ...] = ("prior_mean", "prior_sd")
#: the stop reason of a test ended on purpose (§3)
STOPPED = "STOPPED"
#: the §5a projection needs at least this many windows with a value
MIN_TREND_WINDOWS = 10


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
    """The method's parameters (METHOD.md §10), typed; each field's default is the parameter's one
    default (PARAMS reads it from here); a field without a default is required."""
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
    end_slot: int | None = None
    h_warn: float = 0.5
    n_warn: int = 5
    trend_windows: int = 60
    prior_mean: float | None = None
    prior_sd: float | None = None
    lead: float = 3600.0
    p_due: float = 0.1
    zero_check: bool = True
    zero_tol: float = 0.02
    settle_band: float = 0.1
    settle_time: float = 2.0
    start_timeout: float = 30.0

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
    def n_grid(self) -> int | None:
        """Number of slots of the test's grid (slots 0 .. n_grid-1), or None when open-ended:
        ``end_slot`` for a test ended on purpose (§3: t_end then adds nothing), else t_end / Ts."""
        if self.end_slot is not None:
            return self.end_slot
        if self.t_end is None:
            return None
        return int(round(self.t_end / self.ts))

    def with_delta(self, delta: float) -> MethodParams:
        return replace(self, delta=delta)

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


#: each parameter's default, from the one place it is written (the fields of MethodParams)
_DEFAULTS: dict[str, float | int | bool | None] = {
    f.name: None if f.default is MISSING_FIELD else f.default for f in fields(MethodParams)}
_HAS_DEFAULT = frozenset(f.name for f in fields(MethodParams) if f.default is not MISSING_FIELD)
if set(_DEFAULTS) != set(PARAM_NAMES):
    raise TypeError("method parameters: the MethodParams fields and the PARAMS rows differ: "
                      f"{sorted(set(_DEFAULTS) ^ set(PARAM_NAMES))}")


_TRUE = ("true", "yes", "on", "1")
_FALSE = ("false", "no", "off", "0")


def _flag(name: str, value: Any, source: str) -> bool:
    if isinstance(value, bool):
        return value
    if isinstance(value, (int, float)) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in _TRUE + _FALSE:
        return value.strip().lower() in _TRUE
    raise _err(source, name, f"{value!r} is not true or false ({SPEC[name].doc})", value, "true or false")


def _num(name: str, value: Any, source: str) -> float | int | bool | None:
    spec = SPEC[name]
    if spec.kind == "bool":
        return _flag(name, value, source)
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
    if spec.hi is not None and f > spec.hi:
        raise _err(source, name, f"{value!r} is out of range; allowed: {spec.bound()} ({spec.doc})",
                   value, spec.bound())
    if spec.kind == "int":
        if f != int(f):
            raise _err(source, name, f"{value!r} is not a whole number ({spec.doc})", value,
                       "a whole number")
        return int(f)
    return f


def build_params(values: Mapping[str, Any], source: str = "", *,
                 prior_from_log: bool = False) -> MethodParams:
    """Make MethodParams from a mapping of §10 names. Unknown names and impossible values raise
    ParamError with a message that names the key, the value and what is allowed.

    ``prior_from_log``: the values come from a recorded log's sidecar, where a prior with
    ``prior_sd`` ≤ 0 (or only half of it) means "no prior" (§5b: the prior parts are null);
    everywhere else (a station's configuration, ``--set``) such a prior is an error."""
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
    validate(p, prefix, prior_from_log=prior_from_log)
    return p


def validate(p: MethodParams, prefix: str = "", *, prior_from_log: bool = False) -> None:
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
    if p.end_slot is not None and not p.end_slot >= 0:
        bad("end_slot", "a slot number ≥ 0, or none")
    if not p.n_warn >= 1:
        bad("n_warn", "≥ 1")
    if not p.trend_windows >= MIN_TREND_WINDOWS:
        bad("trend_windows", f"≥ {MIN_TREND_WINDOWS} (the projection needs at least "
            f"{MIN_TREND_WINDOWS} windows with a value)")
    if not p.lead >= 0:
        bad("lead", "≥ 0 s")
    if not 0 < p.p_due < 1:
        bad("p_due", "0 < p_due < 1")
    if not prior_from_log:
        validate_prior(p.prior_mean, p.prior_sd, prefix)
    for name in ("zero_tol", "start_timeout"):
        if not getattr(p, name) > 0:
            bad(name, "> 0")
    if not 0 < p.settle_band < 1:
        bad("settle_band", "0 < settle_band < 1")
    if not p.settle_time >= 0:
        bad("settle_time", "≥ 0")
    if not p.start_timeout > p.settle_time:
        raise _err(prefix, "start_timeout", f"{p.start_timeout!r} must be longer than settle_time "
                   f"{p.settle_time!r}", p.start_timeout, f"> settle_time ({p.settle_time!r})",
                   related=("settle_time",),
                   text=f"{prefix}start_timeout {p.start_timeout!r} must be longer than "
                        f"settle_time {p.settle_time!r}")


def validate_prior(mean: float | None, sd: float | None, prefix: str = "") -> None:
    """A configured prior (§5b, §7a): both or neither; mean > 0 s, SD > 0 s."""
    if mean is None and sd is None:
        return
    if mean is None or sd is None:
        have, lack = ("prior_mean", "prior_sd") if sd is None else ("prior_sd", "prior_mean")
        msg = f"{have} without {lack}; a life prior needs both (mean and SD of the life, s)"
        raise _err(prefix, lack, msg, allowed="a number, given together with " + have,
                   related=(have,), text=prefix + msg)
    if not mean > 0:
        raise _err(prefix, "prior_mean", f"{mean!r} is impossible; allowed: > 0 s (a mean life)",
                   mean, "> 0")
    if not sd > 0:
        raise _err(prefix, "prior_sd", f"{sd!r} is impossible; allowed: > 0 s (the SD of the life)",
                   sd, "> 0")
