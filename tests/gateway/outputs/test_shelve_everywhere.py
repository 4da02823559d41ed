"""Shelve / unshelve from every door, through the one command path (issue 15).

- The PLC (mbpoll) writes `alarm_select` and `shelve_duration`, then command code 8: the wear
  warning is shelved — the PLC reads it in `warning_alarm`, the MES (mosquitto_sub) gets the
  retained `alarm/warning` with `shelved_until`; a refused shelve answers exception 03 with the
  reason code in `last_result`; code 9 unshelves.
- A Sparkplug primary host (tests/kit/sparkplug_host.py, its own protoc build) sees both alarms in
  the DBIRTH (the wear warning with the same State/Active/Priority/Shelved Until as the end of
  life), shelves the wear warning by DCMD and sees the DDATA of the change.
"""
import datetime as dt
import time

from gateway.core.records import EventType
from gateway.outputs.plc import registers as R
from gateway.outputs.sparkplug import metrics as SM
from gateway.outputs.sparkplug.node_settings import SparkplugSettings
from gateway.outputs.sparkplug.output import SparkplugOutput
from gateway.station.command_desk import CODE
from kit.broker import Broker, station_on_broker
from kit.northbound import LoopThread, RunningStation, make_station, mbpoll
from kit.sparkplug_host import PrimaryHost, metric_value
from kit.tools import free_port, require_tool, wait_for

BASE = "hookwatch/lab/hall/l1/shelf"
IR, HR = R.IR, R.HR


def wear_warning(st):
    async def fire():                          # what the method's §5a early warning does
        st.board.emit(EventType.WEAR_WARNING, k=300, warn_slot=300, t_warn=6.02, headroom=0.2,
                       t_cross=40.0, h_warn=0.25, n_warn=3, mu_ss=0.2, mu_th=0.23, sample_id="S-1")
        st.board.push()
    return fire()


def plc_read(port, name):
    r = IR[name]
    rc, v, err = mbpoll(port, "-t", "3", "-r", str(r.address))
    assert rc == 0, err
    return v[r.address]


def plc_write(port, name, value):
    r = HR[name]
    kind = "4:int" if r.type == "uint32" else "4"
    return mbpoll(port, "-t", kind, "-B", "-r", str(r.address), values=(value,))


def test_plc_shelves_and_unshelves_the_wear_warning_seen_by_mqtt_and_the_registers(tmp_path):
    require_tool("mbpoll")
    mport = free_port()
    with station_on_broker(tmp_path, BASE, "shelf", modbus_port=mport) as (_b, sub, st, lt):
        lt.call(wear_warning(st))
        wait_for(lambda: R.ALARM_STATES[plc_read(mport, "warning_alarm")] == "unacknowledged", 10,
                 what="the PLC sees the wear warning")

        # refused before anything changes: a duration beyond one shift (exception 03) …
        rc, _, err = plc_write(mport, "shelve_duration", 50_000)
        assert rc != 0 and "Illegal data value" in err, err
        # … and through the command path: no alarm selected → exception 03, code ALARM
        rc, _, err = plc_write(mport, "shelve_duration", 600)
        assert rc == 0, err
        rc, _, err = plc_write(mport, "command", R.COMMAND_CODE["shelve"])
        assert rc != 0 and "Illegal data value" in err, "a shelve without an alarm must be refused"
        assert plc_read(mport, "last_command") == R.COMMAND_CODE["shelve"]
        assert plc_read(mport, "last_result") == CODE["ALARM"]
        assert R.ALARM_STATES[plc_read(mport, "warning_alarm")] == "unacknowledged"

        # the shelve: alarm_select 2 (wear_warning), 600 s, code 8
        assert R.ALARM_SELECT[2 - 1] == "wear_warning"
        rc, _, err = plc_write(mport, "alarm_select", 2)
        assert rc == 0, err
        t0 = time.time()
        rc, _, err = plc_write(mport, "command", R.COMMAND_CODE["shelve"])
        assert rc == 0, err
        assert plc_read(mport, "last_result") == 0
        wait_for(lambda: R.ALARM_STATES[plc_read(mport, "warning_alarm")] == "shelved", 10,
                 what="the PLC register shows shelved")
        assert R.ALARM_STATES[plc_read(mport, "alarm")] == "normal"      # only the selected alarm
        w = sub.wait(lambda s: [m for m in s.messages("alarm/warning") if m[2]["state"] == "shelved"],
                     20, what="alarm/warning shelved")[-1]
        p = w[2]
        assert p["alarm"] == "warning" and p["priority"] == 2 and p["condition"] is True
        until = dt.datetime.strptime(p["shelved_until"], "%Y-%m-%dT%H:%M:%S.%fZ").replace(
            tzinfo=dt.UTC).timestamp()
        assert abs(until - (t0 + 600)) < 5, (p["shelved_until"], t0)
        ev = sub.wait(lambda s: s.messages("event/alarm_shelved"), 20)[-1][2]
        tr = ev["data"]["transitions"]
        assert [(t["alarm"], t["from"], t["to"]) for t in tr] == [("wear_warning", "unacknowledged",
                                                                   "shelved")]
        assert tr[0]["by"].startswith("plc:")

        # unshelve: code 9 with the same selection
        rc, _, err = plc_write(mport, "command", R.COMMAND_CODE["unshelve"])
        assert rc == 0, err
        wait_for(lambda: R.ALARM_STATES[plc_read(mport, "warning_alarm")] == "unacknowledged", 10,
                 what="unshelved in the register")
        sub.wait(lambda s: s.messages("alarm/warning")[-1][2]["state"] == "unacknowledged", 20,
                 what="alarm/warning unshelved")
        assert sub.messages("alarm/warning")[-1][2]["shelved_until"] is None


def test_sparkplug_host_sees_the_wear_warning_and_shelves_it_by_dcmd(tmp_path):
    lt = LoopThread()
    b = Broker(tmp_path).start()
    host = PrimaryHost(b.port, "unused", "lab", tmp_path)
    run = None
    try:
        st = make_station(tmp_path, [], station_id="loom-07")
        st.outputs.append(SparkplugOutput(SparkplugSettings(
            group_id="lab", edge_node_id="hall-l1", device_id="loom-07", servers=[("127.0.0.1", b.port)],
            data_interval_s=0.2, store_path=str(tmp_path / "spb.sqlite"), reconnect_min_s=0.5), st))
        run = RunningStation(lt, st)
        birth = host.wait(lambda: host.all("DBIRTH"), 30, "DBIRTH")[-1]
        names = {m.name: m for m in birth.p.metrics}
        for folder in SM.ALARM_FOLDERS.values():      # both alarms, the same four metrics
            for leaf in ("State", "Active", "Priority", "Shelved Until"):
                assert f"{folder}/{leaf}" in names, f"{folder}/{leaf} missing from the DBIRTH"
        assert metric_value(names["Alarm/Wear Warning/State"]) == "normal"
        assert metric_value(names["Alarm/Wear Warning/Priority"]) == 2
        assert metric_value(names["Alarm/End Of Life/Priority"]) == 1
        assert names["Alarm/Wear Warning/Shelved Until"].is_null
        by_alias = {m.alias: m.name for m in birth.p.metrics}

        def latest(name, since):
            """The last DDATA value of metric ``name`` since ``since`` (DDATA carries aliases only)."""
            got = None
            for msg in host.all("DDATA", since=since):
                for x in msg.p.metrics:
                    assert not x.name, "DDATA by alias only"
                    if by_alias.get(x.alias) == name:
                        got = (metric_value(x),)
            return got

        mark = host.mark()
        lt.call(wear_warning(st))
        host.wait(lambda: latest("Alarm/Wear Warning/State", mark) == ("unacknowledged",), 20,
                  "the wear warning raised")
        assert latest("Alarm/Wear Warning/Active", mark) == (True,)
        assert latest("Alarm/End Of Life/State", mark) is None              # unchanged: not resent

        topic = "spBv1.0/lab/DCMD/hall-l1/loom-07"
        mark = host.mark()                 # a shelve without a duration: refused (DURATION)
        host.command(topic, [{"name": SM.SHELVE, "boolean_value": True},
                             {"name": SM.ARG_ALARM, "string_value": "wear_warning"}])
        assert host.wait(lambda: latest("Device Control/Last Result Code", mark), 20,
                         "the refusal") == (CODE["DURATION"],)

        mark = host.mark()
        t0 = time.time()
        alias = {v: k for k, v in by_alias.items()}
        host.command(topic, [{"alias": alias[SM.SHELVE], "boolean_value": True},
                             {"alias": alias[SM.ARG_ALARM], "string_value": "wear_warning"},
                             {"alias": alias[SM.ARG_DURATION], "double_value": 900.0}])
        host.wait(lambda: latest("Alarm/Wear Warning/State", mark) == ("shelved",), 20, "shelved")
        assert host.wait(lambda: latest("Device Control/Last Result Code", mark), 20, "the result") == (0,)
        assert latest("Alarm/Wear Warning/Active", mark) == (False,)
        (until,) = latest("Alarm/Wear Warning/Shelved Until", mark)
        assert abs(until / 1000 - (t0 + 900)) < 5, until
        assert st.state.warning_alarm == "shelved" and st.state.alarm == "normal"

        mark = host.mark()
        host.command(topic, [{"name": SM.UNSHELVE, "boolean_value": True},
                             {"name": SM.ARG_ALARM, "string_value": "wear_warning"}])
        host.wait(lambda: latest("Alarm/Wear Warning/State", mark) == ("unacknowledged",), 20, "unshelved")
        assert latest("Alarm/Wear Warning/Shelved Until", mark) == (None,)
    finally:
        if run is not None:
            run.stop()
        host.close()
        lt.close()
        b.stop()


def test_the_register_map_gives_shelve_and_unshelve_their_arguments():
    from gateway.core.ports import StationLimits
    from gateway.core.records import CommandKind

    lim = StationLimits(full_scale=10.0, sat_ratio=0.98, grades=("A",))
    hr = [0] * R.HOLDING_SIZE
    assert R.COMMAND_KINDS[R.COMMAND_CODE["shelve"]] == CommandKind.SHELVE
    assert R.COMMAND_KINDS[R.COMMAND_CODE["unshelve"]] == CommandKind.UNSHELVE
    for word_order in ("big", "little"):
        p = R.plan_write(hr, HR["alarm_select"].address,
                         [1] + R.encode_value(HR["shelve_duration"], 3600, word_order), word_order, lim)
        assert p.exception is None, p.reason
        assert R.command_args(CommandKind.SHELVE, p.new, word_order, ()) == {"alarm": "end_of_life",
                                                                            "duration_s": 3600.0}
        assert R.command_args(CommandKind.UNSHELVE, p.new, word_order, ()) == {"alarm": "end_of_life"}
    # nothing selected: no alarm argument (the command path refuses it with code ALARM)
    assert R.command_args(CommandKind.SHELVE, hr, "big", ()) == {"duration_s": 0.0}
    assert R.command_args(CommandKind.STOP, hr, "big", ()) == {}
    assert R.plan_write(hr, HR["alarm_select"].address, [3], "big", lim).exception == R.EXC_ILLEGAL_VALUE
    # added at the end: the addresses of map version 3 did not move
    assert HR["alarm_select"].address > HR["sample_id"].address and R.MAP_VERSION >= 3   # 4 added input registers only
