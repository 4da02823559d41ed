"""`hookwatch check --probe` through the real CLI against the virtual station (`hookwatch sim` on
ptys, a process of its own), a real Mosquitto with a password file and a port held by another
program: each failure is one plain sentence with its fix, and the exit code says it. And at run time,
a silent meter's failed zero check names the port and its settings."""
import json
import os
import socket
import subprocess
import termios

import pytest
import yaml

from conftest import hookwatch_cmd
from kit.broker import Broker
from kit.e2e import (
    STALL_TOLERANT,
    assert_no_slot_lost,
    read_json,
    run_gateway,
    station_yaml,
    test_dirs,
    virtual_station,
    wait_exit,
    wait_log,
)
from kit.pymodbus_slave import pymodbus_meter
from kit.tools import free_port, require_tool


def check(*args, env=None):
    p = subprocess.run(hookwatch_cmd() + ["check", *args], capture_output=True, text=True, timeout=180,
                       env={**os.environ, **(env or {})})
    return p.returncode, p.stdout, p.stderr


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("probe")
    with virtual_station(tmp, "config/scenarios/demo.yaml") as (proc, links):
        yield tmp, links


def station(tmp, links, name, **kw):
    return station_yaml(tmp, links, name=name, **kw)


def test_a_station_that_answers_everywhere_passes(sim):
    tmp, links = sim
    rc, out, err = check("--probe", station(tmp, links, "good"))
    assert rc == 0, out + err
    assert f"meter answered on {links['meter']} at 115200 8N1, unit 1: channel 1" in out, out
    assert f"STM32 answered a PING on {links['stm32']} at 115200 baud" in out, out
    assert "probe: all OK" in out


def test_a_wrong_baud_fails_and_the_scan_finds_the_meter(sim):
    tmp, links = sim
    path = station(tmp, links, "baud", meter={"baud": 38400})
    rc, out, _ = check("--probe", path)
    assert rc == 1, out
    assert f"meter not answering on {links['meter']} at 38400 8N1, unit 1" in out, out
    assert "hookwatch check --probe --scan" in out                     # the fix
    rc, out, _ = check("--probe", "--scan", path)
    assert rc == 1, out
    assert f"it answered at {links['meter']} at 115200 8N1, unit 1: set meter.baud: 115200." in out, out


def test_a_wrong_unit_is_found_by_the_scan(sim):
    tmp, links = sim
    rc, out, _ = check("--probe", "--scan", station(tmp, links, "unit", meter={"unit_id": 7}))
    assert rc == 1, out
    assert f"meter not answering on {links['meter']} at 115200 8N1, unit 7" in out, out
    assert "set meter.unit_id: 1." in out, out


def test_rs485_mode_on_a_pty_is_reported(sim):
    tmp, links = sim
    rc, out, _ = check("--probe", station(tmp, links, "rs485", meter={"rs485": {"enabled": True}}))
    assert rc == 1, out
    assert f"meter.rs485: {links['meter']}: the port refuses the kernel's RS-485 mode" in out, out
    assert "remove the `rs485:` section" in out


def test_a_dead_port(sim, tmp_path):
    _, links = sim
    dead = {"meter": str(tmp_path / "gone-meter"), "stm32": str(tmp_path / "gone-stm32")}
    rc, out, _ = check("--probe", "--skip-local", station(tmp_path, dead, "dead"))
    assert rc == 1, out
    assert f"meter port {dead['meter']} no such device: check the cable" in out, out
    assert f"STM32 port {dead['stm32']} does not exist" in out, out


def test_a_broker_that_refuses_the_password_and_a_taken_port(sim, tmp_path):
    tmp, links = sim
    passwd = tmp_path / "passwd"
    subprocess.run([require_tool("mosquitto_passwd"), "-b", "-c", str(passwd), "hw", "s3cret"], check=True,
                   capture_output=True, timeout=60)
    b = Broker(tmp_path)
    b.conf.write_text(b.conf.read_text().replace("allow_anonymous true", "allow_anonymous false")
                      + f"password_file {passwd}\n")
    taken = []
    for _ in range(3):          # held by "another program": Modbus TCP, metrics, console
        t = socket.socket()
        t.bind(("127.0.0.1", 0))
        t.listen(1)
        taken.append(t)
    busy, busy_metrics, busy_console = (t.getsockname()[1] for t in taken)
    free = free_port()
    with b:
        mqtt = {"enabled": True, "port": b.port, "username": "hw", "password_env": "HW_PROBE_PW"}
        path = station(tmp, links, "broker", mqtt=mqtt,
                       modbus_tcp={"enabled": True, "port": busy, "unit_id": 1})
        with open(path) as f:
            cfg = yaml.safe_load(f)
        cfg["metrics"] = {"enabled": True, "port": busy_metrics}
        cfg["console"] = {"enabled": True, "listen": [f"127.0.0.1:{busy_console}"]}
        with open(path, "w") as f:
            yaml.safe_dump(cfg, f)
        rc, out, _ = check("--probe", path, env={"HW_PROBE_PW": "wrong"})
        assert rc == 1, out
        assert (f"mqtt broker 127.0.0.1:{b.port} refused user 'hw' (") in out, out
        assert "check mqtt.username and the password" in out
        assert f"modbus_tcp: 127.0.0.1:{busy} is already in use by another program" in out, out
        assert f"metrics: 127.0.0.1:{busy_metrics} is already in use" in out, out
        assert f"console.listen: 127.0.0.1:{busy_console} is already in use" in out, out
        # the right password and a free port: all OK (and the Sparkplug section's broker too)
        path = station(tmp, links, "broker2", mqtt=mqtt, modbus_tcp={"enabled": True, "port": free, "unit_id": 1})
        with open(path) as f:
            cfg = yaml.safe_load(f)
        cfg["sparkplug"] = {**mqtt, "password_env": "HW_PROBE_SPB"}
        with open(path, "w") as f:
            yaml.safe_dump(cfg, f)
        rc, out, _ = check("--probe", path, env={"HW_PROBE_PW": "s3cret", "HW_PROBE_SPB": "nope"})
        assert rc == 1 and f"sparkplug broker 127.0.0.1:{b.port} refused user 'hw'" in out, out
        assert "check sparkplug.username" in out
        rc, out, _ = check("--probe", path, env={"HW_PROBE_PW": "s3cret", "HW_PROBE_SPB": "s3cret"})
        assert rc == 0, out
        assert f"mqtt broker 127.0.0.1:{b.port} accepted user 'hw'." in out
        assert f"sparkplug broker 127.0.0.1:{b.port} accepted user 'hw'." in out
        # a Sparkplug server set: every member is asked
        nobody = free_port()
        cfg["sparkplug"]["servers"] = [f"127.0.0.1:{b.port}", f"127.0.0.1:{nobody}"]
        with open(path, "w") as f:
            yaml.safe_dump(cfg, f)
        rc, out, _ = check("--probe", path, env={"HW_PROBE_PW": "s3cret", "HW_PROBE_SPB": "s3cret"})
        assert rc == 1, out
        assert f"sparkplug broker 127.0.0.1:{b.port} accepted user 'hw'." in out
        assert f"sparkplug broker 127.0.0.1:{nobody} cannot be reached" in out, out
        assert f"modbus_tcp: 127.0.0.1:{free} is free to listen on." in out
    for t in taken:
        t.close()
    # the broker gone: cannot be reached
    rc, out, _ = check("--probe", path, env={"HW_PROBE_PW": "s3cret"})
    assert rc == 1 and f"mqtt broker 127.0.0.1:{b.port} cannot be reached" in out, out


def test_an_echoing_adapter_needs_local_echo(tmp_path):
    sc = tmp_path / "echo.yaml"
    with open(os.path.join(os.path.dirname(__file__), "..", "..", "..", "config", "scenarios", "demo.yaml")) as f:
        data = yaml.safe_load(f)
    data["meter"] = {**(data.get("meter") or {}), "echo": True,
                     "map": os.path.abspath("config/meters/zn-s.yaml")}
    sc.write_text(yaml.safe_dump(data))
    with virtual_station(tmp_path, str(sc)) as (_p, links):
        rc, out, _ = check("--probe", station(tmp_path, links, "echo0"))
        assert rc == 1, out
        assert f"the adapter on {links['meter']} hands our own request back" in out, out
        assert "set meter.local_echo: true." in out
        rc, out, _ = check("--probe", station(tmp_path, links, "echo1", meter={"local_echo": True}))
        assert rc == 0, out
    # and the other way round: local_echo on an adapter that does not echo
    with virtual_station(tmp_path, "config/scenarios/demo.yaml") as (_p, links):
        rc, out, _ = check("--probe", station(tmp_path, links, "echo2", meter={"local_echo": True}))
        assert rc == 1 and "set meter.local_echo: false." in out, out


def test_the_latency_timer_of_a_usb_adapter_is_judged_against_the_slot(tmp_path):
    # the sysfs layout of an FTDI adapter (no FTDI on this machine): 16 ms fails, 1 ms passes
    from types import SimpleNamespace

    from gateway.commission.probe import _latency_findings, meter_map_of

    d = tmp_path / "sys" / "class" / "tty" / "ttyUSB3" / "device"
    d.mkdir(parents=True)
    m = meter_map_of(SimpleNamespace(map=None, baud=None, unit_id=None, parity=None))
    for ms, ok in ((16, False), (1, True)):
        (d / "latency_timer").write_text(f"{ms}\n")
        f, = _latency_findings("/dev/ttyUSB3", m, 0.015, str(tmp_path / "sys"))
        assert f.ok is ok, f
    (d / "latency_timer").write_text("16\n")
    f, = _latency_findings("/dev/ttyUSB3", m, 0.015, str(tmp_path / "sys"))
    assert "holds received bytes for 16 ms" in f.text and "99-hookwatch.rules" in f.text
    assert _latency_findings("/dev/pts/3", m, 0.015, str(tmp_path / "sys")) == []
    # the STM32 link's ACK against its 10 ms timeout
    from gateway.commission.probe import stm32_latency_finding

    stm = SimpleNamespace(port="/dev/ttyUSB3", baud=115200, timeout_s=0.01)
    f = stm32_latency_finding(stm, str(tmp_path / "sys"))
    assert not f.ok and "stm32.timeout_s" in f.text
    (d / "latency_timer").write_text("1\n")
    assert stm32_latency_finding(stm, str(tmp_path / "sys")).ok
    assert stm32_latency_finding(SimpleNamespace(port="/dev/pts/4", baud=115200, timeout_s=0.01),
                                 str(tmp_path / "sys")) is None


def test_a_silent_meter_at_run_time_is_named_with_its_port_and_settings(sim, tmp_path):
    _, links = sim
    path = station_yaml(tmp_path, links, name="silent", meter={"unit_id": 9})
    gw = run_gateway(tmp_path, path, "--start")
    try:
        wait_log(gw, "zero check", timeout=60)
        said = f"meter not answering on {links['meter']} at 115200 8N1, unit 9"
        assert any("zero check" in ln and said in ln for ln in gw.log_all().splitlines()), gw.log()
        # and the station's own counted line on the failing reads (issue 27.8): once in the window
        line = "reads since the last check gave no reading"
        assert sum(line in ln and said in ln for ln in gw.log_all().splitlines()) == 1, gw.log()
    finally:
        gw.stop()


def test_the_probe_limits_are_documented_as_they_are():
    from conftest import ROOT
    from gateway.commission import probe as P

    with open(os.path.join(ROOT, "docs", "limits.md"), encoding="utf-8") as f:
        text = f.read()
    assert ", ".join(map(str, P.SCAN_BAUDS)) in text
    assert f"unit IDs {P.SCAN_UNITS[0]}–{P.SCAN_UNITS[-1]}" in text
    assert f"wire time + {P.METER_MARGIN_S:g} s" in text and f"wire time + {P.SCAN_MARGIN_S:g} s" in text
    assert f"{P.STM32_ATTEMPTS} PINGs" in text and f"CONNACK within {P.BROKER_TIMEOUT_S:g} s" in text


# ------------------------------------------------------------------------------------------------
def test_the_probe_beside_a_running_station_costs_it_no_slot_and_names_it(tmp_path):
    """Issue 27.3: `check --probe --scan` beside a live station once reported its meter "not
    answering", cost it 471 of 582 slots and a protection stop, and left the meter port at 9600
    baud. The probe now finds both ports in use, names the station holding them and touches
    neither: not one byte reaches the virtual meter but the station's own requests (the scan's
    other units and bauds would), the port keeps the station's settings, no reply the station
    reads is garbled, and the running test completes with every slot accounted for.

    That no slot is MISSING while the probe runs is asserted as what it comes down to — nothing
    on the station's line but its own exchanges — not as a count of MISSING slots in the window:
    on a loaded test machine the virtual meter (a process at normal priority) answers late in any
    2-s window, probe or not (measured: 5 MISSING slots in 2.5 s before the probe)."""
    events_path = tmp_path / "sim-events.jsonl"
    with virtual_station(tmp_path, "config/scenarios/demo.yaml",
                         extra=["--events", str(events_path)]) as (_p, links):
        path = station_yaml(tmp_path, links, name="live", method=STALL_TOLERANT, test={"t_end_s": 12})
        stats_path = tmp_path / "stats.json"
        gw = run_gateway(tmp_path, path, "--start", "--exit-when-done", "--stats-json", str(stats_path))
        try:
            wait_log(gw, "test_started {", timeout=90)
            fd = os.open(links["meter"], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            try:
                before = termios.tcgetattr(fd)
                rc, out, _ = check("--probe", "--scan", path)
                after = termios.tcgetattr(fd)
            finally:
                os.close(fd)
            assert rc == 1, out
            who = f"station live (pid {gw.p.pid})"
            assert f"meter port {links['meter']} is in use by {who}" in out, out
            assert f"STM32 port {links['stm32']} is in use by {who}" in out, out
            assert "not answering" not in out and "answered at" not in out, out
            assert after == before and after[4] == termios.B115200, (before, after)
            assert wait_exit(gw, 90) == 0, gw.log()
            log = gw.log_all()
        finally:
            gw.stop()
    [d] = test_dirs(tmp_path, "live")
    res = read_json(os.path.join(d, "result.json"))
    assert res["test_status"] == "completed", res
    stats = read_json(str(stats_path))["live"]
    assert_no_slot_lost(d, res["method"], stats)
    c = stats["meter"]
    assert c["garbage"] == c["crc_errors"] == c["port_lost"] == c["port_in_use"] == 0, c
    with open(events_path) as f:
        [stop] = [e for e in map(json.loads, f) if e["event"] == "stop"]
    seen = stop["counters"]["meter"]
    # the virtual meter heard the station's requests and nothing else
    assert seen.get("other_unit", 0) == seen.get("wrong_baud", 0) == seen.get("garbage", 0) == 0, seen
    assert seen["requests"] <= c["reads"], (seen, c)
    assert "port lost" not in log and "in use" not in log, log


def test_the_probe_reads_an_independent_slave_with_the_station_s_own_driver(tmp_path):
    """Issue 27.8: "meter answered" means the station's own driver read it, not only pymodbus'
    client. pymodbus' serial server behind a pty pair: both read it. With meter.local_echo set
    (the driver then takes the reply's first bytes for the echo of its request) pymodbus' client
    still reads it, and the probe says that the station would not."""
    require_tool("socat")
    stm = tmp_path / "no-stm32"
    with pymodbus_meter(tmp_path) as meter:
        links = {"meter": meter, "stm32": str(stm)}
        rc, out, _ = check("--probe", station(tmp_path, links, "pym"))
        assert f"ok: meter answered on {meter} at 115200 8N1, unit 1: channel 1 0.500 N, channel 2 " \
               "0.250 N; the station's driver read it too" in out, out
        rc, out, _ = check("--probe", station(tmp_path, links, "pymecho", meter={"local_echo": True}))
        assert rc == 1
        assert "ok: meter answered" not in out, out
        # what the driver met is "no reply of this unit" (it took the reply's first bytes for its
        # echo) or, on a loaded box, a timeout within its 15 ms: either way the probe says the
        # station would not read it, and why (the echo setting)
        assert f"FAILED: pymodbus' client reads the meter (on {meter} at 115200 8N1, unit 1: channel 1" \
               f" 0.500 N, channel 2 0.250 N) but the station's own driver does not: " in out, out
        assert (f"the bytes on {meter} at 115200 8N1, unit 1 are no reply of this unit" in out
                or f"meter not answering on {meter}" in out), out
        assert f"FAILED: meter.local_echo is set but the adapter on {meter} does not echo" in out, out
