#!/usr/bin/env python3
"""Issue 16: where the CPU of one 50 Hz slot goes.

drivers — the gateway's meter driver (drivers/meter/driver.py) and STM32 link (drivers/stm32/driver.py) against
          `hookwatch sim` over pseudo-terminals (115200 baud), one exchange per 20 ms slot, as in
          the station: CPU of this process per exchange = (process CPU while exchanging − process
          CPU of the same loop idling the same slots) / exchanges. With ``--old-rev REV`` the meter
          driver and the STM32 link of that git revision are measured in the same run,
          alternating. The STM32 is stopped (no keep-alive traffic) while the idle loop and the
          meter are measured and enabled for the SET_SPEED runs, as in a running test; the
          posted form (post_speed, its ACK collected in the next slot, as the station does) and
          the sender-task form (a LatestValue box feeding one task that awaits set_speed) are
          measured beside the inline awaited set_speed.
pure    — the real Station loop (gateway/station/station.py) on a virtual clock flat out with
          in-memory plant ports (as `bench_station.py memory`), its parts timed by wrapping the
          class methods: method (StreamingMonitor.push), controller (Controller.step), recorder
          (TestRecorder.on_record incl. its flush every second), the rest of Station._process
          (SlotRecord, events, outputs), and the loop's own overhead; the plant ports excluded.

    python bench/bench_slot_cpu.py drivers [--slots 1500] [--runs 3] [--old-rev main]
    python bench/bench_slot_cpu.py pure [--slots 100000]
"""
from __future__ import annotations

import argparse
import asyncio
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time
from types import SimpleNamespace

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, ROOT)
sys.path.insert(0, HERE)

EXE = os.path.join(os.path.dirname(sys.executable), "hookwatch")
SLOT = 0.02


def _old_driver(rev: str, name: str):
    """drivers/<name>.py of git revision ``rev`` as module drivers._<name>_old (its relative
    imports resolve in the drivers package)."""
    src = subprocess.run(["git", "-C", ROOT, "show", f"{rev}:drivers/{name}.py"], capture_output=True,
                         text=True, check=True).stdout
    path = os.path.join(tempfile.mkdtemp(prefix=f"{name}-old-"), f"{name}_old.py")
    with open(path, "w") as f:
        f.write(src)
    spec = importlib.util.spec_from_file_location(f"drivers._{name}_old", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[f"drivers._{name}_old"] = mod
    spec.loader.exec_module(mod)
    return mod


async def _slots(n: int, fn) -> float:
    """Run fn() (a coroutine function or None) once per 20 ms slot for n slots; CPU s used."""
    loop = asyncio.get_running_loop()
    t = loop.time()
    c0 = time.process_time()
    for _ in range(n):
        t += SLOT
        if fn is not None:
            await fn()
        await asyncio.sleep(max(0.0, t - loop.time()))
    return time.process_time() - c0


def drivers(args) -> None:
    from drivers.meter.driver import ZnsMeter
    from drivers.stm32.driver import Stm32Link

    work = tempfile.mkdtemp(prefix="hw-bench-slot-")
    links = os.path.join(work, "links")
    sim = subprocess.Popen([EXE, "sim", os.path.join(ROOT, "config", "scenarios", "quick.yaml"),
                            "--link-dir", links, "--baud", "115200", "--duration", "3600"],
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for _ in range(2):
        sim.stdout.readline()
    old = _old_driver(args.old_rev, "zns") if args.old_rev else None
    old_stm = _old_driver(args.old_rev, "stm32") if args.old_rev else None
    cfg = SimpleNamespace(port=os.path.join(links, "meter"), map=None, baud=115200, unit_id=None,
                          parity=None, timeout_s=0.015, swap_channels=False)
    res: dict[str, list[float]] = {"idle": [], "meter (lean RTU)": [], "stm32 set_speed": [],
                                   "stm32 set_speed via sender box": [], "stm32 post_speed + collect": []}
    if old:
        res[f"meter ({args.old_rev})"] = []
        res[f"stm32 set_speed ({args.old_rev})"] = []

    async def main():
        new_m = ZnsMeter.from_config(cfg)
        await new_m.open()
        old_m = None
        if old:
            old_m = old.ZnsMeter.from_config(cfg)
        stm = Stm32Link(os.path.join(links, "stm32"), watchdog_s=0.2)
        await stm.open()
        await stm.stop("bench")
        n = args.slots

        async def speed_run(link, key):
            await link.open()
            await link.enable()

            async def speed():
                await link.set_speed(150.0)
            res[key].append(await _slots(n, speed) / n)
            if hasattr(link, "post_speed"):
                # as the station: the command posted, its reply collected in the next slot
                async def post():
                    link.collect()
                    link.post_speed(150.0)
                res[key.replace("set_speed", "post_speed + collect")].append(await _slots(n, post) / n)
                link.collect()
                # the station's other form: one long-lived sender task fed through the box
                from gateway.station.station import LatestValue
                box = LatestValue()

                async def sender():
                    while True:
                        await link.set_speed(await box.get())
                task = asyncio.get_running_loop().create_task(sender())

                async def hand_over():
                    box.put(150.0)
                res[key.replace("set_speed", "set_speed via sender box")].append(
                    await _slots(n, hand_over) / n)
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            await link.stop("bench")
            await link.close()
            print(f"  {key}: {link.counters}", flush=True)

        for _ in range(args.runs):
            res["idle"].append(await _slots(n, None) / n)
            m_ok = [0]

            async def read_new(m_ok=m_ok):
                m_ok[0] += await new_m.read() is not None
            res["meter (lean RTU)"].append(await _slots(n, read_new) / n)
            if old_m is not None:
                await new_m.close()
                await old_m.open()

                async def read_old():
                    await old_m.read()
                res[f"meter ({args.old_rev})"].append(await _slots(n, read_old) / n)
                await old_m.close()
                await new_m.open()

            print(f"  run: meter ok {m_ok[0]}/{n}", flush=True)
            await stm.close()
            await speed_run(stm, "stm32 set_speed")
            if old_stm is not None:
                await speed_run(old_stm.Stm32Link(os.path.join(links, "stm32"), watchdog_s=0.2),
                                f"stm32 set_speed ({args.old_rev})")
            await stm.open()
        await stm.close()
        await new_m.close()

    try:
        asyncio.run(main())
    finally:
        sim.terminate()
        sim.wait(10)
    idle = statistics.median(res.pop("idle"))
    print(f"drivers, {args.slots} slots × {args.runs} runs at 50 Hz, load {os.getloadavg()[0]:.2f}; "
          f"idle loop {idle * 1e6:.0f} µs CPU per slot (subtracted)")
    for name, v in res.items():
        per = [x - idle for x in v]
        print(f"  {name:32s} {statistics.median(per) * 1e6:7.0f} µs CPU per exchange "
              f"(runs: {', '.join(f'{x * 1e6:.0f}' for x in per)})")


def pure(args) -> None:
    from bench_station import PlantMeter, PlantStm32, VirtualClock

    from drivers.sim.plant import Plant
    from drivers.sim.scenario import load_scenario
    from gateway.core.control import Controller, ControlParams
    from gateway.core.method.core import StreamingMonitor
    from gateway.station import recorder as recmod
    from gateway.station import station as stmod

    acc: dict[str, float] = {}

    def wrap(cls, name, key, is_async=False):
        f = getattr(cls, name)
        acc[key] = 0.0
        pc = time.thread_time
        if is_async:
            async def w(*a, **k):
                t0 = pc()
                try:
                    return await f(*a, **k)
                finally:
                    acc[key] += pc() - t0
        else:
            def w(*a, **k):
                t0 = pc()
                try:
                    return f(*a, **k)
                finally:
                    acc[key] += pc() - t0
        setattr(cls, name, w)

    wrap(StreamingMonitor, "push", "method")
    wrap(Controller, "step", "controller")
    wrap(recmod.TestRecorder, "on_record", "recorder")
    wrap(stmod.Station, "_process", "process")
    wrap(PlantMeter, "read", "plant meter", True)
    wrap(PlantStm32, "set_speed", "plant stm32", True)

    sc = load_scenario(os.path.join(ROOT, "config", "scenarios", "life-I-0.5.yaml"))
    plant = Plant(sc.plant, seed=sc.seed)
    vclock = VirtualClock(SLOT)
    work = tempfile.mkdtemp(prefix="hw-bench-pure-")
    st = stmod.Station(station_id="cpu", method={}, control=ControlParams(dead_band_n=0.01),
                       meter=PlantMeter(plant, vclock), stm32=PlantStm32(plant), records_dir=work,
                       default_plan=stmod.TestPlan("C-1", "I", 0.5, 3600.0), autostart=True)
    st.clock_factory = lambda ts: vclock

    async def main():
        stop = asyncio.Event()
        await st.run(stop, max_slots=args.slots)

    c0, t0 = time.thread_time(), time.perf_counter()
    asyncio.run(main())
    wall, cpu = time.perf_counter() - t0, time.thread_time() - c0
    n = max(1, st.stats.slots)
    us = {k: v / n * 1e6 for k, v in acc.items()}
    total = cpu / n * 1e6
    plant_us = us["plant meter"] + us["plant stm32"]
    rest = us["process"] - us["method"] - us["controller"] - us["recorder"]
    loop_us = total - us["process"] - plant_us
    print(f"pure slot path, {n:,} slots flat out (virtual clock), load {os.getloadavg()[0]:.2f}: "
          f"{total:.1f} µs CPU per slot in all, {plant_us:.1f} µs of it the in-memory plant (excluded)")
    for k, v in (("method (StreamingMonitor.push)", us["method"]),
                 ("controller (Controller.step)", us["controller"]),
                 ("recorder (TestRecorder.on_record + flush)", us["recorder"]),
                 ("rest of Station._process (SlotRecord, events, outputs)", rest),
                 ("slot loop, clock, stats, task hand-over", loop_us)):
        print(f"  {k:58s} {v:7.1f} µs")
    print(f"  {'= gateway pure part per slot':58s} {total - plant_us:7.1f} µs  "
          f"({(total - plant_us) / (SLOT * 1e6) * 100:.2f} % of a core at 50 Hz)")
    print(f"(wall {wall:.1f} s)")


def main() -> None:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="mode", required=True)
    d = sub.add_parser("drivers")
    d.add_argument("--slots", type=int, default=1500)
    d.add_argument("--runs", type=int, default=3)
    d.add_argument("--old-rev", default=None, help="also measure drivers/meter/driver.py of this git revision")
    p = sub.add_parser("pure")
    p.add_argument("--slots", type=int, default=100_000)
    a = ap.parse_args()
    drivers(a) if a.mode == "drivers" else pure(a)


if __name__ == "__main__":
    main()
