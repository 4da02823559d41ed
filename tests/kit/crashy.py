"""A test-only plug-in output (``HOOKWATCH_OUTPUTS=kit.crashy``: one row of the output registry,
its section ``crashy:``, on unless switched off) that makes a station crash
in a real ``hookwatch run``: its first instance crashes while starting its outputs (the MQTT and
Modbus TCP outputs have started: a leaked client or unit id would show), its second in the slot
loop after ``CRASH_AT_SLOT`` slots (its serial ports are open), the third and later run normally.
The instances are counted in ``$HW_CRASH_DIR/builds``."""
from __future__ import annotations

import os
from dataclasses import dataclass

from gateway.config.sections import key
from gateway.outputs.registry import no_broker, no_doors, plugin_row, register
from gateway.station.clock import SlotClock

CRASH_AT_SLOT = 50


class FailingStart:
    """An output that cannot start (like one whose port or server is gone)."""

    async def start(self) -> None:
        raise RuntimeError("test: this output cannot start")

    async def stop(self) -> None:
        pass

    def on_record(self, rec) -> None:
        pass

    def on_event(self, ev) -> None:
        pass

    def on_state(self, st) -> None:
        pass


class CrashingClock(SlotClock):
    """The station's slot clock, raising (like a bug in the slot path) at one slot."""

    async def wait_for(self, k: int, spin_s: float = 0.0) -> float:
        if k == CRASH_AT_SLOT:
            raise RuntimeError(f"test: a bug in the slot path at slot {k}")
        return await super().wait_for(k, spin_s)


def outputs(cfg, station):
    path = os.path.join(os.environ["HW_CRASH_DIR"], "builds")
    try:
        with open(path) as f:
            n = int(f.read() or 0) + 1
    except FileNotFoundError:
        n = 1
    with open(path, "w") as f:
        f.write(str(n))
    if n == 1:
        return [FailingStart()]
    if n == 2:
        station.clock_factory = CrashingClock
    return []


@dataclass(frozen=True, kw_only=True)
class CrashyConfig:
    enabled: bool = key(True, "crash the station's first two instances", kind="bool")


register(plugin_row("crashy", CrashyConfig, northbound=False, box=False, slot_rows=False, reload=False,
                    build=lambda b: outputs(b.cfg, b.station), feed=None, serve=None,
                    broker=no_broker, doors=no_doors, metrics="none"))
