"""The MQTT pump is supervised (issue 12 item 1): a fault inside it (a callback raising, the outbox
raising, the pump loop raising) no longer ends MQTT for the rest of the run. Through a real
Mosquitto with mosquitto_sub as the MES and a real Station running its slot loop (the §3a start
sequence before slot 0) and taking the commands: the link goes down and up again
(StationState.mqtt_ok), and the test's later messages arrive in order, once."""
import logging
import subprocess

from gateway.outputs.mqtt import schema as S
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker, Sub, pub
from kit.northbound import LoopThread, RunningStation, make_station
from kit.tools import require_tool, wait_for

BASE = "hookwatch/lab/hall/l1/st1"


def _once(fn, when, exc):
    """``fn`` wrapped to raise ``exc`` the first time ``when(*args)`` holds."""
    fired = []

    def wrapper(*args, **kw):
        if not fired and when(*args, **kw):
            fired.append(True)
            raise exc
        return fn(*args, **kw)

    wrapper.fired = fired
    return wrapper


def test_a_failing_pump_restarts_and_loses_nothing(tmp_path, caplog):
    caplog.set_level(logging.ERROR, "hookwatch.mqtt")
    lt = LoopThread()
    with Broker(tmp_path) as b:
        sub = Sub(b.port, BASE + "/#", extra=["-T", BASE + "/cmd/#"])   # not the hostile payloads
        station = make_station(tmp_path, [])
        out = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, port=b.port,
                                      outbox_path=str(tmp_path / "outbox.sqlite"),
                                      reconnect_min_s=0.1, reconnect_max_s=0.5), station)
        station.outputs.append(out)
        pump = out.pump
        links: list[bool] = []
        on_link = pump.on_link
        pump.on_link = lambda ok: (links.append(ok), on_link(ok))
        run = None
        try:
            run = RunningStation(lt, station)     # the slot loop runs the start sequence (§3a)
            wait_for(lambda: station.state.mqtt_ok, 20, what="link up")

            def ask(name, payload):
                n = len(sub.messages("reply"))
                if len(payload) < 1000:
                    pub(b.port, f"{BASE}/cmd/{name}", payload)
                else:   # too long for a command line
                    f = tmp_path / "payload"
                    f.write_text(payload)
                    subprocess.run([require_tool("mosquitto_pub"), "-h", "127.0.0.1", "-p", str(b.port),
                                    "-t", f"{BASE}/cmd/{name}", "-q", "1", "-f", str(f)], check=True,
                                   timeout=20)
                sub.wait(lambda s: len(s.messages("reply")) > n, 20)
                return sub.messages("reply")[n][2]

            assert ask("start", '{"sample_id": "S-1", "t_set": 0.5, "request_id": "go"}')["ok"]
            sub.wait(lambda s: s.messages("event/test_started"), 20)     # slot 0 after the start
            # real hostile payloads (issue 12 item 1): refused, the pump does not even stumble
            for bad in ("[" * 200_000 + "]" * 200_000, '{"t_set": ' + "9" * 5000 + "}",
                        '{"sample_id": "' + "x" * 2_000_000 + '"}'):
                r = ask("setpoint", bad)
                assert not r["ok"] and r["code"] == 9
            assert pump.faults == 0

            # 1. the command callback raises (a fault that used to kill the pump thread)
            inbound = pump.inbound
            inbound.on_command = _once(inbound.on_command, lambda name, raw, *_: raw == b'{"boom": 1}',
                                       RuntimeError("injected callback fault"))
            pub(b.port, f"{BASE}/cmd/ack", '{"boom": 1}')
            wait_for(lambda: pump.faults == 1 and links[-2:] == [False, True], 20, what="restart 1")
            wait_for(lambda: station.state.mqtt_ok, 20, what="the station sees the link up")
            # the Will told the MES the gateway was gone while it restarted
            sub.wait(lambda s: [m for m in s.messages("status") if m[2]["status"] == "offline"], 20)

            # 2. the outbox raises while the stop's messages are stored; 3. the pump loop raises
            #    just before it sends the test_ended event
            pump.outbox.add = _once(pump.outbox.add, lambda rows, *a: any(r.kind == "result" for r in rows),
                                    OSError("injected outbox fault"))
            pending, delivery = pump.outbox.pending, pump.delivery
            delivery.send_more = _once(delivery.send_more, lambda *_: any(
                r.topic.endswith("event/test_ended") for r in pending(delivery.sent_upto, 100)),
                RuntimeError("injected loop fault"))
            r = ask("stop", '{"request_id": "halt"}')
            assert r["ok"] and r["request_id"] == "halt"
            sub.wait(lambda s: s.messages("result"), 20)
            assert pump.outbox.add.fired and delivery.send_more.fired
            wait_for(lambda: pump.faults == 3 and links[-1] is True, 20, what="restart 2, 3")
            wait_for(lambda: station.state.mqtt_ok, 20, what="the station sees the link up")
            wait_for(lambda: pump.outbox.count() == 0, 20, what="the outbox emptied")

            # every outbox message arrived once, in seq order; test_ended before its result. After
            # each reconnect the latest confirmed message of each retained topic comes again with
            # its seq (docs/mqtt.md: a retained replay, seq ≤ the highest seen): only those repeat
            everything = [m for m in sub.messages() if not m[1].endswith("/status")]
            retained = {f"{BASE}/{t.path}" for t in S.TOPICS if t.retain}
            data, seen = [], set()
            for m in everything:
                if m[2]["seq"] in seen:
                    assert m[1] in retained and m[2]["seq"] <= max(seen), m
                    continue
                seen.add(m[2]["seq"])
                data.append(m)
            assert len(data) < len(everything), "no retained message was published again"
            seqs = [m[2]["seq"] for m in data]
            assert seqs == sorted(seqs) and len(seqs) == len(set(seqs)), seqs
            kinds = [m[1][len(BASE) + 1:] for m in data]
            assert kinds.count("event/test_started") == 1
            assert kinds.count("event/test_ended") == 1 and kinds.count("result") == 1
            assert kinds.index("event/test_ended") < kinds.index("result")
            res = sub.messages("result")[0][2]
            assert res["sample_id"] == "S-1" and res["test_status"] == "aborted"
            assert [m[2]["request_id"] for m in sub.messages("reply")][-1] == "halt"
            # the link went down and up with every restart; the station knows it is up
            assert links.count(False) >= 3 and links[-1] is True and station.state.mqtt_ok
            # logged once (rate-limited), with the count
            lines = [r.getMessage() for r in caplog.records if "MQTT pump failed" in r.getMessage()]
            assert len(lines) == 1 and "1 fault(s)" in lines[0] and "injected callback fault" in lines[0]
            assert pump.counters["pump_restarts"] == 3
        finally:
            if run is not None:
                run.stop()                        # closes the station and its outputs
            lt.close()
            sub.stop()
