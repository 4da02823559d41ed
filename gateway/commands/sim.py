"""`hookwatch sim [SCENARIO.yaml]`: a virtual station (bench, ZN-S meter, STM32) on pseudo-terminals."""
from __future__ import annotations

import asyncio
import logging
import os
import signal
import sys

from ..cli import CliError
from drivers.sim.scenario import ScenarioError, load_scenario
from drivers.sim.station import EventLog, SimStation, run_station

HELP = "run a virtual station (plant, ZN-S meter, STM32) on pseudo-terminals"
DESCRIPTION = (HELP + ". Prints 'meter: DEVICE' and 'stm32: DEVICE' on stdout when ready and keeps "
               "the stable symlinks LINK_DIR/meter and LINK_DIR/stm32; point a station's "
               "meter.port and stm32.port at them. Runs until SIGTERM/SIGINT (exit 0) or "
               "--duration. Scenario format and fault kinds: docs/simulator.md.")

DEFAULT_LINK_DIR = "/tmp/hookwatch-sim"


def add_arguments(ap):
    ap.add_argument("scenario", nargs="?", metavar="SCENARIO.yaml",
                    help="scenario file (default: the packaged demo life, config/scenarios/demo.yaml)")
    ap.add_argument("--link-dir", metavar="DIR", default=None,
                    help=f"folder for the stable symlinks meter and stm32 (default: "
                         f"$HOOKWATCH_SIM_DIR or {DEFAULT_LINK_DIR})")
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


def run(args) -> int:

    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.WARNING),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        sc = load_scenario(args.scenario)
        if args.seed is not None and args.seed < 0:
            raise CliError(f"--seed {args.seed}: allowed an integer ≥ 0")
        if args.duration is not None and not args.duration > 0:
            raise CliError(f"--duration {args.duration}: allowed a number of seconds > 0")
        station_kw = dict(seed=args.seed, baud=args.baud)
        if args.baud is not None:
            sc.load_meter_map(args.baud)          # checks the override
    except ScenarioError as e:
        raise CliError(str(e)) from None
    link_dir = args.link_dir or os.environ.get("HOOKWATCH_SIM_DIR") or DEFAULT_LINK_DIR
    try:
        os.makedirs(link_dir, exist_ok=True)
    except OSError as e:
        raise CliError(f"--link-dir {link_dir}: cannot create: {e.strerror}", 1) from None
    if not os.access(link_dir, os.W_OK):
        raise CliError(f"--link-dir {link_dir}: not writable (choose another with --link-dir)", 1)
    for name in ("meter", "stm32"):
        p = os.path.join(link_dir, name)
        if os.path.lexists(p) and not os.path.islink(p):
            raise CliError(f"--link-dir {link_dir}: {name} exists and is not a symlink", 1)

    if args.events:
        try:
            events = EventLog(open(args.events, "w"), close=True)
        except OSError as e:
            raise CliError(f"--events {args.events}: {e.strerror}", 1) from None
    else:
        events = EventLog(sys.stderr, close=False)
    try:
        try:
            station = SimStation(sc, link_dir=link_dir, truth_path=args.truth,
                                 trace_path=args.trace, events=events, **station_kw)
        except ScenarioError as e:
            raise CliError(str(e)) from None
        duration = args.duration if args.duration is not None else sc.duration_s
        try:
            asyncio.run(_main(station, duration))
        except OSError as e:
            raise CliError(f"cannot run the virtual station: {e}", 1) from None
    finally:
        events.close()
    return 0


async def _main(station, duration) -> None:

    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)

    def ready(st) -> None:
        print(f"meter: {st.meter.device}", flush=True)
        print(f"stm32: {st.stm32.device}", flush=True)
        print(f"hookwatch sim: meter {st.meter.device} stm32 {st.stm32.device} (links in "
              f"{st.link_dir}); seed {st.seed}; wear onset after {st.plant.truth()['onset_run_s']:.1f} s "
              f"of running", file=sys.stderr, flush=True)

    try:
        await run_station(station, stop, duration, ready)
    finally:
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(sig)
