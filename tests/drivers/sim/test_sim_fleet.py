"""`hookwatch sim` hosting several virtual stations in one process (a fleet file or --count N):
each station has its own ptys and links, answers with its own plant's readings, and every meter
keeps its reply timing while the others are polled in the same slot."""
import json
import os
import selectors
import signal
import statistics
import subprocess
import time

import pytest
import serial
import yaml

from conftest import ROOT, hookwatch_cmd
from drivers.meter.meter_map import DEFAULT_MAP_PATH, crc_ok, load_map, with_crc
from drivers.stm32 import protocol as sp

REQ = with_crc(bytes([1, 3, 0, 0, 0, 4]))      # the map's read block: 4 holding registers
REPLY_LEN = 13


class FleetSim:
    def __init__(self, tmp_path, *args):
        self.events_path = tmp_path / "events.jsonl"
        self.link_dir = tmp_path / "links"
        self.err = open(tmp_path / "sim.err", "w")
        self.p = subprocess.Popen(
            hookwatch_cmd() + ["sim", *args, "--link-dir", str(self.link_dir),
                               "--events", str(self.events_path)],
            stdout=subprocess.PIPE, stderr=self.err, text=True, cwd=ROOT)
        self.devices = {}
        while True:
            line = self.p.stdout.readline()
            assert line, f"sim ended early: {(tmp_path / 'sim.err').read_text()}"
            if line.startswith("ready:"):
                break
            kind, rest = line.split(" ", 1)
            name, dev = rest.strip().split(": ")
            self.devices[(name, kind)] = dev

    def link(self, name, kind):
        return str(self.link_dir / name / kind)

    def stop(self):
        self.p.send_signal(signal.SIGTERM)
        rc = self.p.wait(30)
        self.p.stdout.close()
        self.err.close()
        with open(self.events_path) as f:
            return rc, [json.loads(x) for x in f if x.strip()]


def poll_all(ports, cycles):
    """Every 20 ms write the request to every meter at once, then collect the replies as they
    complete (selectors): {name: [(reply time s, frame)]}."""
    sel = selectors.DefaultSelector()
    for name, s in ports.items():
        sel.register(s.fileno(), selectors.EVENT_READ, name)
    out = {n: [] for n in ports}
    t_next = time.monotonic()
    for _ in range(cycles):
        t_next += 0.02
        bufs = {n: b"" for n in ports}
        t0 = {}
        for n, s in ports.items():
            s.reset_input_buffer()
            t0[n] = time.perf_counter()
            os.write(s.fileno(), REQ)
        pending = set(ports)
        deadline = time.perf_counter() + 0.1
        while pending and time.perf_counter() < deadline:
            for key, _ in sel.select(0.05):
                n = key.data
                bufs[n] += os.read(key.fd, 64)
                if n in pending and len(bufs[n]) >= REPLY_LEN:
                    out[n].append((time.perf_counter() - t0[n], bufs[n][:REPLY_LEN]))
                    pending.discard(n)
        time.sleep(max(0.0, t_next - time.monotonic()))
    sel.close()
    return out


def poll_links(sim, names, cycles):
    ports = {n: serial.Serial(sim.link(n, "meter"), 115200, timeout=0.2) for n in names}
    try:
        return poll_all(ports, cycles)
    finally:
        for s in ports.values():
            s.close()


def _scenario(tmp_path, name, faults):
    data = {"description": name, "seed": 1, "meter": {"map": DEFAULT_MAP_PATH},
            "stm32": {"watchdog_s": 0.2}, "plant": {"grade": "I", "t_set": 0.5, "time_scale": 150},
            "faults": faults}
    p = tmp_path / f"{name}.yaml"
    p.write_text(yaml.safe_dump(data))
    return p.name


def test_fleet_file_three_stations_own_readings_and_timing(tmp_path):
    normal = _scenario(tmp_path, "normal", [])
    sat = _scenario(tmp_path, "sat", [{"at_s": 0.0, "fault": "saturation"}])
    swap = _scenario(tmp_path, "swap", [{"at_s": 0.0, "fault": "swap_channels"}])
    fleet = tmp_path / "fleet.yaml"
    fleet.write_text(yaml.safe_dump({"stations": [
        {"name": "loom-a", "scenario": normal}, {"name": "loom-b", "scenario": sat},
        {"name": "loom-c", "scenario": swap, "seed": 7}]}))
    sim = FleetSim(tmp_path, str(fleet))
    try:
        names = ["loom-a", "loom-b", "loom-c"]
        assert sorted({n for n, _ in sim.devices}) == names
        devs = list(sim.devices.values())
        assert len(set(devs)) == 6                       # own pty for every meter and STM32
        for n in names:
            for kind in ("meter", "stm32"):
                assert os.path.realpath(sim.link(n, kind)) == sim.devices[(n, kind)]
        time.sleep(0.3)                                  # the faults at 0 s have fired
        res = poll_links(sim, names, 60)
        # each STM32 of the fleet answers on its own link
        with serial.Serial(sim.link("loom-b", "stm32"), 115200, timeout=2.0) as s:
            s.write(sp.req_ping(5))
            frames = sp.FrameParser().feed(s.read(sp.ACK_LEN))
            assert frames and sp.decode_reply(frames[0]).seq == 5
    finally:
        rc, events = sim.stop()
    assert rc == 0
    m = load_map(DEFAULT_MAP_PATH)
    expected = m.poll_time_s()
    for n in names:
        # replies that came within the poll's 100 ms (all of them but on a stalled machine); that
        # every request was answered is the meters' own count, below
        assert res[n], n
    vals = {}
    for n in names:
        ch = []
        for _, fr in res[n]:
            assert crc_ok(fr) and fr[:3] == bytes([1, 3, 8])
            ch.append(m.decode([int.from_bytes(fr[3 + 2 * i:5 + 2 * i], "big")
                                          for i in range(4)]))
        vals[n] = ch
    med = {n: (statistics.median(c[0] for c in vals[n]), statistics.median(c[1] for c in vals[n]))
           for n in names}
    assert med["loom-a"][0] < med["loom-a"][1] < 1.0          # at rest, T2 > T1
    assert med["loom-b"][0] > 4.5 and med["loom-b"][1] > 4.5  # saturated
    assert med["loom-c"][0] > med["loom-c"][1]                # swapped channels
    # timing: every meter's reply comes after the wire time although all were polled at once —
    # never before it; how close after is bench/bench_sim.py's figure (the meters' reply
    # lateness), not asserted on a loaded machine
    for n in names:
        rt = statistics.median(t for t, _ in res[n])
        print(f"{n}: reply time median {rt * 1e3:.2f} ms, expected {expected * 1e3:.2f} ms")
        assert min(t for t, _ in res[n]) >= expected * 0.98, (n, min(t for t, _ in res[n]), expected)
    stops = {e["station"]: e for e in events if e["event"] == "stop"}
    assert sorted(stops) == names
    for n in names:
        lat = stops[n]["meter_reply_lateness_ms"]
        c = stops[n]["counters"]["meter"]
        print(n, "meter's own reply lateness (ms):", lat)
        # every one of the 60 requests reached its own meter and was answered, once (the
        # lateness itself is bench/bench_sim.py's figure, not asserted on a loaded machine)
        assert c["requests"] == c["replies"] == 60 and lat["n"] == c["replies"], c
        assert c["replies"] >= len(res[n]), (n, c, len(res[n]))


def test_count_n_stations_with_own_links_and_samples(tmp_path):
    sim = FleetSim(tmp_path, "--count", "4", "--seed", "3")
    try:
        names = [f"sim0{i}" for i in range(1, 5)]
        assert sorted({n for n, _ in sim.devices}) == names
        res = poll_links(sim, names, 20)
    finally:
        rc, events = sim.stop()
    assert rc == 0
    starts = {e["station"]: e for e in events if e["event"] == "start"}
    assert [starts[n]["seed"] for n in names] == [3, 4, 5, 6]
    stops = {e["station"]: e["counters"]["meter"] for e in events if e["event"] == "stop"}
    for n in names:
        # every request reached its own meter and was answered once (the meters' count); the
        # replies read within the poll's 100 ms are all good frames
        assert stops[n]["requests"] == stops[n]["replies"] == 20, (n, stops[n])
        assert res[n] and all(crc_ok(fr) for _, fr in res[n]), n
    # links removed at exit
    assert not any(os.path.lexists(sim.link(n, k)) for n in names for k in ("meter", "stm32"))


@pytest.mark.parametrize("content, needle", [
    ({"stations": []}, "stations: expected a list"),
    ({"stations": [{"name": "a"}, {"name": "a"}]}, "name: 'a' is used twice"),
    ({"stations": [{"name": "../x"}]}, "name: '../x' is not allowed"),
    ({"stations": [{"name": "a", "sed": 1}]}, "stations[0]: sed: unknown key"),
    ({"stations": [{"name": "a", "scenario": "missing.yaml"}]}, "no such scenario file"),
    ({"stations": [{"seed": -1}]}, "seed: -1 is not allowed"),
])
def test_bad_fleet_file_is_one_line_exit_2(tmp_path, content, needle):
    f = tmp_path / "fleet.yaml"
    f.write_text(yaml.safe_dump(content))
    p = subprocess.run(hookwatch_cmd() + ["sim", str(f), "--link-dir", str(tmp_path / "l")],
                       capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert p.returncode == 2 and p.stdout == ""
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0] and lines[0].startswith("hookwatch sim:"), lines


def test_bad_count_exit_2(tmp_path):
    for n in ("0", "65"):
        p = subprocess.run(hookwatch_cmd() + ["sim", "--count", n, "--link-dir", str(tmp_path)],
                           capture_output=True, text=True, timeout=60, cwd=ROOT)
        assert p.returncode == 2 and "--count" in p.stderr
