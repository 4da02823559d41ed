"""A box of a site for the site-view tests: a process that runs one real MQTT output per station
(gateway.outputs.mqtt.output.MqttOutput: its own session, retained state, the `offline` Last Will)
and hands each a constructed station state once a second, as a station's loop would. No slot
loop: the site view reads only what the outputs publish. Killed with SIGKILL, the broker publishes
the stations' Wills.

``python tests/kit/site_box.py PORT OUTDIR JSON``: JSON is ``{"prefix": "hookwatch/plant",
"stations": [{"id": …, "area": …, "line": …, "state": {StationState fields}}]}``; prints
``connected`` once every output is connected."""
from __future__ import annotations

import asyncio
import json
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [os.path.dirname(os.path.dirname(HERE))]

from gateway.core import records as R  # noqa: E402
from gateway.outputs.mqtt import schema as mqtt_schema  # noqa: E402
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings  # noqa: E402


def state_of(sid: str, fields: dict) -> R.StationState:
    f = dict(fields)
    f["state"] = R.TestState[f.get("state", "IDLE")]
    return R.StationState(station=sid, **f)


async def main(port: int, outdir: str, spec: dict) -> None:
    outs = []
    for s in spec["stations"]:
        base = mqtt_schema.base_topic(spec["prefix"], spec["site"], s["area"], s["line"], s["id"])
        out = MqttOutput(MqttSettings(station_id=s["id"], base_topic=base, port=port,
                                      outbox_path=os.path.join(outdir, s["id"] + ".sqlite"),
                                      reconnect_min_s=0.2, reconnect_max_s=1.0))
        await out.start()
        outs.append((out, state_of(s["id"], s.get("state", {}))))
    while not all(o.connected for o, _ in outs):
        await asyncio.sleep(0.05)
    for o, st in outs:
        o.on_state(st)
    print("connected", flush=True)
    while True:
        await asyncio.sleep(1.0)
        for o, st in outs:
            o.on_state(st)


if __name__ == "__main__":
    asyncio.run(main(int(sys.argv[1]), sys.argv[2], json.loads(sys.argv[3])))
