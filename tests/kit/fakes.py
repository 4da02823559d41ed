"""Fakes of the station's ports (meter, STM32) for tests of the slot loop and the command path
that need no plant; wire-level tests use the virtual devices (kit.meter, kit.e2e) instead.
conftest.py offers them as fixtures (fake_meter, fake_stm32, timed_meter)."""
from __future__ import annotations

import asyncio
import time


class Reading:
    def __init__(self, ch1, ch2, rtt_s=0.004):
        self.ch1, self.ch2, self.rtt_s = ch1, ch2, rtt_s


class FakeMeter:
    """The smallest meter port: constant tensions (None → no reply). For tests of the command path
    that do not need a plant; end-to-end tests use `hookwatch sim` instead."""

    def __init__(self, ch1=0.40, ch2=0.60):
        self.connected = True
        self.counters = {}
        self.value = (ch1, ch2)

    async def open(self):
        pass

    async def read(self):
        await asyncio.sleep(0.002)
        return Reading(*self.value) if self.value else None

    async def close(self):
        pass


class FakeStm32:
    """``stop_delay_s``: the stop is answered after this long (a real STM32's reply comes after
    a serial round trip: the station's loop runs on meanwhile)."""

    def __init__(self, stop_delay_s: float = 0.0):
        self.connected = True
        self.counters = {}
        self.calls = []
        self.stop_delay_s = stop_delay_s

    async def open(self):
        pass

    async def enable(self):
        self.calls.append("enable")

    async def set_speed(self, rpm):
        return None

    async def stop(self, reason=""):
        self.calls.append(f"stop:{reason}")
        if self.stop_delay_s:
            await asyncio.sleep(self.stop_delay_s)

    async def read_status(self):
        return None

    async def close(self):
        pass


#: the STM32 fake of the slot-clock tests: answers every call at once (FakeStm32 also records them)
QuietStm32 = FakeStm32


class _Reading:
    def __init__(self, k):
        self.ch1, self.ch2, self.rtt_s = 0.4, 0.6 + 1e-4 * (k % 7), 0.003


class TimedMeter:
    """Answers after 3 ms; the reads named in ``slow`` take 75 ms (an overrun of ~3 slots)."""
    connected = True

    def __init__(self, slow):
        self.slow, self.calls, self.counters = set(slow), 0, {}
        self.call_times = []

    async def open(self):
        pass

    async def close(self):
        pass

    async def read(self):
        self.calls += 1
        self.call_times.append(time.monotonic())
        await asyncio.sleep(0.075 if self.calls in self.slow else 0.003)
        return _Reading(self.calls)


class Capture:
    """An output that keeps every slot record, event and state (the Output contract, nothing else)."""

    def __init__(self):
        self.records, self.events, self.states = [], [], []

    @property
    def recs(self):
        return self.records

    async def start(self):
        pass

    async def stop(self):
        pass

    def on_record(self, rec):
        self.records.append(rec)

    def on_event(self, ev):
        self.events.append(ev)

    def on_state(self, st):
        self.states.append(st)

