"""The IPC that feeds a fleet's shared outputs (issue 16 item 1): every slot record, event and
state of a worker crosses as strict JSON and comes back equal; a worker's stream drives a
RemoteStation's outputs; a gap in the slot numbers is told to the outputs; a worker down turns
the links off. The end-to-end proof with real processes is tests/test_supervisor_shared_e2e.py."""
from __future__ import annotations

import json
import math
import os
import socket
import threading
import time
from dataclasses import asdict

import yaml

from gateway.compose import shared_sparkplug_nodes
from gateway.config import load_fleet
from gateway.core.records import Event, EventType, SlotRecord, StationState
from gateway.core.records import TestState as TS
from gateway.outputs.sparkplug.output import state_values
from gateway.supervisor import ipc
from gateway.supervisor.remote import RemoteStation
from gateway.supervisor.worker import IpcOutput
from kit.e2e import fleet_dir
from kit.fakes import Capture


def _rec(k: int, **kw) -> SlotRecord:
    d = dict(k=k, t=k * 0.02, present=True, t1=0.41, t2=0.63, q=1, mask=0, ratio=1.5, mu=0.21,
             mean_filt=0.52, speed_cmd=120.0, speed_act=119.5, saturated=False, lateness_s=0.0004,
             rtt_s=0.0046)
    d.update(kw)
    return SlotRecord(**d)


def test_slot_records_events_and_states_cross_as_json_and_come_back_equal():
    recs = [_rec(7), _rec(8, present=False, t1=math.nan, t2=math.nan, q=0, mask=1, ratio=None, mu=None,
                           speed_act=math.nan, rtt_s=math.nan, saturated=True)]
    frame = ipc.encode(ipc.FrameType.SLOTS, {"rows": [ipc.slot_row(r) for r in recs]})
    ((ft, body),) = ipc.FrameDecoder().feed(frame)
    assert ft == ipc.FrameType.SLOTS
    back = [ipc.slot_from_row(r) for r in body["rows"]]
    assert back[0] == recs[0]
    b = back[1]
    assert (b.k, b.present, b.q, b.mask, b.ratio, b.mu, b.saturated) == (8, False, 0, 1, None, None, True)
    assert all(math.isnan(x) for x in (b.t1, b.t2, b.speed_act, b.rtt_s))
    assert list(body["rows"][1]).count(None) >= 6                   # strict JSON: NaN is null
    ev = Event(EventType.BASELINE, "st", 1764000000.5, "T-1", 123, {"mu_ss": 0.2, "k_b": 100})
    assert ipc.event_from_dict(json.loads(json.dumps(ev.as_dict()))) == ev
    st = StationState("st", state=TS.MONITORING, test_id="T-1", mu_ss=0.2, meter_ok=True)
    ((_, wire),) = ipc.FrameDecoder().feed(ipc.encode(ipc.FrameType.STATE, asdict(st)))   # as the worker
    assert ipc.state_from_dict({**wire, "a_newer_field": 1}) == st
    try:
        ipc.slot_from_row([1, 2, 3])
        raise AssertionError("a short row must be refused")
    except ValueError:
        pass


class _Capture(Capture):
    """Capture, plus the hooks a station proxy calls where an output has them."""

    def __init__(self):
        super().__init__()
        self.worker, self.lost, self.metrics = [], [], []

    def on_worker(self, up, restarts=0):
        self.worker.append((up, restarts))

    def on_lost(self, n):
        self.lost.append(n)

    def on_metrics(self, snap):
        self.metrics.append(snap)


class _Hub:
    name = "st"
    sink = None
    worker = None


def test_a_workers_stream_over_a_real_socket_drives_the_proxys_outputs():
    """IpcOutput (worker side) → FrameChannel → socketpair → decoder → RemoteStation → outputs."""
    a, b = socket.socketpair()
    chan = ipc.FrameChannel(a)
    out = IpcOutput(chan, every=10, rows=True)
    proxy = RemoteStation(_Hub())
    cap = _Capture()
    proxy.outputs = [cap]
    got: list = []

    def read():
        dec = ipc.FrameDecoder()
        while True:
            frames = ipc.read_frames(b, dec)
            if frames is None:
                return
            for ft, body in frames:
                got.append(ft)
                proxy.on_frame(ft, body)
    th = threading.Thread(target=read)
    th.start()
    proxy.on_worker(True, 0)
    out.on_state(StationState("st", state=TS.BASELINE_SEARCH, meter_ok=True, stm32_ok=True))
    for k in range(20):
        out.on_record(_rec(k))
    out.on_event(Event(EventType.TEST_STARTED, "st", time.time(), "T-1", 0, {"t_set": 0.5}))
    for k in range(40, 50):                 # slots 20…39 lost between worker and supervisor
        out.on_record(_rec(k))
    for k in range(50, 53):                 # a state in mid-batch: the 3 slots before it go first
        out.on_record(_rec(k))
    out.on_state(StationState("st", state=TS.BASELINE_SEARCH, meter_ok=True, stm32_ok=True, mu_ss=0.2))
    chan.send(ipc.FrameType.METRICS, {"v": 1, "station": "st", "slots": 50})
    chan.flush()
    a.close()
    th.join(5)
    b.close()
    recs = cap.records
    assert [r.k for r in recs] == list(range(20)) + list(range(40, 53))
    assert recs[3] == _rec(3)
    assert cap.lost == [20] and proxy.lost == 20
    assert [e.type for e in cap.events] == [EventType.TEST_STARTED]
    assert proxy.state.state == TS.BASELINE_SEARCH and proxy.state.meter_ok
    assert cap.metrics == [{"v": 1, "station": "st", "slots": 50}]
    # the worker goes down: the outputs see every link off and the proxy refuses commands
    proxy.on_worker(False, 1)
    assert cap.worker[-1] == (False, 1)
    assert not proxy.state.meter_ok and not proxy.state.stm32_ok and cap.states[-1] is proxy.state
    F = ipc.FrameType
    assert got == [F.STATE, F.SLOTS, F.SLOTS, F.EVENT, F.SLOTS, F.SLOTS, F.STATE, F.METRICS], got


def test_stations_sharing_a_sparkplug_edge_node_are_found(tmp_path):
    """Such a node is one MQTT session for several stations (in the supervisor, a device per station)."""
    fleet = fleet_dir(tmp_path, sparkplug={"enabled": True})
    for name in ("a", "b"):
        (fleet / "stations" / f"{name}.yaml").write_text(yaml.safe_dump({
            "station": {"id": name}, "meter": {"port": f"/dev/tty-{name}-m"},
            "stm32": {"port": f"/dev/tty-{name}-s"}}))
    cfgs = load_fleet(str(fleet))
    assert shared_sparkplug_nodes(cfgs) == ["lab/hall-l1"]
    os.remove(fleet / "stations" / "b.yaml")
    assert shared_sparkplug_nodes(load_fleet(str(fleet))) == []


def test_a_shelving_reaches_the_supervisors_sparkplug_values_only_while_shelved():
    """The supervisor has no alarm store: the expiry of a shelving comes from the station's
    alarm_shelved event; the state (the worker's store) decides whether it is shown."""
    def state_to_dict(st):               # as the worker sends it (its STATE frame) and JSON carries it
        return json.loads(json.dumps(asdict(st), default=str))

    proxy = RemoteStation(_Hub())
    until = 1_790_000_000.25
    ev = Event(EventType.ALARM_SHELVED, "st", until - 600, data={"alarm": "wear_warning", "until": until,
                                                                  "source": "plc:127.0.0.1"})
    proxy.on_frame(ipc.FrameType.EVENT, json.loads(json.dumps(ev.as_dict())))
    proxy.on_frame(ipc.FrameType.STATE, state_to_dict(StationState(station="st", warning_alarm="shelved",
                                                                   alarm="unacknowledged")))
    v = state_values(proxy.state, proxy)
    assert v["Alarm/Wear Warning/State"] == "shelved"
    assert v["Alarm/Wear Warning/Shelved Until"] == round(until * 1000)
    assert v["Alarm/End Of Life/Shelved Until"] is None          # the other alarm was not shelved
    # unshelved: the state says so, the old expiry is no longer shown
    proxy.on_frame(ipc.FrameType.STATE, state_to_dict(StationState(station="st")))
    assert state_values(proxy.state, proxy)["Alarm/Wear Warning/Shelved Until"] is None
