"""METHOD.md §5b: remaining life from a prior, the forecast at every window, the early warning.

Informative only: nothing here changes a status, k_life or t_life. Both forms of the method feed
the same :class:`Forecaster` with the same windows in the same order (every complete §4 window
j = 0, 1, … that ends before the detection slot k_det), so they agree by construction; the
streaming form hands each :class:`ForecastOut` to the runtime as soon as the window is complete.

Φ is ½·erfc(−x/√2) (math.erfc: accurate in both tails, as scipy.special.ndtr) and Φ⁻¹ is
statistics.NormalDist's inv_cdf (Wichura's AS241, ≈ 1e-16 relative, as scipy.special.ndtri): the
standard library, imported with the module. scipy.special was imported when the first forecast
was made, on the station's slot thread: ≈ 0.3 s on a quiet box and 0.5–0.85 s on a loaded one, a
stall long enough to trip the STM32's watchdog (issue 23's flaky lives). The tests keep scipy as
the independent oracle of both.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist
from typing import Any

from .params import MethodParams
from .wear import WindowOut

#: the reasons of a due window (§5b), in their sorted order
REASON_HEADROOM = "headroom"
REASON_PRIOR = "prior"
REASON_TREND = "trend"
WARN_REASONS: tuple[str, ...] = (REASON_HEADROOM, REASON_PRIOR, REASON_TREND)
#: below this survival the hook has outlived its prior by far: e_p = t, P = 1
S_FLOOR = 1e-12
#: the forecast's quantiles
QUANTILES: tuple[float, ...] = (0.1, 0.5, 0.9)


_SQRT1_2 = math.sqrt(0.5)
_STANDARD = NormalDist()


def _phi(x: float) -> float:
    """Φ(x), the standard normal distribution function."""
    return 0.5 * math.erfc(-x * _SQRT1_2)


def _phi_inv(p: float) -> float:
    """Φ⁻¹(p) for 0 < p < 1 (p = 0 or 1: ∓inf, as ndtri)."""
    if p <= 0.0:
        return -math.inf
    if p >= 1.0:
        return math.inf
    return _STANDARD.inv_cdf(p)


@dataclass(frozen=True)
class PriorForecast:
    """The prior cut at t (§5b): end quantiles e10/e50/e90 (s from test start, each ≥ t) and the
    chance P that the end comes within the lead."""
    e10: float
    e50: float
    e90: float
    p: float


def prior_forecast(t: float, m: float, s: float, lead: float) -> PriorForecast:
    """§5b at time t for the prior N(m, s²) (s > 0): the hook has lasted until t."""
    a = (t - m) / s
    phi_a = _phi(a)
    surv = 1.0 - phi_a
    if surv < S_FLOOR:
        return PriorForecast(t, t, t, 1.0)
    e = [max(m + s * _phi_inv(1.0 - surv * (1.0 - q)), t) for q in QUANTILES]
    p = (_phi((t + lead - m) / s) - phi_a) / surv
    return PriorForecast(e[0], e[1], e[2], p)


def has_prior(p: MethodParams) -> bool:
    """The prior parts of §5b exist only with both prior_mean and prior_sd, and prior_sd > 0."""
    return p.prior_mean is not None and p.prior_sd is not None and p.prior_sd > 0


@dataclass(frozen=True)
class ForecastOut:
    """The forecast at the end of one complete window j (§5b), as published online."""
    j: int                      # window index: slots [j·N_ss, (j+1)·N_ss − 1]
    last_slot: int              # (j+1)·N_ss − 1
    t: float                    # forecast time t_j = (j+1)·N_ss·Ts, s from test start
    e10: float | None           # end quantiles from the prior (None without a prior)
    e50: float | None
    e90: float | None
    p_end: float | None         # P: chance of the end within the lead (None without a prior)
    headroom: float | None      # h_j of the window (§5a; None before the baseline or without a value)
    t_cross: float | None       # t_cross_j (§5a; None: no projection)
    headroom_run: bool          # the window completes a headroom run (§5a)
    reasons: tuple[str, ...]    # the reasons that make it due, sorted (empty: not due)
    warning: bool               # this window is the early warning (the first due one)

    @property
    def due(self) -> bool:
        return bool(self.reasons)

    def as_dict(self) -> dict[str, Any]:
        return {"j": self.j, "last_slot": self.last_slot, "t": self.t, "end_p10": self.e10,
                "end_p50": self.e50, "end_p90": self.e90, "p_end": self.p_end,
                "headroom": self.headroom, "t_cross": self.t_cross,
                "headroom_run": self.headroom_run, "due": self.due,
                "reasons": list(self.reasons), "warning": self.warning}


class Forecaster:
    """Consumes the forecast times in order (``add``) and keeps the §5b result figures.

    The caller feeds only windows that are complete and end before a protection stop, end_slot,
    the end of the log and the detection slot k_det; ``window`` is the §5a figure of the same
    window (None for the windows up to the end of Ω_stable)."""

    def __init__(self, p: MethodParams):
        self.p = p
        self._prior = has_prior(p)
        self._m = 0.0 if p.prior_mean is None else p.prior_mean
        self._s = 0.0 if p.prior_sd is None else p.prior_sd
        self.warn_slot: int | None = None
        self.warn_reasons: list[str] | None = None
        self.end_p10: float | None = None
        self.end_p50: float | None = None
        self.end_p90: float | None = None
        self.p_end: float | None = None
        self.last: ForecastOut | None = None

    def add(self, j: int, window: WindowOut | None) -> ForecastOut:
        p = self.p
        last = (j + 1) * p.n_ss - 1
        t = (j + 1) * p.n_ss * p.ts
        reasons: list[str] = []
        e10 = e50 = e90 = pe = None
        if self._prior:
            f = prior_forecast(t, self._m, self._s, p.lead)
            e10, e50, e90, pe = f.e10, f.e50, f.e90, f.p
            if f.p >= p.p_due:
                reasons.append(REASON_PRIOR)
        h = tc = None
        run = False
        if window is not None:
            h, tc, run = window.headroom, window.t_cross, window.headroom_run
            if run:
                reasons.append(REASON_HEADROOM)
            if tc is not None and tc - t <= p.lead:
                reasons.append(REASON_TREND)
        reasons.sort()
        warning = False
        if reasons and self.warn_slot is None:
            self.warn_slot = last
            self.warn_reasons = list(reasons)
            warning = True
        self.end_p10, self.end_p50, self.end_p90, self.p_end = e10, e50, e90, pe
        out = ForecastOut(j, last, t, e10, e50, e90, pe, h, tc, run, tuple(reasons), warning)
        self.last = out
        return out


def last_forecast_time(t: float, window_s: float) -> float | None:
    """The last forecast time (a window's end, §5b) at or before t, or None before the first."""
    n = int((t + 1e-9 * max(1.0, t)) // window_s)
    return None if n < 1 else n * window_s


def band_at_half_life(t_life: float, mean: float, sd: float, lead: float,
                      window_s: float) -> PriorForecast | None:
    """The forecast from the prior at the last forecast time at or before t_life / 2 (for the
    report's and the bench's check: how often t_life falls inside [e10, e90] at half of its
    life); None without such a time or without a prior (sd ≤ 0)."""
    t = last_forecast_time(t_life / 2.0, window_s)
    if t is None or not sd > 0:
        return None
    return prior_forecast(t, mean, sd, lead)
