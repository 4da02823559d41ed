"""A slot clock whose time jumps to each deadline, so a Station's loop runs flat out (as
bench/bench_station.py): ``station.clock_factory = lambda ts: VirtualClock(ts)``."""
from __future__ import annotations

import asyncio
import math


class VirtualClock:
    def __init__(self, ts):
        self.ts = ts
        self.now = 0.0
        self.clock = lambda: self.now

    def slot_at(self, t):
        return int(math.floor(t / self.ts + 0.5))

    async def wait_for(self, k, spin_s=0.0):
        self.now = k * self.ts
        await asyncio.sleep(0)
        return 0.0
