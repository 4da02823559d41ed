"""Slot scheduling on absolute deadlines of a monotonic clock: t_k = t0 + k · Ts.

Deadlines never accumulate drift: each is computed from t0, never from the previous wake-up. A
poll that starts more than Ts/2 after its deadline belongs to a later slot, so the slots it
skipped are MISSING and the grid never shifts.
"""
from __future__ import annotations

import asyncio
import math
import time


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
