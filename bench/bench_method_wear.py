#!/usr/bin/env python3
"""Issue 13 benchmark: the streaming method's cost per slot with §5a (headroom, warning,
projection) on, and what one window's projection costs. Prints medians over several runs.

Log: the 10-hour log of bench_analyze.py (paper defaults, written once by gen_long_log.py)."""
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def long_log_slots():
    """The 10-hour log on its slot grid, with its parameters (written once by gen_long_log)."""
    sys.path[:0] = [os.path.dirname(HERE), HERE]
    from gen_long_log import generate

    from gateway.core.method import to_slots
    from gateway.offline.analysis import params_for
    from gateway.offline.logio import read_log

    path = os.path.join(HERE, "data", "long10h.csv.gz")
    if not os.path.exists(path):
        generate(path)
    lg = read_log(path)
    prm = params_for(lg.meta, {}, path)
    return prm, to_slots(lg.t, lg.t1, lg.t2, prm)


def main(runs: int = 3) -> None:
    prm, s = long_log_slots()
    import numpy as np

    from gateway.core.method import StreamingMonitor, analyze_slots
    from gateway.core.method.wear import WearTracker

    pr, a, b = s.present.tolist(), s.t1.tolist(), s.t2.tolist()
    n = len(pr)
    per, worst, window_slot = [], [], []
    for _ in range(runs):
        mon = StreamingMonitor(prm)
        push = mon.push
        clock = time.perf_counter
        slow = 0.0
        wtimes = []
        t0 = clock()
        for k in range(n):
            t = clock()
            out = push(pr[k], a[k], b[k])
            d = clock() - t
            if d > slow:
                slow = d
            if out.window is not None:
                wtimes.append(d)
        per.append((clock() - t0) / n)
        worst.append(slow)
        window_slot.append(statistics.median(wtimes) if wtimes else float("nan"))
    res = mon.result()
    print(f"streaming form with §5a: median {statistics.median(per) * 1e6:.2f} µs per slot over {runs} runs "
          f"of {n:,} slots (timer overhead included)  [goal ≤ 10 µs]")
    print(f"  slot that completes a window (median over the test's {mon.wear.windows if mon.wear else 0} "
          f"post-baseline windows): {statistics.median(window_slot) * 1e6:.0f} µs; slowest slot "
          f"{statistics.median(worst) * 1e3:.2f} ms")
    print(f"  result: {res.status}, headroom {res.headroom}, warn_slot {res.warn_slot}, t_cross {res.t_cross}")
    assert res.as_dict() == analyze_slots(s, prm).as_dict()
    print("  streaming result == batch result: yes")

    # one window's §5a work alone, with a full trend (trend_windows = 60 → 1770 pairs)
    rng = np.random.default_rng(1)
    for tw in (60, 240):
        p2 = prm.__class__(**{**prm.as_dict(), "trend_windows": tw})
        tr = WearTracker(p2, 0.25, 0.3125)
        m = tw + 5 * 200
        vals = 0.25 + 1e-5 * np.arange(m) + 1e-4 * rng.standard_normal(m)
        for j in range(tw):
            tr.add(j, 3000, float(vals[j]))
        ts = []
        for rep in range(5):
            first = tw + rep * 200
            t0 = time.perf_counter()
            for j in range(first, first + 200):
                tr.add(j, 3000, float(vals[j]))
            ts.append((time.perf_counter() - t0) / 200)
        print(f"WearTracker.add with a full trend of {tw} windows ({tw * (tw - 1) // 2} pairs): "
              f"median {statistics.median(ts) * 1e6:.0f} µs per window "
              f"(= {statistics.median(ts) / prm.n_ss * 1e6:.3f} µs per slot at N_ss = {prm.n_ss})")
    win = np.asarray(0.25 + 1e-3 * rng.standard_normal(prm.n_ss))
    from gateway.core.method.rules import window_value
    ts = []
    for _ in range(5):
        t0 = time.perf_counter()
        for _ in range(200):
            window_value(win, prm)
        ts.append((time.perf_counter() - t0) / 200)
    print(f"window median μ̃ over {prm.n_ss} slots: median {statistics.median(ts) * 1e6:.0f} µs per window")


if __name__ == "__main__":
    main()
