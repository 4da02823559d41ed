#!/usr/bin/env python3
"""Write a 10-hour life-test log at the paper's default method parameters (1.8 M slots at 50 Hz)
as bench/data/long10h.csv.gz + sidecar. Written once; later runs reuse it."""
import argparse
import gzip
import math
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def generate(path: str, hours: float = 10.0, seed: int = 7) -> str:
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


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=os.path.join(HERE, "data", "long10h.csv.gz"))
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args()
    if a.force or not os.path.exists(a.out):
        generate(a.out)
    print(a.out)
