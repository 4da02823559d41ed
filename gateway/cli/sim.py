"""`hookwatch sim [SCENARIO.yaml | FLEET.yaml] [--count N]`: virtual stations (bench, ZN-S meter,
STM32) on pseudo-terminals — one, or a fleet of N in this one process."""
from __future__ import annotations

import asyncio
import logging
import os
import signal
import sys

import yaml

from drivers.sim.scenario import ScenarioError, load_scenario
from drivers.sim.twin_station import EventLog, SimStation, fleet_from_dict, fleet_of_count, is_fleet_file, run_fleet

from ..cli import CliError
from ..plumbing.osprio import realtime_thread

MAX_FLEET = 64

HELP = "run a virtual station (plant, ZN-S meter, STM32) on pseudo-terminals"
DESCRIPTION = (HELP + ". Prints 'meter: DEVICE' and 'stm32: DEVICE' on stdout when ready and keeps "
               "the stable symlinks LINK_DIR/meter and LINK_DIR/stm32; point a station's "
               "meter.port and stm32.port at them. Runs until SIGTERM/SIGINT (exit 0) or "
               "--duration. With --count N or a fleet file (a 'stations:' list) it hosts N "
               "stations, each with its own ptys and links LINK_DIR/NAME/meter and "
               "LINK_DIR/NAME/stm32, and prints 'meter NAME: DEVICE' / 'stm32 NAME: DEVICE'. "
               "Scenario format, fleet files and fault kinds: docs/simulator.md.")

DEFAULT_LINK_DIR = "/tmp/hookwatch-sim"


def add_arguments(ap):
    ap.add_argument("scenario", nargs="?", metavar="SCENARIO.yaml",
                    help="scenario file (default: the packaged demo life, config/scenarios/demo.yaml)")
    ap.add_argument("--link-dir", metavar="DIR", default=None,
                    help=f"folder for the stable symlinks meter and stm32 (default: "
                         f"$HOOKWATCH_SIM_DIR or {DEFAULT_LINK_DIR})")
    ap.add_argument("--count", type=int, metavar="N", help="host N virtual stations of the scenario "
                    f"in this process (sim01…simNN, seeds seed…seed+N−1; at most {MAX_FLEET})")
    ap.add_argument("--seed", type=int, metavar="N", help="override the scenario's seed")
    ap.add_argument("--truth", metavar="PATH", help="write the ground truth (wear onset, μ_ss, …) "
                    "here as JSON; rewritten when the yarn first runs, at the onset and at exit")
    ap.add_argument("--baud", type=int, metavar="N", help="override the meter's baud rate")
    ap.add_argument("--duration", type=float, metavar="S", help="exit after S seconds")
    ap.add_argument("--trace", metavar="PATH", help="write a 10 Hz CSV trace (sim time, command, "
                    "speed, true mean tension, T1, T2, true μ, …)")
    ap.add_argument("--events", metavar="PATH", help="write events (faults firing and clearing, "
                    "wear onset, …) as JSON lines here (default: stderr)")
    ap.add_argument("--log-level", default="warning", help="debug, info, warning, error")
    ap.add_argument("--realtime", type=int, default=None, metavar="PRIO",
                    help="run the simulator's loop (plant, meter, STM32 firmware) under "
                         "SCHED_FIFO at PRIO where permitted (below the gateway's slot loops, "
                         "e.g. 10 beside --realtime 20): the twin stands for hardware, which a "
                         "browser or a compile on the same box does not slow down")


def _peek_fleet(path: str | None) -> dict | None:
    """The parsed file if it is a fleet file (a mapping with ``stations``), else None."""
    if path is None or not os.path.isfile(path):
        return None
    try:
        with open(path, encoding="utf-8") as f:
            data = yaml.safe_load(f)
    except (OSError, yaml.YAMLError, UnicodeDecodeError):
        return None                      # load_scenario gives the precise message
    return data if is_fleet_file(data) else None


def _per_station(path: str | None, name: str, multi: bool) -> str | None:
    """--truth/--trace of a fleet: one file per station, NAME inserted before the extension."""
    if path is None or not multi:
        return path
    stem, ext = os.path.splitext(path)
    return f"{stem}-{name}{ext}"


def run(args) -> int:

    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    count = getattr(args, "count", None)
    try:
        if args.seed is not None and args.seed < 0:
            raise CliError(f"--seed {args.seed}: allowed an integer ≥ 0")
        if args.duration is not None and not args.duration > 0:
            raise CliError(f"--duration {args.duration}: allowed a number of seconds > 0")
        if count is not None and not 1 <= count <= MAX_FLEET:
            raise CliError(f"--count {count}: allowed an integer from 1 to {MAX_FLEET}")
        fleet_data = _peek_fleet(args.scenario)
        if fleet_data is not None:
            if count is not None:
                raise CliError(f"--count: not with a fleet file ({args.scenario} lists its stations)")
            entries = fleet_from_dict(fleet_data, args.scenario)
        else:
            sc = load_scenario(args.scenario)
            entries = fleet_of_count(sc, count or 1, args.seed)
        if args.baud is not None:
            for e in entries:
                e.scenario.load_meter_map(args.baud)          # checks the override
    except ScenarioError as e:
        raise CliError(str(e)) from None
    multi = fleet_data is not None or count is not None
    link_dir = args.link_dir or os.environ.get("HOOKWATCH_SIM_DIR") or DEFAULT_LINK_DIR
    dirs = [os.path.join(link_dir, e.name) if multi else link_dir for e in entries]
    for d in dirs:
        try:
            os.makedirs(d, exist_ok=True)
        except OSError as e:
            raise CliError(f"--link-dir {d}: cannot create: {e.strerror}", 1) from None
        if not os.access(d, os.W_OK):
            raise CliError(f"--link-dir {d}: not writable (choose another with --link-dir)", 1)
        for name in ("meter", "stm32"):
            p = os.path.join(d, name)
            if os.path.lexists(p) and not os.path.islink(p):
                raise CliError(f"--link-dir {d}: {name} exists and is not a symlink", 1)

    if args.events:
        try:
            events = EventLog(open(args.events, "w"), close=True)
        except OSError as e:
            raise CliError(f"--events {args.events}: {e.strerror}", 1) from None
    else:
        events = EventLog(sys.stderr, close=False)
    try:
        stations = []
        try:
            for i, (entry, d) in enumerate(zip(entries, dirs)):
                if not multi:
                    seed = args.seed
                elif entry.seed is not None:
                    seed = entry.seed
                else:       # a fleet file entry without a seed: its own sample, not a copy
                    seed = (args.seed if args.seed is not None else entry.scenario.seed) + i
                stations.append(SimStation(
                    entry.scenario, link_dir=d, seed=seed,
                    baud=args.baud if args.baud is not None else entry.baud,
                    truth_path=_per_station(args.truth, entry.name, multi),
                    trace_path=_per_station(args.trace, entry.name, multi), events=events,
                    name=entry.name if multi else None))
        except ScenarioError as e:
            raise CliError(str(e)) from None
        # one scenario (also --count): its duration_s; a fleet file of several: until stopped
        duration = args.duration if args.duration is not None else (
            entries[0].scenario.duration_s if fleet_data is None else None)
        try:
            asyncio.run(_main(stations, duration, multi, args.realtime))
        except OSError as e:
            raise CliError(f"cannot run the virtual station: {e}", 1) from None
    finally:
        events.close()
    return 0


async def _main(stations, duration, multi: bool, realtime: int | None = None) -> None:

    if realtime:
        why = realtime_thread(realtime)
        if why is not None:
            logging.getLogger("hookwatch.sim").warning("simulator at normal priority: SCHED_FIFO "
                                                       "%d %s", realtime, why)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)

    def ready(sts) -> None:
        if not multi:
            st = sts[0]
            print(f"meter: {st.meter.device}", flush=True)
            print(f"stm32: {st.stm32.device}", flush=True)
            print(f"hookwatch sim: meter {st.meter.device} stm32 {st.stm32.device} (links in "
                  f"{st.link_dir}); seed {st.seed}; wear onset after "
                  f"{st.plant.truth()['onset_run_s']:.1f} s of running", file=sys.stderr, flush=True)
            return
        for st in sts:
            print(f"meter {st.name}: {st.meter.device}", flush=True)
            print(f"stm32 {st.name}: {st.stm32.device}", flush=True)
        print(f"ready: {len(sts)} stations", flush=True)
        print(f"hookwatch sim: {len(sts)} virtual stations, links in "
              f"{os.path.dirname(sts[0].link_dir)}/NAME/{{meter,stm32}}", file=sys.stderr, flush=True)

    try:
        await run_fleet(stations, stop, duration, ready)
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(sig)
