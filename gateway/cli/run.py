"""`hookwatch run STATION.yaml | CONFIG_DIR`: the gateway's main job."""
from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from types import FrameType
from typing import Any

from ..cli import CliError
from ..compose import (
    build_console,
    build_station,
    in_process_runtime,
    records_dir_ok,
    served_by_supervisor,
    shared_sparkplug_nodes,
)
from ..config import ConfigError, load_fleet, load_station
from ..core.ports import Runtime
from ..outputs.registry import mqtt_settings
from ..plumbing import safeout, sdnotify
from ..plumbing.osprio import DEPLOYED_NICE, MAX_PRIORITY, deployed_nice
from ..supervisor.fleetcfg import RunOptions, apply_overrides, plan_fleet
from ..supervisor.remote import RemoteFleet
from ..supervisor.supervisor import Supervisor

HELP = "run one station (a YAML file) or a whole fleet (a config folder, one process per station)"
DESCRIPTION = (HELP + ". Polls the meter at 50 Hz, closes the tension loop through the STM32, "
               "computes μ and the wear life online, records every test and reports north. "
               "SIGTERM/SIGINT stop cleanly (a running test is closed as aborted); SIGHUP reloads "
               "the configuration of stations that are not in a test. A fleet folder runs each station in its "
               "own worker process under a supervisor (restart with back-off, watchdog); "
               "--in-process keeps every station in this one process.")


def _rt_priority(text: str) -> int:
    try:
        p = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 1 <= p <= MAX_PRIORITY:
        raise argparse.ArgumentTypeError(f"{p} is outside 1–{MAX_PRIORITY}")
    return p


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
    ap.add_argument("--in-process", action="store_true",
                    help="a fleet: every station in this one process (threads), as for small boxes")
    ap.add_argument("--realtime", type=_rt_priority, default=None, metavar="PRIO",
                    help="run each station's slot-loop thread under SCHED_FIFO at PRIO "
                         f"(1–{MAX_PRIORITY}) where permitted (root, CAP_SYS_NICE or "
                         "LimitRTPRIO=); otherwise a warning and normal scheduling; and the "
                         f"process at niceness {DEPLOYED_NICE} as the units (where permitted) "
                         "(docs/runtime.md, 'Real-time priority')")
    ap.add_argument("--worker-watchdog", type=float, default=5.0, metavar="S",
                    help="a fleet: a worker silent this long is killed and restarted (default 5)")
    ap.add_argument("--restart-backoff", type=float, default=1.0, metavar="S",
                    help="a fleet: first restart delay of a crashed worker, doubled per crash in "
                         "a row up to 60 s; held back 300 s after 5 (default 1)")


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
    return apply_overrides(cfg, RunOptions.from_args(args))


def _setup_logging(level: str | None) -> None:
    logging.basicConfig(level=getattr(logging, (level or "info").upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def _console(cfgs):
    """The operator console of this process (``console:`` of the first station), or None."""
    console = build_console(cfgs)
    if console is None:
        return None
    for url in console.start():
        print(f"console: {url}", flush=True)
    return console


def run(args) -> int:
    """Build the runtime (the stations in this process, or a supervisor with a worker process
    per station) and drive it in the one main loop (:func:`drive`)."""
    if args.realtime:
        # as the units deploy it (Nice=-5), before any thread or worker starts (they inherit
        # it): a thread holding the GIL while the SCHED_FIFO slot thread waits for it is not
        # kept off the CPU by the box's ordinary work (issue 27: a slot started 244 ms late
        # beside Chromium at niceness 0, 63 ms at -5; bench/bench_stall.py)
        why = deployed_nice()
        if why is not None:
            logging.getLogger("hookwatch.run").info("niceness %d not taken: %s", DEPLOYED_NICE, why)
    if os.path.isdir(args.path) and not args.in_process:
        made = _supervised(args)
    else:
        made = _in_process(args)
    if made is None:
        return 1
    runtime, console = made
    try:
        return drive(runtime, DriveOptions.from_args(args))
    finally:
        if console is not None:
            console.stop()


def _in_process(args) -> tuple[Runtime, Any] | None:
    """Every station in this process, each on its own thread (a station file, or --in-process)."""
    cfgs = [_override(c, args) for c in _load(args.path)]
    # each station is a thread with its own loop; a thread woken by its slot deadline must not
    # wait the default 5 ms for the GIL while another station (or paho, or the PLC server) runs
    sys.setswitchinterval(0.0005)
    _setup_logging(args.log_level or getattr(getattr(cfgs[0], "logging", None), "level", "info"))
    for c in cfgs:
        err = records_dir_ok(c.recorder.dir)
        if err:
            raise CliError(f"station {c.station.id}: {err}", 1)
    console = _console(cfgs)
    n = len(cfgs)

    def factories(cs) -> dict[str, Any]:
        return {c.station.id: _factory(c, args, i / n, console) for i, c in enumerate(cs)}

    def reloader() -> dict[str, Any]:
        try:
            return factories([_override(c, args) for c in _load(args.path)])
        except CliError as e:
            raise ValueError(str(e)) from None

    return in_process_runtime(factories(cfgs), rt_priority=args.realtime or 0, reloader=reloader), console


def _factory(cfg, args, phase: float, console=None):
    """Builds the station of ``cfg``; ``phase`` spreads the stations of one process over the slot."""
    def make():
        return build_station(cfg, with_northbound=not args.no_northbound, console=console,
                             slot_phase=phase)
    return make


def _supervised(args) -> tuple[Runtime, Any] | None:
    """A fleet folder, one worker process per station under this supervisor."""
    try:
        plan = plan_fleet(args.path)
    except FileNotFoundError:
        raise CliError(f"{args.path}: no such file or folder", 1) from None
    if not plan.accepted and not plan.refused:
        raise CliError(f"{args.path}: no station files found (expected stations/*.yaml)", 1)
    cfgs = [_override(c, args) for _, c in plan.accepted]
    first = cfgs[0] if cfgs else None
    level = args.log_level or getattr(getattr(first, "logging", None), "level", None) or "info"
    _setup_logging(level)
    log = logging.getLogger("hookwatch.run")
    nodes = [] if args.no_northbound else shared_sparkplug_nodes(cfgs)
    if nodes:
        # one Sparkplug edge node (one MQTT session, one bdSeq) with a device per station: the
        # supervisor hosts it, fed by the stations' proxies (docs/runtime.md)
        log.info("Sparkplug edge node(s) %s: one session in the supervisor, a device per station",
                 ", ".join(nodes))
    opts = RunOptions.from_args(args)
    opts.log_level = level
    with_nb = not args.no_northbound
    # the shared things live here, in the supervisor: the console, the Modbus TCP ports (one unit
    # per station), the Sparkplug edge nodes (a device per station) and the metrics endpoint, fed
    # by each worker over IPC (docs/runtime.md)
    console = _console(cfgs)

    # the console's site view rides on the MQTT session of one worker: the first station with MQTT
    carrier = next((c for c in cfgs if c.mqtt.enabled), None) if with_nb else None
    site = console.site if console is not None else None
    if site is not None and carrier is not None:
        console.attach_site(carrier.station.id, mqtt_settings(carrier).base_topic, lambda f, cb: None)

    def served(cfg) -> frozenset[str]:
        out = served_by_supervisor(cfg, console, with_northbound=with_nb)
        if site is not None and carrier is not None and cfg.station.id == carrier.station.id:
            out |= {"site"}
        return out

    sup = Supervisor(args.path, opts, watchdog_s=args.worker_watchdog, backoff_s=args.restart_backoff,
                     served_for=served, shared=RemoteFleet(console, with_northbound=with_nb),
                     on_site=site.receive if site is not None else None)
    return sup, console


class Hangup(Enum):
    """What SIGHUP means to :func:`drive`."""
    #: a daemon's: load the configuration again (``hookwatch run``)
    RELOAD = "reload"
    #: an interactive command's: its terminal closed, it ends as on SIGTERM (``hookwatch demo``)
    STOP = "stop"


class AfterDone(Enum):
    """What :func:`drive` does once every started test has ended (``DriveOptions.when_done``)."""
    #: the loop ends (with ``exit_when_done``)
    END = "end"
    #: the stations run on until a signal (or the duration): the demo's console after the life
    HOLD = "hold"


@dataclass(frozen=True)
class DriveOptions:
    """What ends :func:`drive`'s loop and what it writes at the end: ``hookwatch run``'s options
    (:meth:`from_args`), or what ``hookwatch demo`` composes."""
    #: the loop ends after this many seconds (``--duration``)
    duration_s: float | None = None
    #: the loop ends once every started test has ended (``--exit-when-done``)
    exit_when_done: bool = False
    #: the report as JSON here at the end (``--stats-json``)
    stats_json: str | None = None
    #: each station's failed starts and results as lines on stdout at the end
    print_report: bool = True
    #: called once, on the main thread, when every started test has ended (the stations run on
    #: meanwhile, on their threads); ``AfterDone.HOLD`` keeps the loop running although
    #: ``exit_when_done`` (the demo's closing words, then its console until Ctrl-C)
    when_done: Callable[[], AfterDone] | None = None
    #: what SIGHUP means
    hangup: Hangup = Hangup.RELOAD

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> DriveOptions:
        """``hookwatch run``'s command line."""
        return cls(duration_s=args.duration, exit_when_done=bool(args.exit_when_done),
                   stats_json=args.stats_json)


def drive(runtime: Runtime, opts: DriveOptions) -> int:
    """The one main loop of ``hookwatch run`` and ``hookwatch demo`` (as gunicorn's arbiter):
    signals, systemd's READY/STATUS/WATCHDOG, SIGHUP, --duration and --exit-when-done, then the
    report. The signal handlers it sets are put back when the loop has ended."""
    log = logging.getLogger("hookwatch.run")
    stop = threading.Event()
    reload_req = threading.Event()
    hup = reload_req if opts.hangup is Hangup.RELOAD else stop
    handlers = {signal.SIGTERM: stop, signal.SIGINT: stop, signal.SIGHUP: hup}
    before = {s: signal.signal(s, _setter(ev)) for s, ev in handlers.items()}
    try:
        return _loop(runtime, opts, stop, reload_req, log)
    finally:
        for s, h in before.items():
            signal.signal(s, h)


def _setter(ev: threading.Event) -> Callable[[int, FrameType | None], None]:
    """A signal handler that sets ``ev``."""
    def handler(_signum: int, _frame: FrameType | None) -> None:
        ev.set()
    return handler


def _loop(runtime: Runtime, opts: DriveOptions, stop: threading.Event, reload_req: threading.Event,
          log: logging.Logger) -> int:
    runtime.start()
    if not runtime.alive():
        log.error("no station can run: every station file was refused")
        runtime.stop()
        return 1
    t0 = time.monotonic()
    ready = False
    last_wd = 0.0
    watch_done = opts.exit_when_done or opts.when_done is not None
    try:
        while not stop.is_set() and runtime.alive():
            now = time.monotonic()
            runtime.tick(now)
            if not ready and runtime.ready():
                ready = True
                sdnotify.ready()
            if now - last_wd >= 2.0:
                last_wd = now
                sdnotify.status(runtime.status())
                if ready and runtime.healthy():
                    sdnotify.watchdog()
            if reload_req.is_set():
                reload_req.clear()
                runtime.reload()
            if opts.duration_s is not None and now - t0 >= opts.duration_s:
                break
            if watch_done and runtime.tests_done():
                watch_done = False          # once
                after = opts.when_done() if opts.when_done is not None else AfterDone.END
                if opts.exit_when_done and after is AfterDone.END:
                    break
            stop.wait(0.2)
    finally:
        sdnotify.stopping()
        runtime.stop()
    report = runtime.report()
    if opts.stats_json:
        with open(opts.stats_json, "w") as fh:
            safeout.dump(report, fh, indent=1)
    if opts.print_report:
        _print_report(report)
    return 0


def _print_report(report: dict[str, dict[str, Any] | None]) -> None:
    for name, r in report.items():
        if r is None:
            continue
        for f in r.get("start_failures") or []:
            print(f"{name}: start of {f['sample_id']} failed: {f['reason']}", flush=True)
        for res in r.get("results") or []:
            m = res["method"]
            print(f"{name}: test {res['test_id']} {res['test_status']} ({res['end_reason']}): "
                  f"status {m['status']}"
                  + (f" ({', '.join(m['stop_reasons'])})" if m.get("stop_reasons") else "")
                  + f", t_life {m['t_life']}, mu_ss {m['mu_ss']}", flush=True)
