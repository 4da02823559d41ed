"""Issue 21: Sparkplug DCMD commands go through the one bounded intake of every door. A real
Mosquitto and the independent primary host (tests/kit/sparkplug_host.py, its own protoc build):
a Setpoint sent as a String metric ("0.6") or a Shelve Duration as a Boolean is refused (code 9),
a long Sample ID is refused and never echoed into DDATA, a Sample ID with a newline gets the
station's code 4 with the value escaped; a well-typed start is carried out; a Stop Test naming
another test (Test ID) is refused (15) and stops nothing, naming the running one ends it."""
from gateway.outputs.sparkplug.node_settings import SparkplugSettings
from gateway.outputs.sparkplug.output import SparkplugOutput
from gateway.station.hook_log import read_hooks
from kit.broker import Broker
from kit.northbound import LoopThread, RunningStation, make_station
from kit.sparkplug_host import PrimaryHost, metric_value
from kit.tools import wait_for

GROUP, NODE, DEV = "lab", "hall-l1", "loom-09"
TOPIC = f"spBv1.0/{GROUP}/DCMD/{NODE}/{DEV}"


def test_dcmd_metrics_are_typed_and_bounded_like_every_other_door(tmp_path):
    lt = LoopThread()
    b = Broker(tmp_path).start()
    host = PrimaryHost(b.port, "unused", GROUP, tmp_path)
    run = None
    try:
        st = make_station(tmp_path, [], station_id=DEV)
        st.outputs.append(SparkplugOutput(SparkplugSettings(
            group_id=GROUP, edge_node_id=NODE, device_id=DEV, servers=[("127.0.0.1", b.port)],
            data_interval_s=0.1, store_path=str(tmp_path / "spb.sqlite")), st))
        run = RunningStation(lt, st)
        host.wait(lambda: host.all("DBIRTH"), 30, "the DBIRTH")
        names = {m.alias: m.name for m in host.all("DBIRTH")[0].p.metrics}

        def results(mark):
            """(Last Command, Last Result Code) after each DDATA since ``mark`` that has a new Last
            Command (a DDATA carries only the metrics that changed: the code may be the same)."""
            out, code = [], None
            for i, msg in enumerate(host.all()):
                if msg.kind != "DDATA":
                    continue
                v = {names.get(x.alias): metric_value(x) for x in msg.p.metrics}
                code = v.get("Device Control/Last Result Code", code)
                if i >= mark and "Device Control/Last Command" in v:
                    out.append((v["Device Control/Last Command"], code))
            return out

        def send(metrics):
            mark = host.mark()
            host.command(TOPIC, metrics)
            return host.wait(lambda: results(mark), 20, "the command's result")[-1]

        start = {"name": "Device Control/Start Test", "boolean_value": True}
        # a String where a number belongs: refused by the intake, nothing started
        text, code = send([start, {"name": "Device Control/Sample ID", "string_value": "SPB-1"},
                           {"name": "Device Control/Setpoint", "string_value": "0.6"}])
        assert code == 9 and "must be a number" in text, text
        assert st.starting is None and st.monitor is None
        # a 200-character Sample ID (within the inbound bounds of the Sparkplug door): refused by the
        # intake, the DDATA that reports it stays small
        text, code = send([start, {"name": "Device Control/Sample ID", "string_value": "X" * 200},
                           {"name": "Device Control/Setpoint", "float_value": 0.5}])
        assert code == 9 and len(text) < 300 and "X" * 60 not in text, text
        # a 1 MB Sample ID: dropped before decoding (the door's inbound bounds), never echoed
        host.command(TOPIC, [start, {"name": "Device Control/Sample ID", "string_value": "X" * 1_000_000},
                             {"name": "Device Control/Setpoint", "float_value": 0.5}])
        # a newline in the Sample ID: the station's code 4, the value escaped
        text, code = send([start, {"name": "Device Control/Sample ID", "string_value": "S-1\nFORGED"},
                           {"name": "Device Control/Setpoint", "float_value": 0.5}])
        assert code == 4 and "\n" not in text, text
        assert all(len(x.p.SerializeToString()) < 2000 for x in host.all("DDATA"))
        # a Boolean where a duration belongs
        text, code = send([{"name": "Device Control/Shelve Alarm", "boolean_value": True},
                           {"name": "Device Control/Alarm", "string_value": "end_of_life"},
                           {"name": "Device Control/Shelve Duration", "boolean_value": True}])
        assert code == 9, text
        assert st.starting is None and st.monitor is None
        # well typed: carried out
        text, code = send([start, {"name": "Device Control/Sample ID", "string_value": "SPB-2"},
                           {"name": "Device Control/Setpoint", "float_value": 0.5}])
        assert code == 0, text
        assert st.plan.sample_id == "SPB-2"
        # issue 20: Hook Replaced with the new hook's Sample ID — a hostile one refused (code 4),
        # nothing logged; a good one carried out (the start in progress ends, hooks.jsonl has it)
        hook = {"name": "Device Control/Hook Replaced", "boolean_value": True}
        text, code = send([hook, {"name": "Device Control/Sample ID", "string_value": "S\tX"}])
        assert code == 4 and "\t" not in text, text
        assert read_hooks(str(tmp_path / "records" / DEV)) == []
        text, code = send([hook, {"name": "Device Control/Sample ID", "string_value": "SPB-3"}])
        assert code == 0, text
        (h,) = read_hooks(str(tmp_path / "records" / DEV))
        assert (h["old_sample_id"], h["new_sample_id"], h["by"]) == ("SPB-2", "SPB-3", "sparkplug")
        # issue 27: a DCMD repeated with the same Request ID is answered again, carried out once
        text, code = send([{"name": "Device Control/Acknowledge Alarm", "boolean_value": True}])
        assert code != 0, text
        again = [hook, {"name": "Device Control/Sample ID", "string_value": "SPB-4"},
                 {"name": "Device Control/Request ID", "string_value": "host-r1"}]
        text, code = send(again)
        assert code == 0 and text == "hook_replaced: accepted", text
        text, code = send(again)
        assert code == 0 and "duplicate" in text and "host-r1" in text, text
        assert [h["new_sample_id"] for h in read_hooks(str(tmp_path / "records" / DEV))] == ["SPB-3", "SPB-4"]
        # issue 34: a Stop Test naming a test (Test ID) ends that test only
        text, code = send([start, {"name": "Device Control/Sample ID", "string_value": "SPB-5"},
                           {"name": "Device Control/Setpoint", "float_value": 0.5}])
        assert code == 0, text
        wait_for(lambda: st.session is not None, 30, what="slot 0 of SPB-5")
        stop = {"name": "Device Control/Stop Test", "boolean_value": True}
        text, code = send([stop, {"name": "Device Control/Test ID", "string_value": "20260101T000000.000Z-OLD"}])
        assert code == 15 and "OLD" in text, text
        assert st.session is not None and not st.results
        text, code = send([stop, {"name": "Device Control/Test ID", "string_value": st.test_id}])
        assert code == 0, text
        wait_for(lambda: st.results, 20, what="SPB-5 ended")
        assert st.results[-1]["end_reason"] == "stopped by command" and st.session is None
    finally:
        if run is not None:
            run.stop()
        lt.close()
        host.close()
        b.stop()
