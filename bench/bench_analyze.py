#!/usr/bin/env python3
"""Issue 2/22 benchmark: a cold `hookwatch analyze` end to end on a 10-hour log (1.8 M slots,
read from .csv.gz; nothing is cached, nothing written beside the log), where its time goes, the
parse candidates side by side in one run (ISA-L + Arrow, the product's path, vs. zlib + numpy,
the reference it replaced, vs. reading a binary companion), the same on a log in the recorder's
own 10-column format, the same log with and without its columnar companion (``log.cols``, written
once by the recorder at close: gateway/offline/logcols.py), and the streaming form's cost per slot.
Medians over several runs; the load average is printed with each figure because the machine is
shared. ``--companion`` runs only the companion comparison."""
import os
import resource
import statistics
import subprocess
import sys
import time
import zlib

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))

from gen_long_log import generate, generate_recorder_format  # noqa: E402


def load() -> str:
    la = os.getloadavg()
    return f"load {la[0]:.1f}/{la[1]:.1f}/{la[2]:.1f}"


def med(xs: list[float]) -> str:
    return f"median {statistics.median(xs):.3f} s (min {min(xs):.3f} s)"


#: `hookwatch analyze` with the reference parse (zlib + numpy, the path before issue 22 without its
#: cache): the same CLI in a fresh interpreter, the fast path switched off
REFERENCE_CLI = r"""
import sys, zlib
from gateway.offline import logio
from gateway import cli
logio._parse_arrow = lambda *a: None
_orig = logio._inflate_members
logio._inflate_members = lambda raw, mod: _orig(raw, zlib)
sys.exit(cli.main(sys.argv[1:]))
"""


CPU: dict[str, list[float]] = {"fast": [], "ref": []}


def cli_cold(log: str, runs: int) -> tuple[list[float], list[float], str]:
    """(fast, reference) wall times of `hookwatch analyze --json`, interleaved run by run; the
    CPU seconds (user + sys, all threads) of each run go to CPU (less sensitive to the load)."""
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    folder = os.path.dirname(log)
    before = sorted(os.listdir(folder))
    fast, ref, out = [], [], None
    CPU["fast"].clear()
    CPU["ref"].clear()
    for _ in range(runs):
        for cmd, times, key in (([exe], fast, "fast"), ([sys.executable, "-c", REFERENCE_CLI], ref, "ref")):
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            p = subprocess.run(cmd + ["analyze", log, "--json"], capture_output=True, text=True,
                               cwd=os.path.dirname(HERE))
            times.append(time.perf_counter() - t0)
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            CPU[key].append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
            assert p.returncode == 0, p.stderr
            assert out is None or p.stdout == out, "results differ"
            out = p.stdout
    assert sorted(os.listdir(folder)) == before, "analyze wrote beside the log"
    return fast, ref, out or ""


def parse_candidates(log: str, runs: int) -> None:
    """In-process, interleaved (same load for each): gunzip ISA-L vs zlib, parse Arrow vs numpy,
    and what reading a compact binary companion of the same columns would cost."""
    import numpy as np
    from isal import isal_zlib

    from gateway.offline import logio

    with open(log, "rb") as f:
        raw = f.read()
    res: dict[str, list[float]] = {k: [] for k in ("gz_isal", "gz_zlib", "read_fast", "arrow", "numpy",
                                                    "comp_f64", "comp_dec")}
    body = logio._inflate_members(raw, zlib)
    nl = body.index(b"\n")
    ncols = body[:nl].count(b",") + 1
    ref_parse = logio._parse_reference
    # the reference as it ran before issue 22 (forked over two cores): pyarrow is loaded in this
    # process, which the product then treats as threaded (no fork); the forked child here only
    # runs numpy and exits, never touching Arrow's idle pool
    logio._may_fork = lambda: (os.cpu_count() or 1) > 1
    text = body.decode()
    fast_cols = None
    for _ in range(runs):
        t0 = time.perf_counter()
        b1 = logio._inflate_members(raw, isal_zlib)
        t1 = time.perf_counter()
        b2 = logio._inflate_members(raw, zlib)
        t2 = time.perf_counter()
        assert b1 == b2
        res["gz_isal"].append(t1 - t0)
        res["gz_zlib"].append(t2 - t1)
        t0 = time.perf_counter()
        fast_cols = logio._parse_arrow(body, nl + 1, len(body), ncols, [0, 1, 2])
        t1 = time.perf_counter()
        ref = ref_parse(log, text, text[nl + 1:], ["t", "T1", "T2"] + ["x"] * (ncols - 3), [0, 1, 2])
        t2 = time.perf_counter()
        res["arrow"].append(t1 - t0)
        res["numpy"].append(t2 - t1)
        assert fast_cols is not None
        assert all(np.array_equal(a, ref[:, i]) and a.tobytes() == ref[:, i].tobytes()
                   for i, a in enumerate(fast_cols))
        t0 = time.perf_counter()
        logio.read_log(log, with_meta=False)
        t1 = time.perf_counter()
        res["read_fast"].append(t1 - t0)
    assert fast_cols is not None
    # companion candidate 1: the exact float64 columns, byte-shuffled, deflated (generic: any value)
    shuffled = [isal_zlib.compress(np.ascontiguousarray(c).view(np.uint8).reshape(-1, 8).T.tobytes(), 1)
                for c in fast_cols]
    n = fast_cols[0].size
    # candidate 2: fixed decimals (t 4 places, T 3 places) as delta-coded ints, deflated — only
    # exact for logs whose every value has those decimals (not the recorder's repr T1/T2)
    scaled = [np.rint(fast_cols[0] * 1e4).astype(np.int64), np.rint(fast_cols[1] * 1e3).astype(np.int64),
              np.rint(fast_cols[2] * 1e3).astype(np.int64)]
    dec = [isal_zlib.compress(np.diff(s, prepend=0).astype(np.int32).tobytes(), 1) for s in scaled]
    for _ in range(runs):
        t0 = time.perf_counter()
        out = [np.frombuffer(isal_zlib.decompress(z), np.uint8).reshape(8, n).T.copy().view(np.float64).ravel()
               for z in shuffled]
        t1 = time.perf_counter()
        out2 = [np.cumsum(np.frombuffer(isal_zlib.decompress(z), np.int32), dtype=np.int64) / d
                for z, d in zip(dec, (1e4, 1e3, 1e3))]
        t2 = time.perf_counter()
        res["comp_f64"].append(t1 - t0)
        res["comp_dec"].append(t2 - t1)
    assert all(a.tobytes() == b.tobytes() for a, b in zip(out, fast_cols))
    dec_exact = all(a.tobytes() == b.tobytes() for a, b in zip(out2, fast_cols))
    m = {k: statistics.median(v) for k, v in res.items()}
    print(f"  gunzip: ISA-L {m['gz_isal']:.3f} s, zlib {m['gz_zlib']:.3f} s "
          f"(ratio {m['gz_zlib'] / m['gz_isal']:.1f}×)")
    print(f"  parse of the 3 columns: Arrow {m['arrow']:.3f} s, numpy reference {m['numpy']:.3f} s "
          f"(ratio {m['numpy'] / m['arrow']:.1f}×); columns bit-identical: yes")
    print(f"  read_log (read + gunzip + parse + sidecar) {m['read_fast']:.3f} s; "
          f"reference path would be ≈ {m['gz_zlib'] + m['numpy']:.3f} s")
    sz_gz = os.path.getsize(log)
    print(f"  companion candidate, exact float64 shuffled+deflate: {sum(map(len, shuffled)) / n:.1f} B/row "
          f"({sum(map(len, shuffled)) / sz_gz:.2f}× the .csv.gz), decode {m['comp_f64']:.3f} s")
    print(f"  companion candidate, fixed-decimal delta ints+deflate: {sum(map(len, dec)) / n:.1f} B/row "
          f"({sum(map(len, dec)) / sz_gz:.2f}× the .csv.gz), decode {m['comp_dec']:.3f} s, "
          f"exact here: {'yes' if dec_exact else 'NO'} (not for repr T1/T2)")


def stage_times(log: str, runs: int) -> None:
    """Where a cold analysis goes, measured in fresh interpreters (imports included)."""
    code = r"""
import time; T0 = time.perf_counter()
import numpy
T1 = time.perf_counter()
import pyarrow.csv, isal.isal_zlib
T2 = time.perf_counter()
from gateway.offline import logio
from gateway.offline.analysis import params_for
from gateway.core.method import analyze_slots, to_slots
T3 = time.perf_counter()
lg = logio.read_log(LOG)
T4 = time.perf_counter()
prm = params_for(lg.meta, {}, LOG)
s = to_slots(lg.t, lg.t1, lg.t2, prm)
T5 = time.perf_counter()
analyze_slots(s, prm)
T6 = time.perf_counter()
print(T1 - T0, T2 - T1, T3 - T2, T4 - T3, T5 - T4, T6 - T5)
""".replace("LOG", repr(log))
    rows = []
    for _ in range(runs):
        p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                           cwd=os.path.dirname(HERE), check=True)
        rows.append([float(x) for x in p.stdout.split()])
    names = ("numpy import", "pyarrow+isal import", "gateway import", "read_log", "slot grid", "method")
    print(f"  stages (median of {runs} fresh interpreters): "
          + ", ".join(f"{n} {statistics.median(c):.3f} s" for n, c in zip(names, zip(*rows))))


STAGES_CODE = r"""
import time; T0 = time.perf_counter()
import numpy
T1 = time.perf_counter()
from gateway.offline import logio
from gateway.offline.analysis import params_for
from gateway.core.method import analyze_slots, to_slots
T2 = time.perf_counter()
lg = logio.read_log(LOG)
T3 = time.perf_counter()
prm = params_for(lg.meta, {}, LOG)
s = to_slots(lg.t, lg.t1, lg.t2, prm)
T4 = time.perf_counter()
analyze_slots(s, prm)
T5 = time.perf_counter()
print(T1 - T0, T2 - T1, T3 - T2, T4 - T3, T5 - T4)
"""


def companion(runs: int = 7) -> None:
    """Cold `hookwatch analyze --json` of the recorder-format 10-hour log with its companion and
    without it (the companion moved aside), interleaved run by run in one loop (same load for
    both); the companion made by the function the recorder calls at close; then where each
    path's time goes, in fresh interpreters."""
    from gateway.offline import logcols, logio

    rlog = os.path.join(HERE, "data", "rec10h", "log.csv.gz")
    if not os.path.exists(rlog):
        generate_recorder_format(rlog)
    cp = logcols.companion_path(rlog)
    away = cp + ".aside"
    for stale in (away, cp):
        if os.path.exists(stale):
            os.remove(stale)
    t0 = time.perf_counter()
    what = logio.write_companion(rlog)
    wt = time.perf_counter() - t0
    if not os.path.exists(cp):
        sys.exit(f"no companion: {what}")
    rows = logio.read_log(rlog, with_meta=False).t.size
    print(f"[{load()}] recorder-format 10-hour log: {os.path.getsize(rlog) / 1e6:.1f} MB .csv.gz "
          f"({os.path.getsize(rlog) / rows:.1f} B/row), {rows:,} rows; companion {what} in {wt:.2f} s "
          f"(parse + encode, in the recorder's background thread): {os.path.getsize(cp) / 1e6:.2f} MB, "
          f"{os.path.getsize(cp) / rows:.2f} B/row ({os.path.getsize(cp) / os.path.getsize(rlog):.2f}× the .csv.gz)")
    with open(cp, "rb") as f:
        import json
        import struct
        f.read(len(logcols.MAGIC))
        (hl,) = struct.unpack("<I", f.read(4))
        hdr = json.loads(f.read(hl))
    print("  encodings: " + ", ".join(f"{e['name']} {e['enc']}{e.get('k', '')} ({e['dtype']}) "
                                      f"{e['len'] / rows:.2f} B/row" for e in hdr["enc"]))
    # what the recorder's background writer costs the station's interpreter: the largest gap of a
    # thread that sleeps 2 ms at a time (a stand-in for the slot loop), idle vs. while the writer
    # builds this companion (in its child interpreter)
    def max_gap(during) -> float:
        import threading
        stop, gaps = [], []

        def tick() -> None:
            last = time.perf_counter()
            while not stop:
                time.sleep(0.002)
                now = time.perf_counter()
                gaps.append(now - last)
                last = now
        th = threading.Thread(target=tick)
        th.start()
        during()
        stop.append(1)
        th.join()
        return max(gaps)

    os.replace(cp, away)
    try:
        idle = max_gap(lambda: time.sleep(wt))
        busy = max_gap(lambda: (logio.write_companion_later(rlog), logcols.wait_idle(600)))
    finally:
        if os.path.exists(cp):          # written again by the background writer: the same file
            os.remove(away)
        else:
            os.replace(away, cp)
    print(f"  a 2 ms ticker in the recorder's process: largest gap {busy * 1e3:.1f} ms while the "
          f"background writer builds the companion, {idle * 1e3:.1f} ms idle")
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    folder = os.path.dirname(rlog)
    with_c: list[float] = []
    without: list[float] = []
    cpu: dict[str, list[float]] = {"with": [], "without": []}
    loads = []
    out = None
    for _ in range(runs):
        for present, times, key in ((True, with_c, "with"), (False, without, "without")):
            if not present:
                os.replace(cp, away)
            try:
                before = sorted(os.listdir(folder))
                r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
                t0 = time.perf_counter()
                p = subprocess.run([exe, "analyze", rlog, "--json"], capture_output=True, text=True,
                                   cwd=os.path.dirname(HERE))
                times.append(time.perf_counter() - t0)
                r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu[key].append(r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime)
                assert sorted(os.listdir(folder)) == before, "analyze wrote beside the log"
            finally:
                if not present:
                    os.replace(away, cp)
            assert p.returncode == 0, p.stderr
            assert out is None or p.stdout == out, "results differ with and without the companion"
            out = p.stdout
        loads.append(os.getloadavg()[0])
    mw, mo = statistics.median(with_c), statistics.median(without)
    print(f"analyze recorder-format 10 h log, cold, WITH companion: {med(with_c)} over {runs} runs  "
          f"[goal ≤ 1.0 s]")
    print(f"  same loop, WITHOUT (ISA-L + Arrow parse of the text): {med(without)}; ratio of medians "
          f"{mo / mw:.1f}×; same result: yes; nothing written beside the log: yes")
    print(f"  CPU seconds per run (user+sys, all threads): with {statistics.median(cpu['with']):.3f} s, "
          f"without {statistics.median(cpu['without']):.3f} s; 1-min load during the loop "
          f"{min(loads):.1f}–{max(loads):.1f}   [{load()}]")
    names = ("interpreter+numpy", "gateway import", "read_log", "slot grid", "method")
    for present in (True, False):
        if not present:
            os.replace(cp, away)
        try:
            rows_t = []
            for _ in range(5):
                p = subprocess.run([sys.executable, "-c", STAGES_CODE.replace("LOG", repr(rlog))],
                                   capture_output=True, text=True, cwd=os.path.dirname(HERE), check=True)
                rows_t.append([float(x) for x in p.stdout.split()])
        finally:
            if not present:
                os.replace(away, cp)
        print(f"  stages {'with' if present else 'without'} (median of 5 fresh interpreters, min in "
              "brackets): " + ", ".join(f"{n} {statistics.median(c):.3f} ({min(c):.3f}) s"
                                         for n, c in zip(names, zip(*rows_t))))
    print(f"  [{load()}]")


def main(runs: int = 7) -> None:
    log = os.path.join(HERE, "data", "long10h.csv.gz")
    if not os.path.exists(log):
        generate(log)
    rlog = os.path.join(HERE, "data", "rec10h", "log.csv.gz")
    if not os.path.exists(rlog):
        generate_recorder_format(rlog)
    print(f"[{load()}] 10-hour log {os.path.getsize(log) / 1e6:.1f} MB .csv.gz (3 columns)")
    ct, rt, out = cli_cold(log, runs)
    print(f"analyze 10 h log, cold (no cache exists any more), end to end: {med(ct)} over {runs} runs"
          f"  [goal ≤ 1.0 s]; nothing written beside the log: yes   [{load()}]")
    print(f"  same runs, reference parse (zlib + numpy): {med(rt)}; ratio of medians "
          f"{statistics.median(rt) / statistics.median(ct):.2f}×; same result: yes")
    print(f"  CPU seconds per run (user+sys, all threads): fast median {statistics.median(CPU['fast']):.3f} s, "
          f"reference {statistics.median(CPU['ref']):.3f} s")
    print("  result:", out.strip()[:160], "…")
    stage_times(log, 5)
    parse_candidates(log, 5)
    print(f"[{load()}] recorder-format 10-hour log {os.path.getsize(rlog) / 1e6:.1f} MB .csv.gz "
          "(10 columns, T1/T2 as repr)")
    ct, rt, _ = cli_cold(rlog, 3)
    print(f"analyze recorder-format 10 h log, cold: {med(ct)} over 3 runs; reference parse "
          f"{med(rt)}; ratio {statistics.median(rt) / statistics.median(ct):.2f}×   [{load()}]")
    print(f"  CPU seconds per run: fast median {statistics.median(CPU['fast']):.3f} s, "
          f"reference {statistics.median(CPU['ref']):.3f} s")
    parse_candidates(rlog, 3)

    from gateway.core.method import StreamingMonitor, analyze_slots, to_slots
    from gateway.offline.analysis import params_for
    from gateway.offline.logio import read_log

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
    print(f"streaming result == batch result: yes   [{load()}]")


if __name__ == "__main__":
    if "--companion" in sys.argv[1:]:
        companion()
    else:
        main()
        companion()
