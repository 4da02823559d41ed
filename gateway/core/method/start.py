"""METHOD.md §3a, the start of a test, as a pure state machine: numbers in, numbers out.

The runtime feeds one call per 20 ms slot and acts on the phase it gets back:

    seq = StartSequence(params)             # phase "zero_check" (or "spin_up" if zero_check off)
    motor off:  seq.zero_slot(present, t1, t2)         while seq.phase == "zero_check"
    motor on:   seq.spin_slot(present, t1, t2, y)      while seq.phase == "spin_up"
                (y: the controller's pre-filtered mean tension, METHOD.md §8.2)
    "settled": the NEXT slot is slot 0 of the test; ``sidecar()`` holds the offsets and the settle
               time for the log's sidecar.
    "failed":  ``reason`` says why (the `start_failed` event text); stop the motor, record nothing.

Rules (one place, each from §3a):
- zero check: the mean of each channel over ``zero_window`` = 1 s of slots must lie within
  ±zero_tol of 0 (`zero check failed: T1 0.061 N`). A meter that gives fewer than half of the
  readings of that second fails too (no mean can be trusted). The offsets are information, never
  subtracted.
- settle: slot 0 follows the first ``settle_time`` of slots with y within ±settle_band·T_set of
  T_set and no protection-stop condition. y out of the band resets the count; a protection-stop
  condition (more than ``stop_after`` of consecutive unsafe slots — MISSING, LOW_TENSION,
  SATURATED) resets it; a shorter unsafe run holds it (y is then not observed: such slots do not
  count toward settle_time, so a test never starts in the middle of a dropout).
- swapped channels: checked when the tension has settled, over the spin-up slots whose readings
  are under tension (both present and ≥ T_min, so the noise of a slack yarn does not vote): T2 < T1
  in most of them (more than half) refuses the start (`channels swapped? set meter.swap_channels`).
- timeout: not settled after ``start_timeout`` of spin-up: `no tension after 30 s: T̄ 0.02 N`
  (T̄: the mean of (T1 + T2)/2 over the last second) when T̄ is under the settle band, else
  `tension not settled after 30 s: T̄ 0.62 N`.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

from .params import MethodParams

ZERO_WINDOW_S = 1.0          # fixed by METHOD.md §10

ZERO_CHECK = "zero_check"
SPIN_UP = "spin_up"
SETTLED = "settled"
FAILED = "failed"


def _finite(x: float) -> bool:
    return x - x == 0.0


@dataclass(frozen=True)
class StartOutcome:
    """What the sequence decided (``phase`` settled or failed), for events and the sidecar."""
    phase: str
    reason: str | None               # why the start failed (None when settled)
    offsets: dict[str, float] | None  # zero offsets found {"T1": N, "T2": N} (None: no zero check)
    settle_s: float | None           # spin-up time until slot 0, s
    spin_slots: int                  # slots of spin-up fed


class StartSequence:
    def __init__(self, p: MethodParams):
        self.p = p
        self._n_zero = max(1, int(round(ZERO_WINDOW_S / p.ts)))
        self._n_settle = max(1, int(round(p.settle_time / p.ts)))
        self._n_timeout = max(1, int(round(p.start_timeout / p.ts)))
        self._n_stop = p.n_stop
        self._lo = p.t_set * (1.0 - p.settle_band)
        self._hi = p.t_set * (1.0 + p.settle_band)
        self.phase = ZERO_CHECK if p.zero_check else SPIN_UP
        self.reason: str | None = None
        self.offsets: dict[str, float] | None = None
        # zero check
        self._z_slots = 0
        self._z_n = 0
        self._z_sum1 = 0.0
        self._z_sum2 = 0.0
        # spin-up
        self.spin_slots = 0
        self._in_band = 0
        self._unsafe_run = 0
        self._tensioned = 0
        self._swapped = 0
        self._recent: deque[float] = deque(maxlen=self._n_zero)   # (T1+T2)/2 of the last second

    # ------------------------------------------------------------------ zero check (motor off)
    def zero_slot(self, present: bool, t1: float = float("nan"), t2: float = float("nan")) -> str:
        """One slot of the zero check; returns the phase (zero_check, spin_up or failed)."""
        if self.phase != ZERO_CHECK:
            raise RuntimeError(f"zero_slot in phase {self.phase}")
        self._z_slots += 1
        if present and _finite(t1) and _finite(t2):
            self._z_n += 1
            self._z_sum1 += t1
            self._z_sum2 += t2
        if self._z_slots < self._n_zero:
            return self.phase
        if 2 * self._z_n < self._n_zero:
            return self._fail(f"zero check failed: {self._z_n} of {self._n_zero} readings in "
                              f"{ZERO_WINDOW_S:g} s")
        m1, m2 = self._z_sum1 / self._z_n, self._z_sum2 / self._z_n
        self.offsets = {"T1": m1, "T2": m2}
        bad = [f"{name} {v:.3f} N" for name, v in (("T1", m1), ("T2", m2)) if abs(v) > self.p.zero_tol]
        if bad:
            return self._fail("zero check failed: " + ", ".join(bad) +
                              f" (allowed ±{self.p.zero_tol:g} N)")
        self.phase = SPIN_UP
        return self.phase

    # ------------------------------------------------------------------ spin-up (loop closed)
    def spin_slot(self, present: bool, t1: float, t2: float, y: float) -> str:
        """One slot of the spin-up; returns the phase (spin_up, settled or failed). After
        ``settled`` the next slot is slot 0."""
        if self.phase != SPIN_UP:
            raise RuntimeError(f"spin_slot in phase {self.phase}")
        p = self.p
        self.spin_slots += 1
        ok = present and _finite(t1) and _finite(t2)
        unsafe = (not ok or t1 < p.t_min or t2 < p.t_min or t1 >= p.t_sat or t2 >= p.t_sat)
        if ok:
            self._recent.append((t1 + t2) / 2.0)
            if t1 >= p.t_min and t2 >= p.t_min:
                self._tensioned += 1
                if t2 < t1:
                    self._swapped += 1
        self._unsafe_run = self._unsafe_run + 1 if unsafe else 0
        if self._unsafe_run > self._n_stop:            # a protection-stop condition
            self._in_band = 0
        elif not (_finite(y) and self._lo <= y <= self._hi):
            self._in_band = 0
        elif not unsafe:                                # an unsafe slot holds the count
            self._in_band += 1
        if self._in_band >= self._n_settle:
            if 2 * self._swapped > self._tensioned:
                return self._fail(f"channels swapped? set meter.swap_channels (T2 < T1 in "
                                  f"{self._swapped} of {self._tensioned} spin-up readings)")
            self.phase = SETTLED
            return self.phase
        if self.spin_slots >= self._n_timeout:
            t = f"{p.start_timeout:g} s"
            if not self._recent:
                return self._fail(f"no tension after {t}: no readings from the meter")
            mean = round(sum(self._recent) / len(self._recent), 2) + 0.0    # never "-0.00"
            what = "no tension" if mean < self._lo else "tension not settled"
            return self._fail(f"{what} after {t}: T̄ {mean:.2f} N (T_set {p.t_set:g} N "
                              f"± {p.settle_band * p.t_set:g} N)")
        return self.phase

    def _fail(self, reason: str) -> str:
        self.phase = FAILED
        self.reason = reason
        return self.phase

    @property
    def motor_on(self) -> bool:
        """The take-up runs during the spin-up and after it; never during the zero check or after
        a failed start."""
        return self.phase in (SPIN_UP, SETTLED)

    @property
    def done(self) -> bool:
        return self.phase in (SETTLED, FAILED)

    def outcome(self) -> StartOutcome:
        settle = self.spin_slots * self.p.ts if self.phase == SETTLED else None
        return StartOutcome(self.phase, self.reason, self.offsets, settle, self.spin_slots)

    def sidecar(self) -> dict[str, Any]:
        """Information for the log's sidecar (never used by the analysis, §3a)."""
        out: dict[str, Any] = {"settle_s": None if self.phase != SETTLED else self.spin_slots * self.p.ts}
        if self.offsets is not None:
            out["zero_offsets_n"] = dict(self.offsets)
        return out
