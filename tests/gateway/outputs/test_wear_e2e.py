"""Issue 13 end to end, north side (METHOD.md §5a): `hookwatch sim` + `hookwatch run` with a real
Mosquitto (the MES is mosquitto_sub) and a PLC played by mbpoll. A life whose early warning comes
before its end of life shows `wear_warning` at the MES and in the PLC's status bit before
`end_of_life`; the headroom and its projection are published per window."""
import os
import threading
import time

import pytest
import yaml

from conftest import ROOT
from gateway.outputs.mqtt import schema as S
from gateway.outputs.plc import registers as R
from kit.broker import Broker, Sub
from kit.e2e import (
    QUICK_END,
    QUICK_METHOD,
    QUICK_SCALE,
    analyze_cli,
    read_json,
    run_gateway,
    station_yaml,
    test_dirs,
    virtual_station,
)
from kit.northbound import mbpoll
from kit.tools import free_port, require_tool

METER_MAP = os.path.join(ROOT, "config", "meters", "zn-s.yaml")
TUNED = {"dead_band_n": 0.01}
# the kit's twice-compressed life and its windows (2 s); the warning after 2 windows under h 0.8
# (lead 0: the headroom run is its only reason, METHOD.md §5b)
METHOD = {**QUICK_METHOD, "n_warn": 2, "h_warn": 0.8, "lead": 0}
IR = R.IR


def scenario(tmp_path):
    """The kit's twice-compressed life with a slow accelerated stage (rise_tau_s 6000 life-s = 5 s
    here, 2.5 windows of 2 s; the h 0.8 → 0 rise takes ~6 s), so that the headroom falls over
    several windows before μ crosses μ_th."""
    sc = {"description": "slow accelerated wear", "seed": 7, "meter": {"map": METER_MAP},
          "stm32": {"watchdog_s": 0.2},
          "plant": {"grade": "I", "t_set": 0.5, "time_scale": QUICK_SCALE,
                    "wear": {"rise_tau_s": 6000}},
          "method": {**QUICK_METHOD, "t_end": QUICK_END}, "faults": []}
    p = tmp_path / "wear.yaml"
    p.write_text(yaml.safe_dump(sc, sort_keys=False))
    return str(p)


class PlcPoller:
    """A PLC scanning the status word with mbpoll: when each bit was first seen set."""

    def __init__(self, port, unit):
        self.port, self.unit = port, unit
        self.first: dict[str, float] = {}
        self.regs: dict[str, dict] = {}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self):
        n = IR["warning_alarm"].address + 1
        while not self._stop.is_set():
            rc, v, _err = mbpoll(self.port, "-t", "3", "-r", "0", "-c", str(n), unit=self.unit)
            t = time.monotonic()
            if rc == 0 and IR["status"].address in v:
                status = v[IR["status"].address]
                for bit in ("wear_warning", "end_of_life"):
                    if status & (1 << R.STATUS_BIT[bit]) and bit not in self.first:
                        self.first[bit] = t
                        self.regs[bit] = v
            self._stop.wait(0.2)

    def stop(self):
        self._stop.set()
        self._t.join(30)


def test_wear_warning_reaches_mosquitto_sub_and_the_plc_bit_before_end_of_life(tmp_path):
    require_tool("mbpoll")
    sc = scenario(tmp_path)
    mport = free_port()
    with Broker(tmp_path) as b:
        sub = Sub(b.port, "hookwatch/#")
        gw = plc = None
        try:
            with virtual_station(tmp_path, sc) as (_sim, links):
                st = station_yaml(tmp_path, links, name="wear", control=TUNED, method=METHOD,
                                  test={"t_end_s": QUICK_END},
                                  mqtt={"enabled": True, "port": b.port},
                                  modbus_tcp={"enabled": True, "port": mport, "unit_id": 2})
                gw = run_gateway(tmp_path, st, "--start", "--exit-when-done")
                sub.wait(lambda s: [m for m in s.messages("status") if m[2].get("status") == "online"],
                         60, what="status online")
                plc = PlcPoller(mport, 2)
                sub.wait(lambda s: s.messages("event/end_of_life"), 180, what="the end of life")
                time.sleep(1.0)                   # the PLC's next scans
                plc.stop()
                res = sub.wait(lambda s: s.messages("result"), 120, what="the result")[0][2]
                assert gw.p.wait(60) == 0, gw.log()
        finally:
            if plc is not None:
                plc.stop()
            if gw is not None:
                gw.stop()
            sub.stop()
    # the MES: one wear_warning event (QoS 1, once per test), before the end of life
    ww = sub.messages("event/wear_warning")
    eol = sub.messages("event/end_of_life")
    assert len(ww) == 1 and len(eol) == 1, [m[1] for m in sub.messages()]
    assert list(ww[0][2]) == S.field_names("event")
    data = ww[0][2]["data"]
    assert {k for k, _ in S.EVENT_DATA[S.EventType.WEAR_WARNING]} <= set(data)
    assert data["headroom"] < METHOD["h_warn"] and data["n_warn"] == 2
    assert ww[0][3] < eol[0][3] and ww[0][2]["seq"] < eol[0][2]["seq"]
    assert data["warn_slot"] < eol[0][2]["k"]
    # the warning alarm: retained, priority 2 (end of life is 1), same lifecycle
    wa = sub.messages("alarm/warning")
    assert wa and list(wa[0][2]) == S.field_names("alarm_warning")
    assert wa[0][2]["state"] == "unacknowledged" and wa[0][2]["priority"] == 2
    assert wa[0][2]["warn_slot"] == data["warn_slot"]
    ea = sub.messages("alarm/end_of_life")
    assert ea and ea[0][2]["priority"] == 1
    # per window: headroom and t_cross in state and telemetry
    states = [m[2] for m in sub.messages("state") if m[2]["headroom"] is not None]
    hs = [s["headroom"] for s in states]
    assert len(set(hs)) >= 3 and max(hs) > 0.8 and min(hs) < 0.8, hs
    assert any(s["wear_warning"] and s["warning_alarm"] == "unacknowledged" for s in states)
    tel = [m[2] for m in sub.messages("telemetry") if m[2]["headroom"] is not None]
    assert tel and all(list(t) == S.field_names("telemetry") for t in tel)
    # the PLC: the wear_warning bit came on before the end_of_life bit
    assert "wear_warning" in plc.first and "end_of_life" in plc.first, plc.first
    assert plc.first["wear_warning"] < plc.first["end_of_life"], plc.first
    v = plc.regs["wear_warning"]
    assert v[IR["warning_alarm"].address] == 1
    assert not v[IR["status"].address] & (1 << R.STATUS_BIT["end_of_life"])
    a = IR["headroom"].address
    h_plc = R.decode_value(IR["headroom"], [v[a], v[a + 1]])
    assert h_plc == pytest.approx(data["headroom"], rel=1e-6), (h_plc, data)
    a = IR["t_cross"].address
    t_plc = R.decode_value(IR["t_cross"], [v[a], v[a + 1]])
    assert t_plc == (0 if data["t_cross"] is None else round(data["t_cross"])), (t_plc, data)
    # the result carries the warning; online == offline
    assert res["result"]["warn_slot"] == data["warn_slot"]
    d = test_dirs(tmp_path, "wear")[0]
    online = read_json(os.path.join(d, "result.json"))["method"]
    assert online == analyze_cli(os.path.join(d, "log.csv.gz"))
