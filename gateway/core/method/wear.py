"""METHOD.md §5a: wear headroom, headroom runs and projection, one window at a time.

Informative only: nothing here changes a status, k_life or t_life. Both forms of the method feed
the same :class:`WearTracker` with the same window values, so they agree by construction; the
streaming form hands each :class:`WindowOut` to the runtime as soon as the window is complete.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import rules as R
from .params import MIN_TREND_WINDOWS, MethodParams


@dataclass(frozen=True)
class WindowOut:
    """One complete window after Ω_stable (§5a), as published online."""
    j: int                    # window index: slots [j·N_ss, (j+1)·N_ss − 1]
    last_slot: int            # (j+1)·N_ss − 1
    n_eff: int                # valid slots in the window
    value: float | None       # μ̃_j, None when the window has no value
    headroom: float | None    # h_j (None without a value)
    t_cross: float | None     # projected crossing of μ_th, s from test start (None: no projection)
    slope: float | None       # Theil–Sen slope used, 1/s (None with fewer than 10 windows)
    headroom_run: bool        # this window completes a headroom run (§5a; a reason of §5b)

    def as_dict(self) -> dict[str, Any]:
        return {"j": self.j, "last_slot": self.last_slot, "n_eff": self.n_eff, "value": self.value,
                "headroom": self.headroom, "t_cross": self.t_cross, "slope": self.slope,
                "headroom_run": self.headroom_run}


class WearTracker:
    """Consumes the post-baseline windows in order (``add``) and keeps the §5a result figures.

    Memory is bounded by ``trend_windows``; the projection runs once per window with a value
    (a Theil–Sen slope over at most trend_windows·(trend_windows−1)/2 pairs)."""

    def __init__(self, p: MethodParams, mu_ss: float, mu_th: float):
        self.p = p
        self.mu_ss = mu_ss
        self.mu_th = mu_th
        self._trend_t: deque[float] = deque(maxlen=p.trend_windows)
        self._trend_v: deque[float] = deque(maxlen=p.trend_windows)
        self._run = 0
        #: the early warning (§5b), set by the streaming monitor when it fires (kept here for the
        #: runtime that reads ``monitor.wear.warn_slot``; the §5b figures are ``monitor.forecast``)
        self.warn_slot: int | None = None
        self.headroom: float | None = None    # h of the last window with a value
        self.t_cross: float | None = None     # t_cross of the last window with a value
        self.windows = 0

    def add(self, j: int, n_eff: int, value: float | None) -> WindowOut:
        p = self.p
        self.windows += 1
        last = (j + 1) * p.n_ss - 1
        if value is None:
            self._run = 0
            return WindowOut(j, last, n_eff, None, None, None, None, False)
        h = R.headroom(value, self.mu_ss, self.mu_th)
        # a run: this window and the n_warn − 1 before it all have a value and h < h_warn
        self._run = self._run + 1 if h < p.h_warn else 0
        run = self._run >= p.n_warn
        self._trend_t.append(R.window_mid_time(j, p))
        self._trend_v.append(value)
        slope = None
        t_cross = None
        if len(self._trend_v) >= MIN_TREND_WINDOWS:
            slope = R.theil_sen_slope(np.array(self._trend_v), np.array(self._trend_t))
            if slope > 0 and h > 0:
                t_cross = (j + 1) * p.n_ss * p.ts + (self.mu_th - value) / slope
        self.headroom = h
        self.t_cross = t_cross
        return WindowOut(j, last, n_eff, value, h, t_cross, slope, run)
