"""Tension control (METHOD.md §8): pure, one call per 20 ms slot.

speed-adaptive notch → first-order pre-filter → dead band → incremental PID with a low-passed
derivative → slew limit → clamp to [0, n_max] (the clamp on the accumulated command is the
anti-windup). Open-loop mode holds a fixed command (through the same slew limit and clamp).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any


@dataclass(frozen=True)
class NotchParams:
    enabled: bool = True
    bw_hz: float = 0.8          # B_w
    q_min: float = 2.0
    q_max: float = 12.0
    alpha_f: float = 0.2
    alpha_q: float = 0.2
    n_min_rpm: float = 30.0     # bypassed below this speed
    f_update_hz: float = 0.2    # recompute coefficients when f0 moved more than this
    q_update: float = 0.5       # … or Q moved more than this
    ratio_i: float = 1.0        # i: transmission ratio
    harmonic_h: int = 1         # h: harmonic order


@dataclass(frozen=True)
class ControlParams:
    ts: float = 0.02
    mode: str = "closed"        # closed | open
    open_loop_rpm: float = 180.0
    kp: float = 60.0            # rpm per N
    ki: float = 300.0           # rpm per N·s
    kd: float = 0.0             # rpm·s per N
    plant_sign: int = 1         # +1: more take-up speed → more tension
    n_max_rpm: float = 400.0
    slew_rpm_per_slot: float = 16.0
    dead_band_n: float = 0.02
    prefilter_fc_hz: float = 2.0
    deriv_fc_hz: float = 5.0
    hold_missing_s: float = 1.0
    notch: NotchParams = NotchParams()

    def as_dict(self) -> dict[str, Any]:
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "notch"}
        d["notch"] = {f.name: getattr(self.notch, f.name) for f in fields(self.notch)}
        return d


def lowpass_alpha(ts: float, fc: float) -> float:
    """a = Ts / (Ts + 1 / (2π f_c))"""
    return ts / (ts + 1.0 / (2.0 * math.pi * fc))


def notch_coefficients(f0: float, q: float, fs: float) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """Second-order IIR notch, identical to scipy.signal.iirnotch(f0, Q, fs): (b, a)."""
    w0 = 2.0 * math.pi * f0 / fs
    bw = w0 / q
    beta = math.tan(bw / 2.0)
    gain = 1.0 / (1.0 + beta)
    c = math.cos(w0)
    b = (gain, -2.0 * c * gain, gain)
    a = (1.0, -2.0 * gain * c, 2.0 * gain - 1.0)
    return b, a


class Notch:
    """Speed-adaptive notch with smoothed, thresholded coefficient updates (§8.1)."""

    def __init__(self, p: NotchParams, ts: float):
        self.p = p
        self.fs = 1.0 / ts
        self.f0: float | None = None
        self.q: float | None = None
        self._f_last = math.nan
        self._q_last = math.nan
        self._b = (1.0, 0.0, 0.0)
        self._a = (1.0, 0.0, 0.0)
        self._z1 = 0.0
        self._z2 = 0.0
        self.active = False
        self.updates = 0

    def _steady_state(self, x: float) -> None:
        b, a = self._b, self._a
        self._z2 = (b[2] - a[2]) * x
        self._z1 = (b[1] - a[1]) * x + self._z2

    def step(self, x: float, speed_rpm: float) -> float:
        p = self.p
        f_tar = speed_rpm / 60.0 * p.ratio_i * p.harmonic_h
        if not p.enabled or speed_rpm < p.n_min_rpm or f_tar <= 0.0:
            self.active = False
            return x
        f_tar = min(f_tar, 0.45 * self.fs)          # stay below Nyquist
        q_tar = min(max(f_tar / p.bw_hz, p.q_min), p.q_max)
        if self.f0 is None or self.q is None:
            f0, q = f_tar, q_tar
        else:
            f0 = self.f0 + p.alpha_f * (f_tar - self.f0)
            q = self.q + p.alpha_q * (q_tar - self.q)
        self.f0, self.q = f0, q
        if (math.isnan(self._f_last) or abs(f0 - self._f_last) > p.f_update_hz
                or abs(q - self._q_last) > p.q_update):
            self._b, self._a = notch_coefficients(f0, q, self.fs)
            self._f_last, self._q_last = f0, q
            self.updates += 1
        if not self.active:                          # (re-)engage without a bump
            self._steady_state(x)
            self.active = True
        b, a = self._b, self._a
        y = b[0] * x + self._z1
        self._z1 = b[1] * x - a[1] * y + self._z2
        self._z2 = b[2] * x - a[2] * y
        return y


@dataclass
class ControlOut:
    u: float              # speed command, rpm
    saturated: bool       # the clamp to [0, n_max] acted
    slew_limited: bool
    y: float              # pre-filtered feedback, N (NaN before the first reading)
    e: float              # error after the dead band, N
    notch_active: bool
    feedback_ok: bool     # a reading (fresh or held ≤ hold_missing_s) was available


class Controller:
    """One :meth:`step` per slot. ``t_mean`` is (T1 + T2)/2 of this slot's reading, or None
    when the slot has none (the last reading is held for at most ``hold_missing_s``)."""

    def __init__(self, p: ControlParams, t_set: float, u0: float = 0.0):
        self.p = p
        self.t_set = t_set
        self.notch = Notch(p.notch, p.ts)
        self._a_pre = lowpass_alpha(p.ts, p.prefilter_fc_hz)
        self._a_d = lowpass_alpha(p.ts, p.deriv_fc_hz)
        self._hold_slots = int(round(p.hold_missing_s / p.ts))
        self.u = min(max(u0, 0.0), p.n_max_rpm)
        self.y: float | None = None
        self._last_x: float | None = None
        self._since_reading = 0
        self._e1 = 0.0
        self._d = 0.0
        self._d1 = 0.0
        self._d2 = 0.0
        self._started = False

    def set_setpoint(self, t_set: float) -> None:
        self.t_set = t_set

    def _limit(self, du: float) -> tuple[float, bool, bool]:
        p = self.p
        slew = False
        if du > p.slew_rpm_per_slot:
            du, slew = p.slew_rpm_per_slot, True
        elif du < -p.slew_rpm_per_slot:
            du, slew = -p.slew_rpm_per_slot, True
        u = self.u + du
        sat = False
        if u > p.n_max_rpm:
            u, sat = p.n_max_rpm, True
        elif u < 0.0:
            u, sat = 0.0, True
        self.u = u
        return u, sat, slew

    def step(self, t_mean: float | None, speed_rpm: float) -> ControlOut:
        p = self.p
        x: float | None
        if t_mean is not None and math.isfinite(t_mean):
            x = t_mean
            self._last_x = x
            self._since_reading = 0
        else:
            self._since_reading += 1
            x = self._last_x if self._since_reading <= self._hold_slots else None
        if p.mode == "open":
            u, sat, slew = self._limit(p.open_loop_rpm - self.u)
            if x is not None:
                self.y = x if self.y is None else self.y + self._a_pre * (x - self.y)
            return ControlOut(u, sat, slew, math.nan if self.y is None else self.y, 0.0,
                              False, x is not None)
        if x is None:
            # no feedback: hold the command (Δu = 0); the protection stop takes over after 1 s
            u, sat, slew = self._limit(0.0)
            return ControlOut(u, sat, slew, math.nan if self.y is None else self.y, 0.0,
                              self.notch.active, False)
        xn = self.notch.step(x, speed_rpm)
        self.y = xn if self.y is None else self.y + self._a_pre * (xn - self.y)
        e = self.t_set - self.y
        if abs(e) < p.dead_band_n:
            e = 0.0
        e *= p.plant_sign
        if not self._started:
            self._e1 = e
            self._d = self._d1 = self._d2 = e
            self._started = True
        self._d += self._a_d * (e - self._d)
        du = (p.kp * (e - self._e1) + p.ki * p.ts * e
              + (p.kd / p.ts) * (self._d - 2.0 * self._d1 + self._d2))
        self._e1 = e
        self._d2, self._d1 = self._d1, self._d
        u, sat, slew = self._limit(du)
        return ControlOut(u, sat, slew, self.y, e, self.notch.active, True)
