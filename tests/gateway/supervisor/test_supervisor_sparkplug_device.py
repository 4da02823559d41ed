"""The supervisor's Sparkplug device of a station proxy (gateway/supervisor/remote.py
``SparkplugDevice``) on one edge node shared by two proxies, through a real Mosquitto and a
primary host with its own decoder: no device before its worker's HELLO, one DBIRTH however often
HELLO is told, DDEATH when the worker goes down and nothing published meanwhile, a DBIRTH when it
is back; a DCMD goes to its own station's hub only, off the node's thread (a worker slow to
answer does not hold the other device's data back); a DCMD for a down worker's device is ignored.
The same with real worker processes: tests/test_supervisor_sparkplug_e2e.py."""
from __future__ import annotations

import threading
import time
from dataclasses import asdict

from gateway.core.records import CommandReply, SlotRecord, StationState
from gateway.core.records import TestState as TS
from gateway.outputs.sparkplug.device import SparkplugDevice
from gateway.outputs.sparkplug.node_settings import SparkplugSettings
from gateway.supervisor import ipc
from gateway.supervisor.remote import RemoteFleet, RemoteStation
from kit.broker import Broker
from kit.sparkplug_host import PrimaryHost

GROUP, NODE = "lab", "hall-l1"


class _Hub:
    """A station's hub as the proxy uses it: its name, its sink, and ``command`` — here the
    worker's answer, slow (1.5 s) as a busy worker's may be."""

    worker = None

    def __init__(self, name: str):
        self.name = name
        self.sink = None
        self.commands: list[tuple[str, dict, str]] = []
        self.lock = threading.Lock()

    def command(self, kind, args=None, source="supervisor", request_id=None, timeout=5.0):
        time.sleep(1.5)
        with self.lock:
            self.commands.append((kind, dict(args or {}), source))
        return CommandReply(True, "", request_id)


def _feed(proxy: RemoteStation, k0: int, n: int) -> None:
    rows = [ipc.slot_row(SlotRecord(k=k, t=k * 0.02, present=True, t1=0.4, t2=0.6, q=1, mask=0, ratio=1.5,
                                    mu=0.2, mean_filt=0.5, speed_cmd=100.0, speed_act=99.0,
                                    saturated=False, lateness_s=0.0, rtt_s=0.005))
            for k in range(k0, k0 + n)]
    proxy.on_frame(ipc.FrameType.SLOTS, {"rows": rows})


def test_devices_follow_their_workers_and_dcmds_reach_their_own_hub(tmp_path):
    b = Broker(tmp_path).start()
    host = PrimaryHost(b.port, "unused", GROUP, tmp_path)
    fleet = RemoteFleet()
    hubs = {n: _Hub(n) for n in ("a", "b")}
    proxies: dict[str, RemoteStation] = {}
    stop = threading.Event()
    try:
        for n, hub in hubs.items():
            p = RemoteStation(hub)
            p.outputs = [SparkplugDevice(SparkplugSettings(
                GROUP, NODE, n, servers=[("127.0.0.1", b.port)], data_interval_s=0.1,
                store_path=str(tmp_path / "spb.sqlite")), p)]
            fleet.add(p)
            proxies[n] = p
        host.wait(lambda: host.all("NBIRTH"), 10, "the NBIRTH")
        time.sleep(0.5)
        assert not host.all("DBIRTH"), "no device before its worker's HELLO"
        _feed(proxies["a"], 0, 20)                      # nothing of a worker not up is published
        for n in ("a", "b"):
            proxies[n].on_worker(True, 0)
            proxies[n].on_worker(True, 0)               # told twice: one DBIRTH
        host.wait(lambda: len(host.all("DBIRTH")) >= 2, 10, "a DBIRTH per device")

        def feeder():
            k = 0
            while not stop.is_set():
                for n in ("a", "b"):
                    if proxies[n].hub.sink is proxies[n]:
                        _feed(proxies[n], k, 5)
                k += 5
                time.sleep(0.1)
        th = threading.Thread(target=feeder, daemon=True)
        th.start()
        proxies["b"].on_frame(ipc.FrameType.STATE, asdict(StationState("b", state=TS.IDLE, meter_ok=True)))
        host.wait(lambda: {m.device for m in host.all("DDATA")} == {"a", "b"}, 10, "DDATA of both")
        assert sorted(m.device for m in host.all("DBIRTH")) == ["a", "b"]
        alias = {m.name: m.alias for m in next(x for x in host.all("DBIRTH") if x.device == "b").p.metrics}

        # a DCMD start to b: b's hub only; while b's worker takes 1.5 s, a's data go on
        mark = host.mark()
        host.command(f"spBv1.0/{GROUP}/DCMD/{NODE}/b", [
            {"alias": alias["Device Control/Start Test"], "boolean_value": True},
            {"alias": alias["Device Control/Sample ID"], "string_value": "S-9"}])
        time.sleep(1.2)
        assert not hubs["b"].commands and len([m for m in host.all("DDATA", mark) if m.device == "a"]) >= 5
        host.wait(lambda: hubs["b"].commands, 5, "b's command")
        assert hubs["b"].commands == [("start", {"sample_id": "S-9"}, "sparkplug")] and not hubs["a"].commands

        # b's worker goes down: DDEATH of b only, nothing of b until it is back, then a DBIRTH
        mark = host.mark()
        proxies["b"].on_worker(False, 1)
        host.wait(lambda: host.all("DDEATH", mark), 5, "b's DDEATH")
        dd = host.mark()
        host.command(f"spBv1.0/{GROUP}/DCMD/{NODE}/b", [
            {"alias": alias["Device Control/Stop Test"], "boolean_value": True}])
        time.sleep(2.0)
        assert [m.device for m in host.all("DDEATH", mark)] == ["b"]
        assert not [m for m in host.all(since=dd) if m.device == "b" and m.kind != "DCMD"]
        assert len([m for m in host.all("DDATA", dd) if m.device == "a"]) >= 10
        assert len(hubs["b"].commands) == 1                  # the dead device's DCMD was ignored
        proxies["b"].on_worker(True, 1)
        host.wait(lambda: [m for m in host.all("DBIRTH", dd) if m.device == "b"], 5, "b's DBIRTH again")
        assert not host.all("NDEATH") and len(host.all("NBIRTH")) == 1
    finally:
        stop.set()
        fleet.stop()
    try:
        # the last proxy stopped ends the node: DDEATHs, then the NDEATH
        host.wait(lambda: host.all("NDEATH"), 10, "the NDEATH")
        tail = [m.kind for m in host.all() if m.kind in ("DDEATH", "NDEATH")][-3:]
        assert tail == ["DDEATH", "DDEATH", "NDEATH"], tail
    finally:
        host.close()
        b.stop()
