"""Issue 27.8 end to end: a station whose meter is pymodbus' own RTU serial server (an independent
slave, a process of its own, behind socat's pty pair: replies not paced at any baud) fills its
slots — it once filled 10 of 1,219, refusing every reply as stale, silently. Asserted as counts:
every slot polled or passed over, every poll a reading or a failure counted by its cause, no
reply refused (no share of filled slots, which is a timing figure)."""
from kit.e2e import read_json, run_gateway, station_yaml, virtual_station, wait_exit
from kit.pymodbus_slave import pymodbus_meter
from kit.tools import require_tool

FAILURES = ("timeouts", "crc_errors", "garbage", "modbus_exceptions", "decode_errors", "stale_replies",
            "errors")


def test_a_station_on_pymodbus_serial_server_fills_its_slots(tmp_path):
    require_tool("socat")
    with virtual_station(tmp_path, "config/scenarios/demo.yaml") as (_sim, links), \
            pymodbus_meter(tmp_path) as meter:
        st = station_yaml(tmp_path, {**links, "meter": meter}, name="pym")
        stats_path = tmp_path / "stats.json"
        gw = run_gateway(tmp_path, st, "--duration", "5", "--stats-json", str(stats_path))
        try:
            assert wait_exit(gw, 60) == 0, gw.log()
            log = gw.log_all()
        finally:
            gw.stop()
    s = read_json(str(stats_path))["pym"]
    c = s["meter"]
    assert c["stale_replies"] == 0, c
    assert c["reads"] > 0 and c["not_connected"] == 0 and c["port_in_use"] == 0, c
    # every slot accounted for: polled, or passed over late (overrun)
    assert s["slots"] == c["reads"] + s["overrun_slots"], (s, c)
    # every poll a reading (a filled slot) or a failure counted by its cause
    assert s["filled"] == c["reads_ok"] == c["reads"] - sum(c[k] for k in FAILURES), (s, c)
    assert s["filled"] > 0
    # a failing read would have been said in the station's counted line; none failed for no reason
    assert ("gave no reading" in log) == (c["reads_ok"] < c["reads"]), log
