#!/usr/bin/env python3
"""Issue 37 item 9: the time from ``git push`` of a signed commit to the site repository to every
box applied, for 3 boxes (tests/kit/site_lab.py: each box its own supervisor, state folder and
virtual station on this machine; the real ``ansible-playbook`` of deploy/ansible/site.yml on the
``local`` connection, canary pause 0, one Mosquitto).

Per run: a fleet default changes (every box's station restarts on it), the commit is signed and
pushed; then ``ansible-playbook site.yml``; "applied" = every box's station runs the new version
(``hookwatch config status``). Figures: push → playbook done, push → every station on it (the
playbook's own end includes the health gate of each box), and the playbook's `--check` alone.
Results as JSON lines on stdout, the medians last.

    bench/bench_rollout.py [--runs 3] [--boxes 3]
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import statistics
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))
sys.path.insert(0, ROOT)

from kit.broker import Broker  # noqa: E402
from kit.site_lab import SiteLab  # noqa: E402


def _on(lab: SiteLab, version: str, timeout: float = 300) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if all((b.status().get("stations") or {}).get(b.station, {}).get("version") == version
               and (b.status().get("stations") or {}).get(b.station, {}).get("running") for b in lab.boxes):
            return
        time.sleep(0.2)
    raise SystemExit(f"not every box on {version[:12]} after {timeout} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--boxes", type=int, default=3)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-rollout-") as d:
        tmp = pathlib.Path(d)
        with Broker(tmp) as broker:
            lab = SiteLab(tmp, broker.port, a.boxes)
            try:
                lab.make()
                r = lab.playbook()
                if r.returncode != 0:
                    raise SystemExit(r.stdout + r.stderr)
                for b in lab.boxes:
                    lab.start_box(b)
                _on(lab, lab.head())
                rows = []
                for i in range(a.runs):
                    check = i % 2 == 1          # every other run: the plan in check mode first
                    fleet = lab.read("defaults/fleet.yaml")
                    fleet["defaults"]["method"]["delta"] = round(0.25 + 0.01 * (i + 1), 2)
                    lab.write("defaults/fleet.yaml", fleet)
                    v = lab.commit(f"bench: delta run {i}")
                    t0 = time.monotonic()
                    lab.push()
                    check_s = None
                    if check:
                        chk = lab.playbook("site.yml", "--check")
                        check_s = round(time.monotonic() - t0, 1)
                        if chk.returncode != 0:
                            raise SystemExit(chk.stdout + chk.stderr)
                        t0 = time.monotonic()
                    r = lab.playbook()
                    t_play = time.monotonic() - t0
                    if r.returncode != 0:
                        raise SystemExit(r.stdout + r.stderr)
                    _on(lab, v)
                    t_all = time.monotonic() - t0
                    row = {"run": i, "boxes": a.boxes, "push_to_playbook_done_s": round(t_play, 1),
                           "push_to_every_station_on_it_s": round(t_all, 1),
                           "check_mode_run_s": check_s, "load": round(os.getloadavg()[0], 1)}
                    rows.append(row)
                    print(json.dumps(row), flush=True)
                checks = [r["check_mode_run_s"] for r in rows if r["check_mode_run_s"] is not None]
                med = {k: statistics.median(r[k] for r in rows)
                       for k in ("push_to_every_station_on_it_s", "push_to_playbook_done_s")}
                print(json.dumps({**{f"median_{k}": v for k, v in med.items()},
                                  "median_check_mode_run_s": statistics.median(checks) if checks else None}))
            finally:
                lab.stop()


if __name__ == "__main__":
    main()
