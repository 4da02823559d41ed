"""ISA-18.2 alarms in the station's one alarm store, driven through the one command path
(Station.submit → commands.validate → a station event → AlarmStore.on_event): every transition is
in one station event, the state the outputs read follows, alarm.json keeps it across a restart and
an alarm.json of the old form (none/active/acknowledged) still loads."""
import asyncio
import json
import time

from gateway.core.command_intake import intake
from gateway.core.records import Command, CommandKind, EventType
from gateway.station.alarm_store import AlarmStore
from gateway.station.command_desk import CODE
from kit.fakes import Capture
from kit.northbound import LoopThread, RunningStation, make_station
from kit.tools import wait_for


def _submit(st, kind, source="mqtt", **args):
    return asyncio.run(st.submit(Command(kind, source, args)))


def _eol(st):
    st.board.emit(EventType.END_OF_LIFE, k=600, k_life=600, t_life=12.0, mu_ss=0.2, mu_th=0.23,
                   sample_id="S-1")


def _trans(out):
    """(event type, [(alarm, from, to, action)]) of each event that carried transitions."""
    return [(e.type, [(t["alarm"], t["from"], t["to"], t["action"]) for t in e.data["transitions"]])
            for e in out.events if e.data.get("transitions")]


def test_the_isa_lifecycle_through_the_command_path_one_event_per_command(tmp_path):
    out = Capture()
    st = make_station(tmp_path, [out], station_id="isa")
    _eol(st)
    assert st.state.alarm == "unacknowledged" and st.state.warning_alarm == "normal"
    # shelve: an MQTT payload through the same parser and validation
    cmd = intake("shelve", {"alarm": "end_of_life", "duration_s": 600}, "mqtt")
    t0 = time.time()
    assert asyncio.run(st.submit(cmd)).ok
    assert st.state.alarm == "shelved"
    until = st.alarms.models["end_of_life"].shelved_until
    assert t0 + 599 < until < time.time() + 601 and st.alarms.record.shelved_until is not None
    assert _submit(st, CommandKind.UNSHELVE, alarm="end_of_life").ok
    assert st.state.alarm == "unacknowledged"
    assert _submit(st, CommandKind.ACK, "plc:127.0.0.1").ok
    assert st.state.alarm == "acknowledged" and st.alarms.record.acknowledged_by == "plc:127.0.0.1"
    # a needle is being changed: both alarms out of service, then back
    assert _submit(st, CommandKind.OUT_OF_SERVICE, "cli").ok
    assert (st.state.alarm, st.state.warning_alarm) == ("out_of_service", "out_of_service")
    assert _submit(st, CommandKind.IN_SERVICE, "cli").ok
    # the worn hook is still in: its alarm comes back unacknowledged; the warning back to normal
    assert (st.state.alarm, st.state.warning_alarm) == ("unacknowledged", "normal")
    assert _submit(st, CommandKind.HOOK_REPLACED, "sparkplug").ok
    assert (st.state.alarm, st.state.warning_alarm) == ("normal", "normal")
    assert st.alarms.models["end_of_life"].closed_by == "hook_replaced"
    assert _trans(out) == [
        (EventType.END_OF_LIFE, [("end_of_life", "normal", "unacknowledged", "activate")]),
        (EventType.ALARM_SHELVED, [("end_of_life", "unacknowledged", "shelved", "shelve")]),
        (EventType.ALARM_UNSHELVED, [("end_of_life", "shelved", "unacknowledged", "unshelve")]),
        (EventType.ALARM_ACK, [("end_of_life", "unacknowledged", "acknowledged", "acknowledge")]),
        (EventType.ALARM_OUT_OF_SERVICE, [("end_of_life", "acknowledged", "out_of_service",
                                           "remove_from_service"),
                                          ("wear_warning", "normal", "out_of_service", "remove_from_service")]),
        (EventType.ALARM_IN_SERVICE, [("end_of_life", "out_of_service", "unacknowledged", "return_to_service"),
                                      ("wear_warning", "out_of_service", "normal", "return_to_service")]),
        (EventType.ALARM_CLEARED, [("end_of_life", "unacknowledged", "normal", "hook_replaced")]),
    ]
    tr = next(e for e in out.events if e.type == EventType.ALARM_ACK).data["transitions"][0]
    assert tr["by"] == "plc:127.0.0.1" and tr["priority"] == 1 and tr["hook"] == st.alarms.record.test_id


def test_alarm_commands_refused_with_reason_and_code(tmp_path):
    out = Capture()
    st = make_station(tmp_path, [out], station_id="rej")

    def code(kind, **args):
        r = _submit(st, kind, **args)
        assert not r.ok and r.reason
        return r.code

    assert code(CommandKind.SHELVE, alarm="end_of_life", duration_s=60) == CODE["ALARM_STATE"]   # normal
    _eol(st)
    assert code(CommandKind.SHELVE, alarm="nope", duration_s=60) == CODE["ALARM"]
    assert code(CommandKind.SHELVE, alarm="end_of_life", duration_s=0) == CODE["DURATION"]
    assert code(CommandKind.SHELVE, alarm="end_of_life", duration_s=13 * 3600) == CODE["DURATION"]
    assert code(CommandKind.SHELVE, alarm="end_of_life", duration_s=True) == CODE["DURATION"]
    assert code(CommandKind.SHELVE, alarm="wear_warning", duration_s=60) == CODE["ALARM_STATE"]
    assert code(CommandKind.UNSHELVE, alarm="end_of_life") == CODE["ALARM_STATE"]
    assert code(CommandKind.IN_SERVICE) == CODE["ALARM_STATE"]
    assert _submit(st, CommandKind.OUT_OF_SERVICE).ok
    assert code(CommandKind.OUT_OF_SERVICE) == CODE["ALARM_STATE"]
    assert code(CommandKind.ACK) == CODE["NO_ALARM"]                     # out of service: nothing to ack
    rej = [e for e in out.events if e.type == EventType.COMMAND_REJECTED]
    # every refusal counted; the events bounded per kind (door, command, code) and window
    assert st.desk.gate.refusals == 10 and len(rej) == 7
    assert all(not e.data.get("transitions") and e.data["count"] == 1 for e in rej)
    assert st.state.alarm == "out_of_service"
    bad = intake("shelve", {"alarm": "end_of_life", "until": 5}, "mqtt")
    assert not bad.ok and bad.code == CODE["BAD_REQUEST"]


def test_a_shelving_expires_in_the_running_station(tmp_path):
    out = Capture()
    st = make_station(tmp_path, [out], station_id="exp")
    _eol(st)
    lt = LoopThread()
    run = RunningStation(lt, st)
    try:
        r = lt.call(st.submit(Command(CommandKind.SHELVE, "mqtt", {"alarm": "end_of_life", "duration_s": 0.3})))
        assert r.ok and st.state.alarm == "shelved"
        wait_for(lambda: st.state.alarm == "unacknowledged", 10, what="shelving expired")
    finally:
        run.stop()
        lt.close()
    exp = [e for e in out.events if e.type == EventType.ALARM_UNSHELVED]
    assert len(exp) == 1 and exp[0].data["expired"] is True
    assert exp[0].data["transitions"][0]["action"] == "shelve_expired"


def test_alarms_persist_across_a_restart_of_the_store(tmp_path):
    st = make_station(tmp_path, [], station_id="per")
    _eol(st)
    st.board.emit(EventType.WEAR_WARNING, warn_slot=10, t_warn=0.22, headroom=0.4, sample_id="S-1")
    assert _submit(st, CommandKind.SHELVE, alarm="wear_warning", duration_s=3600).ok
    assert _submit(st, CommandKind.ACK).ok
    src = st.alarms.path
    again = AlarmStore(src, "per")
    again.restore()
    assert (again.record.state.value, again.warning.state.value) == ("acknowledged", "shelved")
    assert again.models["warning"].shelved_until == st.alarms.models["warning"].shelved_until
    assert again.record.t_life == 12.0 and again.warning.headroom == 0.4
    # a restarted station shows the same, and its unshelve goes on where the old one stopped
    st2 = make_station(tmp_path, [], station_id="per")
    st2.board.restore_alarm()
    assert (st2.state.alarm, st2.state.warning_alarm) == ("acknowledged", "shelved")
    assert _submit(st2, CommandKind.UNSHELVE, alarm="wear_warning").ok
    assert st2.state.warning_alarm == "unacknowledged"
    # an unreadable file: no alarm, no crash
    with open(src, "w") as f:
        f.write("{not json")
    assert AlarmStore(src, "x").restore().state.value == "normal"


def test_an_old_alarm_json_still_loads_and_goes_on(tmp_path):
    """The form before ISA-18.2: ``alarm`` none/active/acknowledged, no ``isa`` model."""
    old = {"alarm": "acknowledged", "raised": True, "acknowledged": True, "test_id": "T-1",
           "sample_id": "S-1", "t_life": 99.5, "k_life": 4975, "mu_ss": 0.2, "mu_th": 0.23,
           "raised_at": "2026-11-01T10:00:00.000Z", "acknowledged_at": "2026-11-01T10:05:00.000Z",
           "acknowledged_by": "mqtt", "cleared_at": None,
           "warning": {"alarm": "active", "raised": True, "acknowledged": False, "test_id": "T-1",
                       "warn_slot": 100, "t_warn": 2.02, "headroom": 0.4}}
    d = tmp_path / "old"
    d.mkdir(parents=True)
    (d / "alarm.json").write_text(json.dumps(old))
    store = AlarmStore(str(d / "alarm.json"), "old")
    rec = store.restore()
    assert rec.state.value == "acknowledged" and rec.t_life == 99.5 and rec.condition
    assert store.warning.state.value == "unacknowledged" and store.warning.headroom == 0.4
    assert store.models["end_of_life"].hook == "T-1" and store.models["end_of_life"].condition
    # the station on top of it: the warning can be acknowledged, the hook replaced closes both
    st = make_station(tmp_path, [], station_id="old2")
    st.alarms = store
    st.board.restore_alarm()
    assert (st.state.alarm, st.state.warning_alarm) == ("acknowledged", "unacknowledged")
    assert _submit(st, CommandKind.ACK).ok and st.state.warning_alarm == "acknowledged"
    assert _submit(st, CommandKind.HOOK_REPLACED).ok
    assert (st.state.alarm, st.state.warning_alarm) == ("normal", "normal")
    kept = json.loads((d / "alarm.json").read_text())
    assert kept["alarm"] == "normal" and kept["isa"]["state"] == "normal"
    assert kept["warning"]["isa"]["closed_by"] == "hook_replaced"
