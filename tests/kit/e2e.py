"""End-to-end helpers: a virtual station (`hookwatch sim`) and the gateway (`hookwatch run`) as
separate processes talking over pseudo-terminals."""
from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import time

import yaml

from conftest import ROOT, hookwatch_cmd
from kit.proc import Proc


@contextlib.contextmanager
def virtual_station(tmp_path, scenario: str, seed: int = 1, extra: list[str] | None = None):
    """Start `hookwatch sim SCENARIO` with its links under tmp_path/links; yields (proc, links)."""
    link_dir = tmp_path / "links"
    link_dir.mkdir(exist_ok=True)
    sc = scenario if os.path.isabs(scenario) else os.path.join(ROOT, scenario)
    truth = tmp_path / "truth.json"
    proc = Proc(hookwatch_cmd() + ["sim", sc, "--link-dir", str(link_dir), "--seed", str(seed),
                                   "--truth", str(truth), *(extra or [])],
                str(tmp_path / "sim.log"))
    try:
        proc.readline_until("meter:")
        proc.readline_until("stm32:")
        yield proc, {"meter": str(link_dir / "meter"), "stm32": str(link_dir / "stm32"),
                     "truth": str(truth)}
    finally:
        # the links go first: a gateway still running would otherwise follow them to the
        # pseudo-terminals the next test's simulator gets under the same numbers
        for name in ("meter", "stm32"):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(link_dir / name)
        proc.stop()


def kill_virtual_station(proc: Proc, links: dict) -> None:
    """The virtual station dies at once with both its ports (SIGKILL), and its links go as udev
    removes a pulled adapter's /dev/hookwatch/… names: a gateway that still follows them would
    otherwise open the pseudo-terminals another test's simulator gets under the same numbers (it
    did: a parallel run's fleet test locked another test's STM32 port and read its meter)."""
    proc.p.send_signal(signal.SIGKILL)
    proc.p.wait(10)
    for name in ("meter", "stm32"):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(links[name])


def station_yaml(tmp_path, links, *, name="e2e", method=None, control=None, test=None,
                 mqtt=None, modbus_tcp=None, meter=None, extra=None) -> str:
    cfg = {
        "station": {"id": name, "site": "lab", "area": "test", "line": "l1"},
        "meter": {"port": links["meter"], "map": os.path.join(ROOT, "config", "meters", "zn-s.yaml"),
                  **(meter or {})},
        "stm32": {"port": links["stm32"]},
        "method": method or {},
        "control": control or {},
        "test": {"sample_id": "S-1", "grade": "I", "t_set_n": 0.5, "t_end_s": 60, **(test or {})},
        "recorder": {"dir": str(tmp_path / "records")},
        "mqtt": {"enabled": False, **(mqtt or {})},
        "modbus_tcp": {"enabled": False, **(modbus_tcp or {})},
        **(extra or {}),          # further sections (forecast:, sparkplug:, metrics: …)
    }
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return str(path)


#: the gateway as deployed (deploy/systemd: ``--realtime 20``): its slot loops under SCHED_FIFO
#: where permitted (root in CI; elsewhere it logs why not and runs on normally). A life whose
#: baseline needs 4 steady windows of 2 s (QUICK_METHOD: ≤ 10 lost slots each) is then not at
#: the mercy of the test workers' CPU-bound work (ci: once no baseline under 4 workers)
DEPLOYED_ARGS = ("--realtime", "20")


def run_gateway(tmp_path, station_path, *args, name="gw") -> Proc:
    extra = () if "--realtime" in args else DEPLOYED_ARGS
    return Proc(hookwatch_cmd() + ["run", station_path, *args, *extra], str(tmp_path / f"{name}.log"))


def test_dirs(tmp_path, station="e2e"):
    d = tmp_path / "records" / station
    return sorted(str(d / x) for x in os.listdir(d) if (d / x).is_dir()) if d.exists() else []


def first_test_dir(tmp_path, station="e2e", timeout=60.0):
    """The station's first test folder, once its log exists (AssertionError after ``timeout``)."""
    t_wait = time.monotonic() + timeout
    while time.monotonic() < t_wait:
        dirs = test_dirs(tmp_path, station)
        if dirs and os.path.exists(os.path.join(dirs[0], "log.csv.gz")):
            return dirs[0]
        time.sleep(0.2)
    raise AssertionError(f"no test folder with a log for {station}")


def read_json(path):
    with open(path) as f:
        return json.load(f)


test_dirs.__test__ = False  # a helper, not a test (pytest collects it where it is imported)


def seed_lives(root, station: str, failures, stopped_slots, t_end: float) -> None:
    """A box's records of ``station``: a completed test per wear-out failure (t_life in s) and a
    test ended on purpose after its baseline per entry of ``stopped_slots`` (its slot count: a hook
    replaced early, a censored life), each a ``result.json`` as the station writes it."""
    tests = [("failure", x, None, round(x / 0.02) + 100, None) for x in failures]
    tests += [("aborted", None, ["STOPPED"], n, "hook_replaced") for n in stopped_slots]
    tag = station.upper()
    for i, (status, t_life, reasons, n_slots, why) in enumerate(tests):
        tid = f"2026030{i}T080000Z-{tag}-{i}"
        d = root / station / tid
        d.mkdir(parents=True)
        (d / "result.json").write_text(json.dumps({
            "test_id": tid, "station": station, "test_status": "aborted" if why else "completed",
            "end_reason": why or "completed", "sample_id": f"{tag}-{i}", "grade": "I", "t_set": 0.5,
            "ts": 0.02, "t_end": t_end,
            "method": {"status": status, "t_life": t_life, "k_b": 400, "n_slots": n_slots,
                       "stop_reasons": reasons}}))


def analyze_cli(log_path) -> dict:
    """`hookwatch analyze LOG --json` as a user runs it: the result keys (without `log`)."""
    p = subprocess.run(hookwatch_cmd() + ["analyze", str(log_path), "--json"], capture_output=True,
                       text=True, cwd=ROOT, timeout=60)
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    out.pop("log")
    return out


def wait_log(proc: Proc, text: str, timeout: float = 60.0) -> None:
    """Wait until ``text`` appears in a process' log (stderr). The timeout is a bound against a
    hang, not a speed goal: generous, for a loaded machine."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if text in proc.log_all():
            return
        time.sleep(0.2)
    raise AssertionError(f"{text!r} not in the log of {proc.p.args}:\n{proc.log()}")


def fleet_dir(tmp_path, **defaults):
    """A fleet folder (fleet.yaml + stations/) for test stations on the virtual bench: short
    method windows, records under tmp_path, no northbound; ``defaults`` are merged in by section."""
    base = {
        "station": {"site": "lab", "area": "hall", "line": "l1"},
        "meter": {"map": os.path.join(ROOT, "config", "meters", "zn-s.yaml")},
        "method": {"w_ss": 5, "w_hold": 20, "tau": 5, **STALL_TOLERANT},
        "test": {"t_set_n": 0.5, "t_end_s": 70},
        "recorder": {"dir": str(tmp_path / "records")},
        "mqtt": {"enabled": False}, "modbus_tcp": {"enabled": False},
    }
    for k, v in defaults.items():
        base[k] = {**base.get(k, {}), **v}
    fleet = tmp_path / "fleet"
    (fleet / "stations").mkdir(parents=True)
    (fleet / "fleet.yaml").write_text(yaml.safe_dump({"defaults": base}))
    return fleet


#: the shipped ZN-S register map (tests' virtual meters and stations)
METER_MAP = os.path.join(ROOT, "config", "meters", "zn-s.yaml")
#: method windows short enough for a compressed virtual life of about a minute
SHORT_METHOD = {"w_ss": 5, "w_hold": 20, "tau": 5}
#: a life compressed twice as much (time_scale 1200 instead of the scenarios' 600: the onset of
#: accelerated wear of a Grade-I hook at 0.5 N after ~25 s of running instead of ~50 s, Grade II
#: ~17 s) with windows of 2/5 of SHORT_METHOD (the stable segment: 4 windows of 2 s; τ 2 s): the
#: same sequence (run-in, baseline, onset, persistent exceedance, end of life) in half the time.
#: A Grade-I end of life comes ~23 s after slot 0, well before QUICK_END.
QUICK_SCALE = 1200
#: the protection stop (METHOD.md §3: `stop_after` of unsafe slots) of the test stations whose
#: subject is not the protection stop: 5 s instead of 1 s. A loaded test machine (other workers'
#: stations, other jobs) can stall a 50 Hz loop for over a second; the stop is then right, but
#: it ends a life that the test wants to see through. The protection stop itself is tested at
#: 1 s (the method's tests; the fault end-to-end tests keep the default).
STALL_TOLERANT = {"stop_after": 5}
QUICK_METHOD = {"w_ss": 2, "w_hold": 8, "tau": 2, **STALL_TOLERANT}
QUICK_END = 35
#: … and a life prior for it (METHOD.md §5b, §7a: Grade I at 0.5 N, compressed like the life) with
#: a lead of 5 s: the early warning comes some 5 s before the end of life
QUICK_PRIOR = {"grade": "I", "t_set_n": 0.5, "mean_s": 24.0, "sd_s": 2.0, "n": 5}
QUICK_LEAD = 5.0


def quick_scenario(tmp_path, shipped: str) -> str:
    """A copy of the shipped scenario ``config/scenarios/<shipped>`` in tmp_path with its life
    compressed to the QUICK_* values (its plant otherwise as shipped)."""
    with open(os.path.join(ROOT, "config", "scenarios", shipped)) as f:
        sc = yaml.safe_load(f)
    sc["meter"]["map"] = METER_MAP
    sc["plant"]["time_scale"] = QUICK_SCALE
    sc["method"] = {**QUICK_METHOD, "t_end": QUICK_END}
    path = tmp_path / shipped
    path.write_text(yaml.safe_dump(sc, sort_keys=False))
    return str(path)


def scenario_file(tmp_path, name, *, plant=None, faults=(), method=None, t_end=70):
    """A scenario file in tmp_path (the shipped ones are for people; tests state what they need):
    a compressed grade-I life at 0.5 N; ``method`` replaces the short windows + ``t_end``."""
    sc = {"description": f"test scenario {name}", "seed": 7,
          "meter": {"map": METER_MAP}, "stm32": {"watchdog_s": 0.2},
          "plant": {"grade": "I", "t_set": 0.5, "time_scale": 600, **(plant or {})},
          "method": method if method is not None else {**SHORT_METHOD, "t_end": t_end},
          "faults": list(faults)}
    p = tmp_path / f"{name}.yaml"
    p.write_text(yaml.safe_dump(sc, sort_keys=False))
    return str(p)


def wait_exit(gw: Proc, timeout: float) -> int:
    """The gateway's exit code; stopped and failed with its log when it runs longer."""
    try:
        return gw.p.wait(timeout)
    except subprocess.TimeoutExpired:
        gw.stop()
        raise AssertionError(f"gateway did not finish in {timeout} s; log:\n{gw.log()}") from None


def events(test_dir) -> list[dict]:
    """The events.jsonl of a recorded test."""
    with open(os.path.join(test_dir, "events.jsonl")) as f:
        return [json.loads(line) for line in f if line.strip()]


def sim_fleet(tmp_path, n: int) -> tuple[Proc, str]:
    """One `hookwatch sim --count n` (stations sim01…); its links under tmp_path/links/NAME/."""
    with open(os.path.join(ROOT, "config", "scenarios", "quick.yaml")) as f:
        sc = yaml.safe_load(f)
    sc["meter"] = {"map": METER_MAP}
    (tmp_path / "sc.yaml").write_text(yaml.safe_dump(sc))
    links = tmp_path / "links"
    p = Proc(hookwatch_cmd() + ["sim", str(tmp_path / "sc.yaml"), "--count", str(n), "--link-dir",
                                str(links), "--duration", "600"], str(tmp_path / "sim.log"))
    p.readline_until("ready:")
    return p, str(links)


def worker_pids(gw: Proc, name: str) -> list[int]:
    """The pids of station ``name``'s worker processes so far, from a fleet supervisor's log."""
    return [int(p) for p in re.findall(rf"{name}: worker started \(pid (\d+)\)", gw.log_all())]


def assert_no_slot_lost(test_dir, online: dict, stats: dict | None = None, ts: float = 0.02) -> int:
    """What must hold for a recorded test on any machine, however loaded (a timing figure such as
    the share of filled slots or the lateness is a bench/ figure, never asserted by a test):

    - the rows of ``log.csv.gz`` are slots of the grid, each at most once and in order (a row's
      ``t`` puts it in its own slot k = round(t / Ts); METHOD.md §9: a slot without a reading
      has no row);
    - every one of the test's ``n_slots`` slots is accounted for: a row with a reading, or
      MISSING (no row, or a row flagged MISSING), and the method counted exactly those
      (``online["reasons"]["MISSING"]``);
    - with the station's slot counters (``--stats-json``): the station counted every slot of
      the test, and each MISSING one as a slot not filled (polled without an answer, or passed
      over late) — none dropped unseen.

    Returns the number of MISSING slots."""
    import csv
    import gzip

    with gzip.open(os.path.join(test_dir, "log.csv.gz"), "rt", encoding="utf-8", newline="") as f:
        rows = list(csv.reader(f))
    head, body = rows[0], rows[1:]
    it, imask = head.index("t"), head.index("mask")
    ks = [int(float(r[it]) / ts + 0.5) for r in body]
    assert all(a < b for a, b in zip(ks, ks[1:])), (test_dir, "slots out of order or twice")
    assert not ks or ks[0] >= 0, (test_dir, ks[:3])
    n = online["n_slots"]
    read = sum(1 for k, r in zip(ks, body) if k < n and not int(r[imask]) & 0x01)
    missing = n - read
    assert missing == online["reasons"].get("MISSING", 0), (test_dir, n, read, online["reasons"])
    if stats is not None:
        assert stats["slots"] >= n, (test_dir, stats, n)
        assert stats["slots"] - stats["filled"] >= missing, (test_dir, stats, missing)
    return missing
