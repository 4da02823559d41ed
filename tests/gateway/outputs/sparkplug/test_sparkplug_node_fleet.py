"""One Sparkplug edge node hosting two stations (two devices, one MQTT session) through a real
Mosquitto, decoded by the test's own protoc build: one NBIRTH and a DBIRTH per station, aliases
unique in the node, a DCMD reaches only its station, a broker outage without a primary host is
bridged by the store (historical replay), Node Control/Reboot restarts the session with the next
bdSeq, a stopping station gets its DDEATH while the node lives on, the last one ends the node."""
import time

from gateway.outputs.sparkplug.node_settings import SparkplugSettings
from gateway.outputs.sparkplug.output import SparkplugOutput
from kit.broker import Broker
from kit.northbound import LoopThread, RunningStation, make_station
from kit.sparkplug_host import PrimaryHost, metric_value

GROUP, NODE = "lab", "hall-l1"
NODE_KINDS = ("NBIRTH", "NDEATH", "DBIRTH", "DDEATH", "NDATA", "DDATA")


def settings(tmp_path, port, device):
    return SparkplugSettings(group_id=GROUP, edge_node_id=NODE, device_id=device,
                             servers=[("127.0.0.1", port)], data_interval_s=0.1,
                             store_path=str(tmp_path / "spb.sqlite"), reconnect_min_s=1.5,
                             reconnect_max_s=1.5)


def bdseq(m):
    return [x.long_value for x in m.p.metrics if x.name == "bdSeq"][0]


def test_two_stations_one_node_outage_reboot_and_stops(tmp_path):
    lts = [LoopThread(), LoopThread()]
    b = Broker(tmp_path).start()
    host = PrimaryHost(b.port, "unused", GROUP, tmp_path)
    runs = []
    try:
        stations = []
        for i, dev in enumerate(("loom-01", "loom-02")):
            st = make_station(tmp_path, [], station_id=dev)
            st.outputs.append(SparkplugOutput(settings(tmp_path, b.port, dev), st))
            stations.append(st)
            runs.append(RunningStation(lts[i], st))
        host.wait(lambda: len(host.all("DBIRTH")) >= 2, 30, "two DBIRTHs")
        node = [m for m in host.all() if m.kind in NODE_KINDS]
        assert [m.kind for m in node].count("NBIRTH") == 1
        assert [m.kind for m in node[:3]] == ["NBIRTH", "DBIRTH", "DBIRTH"], node[:4]   # gathered
        births = {m.device: m for m in host.all("DBIRTH")}
        assert set(births) == {"loom-01", "loom-02"}
        a1 = {m.alias for m in births["loom-01"].p.metrics}
        a2 = {m.alias for m in births["loom-02"].p.metrics}
        assert not a1 & a2, "aliases must be unique in the edge node"
        b0 = bdseq(node[0])

        # a DCMD start for loom-02 only
        alias = {m.name: m.alias for m in births["loom-02"].p.metrics}
        host.command(f"spBv1.0/{GROUP}/DCMD/{NODE}/loom-02", [
            {"alias": alias["Device Control/Start Test"], "boolean_value": True},
            {"alias": alias["Device Control/Sample ID"], "string_value": "S-2"},
            {"alias": alias["Device Control/Setpoint"], "float_value": 0.5}])
        host.wait(lambda: stations[1].monitor is not None, 20, "loom-02 running")
        assert stations[0].monitor is None
        # Hook Replaced without an alarm: refused through the one command path (NO_ALARM = 3)
        a1n = {m.name: m.alias for m in births["loom-01"].p.metrics}
        a1r = {v: k for k, v in a1n.items()}
        mark = host.mark()
        host.command(f"spBv1.0/{GROUP}/DCMD/{NODE}/loom-01",
                     [{"name": "Device Control/Hook Replaced", "boolean_value": True}])

        def result_code():
            for m in host.all("DDATA", since=mark):
                for x in m.p.metrics:
                    if m.device == "loom-01" and a1r.get(x.alias) == "Device Control/Last Result Code":
                        return metric_value(x)
        assert host.wait(result_code, 20, "the Hook Replaced refusal") == 3

        # broker outage: data held in the store, replayed as historical after the births
        b.stop()
        time.sleep(2.0)
        mark = host.mark()
        b = Broker(tmp_path, port=b.port).start()
        host.wait(lambda: [m for m in host.all("DDATA", since=mark)
                           if not any(x.is_historical for x in m.p.metrics)], 40,
                  "live data after the outage")
        back = [m for m in host.all(since=mark) if m.kind in NODE_KINDS]
        assert [m.kind for m in back[:3]] == ["NBIRTH", "DBIRTH", "DBIRTH"], back[:4]
        assert bdseq(back[0]) == (b0 + 1) % 256
        hist = [m for m in back if m.kind == "DDATA" and all(x.is_historical for x in m.p.metrics)]
        assert len(hist) >= 10, "about 2 s of 0.1 s data of two stations were held"
        stamps = {}
        for m in hist:
            stamps.setdefault(m.device, []).append(m.p.metrics[0].timestamp)
        assert all(v == sorted(v) for v in stamps.values())

        # Node Control/Reboot: NDEATH, a new session (bdSeq + 1), births; the tests go on
        mark = host.mark()
        host.command(f"spBv1.0/{GROUP}/NCMD/{NODE}", [{"name": "Node Control/Reboot", "boolean_value": True}])
        host.wait(lambda: len(host.all("DBIRTH", since=mark)) >= 2, 30, "births after the reboot")
        kinds = [m.kind for m in host.all(since=mark) if m.kind in NODE_KINDS]
        # DDATA of the old session may come before the NCMD is handled; after the NDEATH: births
        assert "NDEATH" in kinds and set(kinds[:kinds.index("NDEATH")]) <= {"DDATA"}, kinds[:6]
        assert kinds[kinds.index("NDEATH"):][:2] == ["NDEATH", "NBIRTH"], kinds[:6]
        assert bdseq(host.all("NBIRTH", since=mark)[0]) == (b0 + 2) % 256
        assert stations[1].monitor is not None

        # loom-01 stops: its DDEATH, the node and loom-02 live on
        mark = host.mark()
        runs[0].stop()
        host.wait(lambda: host.all("DDEATH", since=mark), 20, "DDEATH of loom-01")
        assert host.all("DDEATH", since=mark)[0].device == "loom-01"
        time.sleep(0.5)
        assert not host.all("NDEATH", since=mark)
        assert any(m.device == "loom-02" for m in host.all("DDATA", since=mark))
        # the last station: DDEATH then NDEATH
        mark = host.mark()
        runs[1].stop()
        host.wait(lambda: host.all("NDEATH", since=mark), 20, "NDEATH of the node")
        kinds = [m.kind for m in host.all(since=mark) if m.kind in NODE_KINDS]
        assert kinds[-2:] == ["DDEATH", "NDEATH"], kinds
        runs = []
        vals = [metric_value(x) for x in births["loom-01"].p.metrics if x.name == "Test/State"]
        assert vals == ["idle"]
    finally:
        for r in runs:
            r.stop()
        for lt in lts:
            lt.close()
        host.close()
        b.stop()
