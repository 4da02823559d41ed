"""`hookwatch sim`: scenario validation, and the virtual station as a separate process observed on
the wire (its two pseudo-terminals) while its fault timeline runs."""
import errno
import json
import os
import select
import signal
import subprocess
import termios
import threading
import time
import tty

import pytest
import yaml

from conftest import ROOT, hookwatch_cmd
from drivers.meter.meter_map import DEFAULT_MAP_PATH, crc_ok, load_map, with_crc
from drivers.sim.scenario import FAULT_KINDS, ScenarioError, load_scenario, scenario_from_dict
from drivers.stm32 import protocol as sp
from kit.proc import stop_process

SCENARIOS = os.path.join(ROOT, "config", "scenarios")


# ---------------------------------------------------------------------------------- validation
def _err(data, tmp_path, name="bad.yaml") -> str:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ScenarioError) as ei:
        load_scenario(str(path))
    msg = str(ei.value)
    assert str(path) in msg and "\n" not in msg
    return msg


def test_every_shipped_scenario_loads():
    names = sorted(os.listdir(SCENARIOS))
    for g in ("I", "II"):
        for t in ("0.5", "0.7", "0.9"):
            assert f"life-{g}-{t}.yaml" in names
    kinds = set()
    for n in names:
        sc = load_scenario(os.path.join(SCENARIOS, n))
        kinds |= {f.fault for f in sc.faults}
        if n.startswith("life-"):
            assert sc.plant.time_scale == 1.0 and not sc.faults
    assert kinds >= set(FAULT_KINDS) - {"stm32_port_vanish"}
    demo = load_scenario(None)
    assert demo.path.endswith("demo.yaml")
    assert demo.method == {"w_ss": 5, "w_hold": 30, "tau": 5, "t_end": 150}


def test_scenario_validation_messages(tmp_path):
    base = {"seed": 1, "plant": {"grade": "I", "t_set": 0.5}}
    m = _err({**base, "colour": "red"}, tmp_path)
    assert "colour: unknown key; allowed: description, seed" in m
    m = _err({**base, "plant": {"grade": "III"}}, tmp_path)
    assert "plant.grade: 'III' is not allowed; allowed: I, II" in m
    m = _err({**base, "plant": {"t_set": -1}}, tmp_path)
    assert "plant.t_set: -1" in m and "> 0" in m
    m = _err({**base, "plant": {"wear": {"onset": 5}}}, tmp_path)
    assert "plant.wear.onset: unknown key; allowed: mu_ss, onset_s" in m
    m = _err({**base, "plant": {"ripple": {"harmonic_h": 1.5}}}, tmp_path)
    assert "plant.ripple.harmonic_h: 1.5" in m and "an integer" in m
    m = _err({**base, "plant": {"drift": {"sine_amp": "big"}}}, tmp_path)
    assert "plant.drift.sine_amp: 'big'" in m and "a number" in m
    m = _err({**base, "faults": [{"at_s": 1, "duration_s": 1, "fault": "meteor"}]}, tmp_path)
    assert "faults[0].fault: 'meteor' is not allowed; allowed: meter_drop, meter_bad_crc" in m
    m = _err({**base, "faults": [{"at_s": 1, "duration_s": 1, "fault": "meter_late"}]}, tmp_path)
    assert "faults[0].delay_ms: missing" in m
    m = _err({**base, "faults": [{"at_s": 1, "duration_s": 1, "fault": "yarn_break", "delay_ms": 3}]},
             tmp_path)
    assert "faults[0].delay_ms: unknown key" in m
    m = _err({**base, "faults": [{"at_s": -1, "duration_s": 1, "fault": "yarn_break"}]}, tmp_path)
    assert "faults[0].at_s: -1" in m and "≥ 0" in m
    m = _err({**base, "faults": [{"at_s": 1, "duration_s": 0, "fault": "yarn_break"}]}, tmp_path)
    assert "faults[0].duration_s: 0" in m
    m = _err({**base, "faults": [{"at_s": 1, "duration_s": 5, "fault": "yarn_break"},
                                 {"at_s": 3, "duration_s": 1, "fault": "yarn_break"}]}, tmp_path)
    assert "overlaps faults[0]" in m
    m = _err({**base, "meter": {"map": "nowhere.yaml"}}, tmp_path)
    assert "meter.map: 'nowhere.yaml': no such file" in m
    m = _err({**base, "meter": {"baud": 12345}}, tmp_path)
    assert "meter.baud: 12345 is not allowed; allowed: 1200, 2400" in m
    m = _err({**base, "stm32": {"watchdog_s": 0.001}}, tmp_path)
    assert "stm32.watchdog_s: 0.001" in m
    m = _err({**base, "method": {"w_ss": -3}}, tmp_path)
    assert "w_ss" in m and "> 0" in m
    m = _err({**base, "method": {"wss": 3}}, tmp_path)
    assert "unknown parameter 'wss'" in m
    m = _err({**base, "control": {"kq": 3}}, tmp_path)
    assert "control.kq: unknown key" in m
    m = _err([1, 2], tmp_path)
    assert "must be a mapping" in m
    (tmp_path / "broken.yaml").write_text("plant: {grade: I\n")
    with pytest.raises(ScenarioError, match="not valid YAML"):
        load_scenario(str(tmp_path / "broken.yaml"))
    with pytest.raises(ScenarioError, match="no such scenario file"):
        load_scenario(str(tmp_path / "missing.yaml"))
    # relative map paths are relative to the scenario file; defaults fill the rest
    sc = scenario_from_dict({"meter": {"map": os.path.relpath(DEFAULT_MAP_PATH, SCENARIOS)}},
                            os.path.join(SCENARIOS, "x.yaml"))
    assert sc.meter_map == DEFAULT_MAP_PATH and sc.plant.grade == "I"


def test_cli_bad_scenario_is_one_line_exit_2(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("plant: {grade: III}\n")
    p = subprocess.run(hookwatch_cmd() + ["sim", str(bad), "--link-dir", str(tmp_path / "l")],
                       capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert p.returncode == 2
    assert p.stdout == ""
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "plant.grade: 'III'" in lines[0] and lines[0].startswith("hookwatch sim:")
    p = subprocess.run(hookwatch_cmd() + ["sim", str(tmp_path / "none.yaml")],
                       capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert p.returncode == 2 and "no such scenario file" in p.stderr


# ---------------------------------------------------------------------------------- the wire
class Port:
    """A client end of a pty, opened through its symlink at 115200 baud (the virtual meter ignores
    requests sent at another speed, as a real one does); reopens when the link comes back."""

    def __init__(self, path: str, baud: int = 115200):
        self.path = path
        self.speed = getattr(termios, f"B{baud}")
        self.fd: int | None = None

    def ensure(self) -> bool:
        if self.fd is not None:
            return True
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError:
            return False
        tty.setraw(fd, termios.TCSANOW)
        attrs = termios.tcgetattr(fd)
        attrs[4] = attrs[5] = self.speed
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
        self.fd = fd
        return True

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def drain(self) -> None:
        while self.fd is not None and select.select([self.fd], [], [], 0)[0]:
            if not self.read():
                break

    def read(self) -> bytes:
        try:
            data = os.read(self.fd, 256)
        except BlockingIOError:
            return b""
        except OSError as e:
            if e.errno in (errno.EIO, errno.EBADF):
                self.close()
                return b""
            raise
        if not data:
            self.close()
        return data

    def exchange(self, req: bytes, n: int, timeout: float) -> tuple[bytes, float]:
        """Write, collect up to n bytes for at most timeout; (bytes, seconds to the last byte)."""
        self.drain()
        if self.fd is None:
            return b"", 0.0
        t0 = time.monotonic()
        try:
            os.write(self.fd, req)
        except OSError:
            self.close()
            return b"", 0.0
        buf = b""
        t_last = t0
        while len(buf) < n and self.fd is not None:
            left = t0 + timeout - time.monotonic()
            if left <= 0 or not select.select([self.fd], [], [], left)[0]:
                break
            data = self.read()
            if data:
                buf += data
                t_last = time.monotonic()
        return buf, t_last - t0


class Observer:
    """Two threads on the client side of the virtual station: a meter poller (FC 3 every 20 ms)
    and an STM32 driver keeping the motor enabled at 150 rpm. Every outcome is recorded with the
    monotonic time."""

    def __init__(self, links: dict):
        self.map = load_map(DEFAULT_MAP_PATH)
        self.meter = Port(links["meter"])
        self.stm = Port(links["stm32"])
        self.link_meter = links["meter"]
        self.meter_log: list[tuple] = []     # (t, kind, ch1, ch2, rtt)
        self.stm_log: list[tuple] = []       # (t, kind, status)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._poll_meter, daemon=True),
                         threading.Thread(target=self._drive, daemon=True)]

    def __enter__(self):
        for t in self._threads:
            t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        for t in self._threads:
            t.join(10)
        self.meter.close()
        self.stm.close()

    def _poll_meter(self):
        fc, addr, count = self.map.read_block
        req = with_crc(bytes([self.map.unit_id, fc]) + addr.to_bytes(2, "big") + count.to_bytes(2, "big"))
        n = self.map.response_bytes
        while not self._stop.is_set():
            t = time.monotonic()
            if not os.path.lexists(self.link_meter):
                self.meter.close()
                self.meter_log.append((t, "gone", None, None, None))
            elif not self.meter.ensure():
                self.meter_log.append((t, "gone", None, None, None))
            else:
                buf, rtt = self.meter.exchange(req, n, 0.08)
                if len(buf) < n:
                    kind = "gone" if self.meter.fd is None else "none"
                    self.meter_log.append((t, kind, None, None, None))
                elif not crc_ok(buf[:n]):
                    self.meter_log.append((t, "bad_crc", None, None, rtt))
                else:
                    regs = [int.from_bytes(buf[3 + 2 * i:5 + 2 * i], "big") for i in range(count)]
                    ch1, ch2 = self.map.decode(regs)
                    self.meter_log.append((t, "ok", ch1, ch2, rtt))
            self._stop.wait(max(0.0, 0.02 - (time.monotonic() - t)))

    def _drive(self):
        seq = 0
        enabled = False
        while not self._stop.is_set():
            t = time.monotonic()
            if self.stm.ensure():
                seq = (seq + 1) & 0xFF
                req = sp.req_set_speed(seq, 150.0) if enabled else sp.req_enable(seq)
                buf, _ = self.stm.exchange(req, sp.ACK_LEN, 0.03)
                parser = sp.FrameParser()
                frames = parser.feed(buf)
                if frames:
                    rep = sp.decode_reply(frames[0])
                    st = rep.status
                    self.stm_log.append((t, "ok", st))
                    enabled = bool(st is not None and st.enabled)
                else:
                    self.stm_log.append((t, "none", None))
            self._stop.wait(max(0.0, 0.05 - (time.monotonic() - t)))

    def meter_between(self, a, b):
        return [r for r in self.meter_log if a <= r[0] <= b]

    def fresh_between(self, a, b):
        """The replies between a and b but those right after a read that got none: on a loaded
        machine that read's late reply (the value of an instant before) meets the next request."""
        log = self.meter_log
        return [r for i, r in enumerate(log) if a <= r[0] <= b and not (i and log[i - 1][1] == "none")]

    def stm_between(self, a, b):
        return [r for r in self.stm_log if a <= r[0] <= b]


class SimProc:
    def __init__(self, tmp_path, scenario: str, *extra: str):
        self.tmp = tmp_path
        self.links = {"meter": str(tmp_path / "links" / "meter"),
                      "stm32": str(tmp_path / "links" / "stm32")}
        self.events_path = tmp_path / "events.jsonl"
        self.truth_path = tmp_path / "truth.json"
        self.err = open(tmp_path / "sim.err", "w")
        self.p = subprocess.Popen(
            hookwatch_cmd() + ["sim", scenario, "--link-dir", str(tmp_path / "links"),
                               "--truth", str(self.truth_path), "--events", str(self.events_path),
                               *extra],
            stdout=subprocess.PIPE, stderr=self.err, text=True, cwd=ROOT)
        self.lines = [self.p.stdout.readline().strip() for _ in range(2)]

    def events(self):
        with open(self.events_path) as f:
            return [json.loads(x) for x in f if x.strip()]

    def stop(self, sig=signal.SIGTERM) -> int:
        rc = stop_process(self.p, sig, timeout=20)
        self.rest = self.p.stdout.read()
        self.p.stdout.close()
        self.err.close()
        return rc


def test_sim_process_prints_paths_and_each_fault_fires_on_the_wire(tmp_path):
    timeline = [
        ("meter_drop", 2.0, 1.0, {}),
        ("meter_bad_crc", 3.5, 1.0, {}),
        ("meter_late", 5.0, 1.0, {"delay_ms": 40}),
        ("saturation", 6.5, 1.0, {}),
        ("swap_channels", 8.0, 1.0, {}),
        ("yarn_break", 9.5, 1.0, {}),
        ("meter_port_vanish", 11.0, 1.5, {}),
        ("motor_stall", 13.5, 1.0, {}),
        ("stm32_silent", 15.0, 1.0, {}),
    ]
    sc = {"seed": 3, "plant": {"grade": "II", "t_set": 0.5, "time_scale": 150},
          "faults": [{"at_s": a, "duration_s": d, "fault": k, **kw} for k, a, d, kw in timeline]}
    path = tmp_path / "timeline.yaml"
    path.write_text(yaml.safe_dump(sc))
    sim = SimProc(tmp_path, str(path))
    try:
        assert sim.lines[0].startswith("meter: /dev/pts/"), sim.lines
        assert sim.lines[1].startswith("stm32: /dev/pts/"), sim.lines
        for name in ("meter", "stm32"):
            assert os.path.islink(sim.links[name])
            assert os.path.realpath(sim.links[name]) == sim.lines[0 if name == "meter" else 1].split(": ")[1]
        truth = json.loads(sim.truth_path.read_text())
        assert truth["grade"] == "II" and truth["seed"] == 3 and truth["onset_run_s"] > 0
        t0 = truth["t0_monotonic"]
        with Observer(sim.links) as obs:
            deadline = time.monotonic() + 40
            while time.monotonic() < deadline:
                ev = sim.events()
                if sum(e["event"] == "fault_off" for e in ev) >= len(timeline):
                    break
                time.sleep(0.2)
            time.sleep(1.0)
        rc = sim.stop()
    finally:
        if sim.p.poll() is None:
            sim.stop()
    assert rc == 0, (tmp_path / "sim.err").read_text()
    assert not os.path.lexists(sim.links["meter"]) and not os.path.lexists(sim.links["stm32"])
    ev = sim.events()
    assert ev[0]["event"] == "start" and ev[-1]["event"] == "stop"
    assert abs(ev[0]["t0_monotonic"] - t0) < 1e-9
    on = {e["fault"]: e for e in ev if e["event"] == "fault_on"}
    off = {e["fault"]: e for e in ev if e["event"] == "fault_off"}
    assert set(on) == set(off) == {k for k, *_ in timeline}
    for kind, at, dur, _ in timeline:
        assert at <= on[kind]["t"] < at + 1.0, (kind, on[kind])      # fired on time (loaded CPU)
        assert at + dur <= off[kind]["t"] < at + dur + 1.0, (kind, off[kind])
    assert any(e["event"] == "yarn_running" for e in ev)

    def window(kind, margin=0.25):      # a loaded machine logs a toggle late: the edges are left out
        return t0 + on[kind]["t"] + margin, t0 + off[kind]["t"] - margin

    # the wire works before the first fault
    before = obs.meter_between(t0 + 1.0, t0 + on["meter_drop"]["t"] - 0.1)
    assert len(before) > 10 and all(r[1] == "ok" for r in before)
    assert all(0.2 < (r[2] + r[3]) / 2 < 0.8 for r in before[-5:])     # the loop-free motor at 150 rpm
    # meter_drop: no replies at all
    rows = obs.meter_between(*window("meter_drop"))
    assert len(rows) > 4 and all(r[1] == "none" for r in rows)      # 80-ms timeouts
    # meter_bad_crc: replies whose CRC is wrong
    rows = obs.meter_between(*window("meter_bad_crc"))
    assert len(rows) > 10 and all(r[1] == "bad_crc" for r in rows)
    # meter_late: replies 40 ms late
    rows = obs.meter_between(*window("meter_late"))
    assert len(rows) > 5 and all(r[1] == "ok" and r[4] > 0.035 for r in rows)
    # saturation: both channels at full scale
    rows = obs.fresh_between(*window("saturation"))
    assert len(rows) > 10 and all(r[1] == "ok" and r[2] == r[3] == 5.0 for r in rows)
    # swap_channels: the tight side arrives on ch1
    rows = obs.fresh_between(*window("swap_channels"))
    assert len(rows) > 10 and all(r[1] == "ok" and r[2] > r[3] for r in rows)
    # yarn_break: tension gone
    rows = obs.fresh_between(*window("yarn_break"))
    assert len(rows) > 10 and all(r[1] == "ok" and abs(r[2]) < 0.01 and abs(r[3]) < 0.01 for r in rows)
    # meter_port_vanish: the symlink and the device are gone, then back (another device)
    rows = obs.meter_between(*window("meter_port_vanish"))
    assert len(rows) > 10 and all(r[1] == "gone" for r in rows)
    assert off["meter_port_vanish"]["device"].startswith("/dev/pts/")
    after = obs.meter_between(t0 + off["meter_port_vanish"]["t"] + 0.3, t0 + on["motor_stall"]["t"])
    assert after and all(r[1] == "ok" for r in after)
    # motor_stall: the STM32 reports the stall and zero speed
    rows = obs.stm_between(*window("motor_stall", 0.1))
    assert any(r[1] == "ok" and r[2].stalled and r[2].actual_rpm == 0.0 for r in rows)
    # stm32_silent: no answers; answers before and after
    rows = obs.stm_between(*window("stm32_silent"))
    assert len(rows) > 5 and all(r[1] == "none" for r in rows)
    assert any(r[1] == "ok" for r in obs.stm_between(t0 + off["stm32_silent"]["t"] + 0.2, t0 + 1e9))


def _lines(path) -> int:
    try:
        with open(path) as f:
            return sum(1 for _ in f)
    except FileNotFoundError:
        return 0


def test_sim_default_scenario_duration_trace_and_sigint(tmp_path):
    sim = SimProc(tmp_path, os.path.join(SCENARIOS, "demo.yaml"), "--trace", str(tmp_path / "trace.csv"),
                  "--duration", "60")
    try:
        assert sim.lines[0].startswith("meter: ") and sim.lines[1].startswith("stm32: ")
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and _lines(tmp_path / "trace.csv") < 12:
            time.sleep(0.1)
        rc = sim.stop(signal.SIGINT)
    finally:
        if sim.p.poll() is None:
            sim.stop()
    assert rc == 0
    lines = (tmp_path / "trace.csv").read_text().splitlines()
    assert lines[0] == "t,command_rpm,speed_rpm,enabled,t_mean,T1,T2,mu,wear_s,faults"
    ts = [float(x.split(",")[0]) for x in lines[1:]]
    assert len(ts) >= 10 and all(abs(b - a - 0.1) < 1e-6 for a, b in zip(ts, ts[1:]))
    truth = json.loads(sim.truth_path.read_text())
    assert truth["grade"] == "I" and truth["time_scale"] == 300.0
    assert 75 < truth["onset_run_s"] < 125 and truth["cross_run_s"] > truth["onset_run_s"]
    # --duration ends the run by itself (exit 0; one that did not would meet the timeout)
    p = subprocess.run(hookwatch_cmd() + ["sim", "--link-dir", str(tmp_path / "l2"), "--duration", "1.5"],
                       capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert p.returncode == 0, p.stderr
    assert p.stdout.splitlines()[:2][0].startswith("meter: ")
    assert any('"event": "start"' in x for x in p.stderr.splitlines())      # events default to stderr
