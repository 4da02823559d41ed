"""A process that feeds an MqttOutput like a station would (50 Hz records, state, numbered events),
for tests that kill or restart the producer. Prints `ready`, then `emitted <n>` after each event.

    python tests/kit/feeder.py --port P --outbox PATH --first 0 --count 20 [--alarm-at N]
"""
from __future__ import annotations

import argparse
import asyncio
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))

from gateway.core.records import Event, EventType, SlotRecord, StationState, TestState  # noqa: E402
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings  # noqa: E402


async def main(a) -> None:
    import logging
    if os.environ.get("HW_FEEDER_DEBUG"):
        logging.basicConfig(level=logging.DEBUG, format="%(asctime)s %(message)s")
    s = MqttSettings(station_id=a.station, base_topic=a.base, port=a.port, outbox_path=a.outbox,
                     reconnect_min_s=0.2, reconnect_max_s=a.reconnect_max, telemetry_interval_s=1.0)
    out = MqttOutput(s)
    await out.start()
    st = StationState(station=a.station, state=TestState.MONITORING, test_id="T-1", sample_id="S-1",
                      t_set=0.5, mu_ss=0.2, mu_th=0.23)
    out.on_state(st)
    print("ready", flush=True)
    k = 0
    t_next = time.monotonic()
    n = a.first
    next_event = time.monotonic() + a.interval
    try:
        while n < a.first + a.count or a.linger:
            t_next += 0.02
            await asyncio.sleep(max(0.0, t_next - time.monotonic()))
            if a.pause_after is not None and n == a.pause_after + 1 and not os.path.exists(a.resume_file):
                next_event = time.monotonic() + a.interval      # quiet: nothing produced at all
                continue
            out.on_record(SlotRecord(k, k * 0.02, True, 0.4, 0.6, 1, 0, 1.5, 0.25, 0.5, 120.0, 119.0, False))
            k += 1
            if n < a.first + a.count and time.monotonic() >= next_event:
                next_event += a.interval
                if n == a.alarm_at:
                    out.on_event(Event(EventType.END_OF_LIFE, a.station, time.time(), "T-1", k,
                                       {"k_life": k, "t_life": k * 0.02, "mu_ss": 0.2, "mu_th": 0.23,
                                        "sample_id": "S-1", "n": n}))
                else:
                    out.on_event(Event(EventType.PORT_LOST if n % 2 else EventType.PORT_BACK, a.station,
                                       time.time(), "T-1", k, {"port": "meter", "n": n}))
                print(f"emitted {n}", flush=True)
                n += 1
                if n == a.first + a.count:
                    print("done", flush=True)
            if k % 50 == 0:
                out.on_state(st)
    finally:
        await out.stop()
        print("stopped", flush=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--outbox", required=True)
    ap.add_argument("--station", default="st1")
    ap.add_argument("--base", default="hookwatch/lab/hall/l1/st1")
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--count", type=int, default=10)
    ap.add_argument("--interval", type=float, default=0.1)
    ap.add_argument("--alarm-at", type=int, default=-1)
    ap.add_argument("--reconnect-max", type=float, default=1.0)
    ap.add_argument("--pause-after", type=int, default=None,
                    help="after this event produce nothing until --resume-file exists")
    ap.add_argument("--resume-file", default="")
    ap.add_argument("--linger", action="store_true", help="keep running after the last event")
    asyncio.run(main(ap.parse_args()))
