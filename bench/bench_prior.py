#!/usr/bin/env python3
"""Issue 29 benchmark: the §7a prior from failures and right-censored lives.

- the maximum-likelihood fit (gateway/core/method/prior.py, pure Python) for histories of 10 to 40,000
  lives (60 % failures, 40 % hooks replaced early), and its Newton steps;
- what the reading worker does off the slot loop (every group fitted) and what a test start does
  on it (the prior looked up; a test of the group just ended: a small group refitted).

Prints medians over several runs. Usage: bench/bench_prior.py"""
import os
import random
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from gateway.core.method import prior as P  # noqa: E402
from gateway.core.method.prior import PastTest, history_prior  # noqa: E402
from gateway.station.priors import PriorBook, fit_groups  # noqa: E402


def lives(n, seed=1):
    rng = random.Random(seed)
    xs, cs = [], []
    for _ in range(n):
        x, c = rng.gauss(16577, 489), rng.uniform(14000, 17500)
        (xs.append(x) if x <= c else cs.append(c))
    return xs, cs


def tests(n, station, seed):
    rng = random.Random(seed)
    out = []
    for i in range(n):
        x, c = rng.gauss(16577, 489), rng.uniform(14000, 17500)
        if x <= c:
            out.append(PastTest("I", 0.5, "failure", x, k_b=10, n_slots=int(x / 0.02) + 3000, ts=0.02,
                                test_id=f"{station}-{i}", station=station, t_end=36000.0))
        else:
            out.append(PastTest("I", 0.5, "aborted", None, k_b=10, stop_reasons=("STOPPED",),
                                n_slots=int(c / 0.02), ts=0.02, test_id=f"{station}-{i}",
                                station=station, t_end=36000.0))
    return out


def median_s(fn, runs=5):
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main():
    print("fit of n lives (60 % failures): median time, Newton steps")
    for n in (10, 100, 1000, 10000, 40000):
        xs, cs = lives(n)
        steps: list[int] = []
        orig = P._ell

        def counting(*a, orig=orig, steps=steps):
            steps.append(1)
            return orig(*a)
        P._ell = counting
        history_prior(xs, cs)
        P._ell = orig
        t = median_s(lambda xs=xs, cs=cs: history_prior(xs, cs), 3 if n > 5000 else 7)
        print(f"  n={n:6d}: {t * 1e3:9.2f} ms  (ℓ evaluations {len(steps)})")
    hist = tests(20000, "a", 1)
    site = tuple(t for k in range(40) for t in tests(500, f"s{k}", 100 + k))
    print(f"reading worker, {len(hist)} own + {len(site)} site tests: fit_groups "
          f"{median_s(lambda: fit_groups(hist + list(site), 'a'), 3) * 1e3:.0f} ms (off the loop)")
    b = PriorBook("a", "/nonexistent")
    b.history, b.site = hist, site
    b.fitted, b._fitted_site = fit_groups(hist + list(site), "a"), site
    print(f"test start, prior looked up: {median_s(lambda: b.resolve('I', 0.5, {}), 50) * 1e6:.1f} µs")
    b._recent = tests(1, "new", 999)
    print(f"test start, a test of the group just ended (40,000 lives: the last fit): "
          f"{median_s(lambda: b.resolve('I', 0.5, {}), 20) * 1e6:.1f} µs")
    small = tests(300, "a", 5)
    b2 = PriorBook("a", "/nonexistent")
    b2.history, b2.fitted = small, fit_groups(small, "a")
    b2._recent = tests(1, "new", 998)
    print(f"test start, a test of a 300-test group just ended (refitted at the start): "
          f"{median_s(lambda: b2.resolve('I', 0.5, {}), 20) * 1e3:.2f} ms")


if __name__ == "__main__":
    main()
