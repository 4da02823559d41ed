"""The recorder keeps the rows of a flush interval as columns and formats them once per flush
(issue 16): the log file is byte for byte what the per-row formatting wrote before, for a fixed
record sequence with every awkward value (NaN, None, ±inf, negative zero, integers where floats
belong, bools, large masks), and it reads back through gateway.offline.logio."""
import gzip
import math
import random

import numpy as np

from gateway.core.method.rules import LOST  # a LOST slot has no row (its span is in lost_spans)
from gateway.core.records import SlotRecord
from gateway.offline.logio import read_log
from gateway.station.recorder import LOG_COLUMNS, LOG_NAME, TestRecorder

META = {"station": "t", "sample_id": "S", "method": {"t_set": 0.5, "t_end": 100.0}}


def _f(x):
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "nan"
    return repr(float(x))


def row_before(rec):
    """The recorder's per-row formatting before issue 16 (the reference)."""
    return (f"{rec.t:.4f},{_f(rec.t1)},{_f(rec.t2)},{rec.speed_cmd:.3f},"
            f"{'nan' if math.isnan(rec.speed_act) else format(rec.speed_act, '.3f')},"
            f"{int(rec.saturated)},{rec.q},{rec.mask},{_f(rec.mu)},{_f(rec.mean_filt)}\n")


AWKWARD = [math.nan, -0.0, 0.0, math.inf, -math.inf, 1, 0.1, 1e-300, 5e-324, 1.7976931348623157e308,
           -123.456789012345, 0.30000000000000004, 2.5, 1e16]


def records(n=1500, seed=16):
    rng = random.Random(seed)

    def v():
        return rng.choice(AWKWARD) if rng.random() < 0.2 else rng.uniform(-5.0, 5.0)
    out = []
    for k in range(n):
        present = rng.random() > 0.1
        mu = None if rng.random() < 0.3 else v()
        out.append(SlotRecord(k=k, t=round(k * 0.02 + rng.uniform(0, 0.0099), 4) if k % 5 else k * 0.02,
                              present=present, t1=v() if present else math.nan,
                              t2=v() if present else math.nan, q=rng.choice([0, 1]),
                              mask=rng.choice([0, 1, 6, 255 & ~LOST, 1 << 20]), ratio=None, mu=mu,
                              mean_filt=v(), speed_cmd=rng.choice([150.0, 0, -1.25, math.nan, rng.uniform(0, 600)]),
                              speed_act=rng.choice([math.nan, 149.5, 0.0, -0.0004]),
                              saturated=rng.choice([False, True, 0, 1])))
    return out


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def test_log_bytes_identical_to_the_per_row_format(tmp_path):
    clock = Clock()
    r = TestRecorder(str(tmp_path / "x"), META, flush_interval_s=1.0, clock=clock)
    # the expected file: one gzip member per flush (the header's own at the start), the rows
    # formatted as before
    blocks = [[",".join(LOG_COLUMNS) + "\n"], []]
    last = 0.0
    for rec in records():
        clock.now += 0.02
        r.on_record(rec)
        if rec.present:
            blocks[-1].append(row_before(rec))
        if clock.now - last >= 1.0:     # the flush is due on every slot, with a row or not
            last = clock.now
            blocks.append([])
    r.close({"ok": True})
    blocks = [b for b in blocks if b]
    want = b"".join(gzip.compress("".join(b).encode(), compresslevel=5, mtime=0) for b in blocks)
    got = (tmp_path / "x" / LOG_NAME).read_bytes()
    assert len(blocks) > 20
    assert gzip.decompress(got).decode() == "".join("".join(b) for b in blocks)
    assert got == want
    lg = read_log(str(tmp_path / "x" / LOG_NAME))
    present = [rec for rec in records() if rec.present]
    assert len(lg.t) == len(present)
    assert np.array_equal(lg.t1, np.array([float(x.t1) for x in present]), equal_nan=True)


def test_a_row_with_none_where_a_number_belongs_is_kept_and_columns_stay_aligned(tmp_path):
    r = TestRecorder(str(tmp_path / "y"), META)
    good = SlotRecord(k=0, t=0.0, present=True, t1=0.3, t2=0.6, q=1, mask=0, ratio=2.0, mu=0.37,
                      mean_filt=0.45, speed_cmd=1.0, speed_act=1.0, saturated=False)
    bad = SlotRecord(k=1, t=0.02, present=True, t1=None, t2=0.6, q=1, mask=0, ratio=None, mu=None,
                     mean_filt=None, speed_cmd=1.0, speed_act=1.0, saturated=False)
    r.on_record(good)
    r.on_record(bad)
    r.on_record(SlotRecord(**{**{f: getattr(good, f) for f in good.__slots__}, "k": 2, "t": 0.04}))
    r.close({"ok": True})
    text = gzip.decompress((tmp_path / "y" / LOG_NAME).read_bytes()).decode().splitlines()
    assert text[1] == row_before(good).strip()
    assert text[2] == "0.0200,nan,0.6,1.000,1.000,0,1,0,nan,nan"
    assert text[3] == row_before(good).strip().replace("0.0000", "0.0400", 1)
