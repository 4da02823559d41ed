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
