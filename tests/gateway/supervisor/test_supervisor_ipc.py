"""Issue 16: the supervisor ↔ worker IPC (gateway/supervisor/ipc.py) and the fleet read station by
station (gateway/supervisor/fleetcfg.py). Real Unix socketpairs, no mocks."""
from __future__ import annotations

import json
import math
import os
import socket
import struct
import threading
import time

import pytest
import yaml

from conftest import ROOT
from gateway.core.records import Event, EventType, SlotRecord, StationState
from gateway.supervisor.fleetcfg import plan_fleet
from gateway.supervisor.ipc import HEADER, MAX_BODY, FrameChannel, FrameDecoder, FrameType, ProtocolError, encode
from gateway.supervisor.supervisor import StationHub
from gateway.supervisor.worker import IpcOutput


def test_frame_is_length_type_and_strict_json():
    f = encode(FrameType.STATE, {"a": 1.5, "nan": math.nan, "inf": -math.inf, "s": "μ"})
    length, t = struct.unpack(">IB", f[:5])
    assert t == FrameType.STATE == 3 and length == len(f) - 4
    body = json.loads(f[5:].decode("utf-8"))            # any JSON decoder reads it
    assert body == {"a": 1.5, "nan": None, "inf": None, "s": "μ"}


def test_decoder_reassembles_frames_split_anywhere():
    frames = [encode(FrameType.HEARTBEAT, {"slots": i}) for i in range(50)]
    wire = b"".join(frames)
    dec = FrameDecoder()
    got = []
    for i in range(0, len(wire), 7):                     # 7-byte pieces cut through headers
        got += dec.feed(wire[i:i + 7])
    assert [b["slots"] for _, b in got] == list(range(50))
    assert all(t == FrameType.HEARTBEAT for t, _ in got)


@pytest.mark.parametrize("wire", [
    HEADER.pack(MAX_BODY + 2, 2),                        # longer than allowed
    HEADER.pack(0, 2),                                   # no type byte
    HEADER.pack(3, 99) + b"{}",                          # unknown type
    HEADER.pack(4, 2) + b"[1]",                          # not an object
    HEADER.pack(4, 2) + b"{x:",                          # not JSON
])
def test_decoder_refuses_broken_frames(wire):
    with pytest.raises(ProtocolError):
        FrameDecoder().feed(wire)


def _rec(k: int) -> SlotRecord:
    return SlotRecord(k=k, t=k * 0.02, present=True, t1=0.5, t2=0.6, q=1, mask=0, ratio=1.2,
                      mu=0.06, mean_filt=0.55, speed_cmd=100.0, speed_act=math.nan, saturated=False,
                      lateness_s=0.001, rtt_s=0.005)


@pytest.mark.timeout(120)
def test_stalled_consumer_never_blocks_the_station_and_is_bounded():
    """The supervisor stops reading: the worker's slot loop (IpcOutput.on_record) keeps its pace,
    the queue stays at its bound, the oldest frames are dropped and counted; once the supervisor
    reads again it gets the newest frames, in order."""
    a, b = socket.socketpair()
    with a, b:                                           # closed also when an assertion fails
        a.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
        b.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        chan = FrameChannel(a, maxlen=64)
        out = IpcOutput(chan, every=1)                       # one frame per slot: the worst case
        n = 20_000
        # b never reads meanwhile: a send that waited for the socket would wait for ever (the test's
        # timeout); how long a record takes is bench/bench_nonblocking.py's figure, not asserted here
        for k in range(n):
            out.on_record(_rec(k))
            assert len(chan.box) <= 64
        assert chan.dropped > n - 64 - 1000                  # the kernel buffers hold only a few
        # the consumer comes back: what it reads ends with the newest slot, in order
        out.on_record(_rec(n))
        dec = FrameDecoder()
        ks = []
        b.settimeout(2.0)
        t_end = time.monotonic() + 10
        while time.monotonic() < t_end and (not ks or ks[-1] != n):
            try:
                data = b.recv(65536)
            except TimeoutError:
                break
            ks += [body["last"]["k"] for _, body in dec.feed(data)]
        assert ks[-1] == n and ks == sorted(ks)
        assert len(ks) < 1000
        chan.flush(1.0)


def test_output_summarises_slots_and_passes_events_and_state():
    a, b = socket.socketpair()
    chan = FrameChannel(a)
    out = IpcOutput(chan, every=10)
    for k in range(25):
        out.on_record(_rec(k))
    out.on_event(Event(EventType.BASELINE, "st", 1.0, "T1", 5, {"mu_ss": 0.06}))
    out.on_state(StationState(station="st", mu_ss=0.06))
    chan.flush()
    b.settimeout(2)
    got = FrameDecoder().feed(b.recv(1 << 20))
    kinds = [t for t, _ in got]
    assert kinds == [FrameType.SLOTS, FrameType.SLOTS, FrameType.EVENT, FrameType.STATE]
    s = got[1][1]
    assert s["n"] == 10 and s["filled"] == 10 and s["valid"] == 10 and s["last"]["k"] == 19
    assert s["last"]["speed_act"] is None and abs(s["mu_mean"] - 0.06) < 1e-12
    assert got[2][1]["type"] == "baseline_established" and got[2][1]["mu_ss"] == 0.06
    assert got[3][1]["state"] == 0 and got[3][1]["station"] == "st"
    a.close()
    b.close()


@pytest.mark.timeout(120)
def test_hub_slow_subscriber_loses_oldest_and_never_blocks_publisher():
    hub = StationHub("st", None)
    slow = hub.subscribe(maxlen=8)
    fast = hub.subscribe(maxlen=10_000)
    got: list = []
    stop = threading.Event()

    def drain():
        while not stop.is_set():
            fast.wait(0.05)
            got.extend(fast.drain())
    th = threading.Thread(target=drain)
    th.start()
    # `slow` never drains: a publish that waited for it would wait for ever (the test's timeout)
    for i in range(5000):
        hub.publish("slots", {"i": i})
    stop.set()
    th.join()
    got.extend(fast.drain())
    assert [b["i"] for _, b in got] == list(range(5000))
    assert [b["i"] for _, b in slow.drain()] == list(range(4992, 5000))
    assert slow.dropped == 4992
    assert len(hub.stream) <= 512 and hub.stream[-1][1]["i"] == 4999


def _fleet(tmp_path, stations: dict[str, str]):
    (tmp_path / "stations").mkdir()
    (tmp_path / "fleet.yaml").write_text(yaml.safe_dump({"defaults": {
        "meter": {"map": os.path.join(ROOT, "config", "meters", "zn-s.yaml")}, "mqtt": {"enabled": False},
        "modbus_tcp": {"enabled": False}, "recorder": {"dir": str(tmp_path / "rec")}}}))
    for name, text in stations.items():
        (tmp_path / "stations" / f"{name}.yaml").write_text(text)
    return str(tmp_path)


def test_plan_refuses_only_the_broken_and_the_clashing_station(tmp_path):
    folder = _fleet(tmp_path, {
        "a": "station: {id: a}\nmeter: {port: /dev/ttyA}\nstm32: {port: /dev/ttyB}\n",
        "b": "station: {id: b\nmeter: [\n",                                  # not YAML
        "c": "station: {id: c}\nmeter: {port: /dev/ttyA}\nstm32: {port: /dev/ttyC}\n",  # a's port
        "d": "station: {id: d}\nmeter: {port: /dev/ttyD, baudrate: 7}\nstm32: {port: /dev/ttyE}\n",
        "e": "station: {id: e}\nmeter: {port: /dev/ttyF}\nstm32: {port: /dev/ttyG}\n",
    })
    plan = plan_fleet(folder)
    assert [c.station.id for _, c in plan.accepted] == ["a", "e"]
    refused = {r.name: r for r in plan.refused}
    assert set(refused) == {"b", "c", "d"}
    assert "b.yaml" in refused["b"].message() and "YAML" in refused["b"].message()
    assert "c.yaml" in refused["c"].message() and "meter.port" in refused["c"].message()
    assert "d.yaml" in refused["d"].message() and "did you mean 'baud'" in refused["d"].message()
