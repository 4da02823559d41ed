"""ISA-18.2 alarms end to end: a real station with its MQTT output on a real Mosquitto (the MES
is mosquitto_sub) and its Modbus TCP server (the PLC is mbpoll). Each transition — raised, shelved
by the MES, unshelved, acknowledged by the PLC, out of service and back by PLC command codes, the
hook replaced — shows the same ISA-18.2 state in the retained alarm topic, the retained state and
the PLC's alarm enum register (generated from the same enum)."""
from gateway.core.records import AlarmState, EventType
from gateway.outputs.mqtt import schema as S
from gateway.outputs.plc import registers as R
from gateway.station.alarm_store import AlarmStore
from kit.broker import pub, station_on_broker
from kit.northbound import mbpoll
from kit.tools import free_port, require_tool, wait_for

BASE = "hookwatch/lab/hall/l1/isa"
IR, HR = R.IR, R.HR


def plc_alarms(port):
    """(alarm, warning_alarm) as the PLC reads them, as ISA-18.2 names."""
    rc, v, err = mbpoll(port, "-t", "3", "-r", str(IR["alarm"].address), unit=1)
    assert rc == 0, err
    rc, w, err = mbpoll(port, "-t", "3", "-r", str(IR["warning_alarm"].address), unit=1)
    assert rc == 0, err
    return R.ALARM_STATES[v[IR["alarm"].address]], R.ALARM_STATES[w[IR["warning_alarm"].address]]


def test_the_same_isa_state_in_mqtt_and_the_plc_register(tmp_path):
    require_tool("mbpoll")
    assert R.ALARM_STATES == tuple(a.value for a in AlarmState)      # one definition
    mport = free_port()
    with station_on_broker(tmp_path, BASE, "isa", modbus_port=mport) as (b, sub, st, lt):
        rc, v, _ = mbpoll(mport, "-t", "3", "-r", str(IR["map_version"].address))
        assert v[IR["map_version"].address] == R.MAP_VERSION

        async def end_of_life():             # what the method's end of life does
            st.board.emit(EventType.END_OF_LIFE, k=600, k_life=600, t_life=12.0, mu_ss=0.2,
                           mu_th=0.23, sample_id="S-1")
            st.board.push()

        def step(n_alarm_msgs, want):
            """Wait for the n-th alarm message; MQTT alarm, MQTT state and PLC agree on ``want``."""
            sub.wait(lambda s: len(s.messages("alarm/end_of_life")) >= n_alarm_msgs, 20)
            a = sub.messages("alarm/end_of_life")[n_alarm_msgs - 1][2]
            assert a["state"] == want[0], a
            assert list(a) == S.field_names("alarm")
            wait_for(lambda: plc_alarms(mport) == want, 10, what=f"PLC shows {want}")
            sub.wait(lambda s: any(m[2]["alarm"] == want[0] and m[2]["warning_alarm"] == want[1]
                                   for m in s.messages("state")), 20)
            return a

        lt.call(end_of_life())
        a = step(1, ("unacknowledged", "normal"))
        assert a["condition"] and not a["acknowledged"]
        pub(b.port, f"{BASE}/cmd/shelve", '{"alarm": "end_of_life", "duration_s": 600}')
        a = step(2, ("shelved", "normal"))
        assert a["shelved_until"]
        pub(b.port, f"{BASE}/cmd/unshelve", '{"alarm": "end_of_life"}')
        step(3, ("unacknowledged", "normal"))
        # the PLC acknowledges (command code 3) …
        rc, _, err = mbpoll(mport, "-t", "4", "-r", str(HR["command"].address), values=(R.COMMAND_CODE["ack"],))
        assert rc == 0, err
        a = step(4, ("acknowledged", "normal"))
        assert a["acknowledged_by"].startswith("plc:")
        # … takes the alarms out of service while the needle is changed (code 6), and back (7)
        rc, _, err = mbpoll(mport, "-t", "4", "-r", str(HR["command"].address),
                            values=(R.COMMAND_CODE["out_of_service"],))
        assert rc == 0, err
        step(5, ("out_of_service", "out_of_service"))
        w = sub.wait(lambda s: s.messages("alarm/warning"), 20)[-1][2]
        assert w["state"] == "out_of_service" and w["priority"] == 2
        rc, _, err = mbpoll(mport, "-t", "4", "-r", str(HR["command"].address),
                            values=(R.COMMAND_CODE["in_service"],))
        assert rc == 0, err
        step(6, ("unacknowledged", "normal"))
        # the MES reports the hook replaced: closed
        pub(b.port, f"{BASE}/cmd/hook_replaced", "{}")
        a = step(7, ("normal", "normal"))
        assert not a["active"] and a["cleared_at"]
        # every alarm event carried its transitions; the replies were all ok
        evs = [m[2] for m in sub.messages() if "/event/alarm_" in m[1] or m[1].endswith("/event/end_of_life")]
        moves = [(t["from"], t["to"]) for e in evs for t in e["data"]["transitions"]
                 if t["alarm"] == "end_of_life"]
        assert moves == [("normal", "unacknowledged"), ("unacknowledged", "shelved"),
                         ("shelved", "unacknowledged"), ("unacknowledged", "acknowledged"),
                         ("acknowledged", "out_of_service"), ("out_of_service", "unacknowledged"),
                         ("unacknowledged", "normal")]
        assert all(r[2]["ok"] for r in sub.messages("reply"))
    # the store kept the closed alarm: a new process reads normal
    assert AlarmStore(st.alarms.path, "isa").restore().state.value == "normal"
