"""The wear-life method of METHOD.md in two forms: streaming (slot by slot) and batch (numpy).

Both are pure. They share the thresholds (``MethodParams``), the window rule, the baseline rule
and the result assembly (``rules`` and ``_finish``); a property test proves that they agree.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import rules as R
from .forecast import Forecaster, ForecastOut
from .params import STOPPED, MethodParams
from .wear import WearTracker, WindowOut

# ----------------------------------------------------------------------------------------------
# Results
# ----------------------------------------------------------------------------------------------

STATUS_FAILURE = "failure"
STATUS_NO_FAILURE = "no_failure"
STATUS_NO_BASELINE = "no_baseline"
STATUS_ABORTED = "aborted"


@dataclass
class Result:
    """The result of one test (METHOD.md §6, keys of §10)."""
    status: str
    mu_ss: float | None
    mu_th: float | None
    k_b: int | None
    stable_first: int | None
    stable_last: int | None
    k_life: int | None
    t_life: float | None
    n_slots: int
    n_valid: int
    reasons: dict[str, int]
    interrupted: bool
    stop_slot: int | None
    stop_reasons: list[str] | None
    headroom: float | None = None
    t_cross: float | None = None
    warn_slot: int | None = None
    warn_reasons: list[str] | None = None
    end_p10: float | None = None
    end_p50: float | None = None
    end_p90: float | None = None
    p_end: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "status": self.status, "mu_ss": self.mu_ss, "mu_th": self.mu_th, "k_b": self.k_b,
            "stable_first": self.stable_first, "stable_last": self.stable_last,
            "k_life": self.k_life, "t_life": self.t_life, "n_slots": self.n_slots,
            "n_valid": self.n_valid, "reasons": dict(self.reasons),
            "interrupted": self.interrupted, "stop_slot": self.stop_slot,
            "stop_reasons": None if self.stop_reasons is None else list(self.stop_reasons),
            "headroom": self.headroom, "t_cross": self.t_cross, "warn_slot": self.warn_slot,
            "warn_reasons": None if self.warn_reasons is None else list(self.warn_reasons),
            "end_p10": self.end_p10, "end_p50": self.end_p50, "end_p90": self.end_p90,
            "p_end": self.p_end,
        }


def _finish(p: MethodParams, *, n_slots: int, n_valid: int, reason_counts: dict[str, int],
            stable_first: int | None, k_b: int | None, mu_ss: float | None,
            k_life: int | None, stop_slot: int | None, stop_mask: int,
            end_slot: int | None, wear: WearTracker | None, forecast: Forecaster) -> Result:
    """One place that turns the method's findings into a status (§3, §5, §5a, §5b, §6).

    ``end_slot``: the test was ended on purpose there (§3); it applies only when the analysed
    slots reached it without a protection stop."""
    mu_th = None if mu_ss is None else R.threshold(mu_ss, p)
    stop_reasons = None if stop_slot is None else R.reason_names(stop_mask)
    if stop_slot is None and end_slot is not None and n_slots >= end_slot:
        stop_slot = end_slot
        stop_reasons = [STOPPED]
    interrupted = False
    if k_life is not None:
        status = STATUS_FAILURE
        interrupted = stop_slot is not None
    elif stop_slot is not None:
        status = STATUS_ABORTED
    elif k_b is None:
        status = STATUS_NO_BASELINE
    else:
        status = STATUS_NO_FAILURE
    return Result(
        status=status, mu_ss=mu_ss, mu_th=mu_th, k_b=k_b,
        stable_first=stable_first, stable_last=k_b,
        k_life=k_life, t_life=None if k_life is None else k_life * p.ts,
        n_slots=n_slots, n_valid=n_valid, reasons=reason_counts, interrupted=interrupted,
        stop_slot=stop_slot, stop_reasons=stop_reasons,
        headroom=None if wear is None else wear.headroom,
        t_cross=None if wear is None else wear.t_cross,
        warn_slot=forecast.warn_slot,
        warn_reasons=None if forecast.warn_reasons is None else list(forecast.warn_reasons),
        end_p10=forecast.end_p10, end_p50=forecast.end_p50, end_p90=forecast.end_p90,
        p_end=forecast.p_end,
    )


# ----------------------------------------------------------------------------------------------
# Streaming form
# ----------------------------------------------------------------------------------------------

@dataclass
class SlotOut:
    """What the streaming form says about one slot."""
    k: int
    q: int
    mask: int
    ratio: float | None      # R = T2/T1 (diagnostic, also when invalid), None if undefined
    mu: float | None         # only when q = 1
    #: "baseline", "end_of_life", "protection_stop", "window" (a §5a window is complete: see
    #: ``window``), "forecast" (a §5b forecast time: see ``forecast``), "wear_warning" (the §5b
    #: early warning: the first due window, at most once per test, never at or after k_det)
    events: list[str] = field(default_factory=list)
    window: WindowOut | None = None   # the post-baseline window that ended with this slot
    #: the §5b forecast at the end of this slot's window; with "wear_warning" it is the warning
    #: (``forecast.warning`` true) and carries its reasons (``forecast.reasons``)
    forecast: ForecastOut | None = None


class StreamingMonitor:
    """Feed one slot at a time with :meth:`push`; memory is bounded by W_hold.

    States: ``baseline_search`` → ``monitoring`` (baseline established) → ``failed`` (t_life found,
    the test runs on) ; ``stopped`` after a protection stop; ``ended`` after t_end or end_slot.

    After the baseline, every complete window yields a :class:`WindowOut` (§5a: value, headroom,
    t_cross, headroom run) in ``SlotOut.window`` of the slot that completes it, with the event
    ``"window"``; ``wear`` holds the running figures. Every complete window from j = 0 that ends
    before the detection slot k_det yields a :class:`ForecastOut` (§5b: e10/e50/e90 and P from the
    prior, headroom, t_cross, due and its reasons) in ``SlotOut.forecast``, with the event
    ``"forecast"``, and ``"wear_warning"`` the one time the early warning fires (the first due
    window); ``forecast`` holds the running figures. A test ended on purpose (operator, PLC, MES,
    clean shutdown) ends with :meth:`stop`, whose result equals the batch form over the log with
    ``end_slot`` in its sidecar.
    """

    def __init__(self, p: MethodParams):
        self.p = p
        self._t_sat = p.t_sat
        self._t_min = p.t_min
        self._j_max = p.j_max
        self._r_min = p.r_min
        self._r_max = p.r_max
        self._theta = p.theta
        self._n_ss = p.n_ss
        self._m = p.m_windows
        self._n_tau = p.n_tau
        self._n_g = p.n_g
        self._n_stop = p.n_stop
        self._end = p.n_grid
        self._end_slot = p.end_slot
        self.k = 0                       # next slot index
        self.n_valid = 0
        self.counts = [0] * len(R.REASONS)
        self.lost = 0                    # LOST slots (gateway extension, rules.LOST)
        self._prev: tuple[float, float] | None = None   # latest non-MISSING reading
        self._unsafe_run = 0
        self._unsafe_mask = 0
        # baseline search
        self._win_mu: list[float] = []
        self._run: deque[np.ndarray] = deque()
        self.stable_first: int | None = None
        self.k_b: int | None = None
        self.mu_ss: float | None = None
        self.mu_th: float | None = None
        # persistence
        self.c = 0
        self.g = 0
        self.k_life: int | None = None
        # stop
        self.stop_slot: int | None = None
        self._stop_mask = 0
        self.windows_done = 0
        self.windows_steady_run = 0
        self.wear: WearTracker | None = None   # §5a, from the baseline on
        self.forecast = Forecaster(p)           # §5b, every window before k_det

    # -- state for display --
    @property
    def state(self) -> str:
        if self.stop_slot is not None:
            return "stopped"
        if self._end is not None and self.k >= self._end:
            return "ended"
        if self.k_life is not None:
            return "failed"
        if self.k_b is not None:
            return "monitoring"
        return "baseline_search"

    @property
    def finished(self) -> bool:
        return self.stop_slot is not None or (self._end is not None and self.k >= self._end)

    def push(self, present: bool, t1: float = float("nan"), t2: float = float("nan"),
             lost: bool = False) -> SlotOut:
        """Process the next slot. ``present`` False (or a non-finite value) makes it MISSING;
        ``lost`` makes it LOST (its reading could not be recorded: ``rules.LOST``)."""
        if self.finished:
            raise RuntimeError("the test has ended; no further slots are analysed")
        k = self.k
        self.k = k + 1
        mask = 0
        ratio = None
        mu = None
        events: list[str] = []
        # NaN and inf fail the self-comparisons below: x - x == 0 only for finite x
        if lost:
            mask = R.LOST
        elif not present or not (t1 - t1 == 0.0 and t2 - t2 == 0.0):
            mask = R.MISSING
        else:
            if t1 >= self._t_sat or t2 >= self._t_sat:
                mask |= R.SATURATED
            if t1 < self._t_min or t2 < self._t_min:
                mask |= R.LOW_TENSION
            prev = self._prev
            if prev is not None and (abs(t1 - prev[0]) > self._j_max or abs(t2 - prev[1]) > self._j_max):
                mask |= R.JUMP
            self._prev = (t1, t2)
            if t1 > 0:
                ratio = t2 / t1
                if ratio < self._r_min:
                    mask |= R.RATIO_LOW
                if ratio > self._r_max:
                    mask |= R.RATIO_HIGH
        q = 1 if mask == 0 else 0
        if q:
            # a valid slot has its ratio: T1 >= T_min, and T1 > 0 unless t_min_ratio = 0 and T1 = 0
            # (that one case stops here, as np.log(None) did before)
            assert ratio is not None, "valid slot without a ratio (t_min_ratio = 0 and T1 = 0)"
            self.n_valid += 1
            mu = float(R.log_ratio_mu(ratio, self._theta))
        elif lost:
            self.lost += 1
        else:
            for i, (bit, _) in enumerate(R.REASONS):
                if mask & bit:
                    self.counts[i] += 1

        # protection stop (§3); a LOST slot neither counts toward nor breaks an unsafe run
        if lost:
            pass
        elif mask & R.UNSAFE:
            self._unsafe_run += 1
            self._unsafe_mask |= mask & R.UNSAFE
            if self._unsafe_run > self._n_stop:
                self.stop_slot = k
                self._stop_mask = self._unsafe_mask
                events.append("protection_stop")
                return SlotOut(k, q, mask, ratio, mu, events)
        else:
            self._unsafe_run = 0
            self._unsafe_mask = 0

        # persistent exceedance (§5)
        # (k_b and mu_th are set together; mu is set exactly on valid slots, q = 1)
        if self.k_b is not None and self.k_life is None and self.mu_th is not None:
            if mu is not None and mu > self.mu_th:
                self.c += 1
                self.g = 0
                if self.c >= self._n_tau:
                    self.k_life = k - self._n_tau + 1
                    events.append("end_of_life")
            else:
                self.g += 1
                if self.g > self._n_g:
                    self.c = 0
                    self.g = 0

        # windows: baseline search (§4), then headroom (§5a)
        if mu is not None:
            self._win_mu.append(mu)
        if (k + 1) % self._n_ss == 0:
            win = np.array(self._win_mu, dtype=np.float64)
            self._win_mu = []
            self.windows_done += 1
            j = k // self._n_ss
            w = None
            if self.wear is not None:
                w = self.wear.add(j, win.size, R.window_value(win, self.p))
                events.append("window")
            else:
                self._baseline_window(k, win, events)
            fc = None
            # §5b: only windows whose last slot lies before k_det (k_life is set at k_det)
            if self.k_life is None:
                fc = self.forecast.add(j, w)
                events.append("forecast")
                if fc.warning:
                    if self.wear is not None:
                        self.wear.warn_slot = fc.last_slot
                    events.append("wear_warning")
            return SlotOut(k, q, mask, ratio, mu, events, w, fc)
        return SlotOut(k, q, mask, ratio, mu, events)

    def _baseline_window(self, k: int, win: np.ndarray, events: list[str]) -> None:
        """§4: a complete window during the baseline search."""
        if R.window_steady(win, self.p):
            self._run.append(win)
            if len(self._run) == self._m:
                self.k_b = k
                self.stable_first = k - self._m * self._n_ss + 1
                self.mu_ss = R.baseline_value(np.concatenate(list(self._run)))
                self.mu_th = R.threshold(self.mu_ss, self.p)
                self.wear = WearTracker(self.p, self.mu_ss, self.mu_th)
                self._run.clear()
                events.append("baseline")
        else:
            self._run.clear()
        self.windows_steady_run = len(self._run)

    def reason_counts(self) -> dict[str, int]:
        out = {name: self.counts[i] for i, name in enumerate(R.REASON_NAMES)}
        if self.lost:
            out[R.LOST_NAME] = self.lost
        return out

    def result(self) -> Result:
        """The result over the slots pushed so far. With a planned end (t_end) not yet reached, the
        missing remainder counts as MISSING: call :meth:`close` to push it first."""
        return _finish(self.p, n_slots=self.k, n_valid=self.n_valid,
                       reason_counts=self.reason_counts(), stable_first=self.stable_first,
                       k_b=self.k_b, mu_ss=self.mu_ss, k_life=self.k_life,
                       stop_slot=self.stop_slot, stop_mask=self._stop_mask,
                       end_slot=self._end_slot, wear=self.wear, forecast=self.forecast)

    def close(self, n_slots: int | None = None) -> Result:
        """End the test: slots up to the planned end (or up to ``n_slots``) that never came are
        MISSING (§3: a log that stops early ends as ``aborted``)."""
        target = self._end if self._end is not None else n_slots
        if target is not None:
            while not self.finished and self.k < target:
                self.push(False)
        return self.result()

    def stop(self, end_slot: int | None = None) -> Result:
        """End the test on purpose (§3) before its planned end: the test has exactly ``end_slot``
        slots (default: the slots pushed so far; slots up to it that never came are MISSING).
        Write the same ``end_slot`` into the sidecar so that the offline result is the same."""
        if end_slot is None:
            end_slot = self.k
        if end_slot < self.k:
            raise ValueError(f"end_slot {end_slot} < {self.k} slots already analysed")
        if self.stop_slot is None:
            self._end = end_slot          # exactly end_slot slots; t_end adds nothing (§3)
        self._end_slot = end_slot
        return self.close()


def run_streaming(p: MethodParams, present: np.ndarray, t1: np.ndarray, t2: np.ndarray,
                  lost: np.ndarray | None = None) -> Result:
    """Convenience: the streaming form over slot arrays, as the station would feed it (``lost``:
    the LOST slots, ``rules.LOST``)."""
    mon = StreamingMonitor(p)
    n = len(present)
    pr = present.tolist()
    a = t1.tolist()
    b = t2.tolist()
    lo = [False] * n if lost is None else lost.tolist()
    for k in range(n):
        if mon.finished:
            break
        mon.push(pr[k], a[k], b[k], lo[k])
    return mon.close(n)


# ----------------------------------------------------------------------------------------------
# Batch form
# ----------------------------------------------------------------------------------------------

@dataclass
class SlotArrays:
    """A log laid on the slot grid."""
    present: np.ndarray   # bool
    t1: np.ndarray        # float64, NaN where absent
    t2: np.ndarray
    duplicates: int = 0   # readings that landed in an already filled slot (the later one won)
    out_of_grid: int = 0  # readings before slot 0 or after the planned end
    lost: np.ndarray | None = None   # bool, the LOST slots (rules.LOST); None: none


def mark_lost(s: SlotArrays, spans: Any) -> SlotArrays:
    """The slots of ``spans`` ([first, last] slot pairs, the sidecar's ``lost_spans``) are LOST
    (``rules.LOST``): their readings, if any, are ignored. Spans beyond the grid are cut; a
    malformed span is an error (ValueError)."""
    n = s.present.size
    lost = np.zeros(n, dtype=bool) if s.lost is None else s.lost.copy()
    for sp in spans or ():
        if (not isinstance(sp, (list, tuple)) or len(sp) != 2
                or not all(isinstance(x, int) and not isinstance(x, bool) for x in sp)
                or sp[0] < 0 or sp[1] < sp[0]):
            raise ValueError(f"lost span {sp!r}: expected [first slot, last slot], 0 <= first <= last")
        lost[min(sp[0], n):min(sp[1] + 1, n)] = True
    if not lost.any():
        return s
    present = s.present & ~lost
    t1 = np.where(lost, np.nan, s.t1)
    t2 = np.where(lost, np.nan, s.t2)
    return SlotArrays(present, t1, t2, s.duplicates, s.out_of_grid, lost)


def to_slots(t: np.ndarray, t1: np.ndarray, t2: np.ndarray, p: MethodParams) -> SlotArrays:
    """§1: assign readings to slots round(t / Ts); the later of two readings in a slot wins.
    Without t_end the grid ends at the last reading's slot; with t_end it has t_end / Ts slots;
    with end_slot (§3, a test ended on purpose) exactly end_slot slots."""
    tf = np.isfinite(t)
    k = R.slot_index(np.where(tf, t, -1.0), p.ts)
    ok = tf & (k >= 0)
    end = p.n_grid
    if end is not None:
        ok &= k < end
    out = int(np.count_nonzero(~ok))
    if out:
        k, t1, t2 = k[ok], t1[ok], t2[ok]
    n = end if end is not None else (int(k.max()) + 1 if k.size else 0)
    present = np.zeros(n, dtype=bool)
    a = np.full(n, np.nan)
    b = np.full(n, np.nan)
    # fancy assignment keeps the last write for repeated indices (row order = arrival order)
    present[k] = True
    a[k] = t1
    b[k] = t2
    dup = int(k.size - np.count_nonzero(present))
    return SlotArrays(present, a, b, dup, out)


def gate_arrays(present: np.ndarray, t1: np.ndarray, t2: np.ndarray,
                p: MethodParams, lost: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """§2 over whole arrays: returns (mask uint8, ratio with NaN where undefined, μ with NaN where
    invalid). ``lost``: LOST slots (``rules.LOST``, mask exactly LOST; give them present False)."""
    n = present.size
    with np.errstate(invalid="ignore", divide="ignore"):
        fin = present & np.isfinite(t1) & np.isfinite(t2)
        mask = np.where(fin, 0, R.MISSING).astype(np.uint8)
        sat = fin & ((t1 >= p.t_sat) | (t2 >= p.t_sat))
        low = fin & ((t1 < p.t_min) | (t2 < p.t_min))
        # JUMP against the latest earlier non-MISSING slot
        idx = np.where(fin, np.arange(n), -1)
        last = np.maximum.accumulate(idx) if n else idx
        prev = np.empty(n, dtype=np.int64)
        if n:
            prev[0] = -1
            prev[1:] = last[:-1]
        has_prev = fin & (prev >= 0)
        pi = np.where(has_prev, prev, 0)
        jump = has_prev & ((np.abs(t1 - t1[pi]) > p.j_max) | (np.abs(t2 - t2[pi]) > p.j_max))
        rdef = fin & (t1 > 0)
        ratio = np.where(rdef, t2 / np.where(rdef, t1, 1.0), np.nan)
        rlow = rdef & (ratio < p.r_min)
        rhigh = rdef & (ratio > p.r_max)
    mask |= (sat * R.SATURATED).astype(np.uint8)
    mask |= (low * R.LOW_TENSION).astype(np.uint8)
    mask |= (jump * R.JUMP).astype(np.uint8)
    mask |= (rlow * R.RATIO_LOW).astype(np.uint8)
    mask |= (rhigh * R.RATIO_HIGH).astype(np.uint8)
    if lost is not None:
        mask[lost] = R.LOST
    valid = mask == 0
    mu = np.full(n, np.nan)
    mu[valid] = R.log_ratio_mu(ratio[valid], p.theta)
    return mask, ratio, mu


def _protection_stop(mask: np.ndarray, p: MethodParams) -> tuple[int | None, int]:
    """First slot of a run of more than n_stop consecutive unsafe slots, and the run's reasons.
    LOST slots are transparent (neither count toward nor break a run): the run is found over the
    other slots and mapped back."""
    lost = (mask & R.LOST) != 0
    if lost.any():
        idx = np.flatnonzero(~lost)
        s, m = _protection_stop(mask[idx], p)
        return (None, 0) if s is None else (int(idx[s]), m)
    unsafe = (mask & R.UNSAFE) != 0
    need = p.n_stop + 1
    n = unsafe.size
    if n < need:
        return None, 0
    # run length ending at each slot: cumulative count minus the count at the last safe slot
    cs = np.cumsum(unsafe, dtype=np.int64)
    reset = np.where(~unsafe, cs, 0)
    runlen = cs - np.maximum.accumulate(reset)
    hits = np.flatnonzero(runlen >= need)
    if hits.size == 0:
        return None, 0
    s = int(hits[0])
    start = s - need + 1
    run_mask = int(np.bitwise_or.reduce(mask[start:s + 1] & R.UNSAFE))
    return s, run_mask


def _baseline(mu: np.ndarray, valid: np.ndarray, n_usable: int,
              p: MethodParams) -> tuple[int, int, float] | tuple[None, None, None]:
    """§4 over windows that are complete and end before slot n_usable. Returns
    (stable_first, k_b, mu_ss) or (None, None, None)."""
    n_ss = p.n_ss
    m = p.m_windows
    n_win = n_usable // n_ss
    run = 0
    for j in range(n_win):
        a, b = j * n_ss, (j + 1) * n_ss
        v = valid[a:b]
        if np.count_nonzero(v) >= R.n_eff_required(p) and R.window_steady(mu[a:b][v], p):
            run += 1
            if run == m:
                first = (j - m + 1) * n_ss
                k_b = b - 1
                seg = mu[first:b][valid[first:b]]
                return first, k_b, R.baseline_value(seg)
        else:
            run = 0
    return None, None, None


def _persistence(b: np.ndarray, n_tau: int, n_g: int) -> int | None:
    """§5 counter over b (slots k_b+1 …): index (into b) of the slot where c first reaches N_τ.
    c counts b = 1 slots; a run of more than N_g zeros resets it."""
    n = b.size
    if n == 0:
        return None
    zero = ~b
    # position of each zero inside its zero-run (1-based); 0 on ones
    cz = np.cumsum(zero, dtype=np.int64)
    base = np.maximum.accumulate(np.where(b, cz, 0))
    zpos = np.where(zero, cz - base, 0)
    reset = zpos == n_g + 1          # g exceeds N_g here: c ← 0 (later resets in the same run are no-ops)
    seg = np.cumsum(reset)
    ones = np.cumsum(b, dtype=np.int64)
    # ones counted since the last reset
    ones_at_reset = np.maximum.accumulate(np.where(reset, ones, 0))
    c = ones - ones_at_reset
    hits = np.flatnonzero(b & (c >= n_tau))
    del seg
    return int(hits[0]) if hits.size else None


@dataclass
class GatedSlots:
    """The part of the batch form that does not depend on δ (§2–§4): gating, protection stop and
    baseline. :func:`life_result` finishes it for any δ, so a sensitivity study gates once."""
    p: MethodParams
    mask: np.ndarray          # uint8 reason mask per analysed slot (cut at a protection stop)
    ratio: np.ndarray         # R = T2/T1, NaN where undefined (diagnostic)
    mu: np.ndarray            # μ, NaN where invalid
    stop_slot: int | None
    stop_mask: int
    stable_first: int | None
    k_b: int | None
    mu_ss: float | None
    windows: list[tuple[int, int, float | None]] = field(default_factory=list)  # §5a (j, N_eff, μ̃)
    n_usable: int = 0         # windows must end before this slot (§4: complete, before a stop)


def _post_windows(mu: np.ndarray, valid: np.ndarray, k_b: int, n_usable: int,
                  p: MethodParams) -> list[tuple[int, int, float | None]]:
    """§5a: the complete windows after Ω_stable that end before slot n_usable, as (j, N_eff, μ̃)."""
    n_ss = p.n_ss
    out = []
    for j in range((k_b + 1) // n_ss, n_usable // n_ss):
        a, b = j * n_ss, (j + 1) * n_ss
        win = mu[a:b][valid[a:b]]
        out.append((j, int(win.size), R.window_value(win, p)))
    return out


def gate_and_baseline(s: SlotArrays, p: MethodParams) -> GatedSlots:
    mask, ratio, mu = gate_arrays(s.present, s.t1, s.t2, p, s.lost)
    stop_slot, stop_mask = _protection_stop(mask, p)
    n_slots = mask.size if stop_slot is None else stop_slot + 1
    mask = mask[:n_slots]
    mu = mu[:n_slots]
    ratio = ratio[:n_slots]
    valid = mask == 0
    # windows must be complete and end before a protection stop
    n_usable = n_slots if stop_slot is None else stop_slot
    stable_first, k_b, mu_ss = _baseline(mu, valid, n_usable, p)
    windows = [] if k_b is None else _post_windows(mu, valid, k_b, n_usable, p)
    return GatedSlots(p, mask, ratio, mu, stop_slot, stop_mask, stable_first, k_b, mu_ss, windows,
                      n_usable)


def life_result(g: GatedSlots, delta: float | None = None) -> Result:
    """§5–§6 over gated slots, with the δ of the gating parameters or the one given."""
    return life_detail(g, delta)[0]


def life_detail(g: GatedSlots, delta: float | None = None
                ) -> tuple[Result, list[WindowOut], list[ForecastOut]]:
    """:func:`life_result` with the figures the streaming form publishes as it goes: every §5a
    window after Ω_stable and every §5b forecast time, in order."""
    p = g.p if delta is None else g.p.with_delta(delta)
    mask, mu, k_b, mu_ss = g.mask, g.mu, g.k_b, g.mu_ss
    valid = mask == 0
    k_life = None
    wear = None
    outs: dict[int, WindowOut] = {}
    if k_b is not None and mu_ss is not None:    # set together by the baseline search
        mu_th = R.threshold(mu_ss, p)
        wear = WearTracker(p, mu_ss, mu_th)
        for j, n_eff, value in g.windows:
            outs[j] = wear.add(j, n_eff, value)
        with np.errstate(invalid="ignore"):
            bb = valid[k_b + 1:] & (mu[k_b + 1:] > mu_th)
        i = _persistence(bb, p.n_tau, p.n_g)
        if i is not None:
            k_life = k_b + 1 + i - p.n_tau + 1
    forecast = Forecaster(p)
    fouts = [forecast.add(j, outs.get(j)) for j in forecast_windows(p, g.n_usable, k_life)]
    counts = {name: int(np.count_nonzero(mask & bit)) for bit, name in R.REASONS}
    n_lost = int(np.count_nonzero(mask & R.LOST))
    if n_lost:
        counts[R.LOST_NAME] = n_lost
    res = _finish(p, n_slots=mask.size, n_valid=int(np.count_nonzero(valid)),
                  reason_counts=counts, stable_first=g.stable_first, k_b=k_b, mu_ss=g.mu_ss,
                  k_life=k_life, stop_slot=g.stop_slot, stop_mask=g.stop_mask,
                  end_slot=p.end_slot, wear=wear, forecast=forecast)
    return res, list(outs.values()), fouts


def forecast_windows(p: MethodParams, n_usable: int, k_life: int | None) -> range:
    """§5b: the forecast times: every complete window j = 0, 1, … that ends before slot n_usable
    and, with t_life found, whose last slot lies before k_det = k_life + N_τ − 1."""
    n_ss = p.n_ss
    n = n_usable // n_ss
    if k_life is not None:
        k_det = k_life + p.n_tau - 1
        n = min(n, k_det // n_ss)      # last slot (j+1)·N_ss − 1 < k_det  ⇔  j + 1 ≤ k_det // N_ss
    return range(n)


def analyze_slots(s: SlotArrays, p: MethodParams) -> Result:
    """The batch form over a log on the slot grid."""
    return life_result(gate_and_baseline(s, p))


def analyze_readings(t: np.ndarray, t1: np.ndarray, t2: np.ndarray, p: MethodParams) -> Result:
    return analyze_slots(to_slots(t, t1, t2, p), p)
