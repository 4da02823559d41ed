"""Issue 12 item 9 end to end: a test cut off by kill -9 of `hookwatch run` (against `hookwatch
sim`, MQTT through a real Mosquitto) is closed as aborted when the gateway comes back; its
`result` message and its `test_ended` event name the test (its id, not its folder path or null)
and carry the sample, grade and setpoint of its sidecar."""
import os
import signal

from gateway.outputs.mqtt import schema as S
from kit.broker import Broker, Sub
from kit.e2e import read_json, run_gateway, station_yaml, test_dirs, virtual_station


def test_cut_off_test_result_names_the_test_over_mqtt(tmp_path):
    with Broker(tmp_path) as b:
        sub = Sub(b.port, "hookwatch/#")
        gw = None
        try:
            with virtual_station(tmp_path, "config/scenarios/quick.yaml") as (_sim, links):
                st = station_yaml(tmp_path, links, name="cut",
                                  test={"sample_id": "S-77", "grade": "II", "t_set_n": 0.55,
                                        "t_end_s": 600},
                                  mqtt={"enabled": True, "port": b.port})
                gw = run_gateway(tmp_path, st, "--start", name="gw1")
                started = sub.wait(lambda s: [m for m in s.messages("event/test_started") if not m[0]],
                                   90, what="test_started")[0][2]
                test_id = started["test_id"]
                assert test_id
                d = os.path.join(str(tmp_path / "records" / "cut"), test_id)
                assert test_dirs(tmp_path, "cut") == [d]
                gw.p.send_signal(signal.SIGKILL)          # cut off mid-test
                gw.p.wait(20)
                gw.stop()
                gw = run_gateway(tmp_path, st, name="gw2")
                res = sub.wait(lambda s: [m for m in s.messages("result") if not m[0]], 60,
                               what="the result")[0][2]
                ended = sub.wait(lambda s: [m for m in s.messages("event/test_ended") if not m[0]],
                                 30, what="test_ended")[0][2]
            assert list(res) == S.field_names("result")
            assert res["test_id"] == test_id, res
            assert (res["sample_id"], res["grade"], res["t_set"]) == ("S-77", "II", 0.55), res
            assert res["test_status"] == "aborted" and res["end_reason"] == "gateway restart", res
            assert ended["test_id"] == test_id, ended
            assert ended["data"]["test_status"] == "aborted"
            on_disk = read_json(os.path.join(d, "result.json"))
            assert on_disk["test_id"] == test_id and on_disk["sample_id"] == "S-77", on_disk
            assert on_disk["grade"] == "II" and on_disk["t_set"] == 0.55, on_disk
        finally:
            if gw is not None:
                gw.stop()
            sub.stop()
