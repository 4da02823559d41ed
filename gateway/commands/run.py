"""`hookwatch run STATION.yaml | CONFIG_DIR`: the gateway's main job."""
from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time

from .. import sdnotify
from ..cli import CliError
from ..compose import build_station, records_dir_ok
from ..config import ConfigError, load_fleet, load_station
from ..station.fleet import Fleet, StationRunner

HELP = "run one station (a YAML file) or a whole fleet (a config folder)"
DESCRIPTION = (HELP + ". Polls the meter at 50 Hz, closes the tension loop through the STM32, "
               "computes μ and the wear life online, records every test and reports north. "
               "SIGTERM/SIGINT stop cleanly (a running test is closed as aborted); SIGHUP reloads "
               "the configuration of stations that are not in a test.")


def add_arguments(ap):
    ap.add_argument("path", metavar="STATION.yaml|DIR", help="a station file or a fleet folder")
    ap.add_argument("--start", action="store_true", help="start a test at once (test: section, or the options below)")
    ap.add_argument("--sample", help="sample ID of the test to start")
    ap.add_argument("--grade", help="needle grade of the sample")
    ap.add_argument("--t-set", type=float, metavar="N", help="tension setpoint of the test, N")
    ap.add_argument("--t-end", type=float, metavar="S", help="planned test duration, s")
    ap.add_argument("--duration", type=float, metavar="S", help="exit after this many seconds")
    ap.add_argument("--exit-when-done", action="store_true", help="exit when every started test has ended")
    ap.add_argument("--stats-json", metavar="PATH", help="write slot statistics here at exit")
    ap.add_argument("--records-dir", metavar="DIR", help="override recorder.dir")
    ap.add_argument("--no-northbound", action="store_true", help="run without MQTT and Modbus TCP")
    ap.add_argument("--log-level", default=None, help="debug, info, warning, error")


def _load(path: str):
    try:
        if os.path.isdir(path):
            cfgs = load_fleet(path)
        else:
            cfgs = [load_station(path)]
    except ConfigError as e:
        raise CliError(str(e), 1) from None
    except FileNotFoundError:
        raise CliError(f"{path}: no such file or folder", 1) from None
    if not cfgs:
        raise CliError(f"{path}: no station files found (expected stations/*.yaml)", 1)
    return cfgs


def _override(cfg, args):
    import dataclasses

    test = cfg.test
    changes = {}
    if args.sample:
        changes["sample_id"] = args.sample
    if args.grade:
        changes["grade"] = args.grade
    if args.t_set is not None:
        changes["t_set_n"] = args.t_set
    if args.t_end is not None:
        changes["t_end_s"] = args.t_end
    if args.start:
        changes["autostart"] = True
    if changes:
        cfg = dataclasses.replace(cfg, test=dataclasses.replace(test, **changes))
    if args.records_dir:
        cfg = dataclasses.replace(cfg, recorder=dataclasses.replace(cfg.recorder, dir=args.records_dir))
    return cfg


def run(args) -> int:
    cfgs = [_override(c, args) for c in _load(args.path)]
    # each station is a thread with its own loop; a thread woken by its slot deadline must not
    # wait the default 5 ms for the GIL while another station (or paho, or the PLC server) runs
    sys.setswitchinterval(0.0005)
    level = (args.log_level or getattr(getattr(cfgs[0], "logging", None), "level", "info") or "info").upper()
    logging.basicConfig(level=getattr(logging, level, logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    for c in cfgs:
        err = records_dir_ok(c.recorder.dir)
        if err:
            raise CliError(f"station {c.station.id}: {err}", 1)

    runners = []
    for i, c in enumerate(cfgs):
        runners.append(StationRunner(c.station.id, _factory(c, args, i / len(cfgs))))
    fleet = Fleet(runners)
    stop = threading.Event()
    reload_req = threading.Event()

    def on_signal(signum, frame):
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGHUP, lambda s, f: reload_req.set())

    fleet.start()
    sdnotify.ready()
    sdnotify.status(f"running {len(runners)} station(s)")
    t0 = time.monotonic()
    progress: dict[str, int] = {}
    last_wd = 0.0
    started_any = False
    try:
        while not stop.is_set() and fleet.alive():
            stop.wait(0.2)
            now = time.monotonic()
            if now - last_wd >= 2.0:
                last_wd = now
                if fleet.healthy(progress):
                    sdnotify.watchdog()
            if reload_req.is_set():
                reload_req.clear()
                _reload(args, fleet)
            if args.duration is not None and now - t0 >= args.duration:
                break
            if args.exit_when_done:
                sts = [r.station for r in runners]
                if any(s is not None and s.busy for s in sts):
                    started_any = True
                elif started_any or all(s is not None and (s.results or s.start_failures)
                                        for s in sts):
                    break
    finally:
        sdnotify.stopping()
        fleet.stop()
    if args.stats_json:
        out = {r.name: (r.station.stats.summary() if r.station else None) for r in runners}
        for r in runners:
            if r.station is not None:
                out[r.name]["results"] = r.station.results
                out[r.name]["start_failures"] = r.station.start_failures
        with open(args.stats_json, "w") as f:
            json.dump(out, f, indent=1, default=str)
    for r in runners:
        if r.station is not None:
            for f in r.station.start_failures:
                print(f"{r.name}: start of {f['sample_id']} failed: {f['reason']}", flush=True)
            for res in r.station.results:
                m = res["method"]
                print(f"{r.name}: test {res['test_id']} {res['test_status']} ({res['end_reason']}): "
                      f"status {m['status']}"
                      + (f" ({', '.join(m['stop_reasons'])})" if m.get("stop_reasons") else "")
                      + f", t_life {m['t_life']}, mu_ss {m['mu_ss']}", flush=True)
    return 0


def _factory(cfg, args, phase: float):
    """Builds the station of ``cfg``; ``phase`` spreads the stations of one process over the slot."""
    def make():
        st = build_station(cfg, with_northbound=not args.no_northbound)
        st.slot_phase = phase
        return st
    return make


def _reload(args, fleet) -> None:
    """SIGHUP: load the configuration again; each station decides on its own loop whether it
    restarts with it (idle) or keeps the parameters of its running test."""
    log = logging.getLogger("hookwatch.run")
    try:
        cfgs = {c.station.id: _override(c, args) for c in _load(args.path)}
    except CliError as e:
        log.error("reload refused, configuration kept: %s", e)
        return
    n = len(fleet.runners)
    for i, r in enumerate(fleet.runners):
        c = cfgs.get(r.name)
        if c is not None:
            r.request_reload(_factory(c, args, i / n))
