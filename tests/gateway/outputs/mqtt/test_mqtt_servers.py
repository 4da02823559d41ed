"""The MQTT output's server list (`mqtt.servers`, issue 29 item 4) through two real Mosquittos:
the broker it is connected to dies, the output moves to the next server of its list, and the
retained topics are published again there (a retained message is never left to one broker
alone); messages are not lost on the way (the outbox sends again what was not confirmed)."""
import logging

from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker, Sub
from kit.northbound import LoopThread, RunningStation, make_station
from kit.tools import free_port, wait_for

BASE = "hookwatch/lab/hall/l1/st1"


def test_the_output_moves_to_the_next_server_and_publishes_its_retained_topics_again(tmp_path, caplog):
    caplog.set_level(logging.INFO, "hookwatch.mqtt")
    lt = LoopThread()
    dead = free_port()          # nothing listens here: the first server of the list cannot be reached
    with Broker(tmp_path) as a, Broker(tmp_path) as b:
        sub_a = Sub(a.port, BASE + "/#")
        station = make_station(tmp_path, [])
        out = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, protocol="3.1.1",
                                      servers=[("127.0.0.1", dead), ("127.0.0.1", a.port), ("127.0.0.1", b.port)],
                                      outbox_path=str(tmp_path / "outbox.sqlite"),
                                      reconnect_min_s=0.1, reconnect_max_s=0.5), station)
        station.outputs.append(out)
        run = None
        try:
            run = RunningStation(lt, station)
            # the unreachable first server is passed over at once: connected to A
            wait_for(lambda: station.state.mqtt_ok, 20, what="link up")
            assert out.pump.server == ("127.0.0.1", a.port)
            sub_a.wait(lambda s: s.messages("state"), 20)
            wait_for(lambda: out.outbox.count() == 0, 20, what="the state confirmed by A")
            last_on_a = max(m[2]["seq"] for m in sub_a.messages("state"))
            sub_a.stop()
            a.stop()                # the broker node dies (its retained state with it)
            wait_for(lambda: out.pump.server == ("127.0.0.1", b.port) and out.connected, 30,
                     what="moved to B")
            # a fresh subscriber on B: the retained state is there, with a seq A had confirmed
            # (published again after the reconnect, not only a new one)
            sub_b = Sub(b.port, BASE + "/state")
            sub_b.wait(lambda s: s.messages("state"), 20)
            first = sub_b.messages("state")[0]
            assert first[0] is True                       # delivered as retained
            assert first[2]["seq"] <= last_on_a, (first, last_on_a)
            sub_b.stop()
            assert out.counters["retained_republished"] >= 1
            assert out.pump.connect_errors >= 2          # the dead port, and A after it died
            # the station saw the link go down and come back
            wait_for(lambda: station.state.mqtt_ok, 20, what="the station sees the link up")
        finally:
            if run is not None:
                run.stop()
            lt.close()
