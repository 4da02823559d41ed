"""Issue 12, item 2: the outbox on a full disk (a real tmpfs filled to the last byte): nothing
raises past the outbox, telemetry is refused and counted, every event is delivered through a real
Mosquitto — during and after the full-disk period, in order, none twice."""
import asyncio
import logging
import os
import time

from gateway.core.records import Event, EventType, SlotRecord
from gateway.outputs.broker.outbox import Outbox, Row
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import Broker, Sub, pub
from kit.northbound import LoopThread
from kit.smallfs import fill, small_tmpfs
from kit.tools import wait_for

BASE = "hookwatch/lab/hall/l1/st1"


def test_outbox_on_a_full_disk_refuses_telemetry_and_keeps_events(tmp_path, caplog):
    with small_tmpfs(tmp_path / "fs", "1m") as fs:
        ob = Outbox(os.path.join(fs, "ob.sqlite"))
        states = []
        ob.on_disk_state = lambda ok, info: states.append(ok)
        filler = fill(fs)
        kept, n = [], 0
        for _ in range(200):                       # until SQLite needs a page the disk lacks
            rows = [Row(ob.next_seq(), "event", "t/event", b"e" * 3000),
                    Row(ob.next_seq(), "telemetry", "t/tel", b"t" * 3000)]
            kept.append(rows[0].seq)
            ob.add(rows)                           # never raises
            n += 1
            if not ob.disk_ok:
                break
        assert not ob.disk_ok and states == [False]
        for _ in range(20):
            rows = [Row(ob.next_seq(), "event", "t/event", b"e" * 3000),
                    Row(ob.next_seq(), "telemetry", "t/tel", b"t" * 3000)]
            kept.append(rows[0].seq)
            ob.add(rows)
        assert ob.refused_telemetry >= 20
        got = [r.seq for r in ob.pending(0, 10_000) if r.kind == "event"]
        assert got == kept                          # every event, in order
        ob.confirm(kept[:5])                        # confirmations on a full disk: remembered
        assert [r.seq for r in ob.pending(0, 10_000) if r.kind == "event"] == kept[5:]
        assert sum("cannot write" in m for m in caplog.messages) == 1
        os.unlink(filler)
        time.sleep(1.1)
        ob.add([Row(ob.next_seq(), "event", "t/event", b"after")])
        kept.append(ob.last_seq)
        assert ob.disk_ok and states == [False, True]
        ob.close()
        ob = Outbox(os.path.join(fs, "ob.sqlite"))  # what is not confirmed survives a restart
        assert [r.seq for r in ob.pending(0, 10_000) if r.kind == "event"] == kept[5:]
        ob.close()


def test_events_during_and_after_a_full_disk_arrive_in_order_once(tmp_path, caplog):
    caplog.set_level(logging.WARNING)
    lt = LoopThread()
    b = Broker(tmp_path, persistent=True).start()
    sub = Sub(b.port, BASE + "/#", client_id="mes-disk", clean=False)
    with small_tmpfs(tmp_path / "fs", "2m") as fs:
        out = MqttOutput(MqttSettings(station_id="st1", base_topic=BASE, port=b.port,
                                      outbox_path=os.path.join(fs, "outbox.sqlite"),
                                      reconnect_min_s=0.2, reconnect_max_s=1.0,
                                      telemetry_interval_s=0.2))
        running = {"on": True}

        async def records():
            k = 0
            while running["on"]:
                out.on_record(SlotRecord(k, k * 0.02, True, 0.4, 0.6, 1, 0, 1.5, 0.25, 0.5, 120.0,
                                         119.0, False))
                k += 1
                await asyncio.sleep(0.02)

        n = {"next": 0}

        def emit(count, pad=0):
            async def _do():
                for _ in range(count):
                    i = n["next"]
                    out.on_event(Event(EventType.PORT_LOST if i % 2 else EventType.PORT_BACK, "st1",
                                       time.time(), "T-1", i, {"port": "meter", "n": i,
                                                               "pad": "x" * pad}))
                    n["next"] += 1
            lt.call(_do())                  # on the station's loop, like a station's events

        def events():
            return [m for m in sub.messages() if "/event/" in m[1] and not m[0]]

        try:
            lt.call(out.start())
            lt.loop.call_soon_threadsafe(lambda: lt.loop.create_task(records()))
            wait_for(lambda: out.connected, 20, what="connected")
            sub.wait(lambda s: s.messages("status"), 20)
            emit(5)
            sub.wait(lambda s: len(events()) >= 5, 20)
            filler = fill(fs)
            # the broker goes away while the disk is full: the events pile up in the outbox
            n_probe = len(sub.messages("probe"))
            pub(b.port, BASE + "/probe", "{}", qos=1)
            sub.wait(lambda s: len(s.messages("probe")) > n_probe, 20)
            b.stop()
            for _ in range(40):
                emit(5, pad=2000)
                time.sleep(0.1)
                if not out.outbox.disk_ok:
                    break
            assert not out.outbox.disk_ok, "the outbox never hit the full disk"
            emit(10, pad=2000)
            time.sleep(1.0)
            b.start()                                   # broker back, disk still full
            wait_for(lambda: out.connected, 30, what="reconnected")
            emit(5)
            total = n["next"]
            sub.wait(lambda s: len(events()) >= total, 60, what="events sent from memory")
            os.unlink(filler)                           # space returns
            wait_for(lambda: out.outbox.disk_ok, 20, what="disk ok again")
            emit(5)
            total = n["next"]
            sub.wait(lambda s: len(events()) >= total, 30, what="events after the disk is freed")
            time.sleep(1.0)                             # duplicates would show up now
            msgs = events()
            ns = [m[2]["data"]["n"] for m in msgs]
            assert ns == list(range(total)), str(
                [(m[2]["data"]["n"], m[2]["seq"], round(m[3] % 100, 2)) for m in msgs][20:])
            seqs = [m[2]["seq"] for m in msgs]
            assert seqs == sorted(set(seqs))
            assert out.outbox.refused_telemetry > 0
            assert out.connected and out.pump._thread.is_alive()
            assert sum("cannot write" in m for m in caplog.messages) == 1, caplog.messages
        finally:
            running["on"] = False
            lt.call(out.stop())
            lt.close()
            sub.stop()
            b.stop()
