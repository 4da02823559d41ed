"""Sparkplug B 3.0 end to end: `hookwatch sim` + `hookwatch run` with a `sparkplug:` section, a
real Mosquitto, and a primary host whose decoder is compiled here from sparkplug_b.proto (not
the gateway's code): births and deaths in order, aliases, seq, rebirth, a DCMD that starts a
test, STATE offline/online with the held data replayed as historical in order, kill -9 and
restart with bdSeq."""
import os
import signal
import sqlite3

import yaml

from conftest import ROOT
from kit.broker import Broker
from kit.e2e import run_gateway, station_yaml, virtual_station
from kit.sparkplug_host import PrimaryHost, metric_value

METER_MAP = os.path.join(ROOT, "config", "meters", "zn-s.yaml")
GROUP, NODE, DEV = "lab", "test-l1", "spb"
NODE_KINDS = ("NBIRTH", "NDEATH", "DBIRTH", "DDEATH", "NDATA", "DDATA")


def scenario(tmp_path):
    sc = {"description": "sparkplug e2e", "seed": 7, "meter": {"map": METER_MAP},
          "stm32": {"watchdog_s": 0.2}, "plant": {"grade": "I", "t_set": 0.5, "time_scale": 60},
          "method": {"w_ss": 5, "w_hold": 20, "tau": 5, "t_end": 600}, "faults": []}
    p = tmp_path / "sc.yaml"
    p.write_text(yaml.safe_dump(sc, sort_keys=False))
    return str(p)


def spb_station(tmp_path, links, port):
    path = station_yaml(tmp_path, links, name=DEV, control={"dead_band_n": 0.01},
                        method={"w_ss": 5, "w_hold": 20, "tau": 5}, test={"t_end_s": 600})
    with open(path) as f:
        cfg = yaml.safe_load(f)
    cfg["sparkplug"] = {"enabled": True, "port": port, "primary_host_id": "scada", "data_interval_s": 0.1}
    with open(path, "w") as f:
        yaml.safe_dump(cfg, f, sort_keys=False)
    return path


def bdseq(msg):
    v = [m.long_value for m in msg.p.metrics if m.name == "bdSeq"]
    assert len(v) == 1, msg
    return v[0]


def check_session(msgs):
    """From an NBIRTH on: seq 0, then +1 mod 256 for every message of the node; DDATA by alias only,
    each alias one of the DBIRTH's. Returns the number of seq wraps seen."""
    msgs = [m for m in msgs if m.kind in NODE_KINDS]
    assert msgs[0].kind == "NBIRTH" and msgs[0].p.seq == 0, msgs[:3]
    aliases = {}
    wraps = 0
    for a, b in zip(msgs, msgs[1:]):
        if b.kind in ("NDEATH", "NBIRTH"):
            break
        assert b.p.seq == (a.p.seq + 1) % 256, (a, b)
        wraps += b.p.seq == 0
        if b.kind == "DBIRTH":
            aliases[b.device] = {m.alias: m.name for m in b.p.metrics}
            assert all(m.name and m.alias and m.datatype for m in b.p.metrics)
        elif b.kind == "DDATA":
            assert b.device in aliases, f"DDATA before DBIRTH of {b.device}"
            for m in b.p.metrics:
                assert not m.name and m.alias in aliases[b.device], m
    return wraps, aliases


def values(msgs, aliases, name):
    """(value, is_historical, timestamp) of a named metric in DDATA, in arrival order."""
    out = []
    for msg in msgs:
        if msg.kind != "DDATA":
            continue
        for m in msg.p.metrics:
            if aliases[msg.device].get(m.alias) == name:
                out.append((metric_value(m), m.is_historical, m.timestamp))
    return out


def test_primary_host_sees_a_trustworthy_edge_node(tmp_path):
    with Broker(tmp_path) as b:
        host = PrimaryHost(b.port, "scada", GROUP, tmp_path)
        host.state(True)
        gw = None
        try:
            with virtual_station(tmp_path, scenario(tmp_path)) as (_sim, links):
                st = spb_station(tmp_path, links, b.port)
                gw = run_gateway(tmp_path, st)
                # --- birth: NBIRTH (seq 0, bdSeq) then DBIRTH with every metric and its properties
                host.wait(lambda: host.all("DDATA"), 60, "DDATA after the births")
                first = host.all()
                assert [m.kind for m in first[:2]] == ["NBIRTH", "DBIRTH"], first[:5]
                assert first[0].topic == f"spBv1.0/{GROUP}/NBIRTH/{NODE}"
                assert first[1].topic == f"spBv1.0/{GROUP}/DBIRTH/{NODE}/{DEV}"
                assert all(m.qos == 0 and not m.retain for m in first)
                b0 = bdseq(first[0])
                nb = {m.name: m for m in first[0].p.metrics}
                assert {"Node Control/Rebirth", "Node Control/Next Server", "Node Control/Reboot"} <= set(nb)
                db = {m.name: m for m in first[1].p.metrics}
                t1 = db["Tension/T1"]
                props = dict(zip(t1.properties.keys, t1.properties.values))
                assert props["engUnit"].string_value == "N" and t1.datatype == 9   # Float
                assert metric_value(db["Test/State"]) == "idle"

                # --- DCMD start (by alias, arguments by name) through the one command path
                alias = {n: m.alias for n, m in db.items()}
                mark = host.mark()
                host.command(f"spBv1.0/{GROUP}/DCMD/{NODE}/{DEV}", [
                    {"alias": alias["Device Control/Start Test"], "boolean_value": True},
                    {"name": "Device Control/Sample ID", "string_value": "SPB-1"},
                    {"name": "Device Control/Setpoint", "float_value": 0.5}])
                _, aliases = check_session(first)

                # the start (METHOD.md §3a) first: `starting` during the zero check and the spin-up,
                # then slot 0 and `baseline_search`; the start may take up to the method's
                # start_timeout (30 s) before it succeeds or fails, so wait longer than that
                def states():
                    return [v[0] for v in values(host.all(since=mark), aliases, "Test/State")]
                host.wait(lambda: "starting" in states(), 20, "Test/State starting after the DCMD start")
                host.wait(lambda: states()[-1] != "starting", 60, "the end of the start (§3a)")
                seen = states()
                assert seen[-1] in ("baseline_search", "monitoring"), seen
                assert seen.index("starting") < seen.index(seen[-1]), seen
                host.wait(lambda: any(v[0] == 0 for v in values(host.all(since=mark), aliases,
                                                                "Device Control/Last Result Code")),
                          20, "Last Result Code 0 (the start accepted)")
                assert ("SPB-1", False) in [v[:2] for v in values(host.all(since=mark), aliases,
                                                                    "Test/Sample ID")]

                # --- rebirth on NCMD: NBIRTH seq 0, same bdSeq, DBIRTH again
                mark = host.mark()
                host.command(f"spBv1.0/{GROUP}/NCMD/{NODE}",
                             [{"name": "Node Control/Rebirth", "boolean_value": True}])
                host.wait(lambda: host.all("DBIRTH", since=mark), 20, "DBIRTH after the rebirth")
                re = host.all(since=mark)
                nbirths = [m for m in re if m.kind == "NBIRTH"]
                assert len(nbirths) == 1 and bdseq(nbirths[0]) == b0 and nbirths[0].p.seq == 0
                check_session(host.all())  # the first session, up to the rebirth
                check_session(re[re.index(nbirths[0]):])

                # --- STATE offline: NDEATH, nothing live, the data held in the store
                mark = host.mark()
                host.state(False)
                host.wait(lambda: host.all("NDEATH", since=mark), 20, "NDEATH after STATE offline")
                nd = host.all("NDEATH", since=mark)[0]
                assert bdseq(nd) == b0
                quiet_from = host.mark()
                store = os.path.join(str(tmp_path / "records"), f"sparkplug-{GROUP}-{NODE}.sqlite")

                def held():
                    with sqlite3.connect(store) as db_:
                        return db_.execute("SELECT COUNT(*) FROM messages").fetchone()[0]
                host.wait(lambda: held() >= 270, 90, "270 DDATA held in the store")
                quiet = [m for m in host.all(since=quiet_from) if m.kind in NODE_KINDS]
                assert quiet == [], quiet[:5]

                # --- STATE online: new session (bdSeq+1), births, historical replay in order, live
                mark = host.mark()
                host.state(True)
                host.wait(lambda: host.mark() > mark and held() == 0 and [
                    m for m in host.all("DDATA", since=mark)
                    if not any(x.is_historical for x in m.p.metrics)], 60, "live DDATA after the replay")
                back = [m for m in host.all(since=mark) if m.kind in NODE_KINDS]
                assert [m.kind for m in back[:2]] == ["NBIRTH", "DBIRTH"]
                assert bdseq(back[0]) == (b0 + 1) % 256
                wraps, aliases = check_session(back)
                assert wraps >= 1, "the replay crossed seq 255 → 0"
                ddata = [m for m in back if m.kind == "DDATA"]
                hist = [m for m in ddata if all(x.is_historical for x in m.p.metrics)]
                assert len(hist) >= 270
                first_live = next(i for i, m in enumerate(ddata) if not any(x.is_historical for x in m.p.metrics))
                assert all(all(x.is_historical for x in m.p.metrics) for m in ddata[:first_live])
                assert first_live >= 270
                stamps = [m.p.metrics[0].timestamp for m in ddata[:first_live]]
                assert stamps == sorted(stamps), "history replayed out of order"
                assert ddata[first_live].p.metrics[0].timestamp >= stamps[-1]

                # --- kill -9: the broker sends the Will (NDEATH, QoS 1) with the session's bdSeq
                mark = host.mark()
                gw.stop(signal.SIGKILL)
                host.wait(lambda: host.all("NDEATH", since=mark), 90, "the Will NDEATH after kill -9")
                will = host.all("NDEATH", since=mark)[0]
                assert bdseq(will) == bdseq(back[0]) and will.qos == 1 and not will.retain
                # --- restart: bdSeq continues from the persisted value
                mark = host.mark()
                gw = run_gateway(tmp_path, st, name="gw2")
                host.wait(lambda: host.all("DBIRTH", since=mark), 60, "births after the restart")
                again = [m for m in host.all(since=mark) if m.kind in NODE_KINDS]
                assert again[0].kind == "NBIRTH" and bdseq(again[0]) == (bdseq(back[0]) + 1) % 256

                # --- a clean stop: DDEATH, then NDEATH with the session's bdSeq
                mark = host.mark()
                gw.stop()
                gw = None
                host.wait(lambda: host.all("NDEATH", since=mark), 30, "NDEATH on a clean stop")
                end = [m.kind for m in host.all(since=mark) if m.kind in ("DDEATH", "NDEATH")]
                assert end[:2] == ["DDEATH", "NDEATH"], end
                assert bdseq(host.all("NDEATH", since=mark)[0]) == bdseq(again[0])
        finally:
            if gw is not None:
                gw.stop()
            host.close()
