"""`hookwatch demo` as a newcomer runs it, on the one-minute life (compressed twice more here): it
prints the console URL, a working mbpoll line (the PLC's side) and a working mosquitto_sub line
(the MES's side), ends in plain words from the real numbers and writes the Fig. 7 PNG."""
from __future__ import annotations

import os
import re
import shlex
import signal
import socket
import subprocess
import time
import urllib.request

from conftest import ROOT, hookwatch_cmd
from gateway.cli.demo import AFTER_LIFE
from kit.broker import check_message
from kit.e2e import QUICK_END, QUICK_LEAD, QUICK_METHOD, QUICK_PRIOR, Proc, quick_scenario, read_json, station_yaml
from kit.tools import require_tool


def _fresh_clone(tmp_path) -> str:
    """This checkout's committed tree, cloned as a newcomer gets it (no .venv)."""
    dst = str(tmp_path / "hookwatch")
    subprocess.run(["git", "clone", "-q", "--no-hardlinks", ROOT, dst], check=True, timeout=120)
    return dst


def test_demo_shows_console_plc_and_mqtt(tmp_path):
    """From a fresh clone, as root: ./hookwatch-demo sets itself up (venv, the Debian tools its
    output promises) and its printed lines work as pasted."""
    require_tool("mosquitto")
    require_tool("mosquitto_sub")
    require_tool("mbpoll")
    clone = _fresh_clone(tmp_path)
    # with a life prior and a lead compressed like the life (as config/demo/station.yaml has them)
    st = station_yaml(tmp_path, {"meter": "/dev/ttyDEMO0", "stm32": "/dev/ttyDEMO1"}, name="demo",
                      method={**QUICK_METHOD, "lead": QUICK_LEAD}, control={"dead_band_n": 0.01},
                      test={"sample_id": "DEMO-Q", "t_end_s": QUICK_END},
                      extra={"forecast": {"priors": [QUICK_PRIOR]}})
    # the shipped one-minute life (quick.yaml) compressed twice more (the kit's QUICK_*: the end of
    # life ~23 s after the start instead of ~53 s)
    sc = quick_scenario(tmp_path, "quick.yaml")
    work = tmp_path / "work"
    demo = Proc([os.path.join(clone, "hookwatch-demo"), "--scenario", sc,
                                   "--station", st, "--dir", str(work), "--t-end", str(QUICK_END),
                                   "--every", "20",
                                   "--console-port", "0", "--plc-port", "0", "--mqtt-port", "0"],
                str(tmp_path / "demo.log"))
    try:
        url = demo.readline_until("console :", timeout=400).split()[0]
        # the console opens on the demo station's page (μ(t) live), not on the fleet
        assert re.match(r"^http://127\.0\.0\.1:\d+/#/station/demo$", url), url
        url = url.split("#")[0]
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
        # after the life the console and the broker stay up until Ctrl-C, and the demo says so
        assert demo.readline_until(AFTER_LIFE, timeout=180) == ""      # exactly this line
        assert demo.p.poll() is None, demo.log()
        with urllib.request.urlopen(url + "api/fleet", timeout=10) as r:
            assert b'"demo"' in r.read()
        q = subprocess.run(["mosquitto_sub"] + shlex.split(sub) + ["-W", "4"], capture_output=True,
                           text=True, timeout=30)
        assert "/demo/status" in q.stdout, q.stdout + q.stderr
        # Ctrl-C: it stops cleanly, with the life's verdict (a detected end of life, online == offline)
        demo.p.send_signal(signal.SIGINT)
        assert demo.p.wait(60) == 0, demo.log()
    finally:
        demo.stop()
    out = "".join(demo.stdout_lines()) + demo.stdout_rest
    truth = read_json(str(work / "truth.json"))
    tau = QUICK_METHOD["tau"]
    m = re.search(r"the hook reached its end of life ([\d.]+) s after the start; "
                  rf"detected ([\d.]+) s later \(the {tau:g} s persistence\); "
                  r"warned ([\d.]+) s before the end of life \(reasons: ([a-z, ]+)\); "
                  r"the simulated wear began to accelerate at ([\d.]+) s; "
                  r"offline analysis of the recorded log agrees", out)
    assert m, out
    t_life, later, ahead, reasons, onset = (float(m.group(1)), float(m.group(2)), float(m.group(3)),
                                            m.group(4), float(m.group(5)))
    # the early warning (METHOD.md §5b) came first, from the prior, as the result has it
    result = read_json([os.path.join(dp, "result.json") for dp, _d, fs in os.walk(work / "records")
                        if "result.json" in fs][0])["method"]
    assert ahead > 0 and "prior" in reasons.split(", ") and reasons.split(", ") == result["warn_reasons"]
    # … and the words say where the lead came from
    assert "  warning: its lead came from the life prior (what earlier hooks" in out, out
    assert abs(t_life - (result["warn_slot"] + 1) * 0.02 - ahead) < 0.06
    t_det = t_life + later
    (res_path,) = [os.path.join(dp, "result.json") for dp, _d, fs in os.walk(work / "records") if "result.json" in fs]
    assert abs(read_json(res_path)["method"]["t_life"] - t_life) < 0.06
    assert abs(truth["onset_run_s"] - onset) < 0.06
    # detected τ after t_life (the persistence, N_τ slots); the same 1 s of margin as before
    assert tau <= t_det - t_life <= tau + 1.0
    fig = re.search(r"Fig\. 7 : (\S+\.png)", out).group(1)
    with open(fig, "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    assert "gives the identical result" in out
    # what a person reads: rounded numbers, no packaging chatter, where the files are
    # (no binary-float tails such as 208.14000000000001 or 0.006180000000000004)
    assert not re.search(r"\d\.\d*(0{6,}|9{6,})\d", out), out
    log = demo.log()
    assert "BuildBackendWarning" not in log and "!!" not in log, log
    assert f"everything the demo wrote is under {work}" in out


def test_an_interrupted_demo_exits_non_zero(tmp_path):
    """A demo that did not complete says so and exits non-zero (Ctrl-C in the middle of the life).
    Its station runs in `hookwatch run`'s one main loop (drive): it speaks systemd's notify
    protocol as the gateway does (READY once the station runs, STATUS, STOPPING at the end)."""
    st = station_yaml(tmp_path, {"meter": "/dev/ttyDEMO0", "stm32": "/dev/ttyDEMO1"}, name="demo",
                      method=QUICK_METHOD, test={"sample_id": "DEMO-I", "t_end_s": QUICK_END})
    sc = quick_scenario(tmp_path, "quick.yaml")
    sock = str(tmp_path / "notify.sock")
    rx = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    rx.bind(sock)
    got: list[str] = []
    demo = Proc(hookwatch_cmd() + ["demo", "--scenario", sc, "--station", st, "--dir", str(tmp_path / "w"),
                                   "--t-end", str(QUICK_END), "--every", "1", "--no-console", "--no-northbound"],
                str(tmp_path / "demo.log"), env={**os.environ, "NOTIFY_SOCKET": sock})
    try:
        demo.readline_until("[demo] EVENT test_started", timeout=120)
        demo.readline_until("[demo] t=", timeout=120)
        demo.p.send_signal(signal.SIGINT)
        rc = demo.p.wait(60)
        rx.setblocking(False)
        while True:
            try:
                got.append(rx.recv(4096).decode())
            except BlockingIOError:
                break
    finally:
        demo.stop()
        rx.close()
    assert rc != 0, demo.log()
    assert "did not complete" in demo.log()
    ready = [m for m in got if m.startswith("READY=1")]
    assert len(ready) == 1 and f"MAINPID={demo.p.pid}" in ready[0], got
    assert "STATUS=running 1 station(s)" in got and got[-1] == "STOPPING=1", got


def _children(pid: int) -> set[int]:
    out: set[int] = set()
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as f:
            out |= {int(x) for x in f.read().split()}
    return out


def test_a_killed_demo_leaves_no_simulator_or_broker_behind(tmp_path):
    """SIGKILL (or a crash, or a closed terminal) gives the demo no chance to stop its children:
    the simulator and the demo's Mosquitto end with it (PR_SET_PDEATHSIG)."""
    require_tool("mosquitto")
    st = station_yaml(tmp_path, {"meter": "/dev/ttyDEMO0", "stm32": "/dev/ttyDEMO1"}, name="demo",
                      method=QUICK_METHOD, test={"sample_id": "DEMO-I", "t_end_s": QUICK_END})
    sc = quick_scenario(tmp_path, "quick.yaml")
    demo = Proc(hookwatch_cmd() + ["demo", "--scenario", sc, "--station", st, "--dir", str(tmp_path / "w"),
                                   "--t-end", str(QUICK_END), "--every", "1", "--no-console",
                                   "--mqtt-port", "0"],
                str(tmp_path / "demo.log"))
    try:
        demo.readline_until("[demo] EVENT test_started", timeout=120)
        kids = _children(demo.p.pid)
        names = set()
        for k in kids:
            with open(f"/proc/{k}/cmdline", "rb") as f:
                names.add("mosquitto" if b"mosquitto" in f.read() else "sim")
        assert names == {"mosquitto", "sim"}, demo.log()
        demo.p.kill()
        demo.p.wait(30)
        t_end = time.monotonic() + 30          # a bound against a hang, not a speed goal
        while any(os.path.exists(f"/proc/{k}") and _state(k) != "Z" for k in kids) and time.monotonic() < t_end:
            time.sleep(0.1)
        left = [k for k in kids if os.path.exists(f"/proc/{k}") and _state(k) != "Z"]
        assert left == [], demo.log()
    finally:
        demo.stop()


def _state(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "gone"
