"""Slot scheduling on absolute deadlines of a monotonic clock: t_k = t0 + k · Ts.

Deadlines never accumulate drift: each is computed from t0, never from the previous wake-up. A
poll that starts more than Ts/2 after its deadline belongs to a later slot, so the slots it
skipped are MISSING and the grid never shifts. :class:`SlotStats` keeps the figures of a
station's schedule (lateness, meter round trips, STM32 commands that could not go out).
"""
from __future__ import annotations

import asyncio
import math
import statistics
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any


class SlotClock:
    def __init__(self, ts: float, t0: float | None = None, clock=time.monotonic):
        self.ts = ts
        self.clock = clock
        self.t0 = clock() if t0 is None else t0

    def deadline(self, k: int) -> float:
        return self.t0 + k * self.ts

    def slot_at(self, t: float) -> int:
        return int(math.floor((t - self.t0) / self.ts + 0.5))

    async def wait_for(self, k: int, spin_s: float = 0.0) -> float:
        """Sleep until slot k's deadline; returns the lateness (s, ≥ 0 normally).
        The last ``spin_s`` are spent yielding to the loop rather than in one long sleep, because
        the selector's timeout is rounded to whole milliseconds."""
        target = self.deadline(k)
        while True:
            now = self.clock()
            rem = target - now
            if rem <= 0:
                return now - target
            if rem > spin_s:
                await asyncio.sleep(rem - spin_s)
            else:
                await asyncio.sleep(0)


@dataclass
class SlotStats:
    """Scheduling figures, for logs and benchmarks."""
    slots: int = 0
    filled: int = 0
    overrun_slots: int = 0
    lateness: deque = field(default_factory=lambda: deque(maxlen=200_000))
    rtt: deque = field(default_factory=lambda: deque(maxlen=200_000))
    #: speed commands never sent: replaced in the sender's box by a newer one, or not postable
    #: (the link busy with another exchange, or its port gone)
    stm32_busy_skips: int = 0

    def summary(self) -> dict[str, Any]:
        lat = sorted(self.lateness)

        def pct(p):
            return lat[min(len(lat) - 1, int(p * len(lat)))] * 1e3 if lat else math.nan

        return {"slots": self.slots, "filled": self.filled,
                "filled_ratio": self.filled / self.slots if self.slots else math.nan,
                "overrun_slots": self.overrun_slots,
                "lateness_ms_p50": pct(0.5), "lateness_ms_p99": pct(0.99),
                "lateness_ms_max": lat[-1] * 1e3 if lat else math.nan,
                "rtt_ms_median": statistics.median(self.rtt) * 1e3 if self.rtt else math.nan,
                "stm32_busy_skips": self.stm32_busy_skips}


class LateStarts:
    """The log of late slot starts (overruns), bounded like every refusal log
    (:mod:`gateway.plumbing.ratelog`): the first overrun of a window is one line at once; the rest of the
    window is counted and said in one line when the window ends (how many, the slots recorded as
    MISSING, the worst lateness), so a loaded box writes two lines a minute, not one per slot.
    The caller passes the time; each line goes to ``say`` (the station's log) and is returned."""

    def __init__(self, window_s: float, say: Callable[[str], None] = lambda line: None) -> None:
        self.window_s = float(window_s)
        self.say = say
        self._start: float | None = None     # the open window's start (its first overrun)
        self._count = 0                      # overruns after the first, not yet said
        self._missing = 0
        self._worst_s = 0.0
        self._last_k = 0

    def add(self, now: float, k: int, lateness_s: float, missing: int) -> str | None:
        """One overrun: slot ``k`` started ``lateness_s`` late, ``missing`` slots recorded as
        MISSING. Returns the line to log now (the first of a window), else None (counted)."""
        if self._start is not None and now - self._start < self.window_s:
            self._count += 1
            self._missing += missing
            self._worst_s = max(self._worst_s, lateness_s)
            self._last_k = k
            return None
        self._start = now
        line = f"slot {k} started {lateness_s * 1e3:.0f} ms late: {missing} slot(s) recorded as MISSING"
        self.say(line)
        return line

    def due(self, now: float, force: bool = False) -> str | None:
        """The line for the counted overruns once their window has ended (``force``: now)."""
        if self._start is None or not (force or now - self._start >= self.window_s):
            return None
        self._start = None
        if not self._count:
            return None
        line = (f"{self._count} more late slot start(s) in the last {self.window_s:.0f} s: "
                f"{self._missing} slot(s) recorded as MISSING, the worst {self._worst_s * 1e3:.0f} ms "
                f"late, the last at slot {self._last_k}")
        self._count = self._missing = 0
        self._worst_s = 0.0
        self.say(line)
        return line
