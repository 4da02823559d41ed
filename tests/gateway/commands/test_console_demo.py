"""`hookwatch demo` as a newcomer runs it, on the one-minute life (compressed twice more here): it
prints the console URL, a working mbpoll line (the PLC's side) and a working mosquitto_sub line
(the MES's side), ends in plain words from the real numbers and writes the Fig. 7 PNG."""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import time
import urllib.request

from conftest import hookwatch_cmd
from kit.broker import check_message
from kit.e2e import QUICK_END, QUICK_METHOD, Proc, quick_scenario, read_json, station_yaml
from kit.tools import require_tool


def test_demo_shows_console_plc_and_mqtt(tmp_path):
    require_tool("mosquitto")
    require_tool("mosquitto_sub")
    require_tool("mbpoll")
    st = station_yaml(tmp_path, {"meter": "/dev/ttyDEMO0", "stm32": "/dev/ttyDEMO1"}, name="demo",
                      method=QUICK_METHOD, control={"dead_band_n": 0.01},
                      test={"sample_id": "DEMO-Q", "t_end_s": QUICK_END})
    # the shipped one-minute life (quick.yaml) compressed twice more (the kit's QUICK_*: the end of
    # life ~23 s after the start instead of ~53 s)
    sc = quick_scenario(tmp_path, "quick.yaml")
    work = tmp_path / "work"
    demo = Proc(hookwatch_cmd() + ["demo", "--scenario", sc,
                                   "--station", st, "--dir", str(work), "--t-end", str(QUICK_END),
                                   "--every", "20",
                                   "--console-port", "0", "--plc-port", "0", "--mqtt-port", "0"],
                str(tmp_path / "demo.log"))
    try:
        url = demo.readline_until("console :", timeout=60).split()[0]
        assert re.match(r"^http://127\.0\.0\.1:\d+/$", url)
        demo.readline_until("MES     :")
        t_end = time.monotonic() + 10
        while not any("mosquitto_sub " in ln for ln in demo.stdout_lines()) and time.monotonic() < t_end:
            time.sleep(0.1)
        lines = [ln.strip() for ln in demo.stdout_lines()]
        mbpoll = [ln for ln in lines if ln.startswith("mbpoll ")][-1].split(" ", 1)[1]   # T1, T2, μ …
        sub = [ln for ln in lines if ln.startswith("mosquitto_sub ")][0].split(" ", 1)[1]
        time.sleep(3)
        # the console serves the fleet
        with urllib.request.urlopen(url + "api/fleet", timeout=10) as r:
            assert b'"demo"' in r.read()
        # the printed lines work as pasted: the PLC's and the MES's view of the same station
        p = subprocess.run(["mbpoll"] + shlex.split(mbpoll), capture_output=True, text=True, timeout=30)
        assert p.returncode == 0 and "[8]:" in p.stdout, p.stdout + p.stderr
        q = subprocess.run(["mosquitto_sub"] + shlex.split(sub) + ["-W", "4"], capture_output=True,
                           text=True, timeout=30)
        assert "/demo/status" in q.stdout and "/demo/telemetry" in q.stdout, q.stdout + q.stderr
        for ln in q.stdout.splitlines():        # `-v`: topic, space, payload; each valid for its topic
            topic, _, payload = ln.partition(" ")
            bad = check_message(topic, payload)
            assert bad is None, bad
        assert demo.p.wait(180) == 0, demo.log()
    finally:
        demo.stop()
    out = "".join(demo.stdout_lines()) + demo.stdout_rest
    truth = read_json(str(work / "truth.json"))
    tau = QUICK_METHOD["tau"]
    m = re.search(r"end of life at ([\d.]+) s after the start; simulated wear onset ([\d.]+) s; "
                  rf"detected (\d+) s later \(at ([\d.]+) s\), as the {tau} s persistence requires",
                  out)
    assert m, out
    t_life, onset, _later, t_det = map(float, m.groups())
    (res_path,) = [os.path.join(dp, "result.json") for dp, _d, fs in os.walk(work / "records") if "result.json" in fs]
    assert abs(read_json(res_path)["method"]["t_life"] - t_life) < 0.06
    assert abs(truth["onset_run_s"] - onset) < 0.06
    # detected τ after t_life (the persistence, N_τ slots); the same 1 s of margin as before
    assert tau <= t_det - t_life <= tau + 1.0
    fig = re.search(r"Fig\. 7 : (\S+\.png)", out).group(1)
    with open(fig, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    assert "the identical result" in out
