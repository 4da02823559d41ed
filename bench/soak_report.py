#!/usr/bin/env python3
"""The bench/README.md table of a soak (``bench/soak_site_lives.py``'s JSON lines).

Per hour of the soak (the sample nearest each whole hour, the first after the warm-up as hour 0):
the gateway's processes (supervisor + workers) — RSS in all and of the largest process, threads,
open descriptors —, the disk (records folder, the site's lives files, the outboxes) and Mosquitto's
RSS; then each figure's growth per hour (least squares over the samples after ``--settle`` s) and
its extrapolation to a month (30 days) of the same load; the CPU of the gateway; the stations'
slots from the ``end`` line. The growth is fitted after ``--settle`` (by default 70 minutes in a
soak of 2 hours: a station's slot statistics — ``SlotStats.lateness`` and ``rtt``, bounded deques
of 200,000 slots — fill in its first 67 minutes at 50 Hz, ≈ 12.8 MB per station, and stay full).

    bench/soak_report.py /work/coord/soak/lives-soak.jsonl [--settle 4200]
"""
from __future__ import annotations

import argparse
import json
import sys

FIGURES = (("rss_mb_sum", "RSS, all processes (MB)"), ("rss_mb_max", "RSS, largest process (MB)"),
           ("threads_sum", "threads"), ("fds_sum", "descriptors"),
           ("disk_records_mb", "disk: records (MB)"), ("disk_site_lives_mb", "disk: site_lives.json (MB)"),
           ("disk_outbox_mb", "disk: outboxes (MB)"), ("mosquitto_rss_mb", "Mosquitto RSS (MB)"))
MONTH_H = 30 * 24


def slope(xs: list[float], ys: list[float]) -> float:
    n = len(xs)
    if n < 2:
        return 0.0
    mx, my = sum(xs) / n, sum(ys) / n
    den = sum((x - mx) ** 2 for x in xs)
    return 0.0 if den == 0 else sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / den


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("samples")
    ap.add_argument("--settle", type=float, default=None,
                    help="seconds before the growth is fitted (default: 70 min when the soak is "
                    "longer than 100 min, else 10 min — a station's slot statistics fill their "
                    "bounded deques of 200,000 slots (12.8 MB) in its first 67 minutes at 50 Hz)")
    args = ap.parse_args()
    start, end, samples = None, None, []
    with open(args.samples) as f:
        for line in f:
            try:
                d = json.loads(line)
            except ValueError:
                continue            # a line cut by a stop: the others stand
            if d.get("kind") == "start":
                start, end, samples = d, None, []       # the last run of the file
            elif d.get("kind") == "sample":
                d["mosquitto_rss_mb"] = (d.get("mosquitto") or {}).get("rss_mb", 0.0)
                samples.append(d)
            elif d.get("kind") == "end":
                end = d
    if not samples:
        sys.exit("no samples")
    hours = samples[-1]["t_s"] / 3600
    if args.settle is None:
        args.settle = 4200.0 if samples[-1]["t_s"] > 6000 else 600.0
    print(f"Soak: {start.get('stations') if start else '?'} stations, "
          f"{start.get('peers') if start else '?'} site peers × {start.get('peer_lives') if start else '?'} "
          f"lives at {start.get('peer_rate') if start else '?'} snapshots/s each, a burst of "
          f"{start.get('burst') if start else '?'} every {start.get('burst_every') if start else '?'} s; "
          f"{len(samples)} samples over {hours:.2f} h; {samples[-1]['peer_snapshots']} snapshots published\n")
    picks = []
    for h in range(int(hours) + 1):
        best = min(samples, key=lambda s: abs(s["t_s"] - max(h * 3600, samples[0]["t_s"])))
        if best not in picks:
            picks.append(best)
    if samples[-1] not in picks:
        picks.append(samples[-1])
    head = ["figure"] + [f"{p['t_s'] / 3600:.2f} h" for p in picks] + ["growth / h", "in a month (30 d)"]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    fit = [s for s in samples if s["t_s"] >= args.settle] or samples
    for key, name in FIGURES:
        vals = [p.get(key, 0.0) for p in picks]
        k = slope([s["t_s"] / 3600 for s in fit], [s.get(key, 0.0) for s in fit])
        month = samples[-1].get(key, 0.0) + k * (MONTH_H - hours)
        cells = [name] + [f"{v:g}" for v in vals] + [f"{k:+.3g}", f"{month:.4g}"]
        print("| " + " | ".join(cells) + " |")
    cpu = (samples[-1]["cpu_s_sum"] - fit[0]["cpu_s_sum"]) / max(1e-9, samples[-1]["t_s"] - fit[0]["t_s"])
    print(f"\n(growth fitted over {len(fit)} samples from {fit[0]['t_s'] / 60:.0f} min on)")
    print(f"Gateway CPU (supervisor + workers, after the settling): {100 * cpu:.1f} % of one core; "
          f"processes {samples[0]['n_procs']} → {samples[-1]['n_procs']}; "
          f"load (1 min) {min(s['loadavg_1min'] for s in samples):.1f}–{max(s['loadavg_1min'] for s in samples):.1f}")
    if end is not None:
        st = {k: v for k, v in (end.get("stats") or {}).items() if isinstance(v, dict) and "slots" in v}
        if st:
            worst = min(st.items(), key=lambda kv: kv[1].get("filled_ratio", 0.0))
            missing = sum(v["slots"] - v["filled"] for v in st.values())
            print(f"Slots: {sum(v['slots'] for v in st.values())} in all, {missing} MISSING; the worst "
                  f"station {worst[0]} filled {100 * worst[1].get('filled_ratio', 0.0):.3f} %; "
                  f"restarts {sum(v.get('restarts', 0) for v in st.values())}")
        print(f"Gateway log: {end.get('log_lines')} lines ({end.get('log_lines_site_lives')} about the "
              f"site's lives) for {end.get('peer_snapshots')} snapshots; exit code {end.get('rc')}")
    else:
        print("(no end line yet: the soak is running or was stopped)")


if __name__ == "__main__":
    main()
