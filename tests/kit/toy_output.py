"""A toy plug-in output in ONE row of the output registry (``HOOKWATCH_OUTPUTS=kit.toy_output``),
for tests/gateway/outputs/test_output_registry_e2e.py (issue 35 item 1).

Its section ``toy:`` (``enabled``, ``host``, ``port``, ``tag``) is its schema; in a fleet the
supervisor serves it for the station's proxy (``box``), it needs every slot record
(``slot_rows``) and a change of its section rebuilds it on SIGHUP (``reload``). It listens on its
door (``toy.port``) and answers each connection with one JSON line: its tag, its instance
number, the process that built it, the slot records it got (count, first and last k, gaps in k)
and the slots reported lost to it (a fleet's IPC)."""
from __future__ import annotations

import asyncio
import itertools
import json
import os
from dataclasses import dataclass

from gateway.config.plugins import Door, plugin_config
from gateway.config.sections import StationConfig, key
from gateway.core.ports import StationView
from gateway.outputs.registry import BoxBuild, StationBuild, no_broker, plugin_row, register

_INSTANCES = itertools.count(1)


@dataclass(frozen=True, kw_only=True)
class ToyConfig:
    enabled: bool = key(False, "run the toy output", kind="bool")
    host: str = key("127.0.0.1", "address it listens on", kind="str")
    port: int = key(7777, "TCP port it listens on", kind="int", lo=1, hi=65535)
    tag: str = key("", "a word it reports (a change rebuilds it)", kind="str")


class ToyOutput:
    """Counts the slot records it is given; tells them on its door."""

    def __init__(self, cfg: ToyConfig, station: StationView) -> None:
        self.cfg = cfg
        self.station = station
        self.instance = next(_INSTANCES)
        self.n = 0
        self.first: int | None = None
        self.last: int | None = None
        self.gaps = 0
        self.lost = 0
        self.server: asyncio.base_events.Server | None = None

    async def start(self) -> None:
        self.server = await asyncio.start_server(self._client, self.cfg.host, self.cfg.port,
                                                 reuse_address=True)

    async def stop(self) -> None:
        if self.server is not None:
            self.server.close()
            await self.server.wait_closed()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(json.dumps({
            "station": self.station.id, "tag": self.cfg.tag, "instance": self.instance,
            "pid": os.getpid(), "n": self.n, "first": self.first, "last": self.last,
            "gaps": self.gaps, "lost": self.lost}).encode() + b"\n")
        await writer.drain()
        writer.close()

    def on_record(self, rec) -> None:
        k = rec.k
        if self.last is not None and k > self.last + 1:
            self.gaps += k - self.last - 1
        if self.first is None:
            self.first = k
        self.last = k
        self.n += 1

    def on_event(self, ev) -> None:
        pass

    def on_state(self, st) -> None:
        pass

    # a fleet's station proxy (gateway.core.ports.WorkerHooks)
    def on_worker(self, up: bool, restarts: int = 0) -> None:
        pass

    def on_lost(self, n: int) -> None:
        self.lost += n

    def on_metrics(self, snap) -> None:
        pass


def _toy(cfg: StationConfig) -> ToyConfig:
    return plugin_config(cfg, "toy", ToyConfig)


def _doors(cfg: StationConfig) -> list[Door]:
    t = _toy(cfg)
    return [("toy.port", t.host, t.port)] if t.enabled else []


def _build(b: StationBuild) -> list:
    return [ToyOutput(_toy(b.cfg), b.station)]


def _serve(b: BoxBuild) -> list:
    return [ToyOutput(_toy(b.cfg), b.station)]


# the one row
register(plugin_row("toy", ToyConfig, northbound=False, box=True, slot_rows=True, reload=True,
                    build=_build, feed=None, serve=_serve, broker=no_broker, doors=_doors,
                    metrics="none of its own"))
