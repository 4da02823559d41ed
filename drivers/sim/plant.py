"""The physical test bench as a pure, seeded model: take-up motor, yarn tension, capstan split
around the needle hook, two tension sensors, and the wear of the hook (μ over its life).

Pure: no clock, no I/O, no asyncio. Time only moves through :meth:`Plant.step` /
:meth:`Plant.advance_to`, in fixed internal steps of ``step_s`` (2 ms), and every step consumes
the same amount of random numbers, so the trace as a function of time is a deterministic function
of the seed — independent of when, or how often, it is sampled. docs/simulator.md has the
equations and the reasoning behind every default number.

Signal chain (per internal step h)::

    command ─▶ motor (first-order lag τ_m, acceleration limit, enable, stall) ─▶ n
    n ─▶ dead time L ─▶ T_ss = T_pre + K·d(t)·max(0, n_L − n_0) ─▶ first-order lag τ_T ─▶ T_m
    T_m · (1 + A·sin φ),  dφ/dt = 2π·n/60·i·h           (periodic ripple, what the notch removes)
    T1 = 2·T_m/(1 + e^(μθ)),  T2 = T1·e^(μθ)             (capstan split around the mean)
    reading = clip(round((g·T + noise) / 0.001 N) · 0.001 N, ±full scale)

μ(u) over the wear time u (running time × time_scale): run-in (decaying from higher, with decaying
fluctuations), steady stage (slight rise), then an accelerated rise from the onset u_on.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numpy as np

# ----------------------------------------------------------------------------------------------
# Wear profiles from the paper's Table 3 / Table 4 (Chen et al. 2026)
# ----------------------------------------------------------------------------------------------

#: (grade, T_set N) -> (mean t_life s, SD t_life s) — Table 4, i.e. Table 3 per group
TABLE4_LIFE: dict[tuple[str, float], tuple[float, float]] = {
    ("I", 0.5): (32306.9, 951.7),
    ("I", 0.7): (29043.8, 488.1),
    ("I", 0.9): (26579.5, 113.9),
    ("II", 0.5): (21643.5, 120.6),
    ("II", 0.7): (18840.5, 699.2),
    ("II", 0.9): (16577.1, 489.3),
}
#: (grade, T_set N) -> (mean μ_ss, SD μ_ss) of the three samples of Table 3
TABLE3_MU: dict[tuple[str, float], tuple[float, float]] = {
    ("I", 0.5): (0.32490, 0.05677),
    ("I", 0.7): (0.25303, 0.00448),
    ("I", 0.9): (0.25053, 0.00401),
    ("II", 0.5): (0.35030, 0.07874),
    ("II", 0.7): (0.24490, 0.00751),
    ("II", 0.9): (0.25630, 0.00150),
}
GRADES = ("I", "II")
TABLE_T_SET = (0.5, 0.7, 0.9)
MU_SS_RANGE = (0.24, 0.40)          # drawn μ_ss is clipped to Table 3's span
CV_FLOOR = 0.005                    # drawn t_life spread is at least 0.5 %


def _interp(t_set: float, values: tuple[float, float, float]) -> float:
    """Piecewise-linear in T_set through the table's three setpoints, extrapolated with the end
    slopes."""
    xs = TABLE_T_SET
    if t_set <= xs[1]:
        i = 0
    else:
        i = 1
    x0, x1 = xs[i], xs[i + 1]
    y0, y1 = values[i], values[i + 1]
    return y0 + (y1 - y0) * (t_set - x0) / (x1 - x0)


def table_life(grade: str, t_set: float) -> tuple[float, float]:
    """Mean and SD of the paper's t_life for a grade at a setpoint (interpolated in T_set)."""
    means = tuple(TABLE4_LIFE[(grade, x)][0] for x in TABLE_T_SET)
    cvs = tuple(TABLE4_LIFE[(grade, x)][1] / TABLE4_LIFE[(grade, x)][0] for x in TABLE_T_SET)
    m = max(1000.0, _interp(t_set, means))
    cv = max(CV_FLOOR, _interp(min(max(t_set, 0.5), 0.9), cvs))
    return m, m * cv


def table_mu(grade: str, t_set: float) -> tuple[float, float]:
    ts = min(max(t_set, 0.5), 0.9)     # μ_ss is not extrapolated
    means = tuple(TABLE3_MU[(grade, x)][0] for x in TABLE_T_SET)
    sds = tuple(TABLE3_MU[(grade, x)][1] for x in TABLE_T_SET)
    return _interp(ts, means), _interp(ts, sds)


# ----------------------------------------------------------------------------------------------
# Parameters
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class MotorParams:
    tau_s: float = 0.05             # first-order lag of the stepper + driver ramp
    accel_rpm_s: float = 3000.0     # acceleration limit
    max_rpm: float = 600.0          # mechanical limit (the controller clamps at 400)
    stall_decel_rpm_s: float = 20000.0  # a stall brings the speed to 0 within ~10 ms


@dataclass(frozen=True)
class TensionParams:
    gain_n_per_rpm: float = 0.005   # K: N per rpm above the offset
    offset_rpm: float = 40.0        # n_0: below this the yarn is slack (only pretension)
    pretension_n: float = 0.01      # T_pre: supply brake with the take-up stopped
    tau_s: float = 0.25             # τ_T: first-order lag of the mean tension
    dead_time_s: float = 0.08       # L: yarn transport take-up → hook
    mu_tension_coeff: float = -0.1  # μ·(1 + c·(T_m/T_set − 1)): slightly lower μ at higher load
    slack_s: float = 0.0            # slow spin-up: running seconds (yarn moving above n_0) of slack
                                    # yarn to wind up after each standstill before tension builds


@dataclass(frozen=True)
class DriftParams:
    sine_amp: float = 0.03          # relative amplitude of the slow sinusoid (yarn batch)
    sine_period_s: float = 240.0
    walk_sigma: float = 0.03        # stationary σ of the relative random walk (Ornstein–Uhlenbeck)
    walk_tau_s: float = 300.0
    package_per_h: float = 0.02     # take-up package diameter: +2 % gain per running hour


@dataclass(frozen=True)
class RippleParams:
    amplitude: float = 0.03         # relative to T_m (3 %)
    ratio_i: float = 1.0            # i: transmission ratio motor → disturbing element
    harmonic_h: int = 1             # h: harmonic order; f = n/60·i·h


@dataclass(frozen=True)
class SensorParams:
    noise_n: float = 0.0006         # white noise σ per channel, N
    resolution_n: float = 0.001     # quantisation step, N
    full_scale_n: float = 5.0       # readings clip at ± full scale
    gain_ch1: float = 1.0           # channel gain mismatch
    gain_ch2: float = 1.0
    offset_ch1: float = 0.0         # zero offset of each channel, N (a mis-zeroed or drifted sensor)
    offset_ch2: float = 0.0


@dataclass(frozen=True)
class WearParams:
    """The wear profile over the wear time u (life seconds). ``None`` = drawn from the grade's
    Table 3 profile with the seed."""
    mu_ss: float | None = None          # steady-stage μ at u = 0 (without run-in excess)
    onset_s: float | None = None        # u_on: start of the accelerated rise, life s
    run_in_excess: float = 0.12         # μ starts at μ_ss·(1 + run_in_excess)
    run_in_tau_s: float = 1200.0        # mean excess decays with this; fluctuations with 2×
    run_in_jitter: float = 0.02         # σ of the run-in fluctuation of μ at u = 0
    run_in_jitter_tau_s: float = 1.0    # correlation time of that fluctuation, real s
    steady_rise: float = 0.04           # relative rise of μ from u = 0 to the onset
    rise_a: float = 0.05                # accelerated stage: μ_base·(1 + cap·tanh(a(e^x − 1)/cap))
    rise_tau_s: float = 1000.0          # x = (u − u_on)/rise_tau_s
    rise_cap: float = 0.7               # μ never exceeds μ_base·(1 + cap)
    jitter_sigma: float = 0.0008        # steady fluctuation of μ (OU), absolute
    jitter_tau_s: float = 10.0          # its correlation time, real s
    wear_min_rpm: float = 5.0           # the hook wears only while yarn runs


@dataclass(frozen=True)
class PlantParams:
    grade: str = "I"
    t_set: float = 0.5                  # the test's tension setpoint (selects the wear profile)
    time_scale: float = 1.0             # wear seconds per running second
    step_s: float = 0.002               # fixed internal step
    theta_deg: float = 105.0
    trace_every_s: float = 0.1          # trace decimation (10 Hz)
    threaded: bool = True               # False: the yarn is not threaded (no tension at all)
    motor: MotorParams = field(default_factory=MotorParams)
    tension: TensionParams = field(default_factory=TensionParams)
    drift: DriftParams = field(default_factory=DriftParams)
    ripple: RippleParams = field(default_factory=RippleParams)
    sensor: SensorParams = field(default_factory=SensorParams)
    wear: WearParams = field(default_factory=WearParams)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


#: the nested sections of PlantParams and their classes (the scenario loader uses this)
SECTIONS: dict[str, type] = {"motor": MotorParams, "tension": TensionParams, "drift": DriftParams,
                             "ripple": RippleParams, "sensor": SensorParams, "wear": WearParams}


# ----------------------------------------------------------------------------------------------
# The resolved wear profile
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class WearProfile:
    """Concrete numbers of one sample's μ(u)."""
    mu_ss: float
    onset_s: float
    run_in_excess: float
    run_in_tau_s: float
    steady_rise: float
    rise_a: float
    rise_tau_s: float
    rise_cap: float
    table_life_s: float | None = None   # the drawn Table-3 life this onset was derived from

    def base(self, u: float) -> float:
        """μ without fluctuations and without the accelerated rise."""
        frac = min(max(u, 0.0), self.onset_s) / self.onset_s if self.onset_s > 0 else 0.0
        return self.mu_ss * (1.0 + self.steady_rise * frac
                             + self.run_in_excess * math.exp(-max(u, 0.0) / self.run_in_tau_s))

    def rise_factor(self, u: float) -> float:
        if u <= self.onset_s:
            return 1.0
        x = (u - self.onset_s) / self.rise_tau_s
        g = self.rise_a * math.expm1(min(x, 50.0))
        return 1.0 + self.rise_cap * math.tanh(g / self.rise_cap)

    def mu(self, u: float) -> float:
        """The deterministic μ(u) (no fluctuation, nominal tension)."""
        return self.base(u) * self.rise_factor(u)

    def crossing_s(self, delta: float = 0.25, ref: float | None = None) -> float:
        """First wear time after the onset where μ(u) > (1 + δ)·ref (ref = μ_ss): bisection."""
        ref = self.mu_ss if ref is None else ref
        target = (1.0 + delta) * ref
        lo, hi = self.onset_s, self.onset_s + self.rise_tau_s
        while self.mu(hi) <= target:
            hi = lo + 2.0 * (hi - lo)
            if hi - self.onset_s > 1e9:
                return math.inf
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            if self.mu(mid) > target:
                hi = mid
            else:
                lo = mid
        return hi

    def x_for(self, rel: float) -> float:
        """x at which the rise factor reaches 1 + rel."""
        # 1 + cap·tanh(g/cap) = 1 + rel → g = cap·atanh(rel/cap); g = a·(e^x − 1)
        g = self.rise_cap * math.atanh(rel / self.rise_cap)
        return math.log1p(g / self.rise_a)


def resolve_wear(grade: str, t_set: float, wear: WearParams, rng: np.random.Generator,
                 delta: float = 0.25) -> WearProfile:
    """The sample's concrete profile: μ_ss and the onset drawn from the grade's Table-3 numbers
    (unless given). The onset is placed so that μ crosses (1 + δ0)·μ_base at the drawn t_life."""
    if grade not in GRADES:
        raise ValueError(f"grade {grade!r}: allowed {', '.join(GRADES)}")
    life_mean, life_sd = table_life(grade, t_set)
    mu_mean, mu_sd = table_mu(grade, t_set)
    z_life, z_mu = rng.standard_normal(2)           # always drawn: stream independent of overrides
    if wear.mu_ss is not None:
        mu_ss = float(wear.mu_ss)
    else:
        mu_ss = float(np.clip(mu_mean + mu_sd * z_mu, *MU_SS_RANGE))
    prof = WearProfile(mu_ss=mu_ss, onset_s=1.0, run_in_excess=wear.run_in_excess,
                       run_in_tau_s=wear.run_in_tau_s, steady_rise=wear.steady_rise,
                       rise_a=wear.rise_a, rise_tau_s=wear.rise_tau_s, rise_cap=wear.rise_cap)
    if wear.onset_s is not None:
        return replace(prof, onset_s=float(wear.onset_s))
    t_life = max(life_mean + life_sd * float(z_life), 0.1 * life_mean)
    # the onset for which μ(u) first exceeds (1 + δ0)·μ_ss at u = t_life (bisection; the
    # crossing moves monotonically with the onset)
    lo, hi = 0.0, t_life
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        if replace(prof, onset_s=max(mid, 1e-6)).crossing_s(delta) > t_life:
            hi = mid
        else:
            lo = mid
    return replace(prof, onset_s=max(lo, 1e-6), table_life_s=t_life)


# ----------------------------------------------------------------------------------------------
# Plant
# ----------------------------------------------------------------------------------------------

@dataclass
class PlantFaults:
    """Fault switches, set by the scenario timeline (or by tests)."""
    yarn_break: bool = False        # mean tension → 0 (both readings ≈ 0)
    saturate: bool = False          # both readings at full scale
    stall: bool = False             # motor stalls: speed → 0
    swap_channels: bool = False     # ch1 ↔ ch2 on the wire


STANDSTILL_RPM = 1.0    # below this the take-up stands still (its slack forms again)
_N_RANDOM = 5       # normals consumed per step: noise ch1, noise ch2, μ jitter, run-in jitter, drift


class Plant:
    """One virtual bench. Implements the ``motor`` interface of the virtual STM32
    (``set_command``, ``enable``, ``speed_rpm``, ``stalled``) and the meter's ``source``
    (``tensions()``)."""

    TRACE_COLUMNS = ("t", "command_rpm", "speed_rpm", "enabled", "t_mean", "T1", "T2", "mu",
                     "wear_s", "faults")

    def __init__(self, params: PlantParams | None = None, seed: int = 0):
        self.p = p = params or PlantParams()
        if p.step_s <= 0:
            raise ValueError("step_s must be > 0")
        self.seed = int(seed)
        ss = np.random.SeedSequence(self.seed)
        s_prof, s_noise, s_init = ss.spawn(3)
        self.profile = resolve_wear(p.grade, p.t_set, p.wear, np.random.default_rng(s_prof))
        self._rng = np.random.default_rng(s_noise)
        init = np.random.default_rng(s_init)
        self._phase0 = float(init.uniform(0.0, 2.0 * math.pi))      # drift sinusoid
        self._walk = float(init.standard_normal()) * p.drift.walk_sigma
        self._jit = float(init.standard_normal()) * p.wear.jitter_sigma
        self._rij = float(init.standard_normal())
        self._block: list[list[float]] = []
        self._bi = 0
        self.h = p.step_s
        self.k = 0                          # steps done; time t = k·h
        self._t_req = 0.0                   # latest time asked for (≥ t)
        self.faults = PlantFaults()
        # motor
        self.command_rpm = 0.0
        self.enabled = False
        self._speed = 0.0
        # tension
        nd = int(round(p.tension.dead_time_s / self.h))
        self._delay = [0.0] * max(nd, 1)
        self._di = 0
        self._nd = nd
        self.t_mean = p.tension.pretension_n if p.threaded else 0.0   # true mean tension, no ripple
        self.slack_left_s = p.tension.slack_s   # slack yarn still to wind up (slow spin-up)
        self._phi = 0.0
        # wear
        self.run_s = 0.0                    # running time (yarn moving), real s
        self.wear_s = 0.0                   # wear time u = running time × time_scale
        self.first_run_t: float | None = None
        self.onset_t: float | None = None   # plant time at which u crossed the onset
        self.mu_true = self.profile.mu(0.0)
        self.t1_true = self.t2_true = 0.0
        self.ch1 = self.ch2 = 0.0
        self._trace_every = max(1, int(round(p.trace_every_s / self.h)))
        self._trace: list[tuple] = []
        self.trace_enabled = False
        # precomputed constants
        self._a_m = -math.expm1(-self.h / p.motor.tau_s) if p.motor.tau_s > 0 else 1.0
        self._a_t = -math.expm1(-self.h / p.tension.tau_s) if p.tension.tau_s > 0 else 1.0
        self._theta = math.radians(p.theta_deg)
        self._update_readings([0.0] * _N_RANDOM)

    # ------------------------------------------------------------------ motor interface
    def set_command(self, rpm: float) -> None:
        r = float(rpm)
        self.command_rpm = min(max(r, 0.0), self.p.motor.max_rpm) if math.isfinite(r) else 0.0

    def enable(self, on: bool) -> None:
        self.enabled = bool(on)

    @property
    def speed_rpm(self) -> float:
        return self._speed

    @property
    def stalled(self) -> bool:
        return self.faults.stall

    # ------------------------------------------------------------------ meter interface
    def tensions(self) -> tuple[float, float]:
        """The two sensor readings (ch1, ch2) in N at the current step."""
        if self.faults.swap_channels:
            return self.ch2, self.ch1
        return self.ch1, self.ch2

    # ------------------------------------------------------------------ time
    @property
    def t(self) -> float:
        return self.k * self.h

    def step(self, dt: float) -> int:
        """Advance by dt seconds (in whole internal steps; a remainder carries over to the next
        call, so many small steps end where one big step would)."""
        return self.advance_to(self._t_req + dt)

    def advance_to(self, t: float) -> int:
        """Advance to plant time t: every internal step that ends at or before t is done.
        Returns the number of steps done. Never goes back."""
        if t > self._t_req:
            self._t_req = t
        target = int(math.floor(self._t_req / self.h + 1e-9))
        n = 0
        while self.k < target:
            self._step_once()
            n += 1
        return n

    def _normals(self) -> list[float]:
        if self._bi >= len(self._block):
            self._block = self._rng.standard_normal((4096, _N_RANDOM)).tolist()
            self._bi = 0
        z = self._block[self._bi]
        self._bi += 1
        return z

    def _step_once(self) -> None:
        p = self.p
        h = self.h
        z = self._normals()
        f = self.faults
        # ---- motor
        m = p.motor
        v = self._speed
        if f.stall:
            v = max(0.0, v - m.stall_decel_rpm_s * h)
        else:
            target = self.command_rpm if self.enabled else 0.0
            dv = (target - v) * self._a_m
            lim = m.accel_rpm_s * h
            if dv > lim:
                dv = lim
            elif dv < -lim:
                dv = -lim
            v = max(0.0, v + dv)
        self._speed = v
        # ---- dead time
        if self._nd > 0:
            n_l = self._delay[self._di]
            self._delay[self._di] = v
            self._di = (self._di + 1) % self._nd
        else:
            n_l = v
        # ---- drift
        d = p.drift
        t = (self.k + 1) * h
        if d.walk_tau_s > 0:
            self._walk += (-self._walk * h / d.walk_tau_s
                           + d.walk_sigma * math.sqrt(2.0 * h / d.walk_tau_s) * z[4])
        drift = (1.0 + d.sine_amp * math.sin(2.0 * math.pi * t / d.sine_period_s + self._phase0)
                 + self._walk) * (1.0 + d.package_per_h * self.run_s / 3600.0)
        # ---- mean tension
        tp = p.tension
        if f.yarn_break or not p.threaded:
            self.t_mean = 0.0
        else:
            excess = max(n_l - tp.offset_rpm, 0.0)
            if tp.slack_s > 0:
                if v < STANDSTILL_RPM and n_l < STANDSTILL_RPM:
                    self.slack_left_s = tp.slack_s     # standstill: the slack forms again
                elif excess > 0.0 and self.slack_left_s > 0.0:
                    self.slack_left_s -= h             # winding the slack up: no tension yet
                    excess = 0.0
            t_ss = tp.pretension_n + tp.gain_n_per_rpm * max(drift, 0.0) * excess
            self.t_mean += (t_ss - self.t_mean) * self._a_t
        # ---- ripple
        r = p.ripple
        self._phi = (self._phi + 2.0 * math.pi * v / 60.0 * r.ratio_i * r.harmonic_h * h) % (2.0 * math.pi)
        # ---- wear clock and μ
        w = p.wear
        # the hook wears while yarn runs over it: not while the slack is wound up
        running = (v >= w.wear_min_rpm and not f.yarn_break and p.threaded
                   and self.slack_left_s <= 0.0)
        if running:
            if self.first_run_t is None:
                self.first_run_t = t
            self.run_s += h
            self.wear_s += h * p.time_scale
            if self.onset_t is None and self.wear_s >= self.profile.onset_s:
                self.onset_t = t
        if w.jitter_tau_s > 0:
            self._jit += (-self._jit * h / w.jitter_tau_s
                          + w.jitter_sigma * math.sqrt(2.0 * h / w.jitter_tau_s) * z[2])
        if w.run_in_jitter_tau_s > 0:
            self._rij += (-self._rij * h / w.run_in_jitter_tau_s
                          + math.sqrt(2.0 * h / w.run_in_jitter_tau_s) * z[3])
        self.k += 1
        self._update_readings(z)
        if self.trace_enabled and self.k % self._trace_every == 0:
            self._trace.append(self.trace_row())

    def _update_readings(self, z) -> None:
        p = self.p
        w = p.wear
        prof = self.profile
        u = self.wear_s
        mu = prof.mu(u)
        mu += self._jit + w.run_in_jitter * math.exp(-u / (2.0 * prof.run_in_tau_s)) * self._rij
        tm = self.t_mean
        if p.t_set > 0 and tm > 0:
            fac = 1.0 + p.tension.mu_tension_coeff * (tm / p.t_set - 1.0)
            mu *= min(max(fac, 0.8), 1.2)
        mu = max(mu, 0.0)
        self.mu_true = mu
        tm_r = tm * (1.0 + p.ripple.amplitude * math.sin(self._phi))
        e = math.exp(mu * self._theta)
        t1 = 2.0 * tm_r / (1.0 + e)
        t2 = t1 * e
        self.t1_true, self.t2_true = t1, t2
        s = p.sensor
        fs = s.full_scale_n
        if self.faults.saturate:
            self.ch1 = self.ch2 = fs
            return
        self.ch1 = self._quantise(s.gain_ch1 * t1 + s.offset_ch1 + s.noise_n * z[0], s.resolution_n, fs)
        self.ch2 = self._quantise(s.gain_ch2 * t2 + s.offset_ch2 + s.noise_n * z[1], s.resolution_n, fs)

    @staticmethod
    def _quantise(x: float, res: float, fs: float) -> float:
        if res > 0:
            x = round(x / res) * res
        return min(max(x, -fs), fs)

    # ------------------------------------------------------------------ trace and truth
    def trace_row(self) -> tuple:
        f = self.faults
        flags = "|".join(n for n in ("yarn_break", "saturate", "stall", "swap_channels") if getattr(f, n))
        ch1, ch2 = self.tensions()
        return (round(self.t, 6), round(self.command_rpm, 3), round(self._speed, 3), int(self.enabled),
                round(self.t_mean, 6), ch1, ch2, round(self.mu_true, 6), round(self.wear_s, 3), flags)

    def drain_trace(self) -> list[tuple]:
        rows, self._trace = self._trace, []
        return rows

    def truth(self, delta: float = 0.25) -> dict[str, Any]:
        """Ground truth of this sample (JSON-able). Times: ``*_wear_s`` in wear (life) seconds,
        ``*_run_s`` in running seconds of this plant (= wear / time_scale; with the yarn running
        from the start of a test these are the test's own times), ``*_t`` in plant time."""
        prof = self.profile
        ts = self.p.time_scale
        cross = prof.crossing_s(delta)
        return {
            "seed": self.seed,
            "grade": self.p.grade,
            "t_set": self.p.t_set,
            "time_scale": ts,
            "theta_deg": self.p.theta_deg,
            "mu_ss": prof.mu_ss,
            "mu_at_onset": prof.base(prof.onset_s),
            "delta": delta,
            "table_life_s": prof.table_life_s,
            "onset_wear_s": prof.onset_s,
            "onset_run_s": prof.onset_s / ts,
            "cross_wear_s": cross,
            "cross_run_s": cross / ts,
            "run_in_wear_s": 2.0 * prof.run_in_tau_s * math.log(max(self.p.wear.run_in_jitter, 1e-9) / 0.003)
            if self.p.wear.run_in_jitter > 0.003 else 0.0,
            "profile": asdict(prof),
            "first_run_t": self.first_run_t,
            "onset_t": self.onset_t,
            "t": self.t,
            "run_s": self.run_s,
            "wear_s": self.wear_s,
        }


def params_from_dict(d: dict[str, Any]) -> PlantParams:
    """PlantParams from a (validated) mapping: top-level fields and nested sections."""
    kw: dict[str, Any] = {}
    for f in fields(PlantParams):
        if f.name not in d:
            continue
        if f.name in SECTIONS:
            kw[f.name] = SECTIONS[f.name](**d[f.name])
        else:
            kw[f.name] = d[f.name]
    return PlantParams(**kw)
