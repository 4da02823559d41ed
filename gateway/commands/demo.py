"""`hookwatch demo`: the main job on its built-in default — a simulated loom station, no hardware.

It starts the virtual station (`hookwatch sim` on the demo scenario: a compressed needle life of a
few minutes) as its own process, runs the gateway's station runtime against its two
pseudo-terminals exactly as it would run against a real ZN-S meter and STM32, and when the test
has ended re-analyses the recorded log offline to show that both results are identical.
"""
from __future__ import annotations

import asyncio
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time

from ..analysis import analyze_file
from ..cli import CliError
from ..compose import build_station
from ..config import ConfigError, load_station
from ..records import EventType
from ..station.console import ConsoleOutput

HELP = "run hookwatch on its built-in default: a simulated loom station through a compressed needle life"
DESCRIPTION = HELP + (". Starts `hookwatch sim` on the demo scenario, runs the station against its "
                      "serial ports, prints progress and events, and compares the online result "
                      "with `hookwatch analyze` of the recorded log.")

_ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
DEMO_SCENARIO = os.path.join(_ROOT, "config", "scenarios", "demo.yaml")
DEMO_STATION = os.path.join(_ROOT, "config", "demo", "station.yaml")


def add_arguments(ap):
    ap.add_argument("--scenario", default=DEMO_SCENARIO, help="virtual-station scenario (default: the demo life)")
    ap.add_argument("--station", default=DEMO_STATION, help="station configuration (default: config/demo/station.yaml)")
    ap.add_argument("--dir", help="where to keep the links and records (default: a new temporary folder)")
    ap.add_argument("--seed", type=int, default=1, help="simulator seed")
    ap.add_argument("--every", type=float, default=5.0, metavar="S", help="progress line interval, s")
    ap.add_argument("--timeout", type=float, default=1800.0, metavar="S", help="give up after this long")


class _EndWatcher:
    """An output that stops the station once its test has ended (or its start failed, §3a)."""

    def __init__(self, stop: asyncio.Event):
        self.stop_ev = stop

    async def start(self):
        pass

    async def stop(self):
        pass

    def on_record(self, rec):
        pass

    def on_state(self, st):
        pass

    def on_event(self, ev):
        if (ev.type == EventType.TEST_ENDED and ev.test_id) or ev.type == EventType.START_FAILED:
            self.stop_ev.set()


def _start_sim(args, work: str) -> tuple[subprocess.Popen, dict[str, str]]:
    links = os.path.join(work, "links")
    os.makedirs(links, exist_ok=True)
    truth = os.path.join(work, "truth.json")
    cmd = [sys.executable, "-m", "gateway.cli", "sim", args.scenario, "--link-dir", links,
           "--seed", str(args.seed), "--truth", truth]
    log = open(os.path.join(work, "sim.log"), "w")
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True)
    log.close()
    paths: dict[str, str] = {}
    t_end = time.monotonic() + 30
    while len(paths) < 2 and time.monotonic() < t_end:
        line = p.stdout.readline()
        if not line:
            break
        for key in ("meter", "stm32"):
            if line.startswith(key + ":"):
                paths[key] = line.split(":", 1)[1].strip()
    if len(paths) < 2:
        p.kill()
        p.wait()
        with open(os.path.join(work, "sim.log")) as f:
            raise CliError("the virtual station did not start:\n" + f.read()[-2000:], 1)
    return p, {"meter": os.path.join(links, "meter"), "stm32": os.path.join(links, "stm32"),
               "truth": truth}


def run(args) -> int:
    import dataclasses

    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        cfg = load_station(args.station)
    except ConfigError as e:
        raise CliError(str(e), 1) from None
    work = args.dir or tempfile.mkdtemp(prefix="hookwatch-demo-")
    os.makedirs(work, exist_ok=True)
    print(f"hookwatch demo: a virtual loom station (scenario {os.path.relpath(args.scenario)}), "
          f"files under {work}", flush=True)
    sim, links = _start_sim(args, work)
    try:
        cfg = dataclasses.replace(
            cfg,
            meter=dataclasses.replace(cfg.meter, port=links["meter"]),
            stm32=dataclasses.replace(cfg.stm32, port=links["stm32"]),
            recorder=dataclasses.replace(cfg.recorder, dir=os.path.join(work, "records")),
            test=dataclasses.replace(cfg.test, autostart=True),
        )
        print(f"meter on {os.path.realpath(links['meter'])}, STM32 on {os.path.realpath(links['stm32'])}; "
              f"test {cfg.test.sample_id} grade {cfg.test.grade}, T_set {cfg.test.t_set_n} N, "
              f"planned {cfg.test.t_end_s:g} s", flush=True)

        async def main():
            stop = asyncio.Event()
            st = build_station(cfg, outputs=[ConsoleOutput(every_s=args.every), _EndWatcher(stop)],
                               with_northbound=False)
            loop = asyncio.get_running_loop()
            for s in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(s, stop.set)
            task = asyncio.create_task(st.run(stop))
            try:
                await asyncio.wait_for(stop.wait(), args.timeout)
            except asyncio.TimeoutError:
                print("hookwatch demo: timed out", file=sys.stderr)
                stop.set()
            await task
            return st

        st = asyncio.run(main())
    finally:
        sim.send_signal(signal.SIGTERM)
        try:
            sim.wait(10)
        except subprocess.TimeoutExpired:
            sim.kill()
            sim.wait()
        if sim.stdout:
            sim.stdout.close()
    if not st.results:
        print("hookwatch demo: no test was completed", file=sys.stderr)
        return 1
    res = st.results[-1]
    m = res["method"]
    test_dir = os.path.join(cfg.recorder.dir, cfg.station.id, res["test_id"])
    log_path = os.path.join(test_dir, "log.csv.gz")
    off = analyze_file(log_path).as_dict()
    same = off == m
    print()
    print(f"test {res['test_id']}: {res['test_status']} ({res['end_reason']})")
    print(f"  online : status {m['status']}, μ_ss {m['mu_ss']}, μ_th {m['mu_th']}, t_life {m['t_life']} s, "
          f"valid {m['n_valid']}/{m['n_slots']} slots")
    print(f"  offline: `hookwatch analyze {log_path}` gives "
          f"{'the identical result' if same else 'A DIFFERENT RESULT: ' + json.dumps(off)}")
    try:
        with open(links["truth"]) as f:
            truth = json.load(f)
        onset = truth.get("onset_run_s")
        if onset is not None:
            print(f"  simulated onset of accelerated wear (ground truth): {onset:.1f} s after the yarn started")
    except (OSError, ValueError):
        pass
    print(f"  recorded: {test_dir}/ (log.csv.gz, log.meta.yaml, events.jsonl, result.json)")
    return 0 if same else 1
