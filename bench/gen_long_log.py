#!/usr/bin/env python3
"""Write a 10-hour life-test log at the paper's default method parameters (1.8 M slots at 50 Hz)
as bench/data/long10h.csv.gz + sidecar. Written once; later runs reuse it."""
import argparse
import gzip
import math
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def _signal(hours: float, seed: int) -> tuple[np.ndarray, ...]:
    ts = 0.02
    n = int(round(hours * 3600 / ts))
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    t = k * ts + rng.uniform(-0.004, 0.004, n)
    th = math.radians(105)
    t_acc = 0.75 * hours * 3600
    mu = 0.26 + 0.002 * rng.standard_normal(n)
    mu += 0.00004 * np.minimum(k * ts, 1800) / 1800 * 0  # steady after run-in
    mu += np.where(k * ts < 600, 0.03 * (1 - k * ts / 600), 0.0)        # run-in
    mu += np.where(k * ts > t_acc, 0.25 * ((k * ts - t_acc) / 3600) ** 2, 0.0)  # accelerated wear
    mean = 0.5 + 0.004 * np.sin(2 * np.pi * 3.0 * k * ts) + 0.003 * rng.standard_normal(n)
    e = np.exp(mu * th)
    t1 = np.round(2 * mean / (1 + e), 3)
    t2 = np.round(t1 * e, 3)
    keep = rng.random(n) > 0.002                      # dropped readings
    return t, t1, t2, keep, mu, mean


def generate(path: str, hours: float = 10.0, seed: int = 7) -> str:
    t, t1, t2, keep, _, _ = _signal(hours, seed)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with gzip.open(path, "wt", compresslevel=6) as f:
        f.write("t,T1,T2\n")
        tk, a, b = t[keep], t1[keep], t2[keep]
        chunk = 200_000
        for i in range(0, tk.size, chunk):
            rows = np.column_stack([tk[i:i + chunk], a[i:i + chunk], b[i:i + chunk]])
            np.savetxt(f, rows, fmt=("%.4f", "%.3f", "%.3f"), delimiter=",")
    meta = path[: -len(".csv.gz")] + ".meta.yaml"
    with open(meta, "w") as f:
        # as the recorder writes it: a log hookwatch recorded (its analyses may cache columns)
        f.write("software: hookwatch bench\nsample_id: bench-10h\ngrade: I\n"
                f"method:\n  t_set: 0.5\n  t_end: {hours * 3600:g}\n")
    return path


def generate_recorder_format(path: str, hours: float = 10.0, seed: int = 7) -> str:
    """The same test as the station's recorder writes it (gateway/station/recorder.py): its 10
    columns and ROW_FORMAT (T1/T2 as repr of float32-derived readings — long, variable digit
    counts; mu and mean_filt as repr), one gzip member per second of rows."""
    from gateway.station.recorder import LOG_COLUMNS, ROW_FORMAT

    t, t1, t2, keep, mu, mean = _signal(hours, seed)
    a = t1.astype(np.float32).astype(np.float64)[keep].tolist()
    b = t2.astype(np.float32).astype(np.float64)[keep].tolist()
    tk, m, mf = t[keep].tolist(), mu[keep].tolist(), mean[keep].tolist()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(gzip.compress((",".join(LOG_COLUMNS) + "\n").encode(), compresslevel=5, mtime=0))
        for i in range(0, len(tk), 50):
            rows = [ROW_FORMAT % (tk[j], a[j], b[j], 120.0, 119.87, 0, 1, 0, m[j], mf[j])
                    for j in range(i, min(i + 50, len(tk)))]
            f.write(gzip.compress("".join(rows).encode(), compresslevel=5, mtime=0))
    with open(os.path.join(os.path.dirname(path), "log.meta.yaml"), "w") as f:
        f.write("software: hookwatch bench\nsample_id: bench-10h-rec\ngrade: I\n"
                f"method:\n  t_set: 0.5\n  t_end: {hours * 3600:g}\n")
    return path


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=os.path.join(HERE, "data", "long10h.csv.gz"))
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args()
    if a.force or not os.path.exists(a.out):
        generate(a.out)
    print(a.out)
