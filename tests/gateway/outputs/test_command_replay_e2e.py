"""Issue 34 item 3 end to end: a replayed stop never ends a new test. Real processes: the
virtual station (``hookwatch sim``) and the gateway (``hookwatch run``) over pseudo-terminals,
a real Mosquitto, the MES as mosquitto_pub / mosquitto_sub.

The attack as it was measured: the MES stops test 1 with ``request_id`` X; then 1,100 commands
that are refused (stops while no test runs, each with its own request_id) come in a burst; a new
test starts; X is sent again. The refusals cost no budget and each was remembered, so they
pushed X out of the 1,024-id memory, and the replay ended test 2. Now every command taken costs
its source's budget (refused ones too) and the memory per source holds what that budget lets
through in 600 s: the flood runs into the budget (14), X is answered from memory (the first
answer, ``duplicate``) and ends nothing; a stop naming test 1's id is refused (15 WRONG_TEST)
and ends nothing; a stop naming test 2 ends test 2."""
import json
import os
import time

from gateway.station.command_desk import CODE
from kit.broker import Broker, Sub, pub, pub_lines
from kit.e2e import SHORT_METHOD, STALL_TOLERANT, run_gateway, scenario_file, station_yaml, virtual_station
from kit.tools import wait_for

STATION = "replay"
BASE = f"hookwatch/lab/test/l1/{STATION}"
FLOOD = 1100
#: a life that does not end while the test looks (one running second = 60 s of wear)
PLANT = {"time_scale": 60}


def _replies(mes: Sub, rid: str) -> list[dict]:
    return [m[2] for m in mes.messages("reply") if m[2].get("request_id") == rid]


def _command(mes: Sub, port: int, name: str, rid: str, **args) -> dict:
    """The MES's command as a careful MES sends it: with its request_id, sent again unchanged
    while the answer is 14 RATE_LIMITED (not remembered: a retry may pass; the budget refills
    one command a second). Returns the answer that is not a refusal for the rate."""
    t_end = time.monotonic() + 120
    while True:
        n = len(_replies(mes, rid))
        pub(port, f"{BASE}/cmd/{name}", json.dumps({**args, "request_id": rid}))
        r = mes.wait(lambda s, n=n: _replies(s, rid)[n:] or None, 60, what=f"the answer to {rid}")[-1]
        if r["code"] != CODE["RATE_LIMITED"]:
            return r
        assert time.monotonic() < t_end, r
        time.sleep(1.0)


def _events(mes: Sub, kind: str) -> list[dict]:
    return [m[2] for m in mes.messages(f"event/{kind}")]


def test_a_replayed_stop_never_ends_a_new_test(tmp_path):
    sc = scenario_file(tmp_path, "replay", plant=PLANT)
    with Broker(tmp_path) as b, virtual_station(tmp_path, sc) as (_sim, links):
        st = station_yaml(tmp_path, links, name=STATION, method={**SHORT_METHOD, **STALL_TOLERANT},
                          test={"t_end_s": 600}, mqtt={"enabled": True, "port": b.port})
        mes = Sub(b.port, BASE + "/#")
        gw = run_gateway(tmp_path, st)
        try:
            mes.wait(lambda s: [m for m in s.messages("status") if m[2].get("status") == "online"], 60,
                     what="the gateway online")
            # test 1, stopped by the MES with request_id X
            assert _command(mes, b.port, "start", "start-1", sample_id="R-1", grade="I", t_set=0.5)["ok"]
            test1 = mes.wait(lambda s: _events(s, "test_started"), 90, what="test 1 started")[0]["test_id"]
            first = _command(mes, b.port, "stop", "X")
            assert first["ok"] and first["code"] == 0, first
            mes.wait(lambda s: [e for e in _events(s, "test_ended") if e["test_id"] == test1], 60,
                     what="test 1 ended")
            # 1,100 commands that are refused, at once, each with its own request_id
            n0 = len(mes.messages("reply"))
            pub_lines(b.port, f"{BASE}/cmd/stop", [json.dumps({"request_id": f"flood-{i}"})
                                                   for i in range(FLOOD)])
            flood = mes.wait(lambda s: s.messages("reply")[n0:] if len(s.messages("reply")) >= n0 + FLOOD
                             else None, 120, what=f"{FLOOD} answers")
            codes = [m[2]["code"] for m in flood]
            assert set(codes) <= {CODE["NOT_RUNNING"], CODE["RATE_LIMITED"]}, set(codes)
            # test 2 (the MES resends its start while the budget refills)
            assert _command(mes, b.port, "start", "start-2", sample_id="R-2", grade="I", t_set=0.5)["ok"]
            test2 = mes.wait(lambda s: [e for e in _events(s, "test_started") if e["test_id"] != test1],
                             90, what="test 2 started")[0]["test_id"]
            # the replay of X: the first answer again, nothing carried out (it ended test 2)
            again = _command(mes, b.port, "stop", "X")
            time.sleep(1.0)
            assert not [e for e in _events(mes, "test_ended") if e["test_id"] == test2], again
            assert again["ok"] and "duplicate of request_id" in again["reason"], again
            # a stop naming test 1 (a new request_id): refused, nothing stopped
            old = _command(mes, b.port, "stop", "stop-test-1", test_id=test1)
            assert not old["ok"] and old["code"] == CODE["WRONG_TEST"] and test1 in old["reason"], old
            # test 2 runs on: no end of it, its folder without a result
            time.sleep(1.0)
            assert not [e for e in _events(mes, "test_ended") if e["test_id"] == test2]
            d2 = tmp_path / "records" / STATION / test2
            assert d2.is_dir() and not (d2 / "result.json").exists()
            # the stop naming test 2 ends it
            mine = _command(mes, b.port, "stop", "stop-test-2", test_id=test2)
            assert mine["ok"], mine
            ended = mes.wait(lambda s: [e for e in _events(s, "test_ended") if e["test_id"] == test2], 60,
                             what="test 2 ended")
            wait_for(lambda: os.path.exists(d2 / "result.json"), 30, what="test 2's result")
        finally:
            gw.stop()
            mes.stop()
    # the refused commands cost the budget: most of the flood ran into it (code 14)
    assert codes.count(CODE["RATE_LIMITED"]) > FLOOD // 2, codes.count(CODE["NOT_RUNNING"])
    assert len(ended) == 1 and ended[0]["data"]["reason"] == "stopped by command", ended
    assert ended[0]["data"]["source"] == "mqtt"
    with open(d2 / "result.json") as f:
        assert json.load(f)["end_reason"] == "stopped by command"
    # test 1 ended once, by X
    ended1 = [e for e in _events_of(tmp_path, test1) if e["type"] == "test_ended"]
    assert len(ended1) == 1 and ended1[0]["reason"] == "stopped by command", ended1


def _events_of(tmp_path, test_id) -> list[dict]:
    with open(tmp_path / "records" / STATION / test_id / "events.jsonl") as f:
        return [json.loads(ln) for ln in f if ln.strip()]
