"""Issue 12 item 4 end to end: a station of a real `hookwatch run` (against `hookwatch sim`, MQTT
through Mosquitto, the PLC played by mbpoll) crashes twice, once while starting its outputs (its
MQTT client and PLC unit id already up) and once in its slot loop (its serial ports open). Each
crashed instance is closed completely before the next is built, with a growing back-off: the
third opens its ports, serves its unit id, fills slots, and keeps one MQTT connection."""
import os
import re
import time

from conftest import ROOT, hookwatch_cmd
from gateway.outputs.mqtt import schema as S
from gateway.outputs.plc import registers as R
from kit.broker import Broker, Sub
from kit.e2e import station_yaml, virtual_station, wait_log
from kit.northbound import mbpoll
from kit.proc import Proc
from kit.tools import free_port, require_tool

IR = R.IR


def test_crashed_station_is_closed_before_its_restart_with_backoff(tmp_path):
    require_tool("mbpoll")
    mport = free_port()
    crash_dir = tmp_path / "crash"
    crash_dir.mkdir()
    env = {**os.environ, "HOOKWATCH_OUTPUTS": "kit.crashy", "HW_CRASH_DIR": str(crash_dir),
           "PYTHONPATH": os.pathsep.join([os.path.join(ROOT, "tests"), os.environ.get("PYTHONPATH", "")])}
    with Broker(tmp_path) as b:
        sub = Sub(b.port, "hookwatch/#")
        gw = None
        try:
            with virtual_station(tmp_path, "config/scenarios/quick.yaml") as (_sim, links):
                st = station_yaml(tmp_path, links, name="cr", mqtt={"enabled": True, "port": b.port},
                                  modbus_tcp={"enabled": True, "port": mport, "unit_id": 2})
                gw = Proc(hookwatch_cmd() + ["run", st], str(tmp_path / "gw.log"), env=env)
                wait_log(gw, "crashed again (2 crashes, 2 in a row)", 60)
                wait_log(gw, "cr: slot stats", 30)
                t_third = time.time()
                # the third instance runs: its meter answers, its unit id is served, it counts on
                deadline = time.monotonic() + 30
                while True:
                    rc, v, err = mbpoll(mport, "-t", "3", "-r", "0", "-c", str(IR["status"].address + 1),
                                        unit=2)
                    ok = rc == 0 and v[IR["status"].address] & (1 << R.STATUS_BIT["meter_ok"]) \
                        and v[IR["status"].address] & (1 << R.STATUS_BIT["stm32_ok"]) \
                        and v[IR["status"].address] & (1 << R.STATUS_BIT["mqtt_connected"])
                    if ok or time.monotonic() > deadline:
                        break
                    time.sleep(0.5)
                assert ok, (rc, v, err, gw.log())
                hb1 = v[IR["heartbeat"].address]
                time.sleep(8.0)
                rc, v, err = mbpoll(mport, "-t", "3", "-r", "0", "-c", str(IR["status"].address + 1),
                                    unit=2)
                assert rc == 0 and v[IR["heartbeat"].address] >= hb1 + 6, (hb1, v)
                base = S.base_topic("hookwatch", "lab", "test", "l1", "cr")
                tel = [m for m in sub.messages("telemetry") if m[3] > t_third + 2]
                assert len(tel) >= 4, len(tel)
                online = [m for m in sub.messages("status") if m[1] == f"{base}/status"
                          and m[2].get("status") == "online" and m[3] > t_third + 1]
                assert len(online) <= 1, online          # one connection, no reconnect loop
                log = gw.log_all()
            assert "Could not exclusively lock" not in log, log
            assert "already used by station" not in log, log
            assert "MQTT connection lost" not in log and "MQTT disconnected" not in log, log
            # the back-off grows: 1 s, then 2 s; the traceback once, then one line with the count
            assert re.search(r"station cr crashed; closed; restarting in 1\.0 s", log), log
            assert re.search(r"crashed again \(2 crashes, 2 in a row\): RuntimeError: test: a bug in "
                             r"the slot path at slot 50; closed; restarting in 2\.0 s", log), log
            assert log.count("Traceback") == 1, log
            assert (crash_dir / "builds").read_text() == "3"
        finally:
            if gw is not None:
                gw.stop()
            sub.stop()
