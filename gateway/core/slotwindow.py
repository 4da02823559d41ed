"""The one per-window aggregation of slot records (pure: records in, figures out; no clock, no I/O).

Every output that reports slots by the window — MQTT telemetry, a Sparkplug device's data, a fleet
worker's SLOTS frames, the PLC's test counters, the Prometheus slot counters — adds each
:class:`~gateway.core.records.SlotRecord` to a :class:`SlotWindow` (O(1), a few attribute updates) and
reads its figures when the window closes; when and how a window closes is the output's (an
interval on its clock, a number of slots, a test, the life of the process). The figures are sums
and counts, so each output's derived values (means, ratios) are computed from them the same way
every time; the window never drops a slot.
"""
from __future__ import annotations

import math

from .catalog import MEANS, SlotSource
from .method.rules import REASONS
from .records import SlotRecord

__all__ = ["SlotWindow"]


class SlotWindow:
    """The figures of the slot records added since ``t0`` (the opening time, as its owner counts
    time; not read here).

    - ``n``: slots; ``n_present``: slots with a meter reading; ``n_read``: of those, the ones
      whose both channels are numbers (``s1``, ``s2``: their sums, N; ``sm``: the sum of their
      mean tension, ``mn``/``mx``: its extremes);
    - ``n_valid``: valid slots (q = 1); ``n_mu``/``s_mu``: those with a friction value, and its sum;
    - ``counts``: slots per reason of ``gateway.core.method.rules.REASONS`` (same order);
    - ``n_sat``: slots whose control output was clamped; ``speed_cmd``/``speed_act``: of the
      last slot;
    - ``late_max``: the latest poll start, s (0 when none was late); ``rtt_max``: the longest meter
      round trip of a present slot, s (0 when none was measured);
    - ``means``: the readings of the slot records whose mean the window keeps (the catalog's slot
      rows with a ``mean``: a new channel's row, gateway/core/catalog.py), ``m_sum``/``m_n``:
      their sums and counts over the slots where each is a number (:meth:`mean`).
    """
    __slots__ = ("t0", "n", "n_present", "n_read", "s1", "s2", "sm", "mn", "mx", "n_valid", "n_mu",
                 "s_mu", "counts", "n_sat", "speed_cmd", "speed_act", "late_max", "rtt_max",
                 "means", "m_sum", "m_n")
    t0: float
    n: int
    n_present: int
    n_read: int
    n_valid: int
    n_mu: int
    n_sat: int
    s1: float
    s2: float
    sm: float
    s_mu: float
    mn: float
    mx: float
    counts: list[int]
    speed_cmd: float
    speed_act: float
    late_max: float
    rtt_max: float
    means: tuple[SlotSource, ...]
    m_sum: list[float]
    m_n: list[int]

    def __init__(self, t0: float = 0.0, means: tuple[SlotSource, ...] = MEANS) -> None:
        self.t0 = t0
        self.means = means
        self.m_sum = [0.0] * len(means)
        self.m_n = [0] * len(means)
        self.n = self.n_present = self.n_read = self.n_valid = self.n_mu = self.n_sat = 0
        self.s1 = self.s2 = self.sm = self.s_mu = 0.0
        self.mn = math.inf
        self.mx = -math.inf
        self.counts = [0] * len(REASONS)
        self.speed_cmd = 0.0
        self.speed_act = math.nan
        self.late_max = self.rtt_max = 0.0

    def add(self, rec: SlotRecord) -> None:
        """Count one slot record (O(1); NaN readings and round trips are skipped, never summed)."""
        self.n += 1
        if rec.present:
            self.n_present += 1
            t1, t2 = rec.t1, rec.t2
            if t1 == t1 and t2 == t2:
                self.n_read += 1
                self.s1 += t1
                self.s2 += t2
                m = (t1 + t2) * 0.5
                self.sm += m
                if m < self.mn:
                    self.mn = m
                if m > self.mx:
                    self.mx = m
            rtt = rec.rtt_s
            if rtt == rtt and rtt > self.rtt_max:
                self.rtt_max = rtt
        if rec.q:
            self.n_valid += 1
            if rec.mu is not None:
                self.s_mu += rec.mu
                self.n_mu += 1
        mask = rec.mask
        if mask:
            for i, (bit, _) in enumerate(REASONS):
                if mask & bit:
                    self.counts[i] += 1
        if rec.saturated:
            self.n_sat += 1
        if rec.lateness_s > self.late_max:
            self.late_max = rec.lateness_s
        self.speed_cmd = rec.speed_cmd
        self.speed_act = rec.speed_act
        if self.means:
            self._add_means(rec)

    def _add_means(self, rec: SlotRecord) -> None:
        for i, read in enumerate(self.means):
            x = read(rec)
            if isinstance(x, (int, float)) and x == x:
                self.m_sum[i] += x
                self.m_n[i] += 1

    # -- the derived figures (None when the window has nothing to average)
    @property
    def t1_mean(self) -> float | None:
        return self.s1 / self.n_read if self.n_read else None

    @property
    def t2_mean(self) -> float | None:
        return self.s2 / self.n_read if self.n_read else None

    @property
    def tension_mean(self) -> float | None:
        """The mean of the slots' mean tension, N."""
        return self.sm / self.n_read if self.n_read else None

    @property
    def mu_mean(self) -> float | None:
        return self.s_mu / self.n_mu if self.n_mu else None

    @property
    def valid_ratio(self) -> float | None:
        return self.n_valid / self.n if self.n else None

    def mean(self, read: SlotSource) -> float | None:
        """The mean of the reading ``read`` (one of ``means``) over the slots where it is a number."""
        i = self.means.index(read)
        return self.m_sum[i] / self.m_n[i] if self.m_n[i] else None

    def reason_counts(self) -> dict[str, int]:
        """Slots per reason name, in the order of ``REASONS``."""
        return {name: c for (_, name), c in zip(REASONS, self.counts)}
