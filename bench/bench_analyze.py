#!/usr/bin/env python3
"""Issue 2 benchmark: `hookwatch analyze` end to end on a 10-hour log (1.8 M slots, read from
.csv.gz), and the streaming form's cost per slot. Prints medians over several runs."""
import os
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from gen_long_log import generate  # noqa: E402


def main(runs: int = 7) -> None:
    log = os.path.join(HERE, "data", "long10h.csv.gz")
    if not os.path.exists(log):
        generate(log)
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        p = subprocess.run([exe, "analyze", log, "--json"], capture_output=True, text=True)
        times.append(time.perf_counter() - t0)
        assert p.returncode == 0, p.stderr
    print("analyze 10 h log end to end (process start, gunzip, parse, method): "
          f"median {statistics.median(times):.3f} s, "
          f"min {min(times):.3f} s over {runs} runs  [goal ≤ 1.0 s]")
    print("  result:", p.stdout.strip()[:160], "…")

    from gateway.analysis import params_for
    from gateway.logio import read_log
    from gateway.method import StreamingMonitor, analyze_slots, to_slots

    lg = read_log(log)
    prm = params_for(lg.meta, {}, log)
    s = to_slots(lg.t, lg.t1, lg.t2, prm)
    pr, a, b = s.present.tolist(), s.t1.tolist(), s.t2.tolist()
    per = []
    for _ in range(3):
        mon = StreamingMonitor(prm)
        push = mon.push
        t0 = time.perf_counter()
        for k in range(len(pr)):
            push(pr[k], a[k], b[k])
        per.append((time.perf_counter() - t0) / len(pr))
    print(f"streaming form: median {statistics.median(per) * 1e6:.2f} µs per slot over 3 runs of "
          f"{len(pr):,} slots  [goal ≤ 10 µs]")
    bt = []
    for _ in range(5):
        t0 = time.perf_counter()
        analyze_slots(s, prm)
        bt.append(time.perf_counter() - t0)
    print(f"batch form alone (slots in memory): median {statistics.median(bt) * 1e3:.1f} ms")
    assert mon.result().as_dict() == analyze_slots(s, prm).as_dict()
    print("streaming result == batch result: yes")


if __name__ == "__main__":
    main()
