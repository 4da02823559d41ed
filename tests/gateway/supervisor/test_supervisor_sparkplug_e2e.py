"""A Sparkplug B edge node shared by the stations of a fleet lives in the supervisor: one MQTT
session (one NBIRTH, one bdSeq, the supervisor's Will) with a device per station, each fed by
its worker process over the IPC. Real parts: `hookwatch sim --count 2`, `hookwatch run
FLEET_DIR` (a supervisor and a worker per station), Mosquitto, and a primary host that decodes
with its own protoc build (tests/kit/sparkplug_host.py): a DBIRTH and moving DDATA per station,
a DCMD reaches only its station, `kill -9` of one worker → DDEATH of that device only and a
DBIRTH after its restart while the other device's DDATA goes on; a clean stop → NDEATH."""
from __future__ import annotations

import os
import signal

import yaml

from kit.broker import Broker
from kit.e2e import fleet_dir, run_gateway, sim_fleet, wait_log, worker_pids
from kit.sparkplug_host import PrimaryHost, metric_value
from kit.tools import wait_for

GROUP, NODE = "lab", "hall-l1"          # fleet_dir's site / area-line: the shared default node
NAMES = ("sim01", "sim02")
NODE_KINDS = ("NBIRTH", "NDEATH", "DBIRTH", "DDEATH", "NDATA", "DDATA")


def _count(host: PrimaryHost, kind: str, device: str | None = None, since: int = 0) -> int:
    return sum(1 for m in host.all(kind, since) if device is None or m.device == device)


def _seq_ok(msgs) -> None:
    """One session: NBIRTH seq 0, then +1 mod 256 per message of the node, whatever the device."""
    msgs = [m for m in msgs if m.kind in NODE_KINDS and m.kind != "NDEATH"]
    assert msgs[0].kind == "NBIRTH" and msgs[0].p.seq == 0, msgs[:3]
    for a, b in zip(msgs, msgs[1:]):
        assert b.p.seq == (a.p.seq + 1) % 256, (a, b)


def _bdseq(msg) -> int:
    return [m.long_value for m in msg.p.metrics if m.name == "bdSeq"][0]


def test_fleet_shares_one_edge_node_in_the_supervisor_kill_9_is_a_ddeath(tmp_path):
    b = Broker(tmp_path).start()
    host = PrimaryHost(b.port, "unused", GROUP, tmp_path)
    sim, links = sim_fleet(tmp_path, 2)
    gw = None
    rc = None
    try:
        fleet = fleet_dir(tmp_path, sparkplug={"enabled": True, "port": b.port, "data_interval_s": 0.2})
        for name in NAMES:
            (fleet / "stations" / f"{name}.yaml").write_text(yaml.safe_dump({
                "station": {"id": name}, "meter": {"port": os.path.join(links, name, "meter")},
                "stm32": {"port": os.path.join(links, name, "stm32")}}))
        gw = run_gateway(tmp_path, str(fleet), "--restart-backoff", "1")
        for name in NAMES:
            wait_for(lambda n=name: worker_pids(gw, n), 30, 0.2, what=f"{name}: worker started")
        pids = {n: worker_pids(gw, n)[0] for n in NAMES}
        # a process per station, the supervisor apart, and no fallback to one process
        assert len(set(pids.values())) == 2 and gw.p.pid not in pids.values()

        # one NBIRTH, then a DBIRTH per station; DDATA moving for both
        host.wait(lambda: {m.device for m in host.all("DBIRTH")} >= set(NAMES), 30, "a DBIRTH per station")
        log = gw.log_all()
        assert "runs in one process" not in log and "in-process" not in log, log
        assert f"Sparkplug edge node(s) {GROUP}/{NODE}: one session in the supervisor" in log
        assert _count(host, "NBIRTH") == 1 and host.all()[0].kind == "NBIRTH", host.all()[:4]
        assert all(m.topic.startswith(f"spBv1.0/{GROUP}/") and f"/{NODE}" in m.topic for m in host.all())
        births = {m.device: m for m in host.all("DBIRTH")}
        assert [_count(host, "DBIRTH", n) for n in NAMES] == [1, 1]
        aliases = {n: {m.name: m.alias for m in births[n].p.metrics} for n in NAMES}
        assert not set(aliases["sim01"].values()) & set(aliases["sim02"].values())
        mark = host.mark()
        host.wait(lambda: all(_count(host, "DDATA", n, mark) >= 5 for n in NAMES), 10, "DDATA of both")

        # a DCMD start to sim02 reaches sim02's worker only (hub.command, off the node's thread)
        a2 = aliases["sim02"]
        mark = host.mark()
        host.command(f"spBv1.0/{GROUP}/DCMD/{NODE}/sim02", [
            {"alias": a2["Device Control/Start Test"], "boolean_value": True},
            {"alias": a2["Device Control/Sample ID"], "string_value": "SPB-2"},
            {"alias": a2["Device Control/Setpoint"], "float_value": 0.5}])
        wait_log(gw, "sim02: test_starting", 15)
        by_alias = {v: k for k, v in a2.items()}

        def result_code():
            for m in host.all("DDATA", mark):
                if m.device == "sim02":
                    for x in m.p.metrics:
                        if by_alias.get(x.alias) == "Device Control/Last Result Code":
                            return [metric_value(x)]
            return None
        assert host.wait(result_code, 10, "sim02's Last Result Code") == [0]
        host.wait(lambda: any(m.device == "sim02" and any(
            by_alias.get(x.alias) == "Test/State" and metric_value(x) != "idle" for x in m.p.metrics)
            for m in host.all("DDATA", mark)), 10, "sim02's Test/State leaving idle")
        assert "sim01: test_starting" not in gw.log_all()

        # kill -9 of sim02's worker: its device dies (DDEATH), the node and sim01 go on
        mark = host.mark()
        os.kill(pids["sim02"], signal.SIGKILL)
        host.wait(lambda: _count(host, "DDEATH", "sim02", mark), 10, "sim02's DDEATH")
        dd = next(i for i, m in enumerate(host.all(since=mark)) if m.kind == "DDEATH") + mark
        wait_for(lambda: len(worker_pids(gw, "sim02")) == 2, 20, 0.2, what="sim02 restarted")
        host.wait(lambda: _count(host, "DBIRTH", "sim02", dd), 20, "sim02's DBIRTH after its restart")
        reborn = next(i for i, m in enumerate(host.all(since=dd)) if m.kind == "DBIRTH") + dd
        host.wait(lambda: _count(host, "DDATA", "sim02", reborn) >= 3, 10, "sim02's DDATA again")
        since_kill = host.all(since=mark)
        assert _count(host, "DDEATH", "sim01", mark) == 0 and _count(host, "DDEATH", "sim02", mark) == 1
        assert _count(host, "NDEATH", since=mark) == 0 and _count(host, "NBIRTH", since=mark) == 0
        assert _count(host, "DBIRTH", "sim01", mark) == 0
        # sim01's data went on while sim02 was down, and nothing of sim02 between death and birth
        assert _count(host, "DDATA", "sim01", dd) - _count(host, "DDATA", "sim01", reborn) >= 3
        assert not [m for m in host.all(since=dd)[:reborn - dd] if m.device == "sim02" and m.kind == "DDATA"]
        assert worker_pids(gw, "sim01") == [pids["sim01"]]
        _seq_ok(host.all())           # still the one session: seq runs on through death and birth
        assert since_kill and all(m.qos == 0 and not m.retain for m in since_kill)
    finally:
        if gw is not None:
            rc = gw.stop()
        sim.stop()
    try:
        # a clean stop: the supervisor's session ends with its NDEATH (same bdSeq as the NBIRTH)
        host.wait(lambda: host.all("NDEATH"), 10, "the NDEATH of a clean stop")
        assert _bdseq(host.all("NDEATH")[-1]) == _bdseq(host.all("NBIRTH")[0])
    finally:
        host.close()
        b.stop()
    assert rc == 0, gw.log()
    assert "Traceback" not in gw.log_all(), gw.log_all()[-4000:]
