#!/usr/bin/env python3
"""Issue 37: a box run from a site repository — how long the steps take.

One box (box file, state folder, ``hookwatch run STATE/config/current``: a supervisor and a worker
per station) with ``--stations`` virtual stations (``hookwatch sim``), idle; a site repository
(Git, commits signed with an OpenSSH key). Measured, ``--runs`` times each:

- ``config check --site`` of the repository (process start included);
- ``config plan --version`` of a changed commit;
- ``config apply`` of a fleet-default change (every station restarts): from the command's start
  to its exit with the health gate passed (staging, switch, SIGHUP, every station on the new
  version with its meter read);
- ``config apply`` of the same version again (nothing to do);
- drift: a hand edit of the effective tree until the supervisor's status names it.

Results as JSON lines on stdout, then the medians.

    bench/bench_site_config.py [--stations 2] [--runs 5]
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)

import yaml  # noqa: E402

from kit.e2e import METER_MAP, QUICK_SCALE, virtual_station  # noqa: E402
from kit.site_repo import Box, SiteRepo, ssh_key  # noqa: E402


def _scenario(path: Path, seed: int) -> str:
    with open(os.path.join(ROOT, "config", "scenarios", "quick.yaml")) as f:
        sc = yaml.safe_load(f)
    sc.update(seed=seed, meter={"map": METER_MAP})
    sc["plant"]["time_scale"] = QUICK_SCALE
    path.write_text(yaml.safe_dump(sc))
    return str(path)


def _timed(fn):
    t = time.monotonic()
    r = fn()
    return time.monotonic() - t, r


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stations", type=int, default=2)
    ap.add_argument("--runs", type=int, default=5)
    a = ap.parse_args()
    out: dict[str, list[float]] = {"check_site": [], "plan": [], "apply": [], "apply_same": [], "drift": []}
    with tempfile.TemporaryDirectory() as td, contextlib.ExitStack() as stack:
        tmp = Path(td)
        key, signer = ssh_key(tmp, "ops")
        repo = SiteRepo(tmp / "site", None)
        box = Box(tmp, "b1", signer)
        repo.box("b1", box.records)
        for i in range(a.stations):
            sub = tmp / f"sim{i}"
            sub.mkdir()
            links = stack.enter_context(virtual_station(sub, _scenario(sub / "sc.yaml", 60 + i)))[1]
            repo.station("b1", f"st{i}", links)
        v = repo.commit("start", key)
        assert box.config("apply", str(repo.path), "--version", v).returncode == 3
        box.start()
        stack.callback(box.stop)
        while not all((s.get("meter_ok") and s.get("version") == v)
                      for s in box.status().get("stations", {}).values()) or \
                len(box.status().get("stations", {})) < a.stations:
            time.sleep(0.2)
        for run in range(a.runs):
            delta = 0.3 + 0.01 * run
            repo.edit("defaults/fleet.yaml", lambda d, x=delta: d["defaults"]["method"].update(delta=x))
            v = repo.commit(f"delta {delta}", key)
            t, p = _timed(lambda: box.config("check", str(repo.path), "--site"))
            assert p.returncode == 0, p.stdout + p.stderr
            out["check_site"].append(t)
            t, p = _timed(lambda x=v: box.config("plan", str(repo.path), "--version", x))
            assert p.returncode == 3, p.stdout + p.stderr
            out["plan"].append(t)
            t, p = _timed(lambda x=v: box.config("apply", str(repo.path), "--version", x))
            assert p.returncode == 3, p.stdout + p.stderr
            out["apply"].append(t)
            t, p = _timed(lambda x=v: box.config("apply", str(repo.path), "--version", x))
            assert p.returncode == 0, p.stdout + p.stderr
            out["apply_same"].append(t)
            f = box.current_dir / "stations" / "st0.yaml"
            t0 = time.monotonic()
            with open(f, "a") as fh:
                fh.write(f"# hand edit {run}\n")
            while not box.status().get("drift_files"):
                time.sleep(0.05)
            out["drift"].append(time.monotonic() - t0)
            print(json.dumps({k: round(x[-1], 3) for k, x in out.items()}), flush=True)
    print(json.dumps({"stations": a.stations, "runs": a.runs,
                      "median_s": {k: round(statistics.median(x), 3) for k, x in out.items()},
                      "max_s": {k: round(max(x), 3) for k, x in out.items()}}), flush=True)


if __name__ == "__main__":
    main()
