"""The compact columnar companion of a log (gateway/offline/logcols.py, issue 22 item 7): written once by
a real recorder when a test closes (in its background thread), used by every reader when it was
made from exactly the log's bytes (results identical with and without it, awkward values
included), ignored when stale (log appended to, rewritten within the same size and mtime,
touched) or damaged (any flipped byte, cut off, foreign), never written by `hookwatch analyze`,
never written into a read-only folder or a disk short of space (one log line, no exception)."""
import gzip
import logging
import math
import os
import random
import shutil
import struct
import subprocess
import sys

import numpy as np
import pytest

from gateway.core.records import SlotRecord
from gateway.offline import logcols, logio
from gateway.station.recorder import LOG_NAME, TestRecorder
from kit.smallfs import small_tmpfs

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
META = {"station": "c", "sample_id": "S", "method": {"t_set": 0.5, "t_end": 900.0}}
AWKWARD = [math.nan, -0.0, 0.0, math.inf, -math.inf, 1, 0.1, 1e-300, 5e-324, 1.7976931348623157e308,
           -123.456789012345, 0.30000000000000004, 2.5, 1e16, None]
ROWS = logcols.MIN_ROWS + 2_000


class Clock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def _records(n, seed=22):
    """A plausible test (float32 meter readings, a 4-decimal time base, a few dropped slots)
    with every awkward value sprinkled into T1/T2."""
    rng = random.Random(seed)
    for k in range(n):
        if rng.random() < 0.01:
            continue                              # a slot without a row
        a = float(np.float32(0.3 + rng.gauss(0, 0.004)))
        b = float(np.float32(a * 2.2 + rng.gauss(0, 0.004)))
        if rng.random() < 0.002:
            a = rng.choice(AWKWARD)
        if rng.random() < 0.002:
            b = rng.choice(AWKWARD)
        yield SlotRecord(k=k, t=round(k * 0.02 + rng.uniform(-0.004, 0.004), 4), present=True, t1=a, t2=b,
                         q=1, mask=0, ratio=None, mu=None, mean_filt=0.45, speed_cmd=120.0,
                         speed_act=119.87, saturated=False)


def _record(folder, n=ROWS):
    clock = Clock()
    r = TestRecorder(folder, META, flush_interval_s=1.0, clock=clock)
    for rec in _records(n):
        clock.now += 0.02
        r.on_record(rec)
    r.close({"ok": True})
    assert logcols.wait_idle(120)
    return os.path.join(folder, LOG_NAME)


def _parsed(path):
    """The columns of the log's text (never the companion)."""
    with open(path, "rb") as f:
        return logio.parse_raw(path, f.read())


def _same(lg, ref):
    t, t1, t2, columns = ref
    return (lg.t.tobytes() == t.tobytes() and lg.t1.tobytes() == t1.tobytes()
            and lg.t2.tobytes() == t2.tobytes() and lg.columns == columns)


def _analyze(path):
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    p = subprocess.run([exe, "analyze", path, "--json"], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    return p.returncode, p.stdout


def _from_companion(path):
    with open(path, "rb") as f:
        raw, st = f.read(), os.fstat(f.fileno())
    return logcols.load(path, raw, st)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """One log written by a real recorder (closed: its companion written in the background)."""
    return _record(str(tmp_path_factory.mktemp("rec") / "t"))


def test_the_recorder_writes_the_companion_at_close_and_every_reader_uses_it(recorded, tmp_path,
                                                                               monkeypatch):
    folder = str(tmp_path / "t")
    shutil.copytree(os.path.dirname(recorded), folder)    # copy2: size, mtime and bytes kept
    path = os.path.join(folder, LOG_NAME)
    cp = logcols.companion_path(path)
    assert os.path.basename(cp) == "log.cols" and os.path.exists(cp)
    ref = _parsed(path)
    assert ref[0].size > logcols.MIN_ROWS
    tt = np.concatenate(ref[1:3])
    assert np.isnan(tt).any() and np.isinf(tt).any() and (np.signbit(tt) & (tt == 0)).any()
    got = _from_companion(path)
    assert got is not None
    assert all(a.tobytes() == b.tobytes() for a, b in zip(got[:3], ref[:3])) and got[3] == ref[3]
    # compact: a few bytes per row (the .csv.gz takes several times that)
    assert os.path.getsize(cp) < 0.5 * os.path.getsize(path)
    # read_log takes it (the text parser is not even called) and gives the parse's bits
    real_parse = logio.parse_raw
    monkeypatch.setattr(logio, "parse_raw", lambda *a: pytest.fail("parsed although the companion is valid"))
    assert _same(logio.read_log(path), ref)
    monkeypatch.setattr(logio, "parse_raw", real_parse)
    # hookwatch analyze: the same result with and without it, and it writes nothing
    before = sorted(os.listdir(folder))
    with_cols = _analyze(path)
    assert sorted(os.listdir(folder)) == before
    os.rename(cp, cp + ".away")
    before = sorted(os.listdir(folder))
    without = _analyze(path)
    assert sorted(os.listdir(folder)) == before               # no companion made by a reader
    assert with_cols == without and with_cols[0] == 0 and '"mu' in with_cols[1]


def test_every_awkward_value_round_trips_bit_for_bit(tmp_path):
    """The encoder picks dec / f32 / f64 per column only when exact: NaN payloads, signed zeros,
    subnormals, infinities, huge and tiny values, mixed decimals all come back as they went in."""
    rng = np.random.default_rng(5)
    n = 50_000
    payload_nan = np.frombuffer(struct.pack("<Q", 0x7FF8_0000_0000_1234), np.float64)[0]
    cases = {
        "4 decimals": np.round(np.arange(n) * 0.02 + rng.uniform(-0.004, 0.004, n), 4),
        "float32": rng.normal(0.3, 0.01, n).astype(np.float32).astype(np.float64),
        "awkward": rng.choice(np.array([math.nan, -0.0, 0.0, math.inf, -math.inf, 5e-324, 1e-300,
                                        1.7976931348623157e308, 0.1, 1e16, payload_nan]), n),
        "mixed": np.where(rng.random(n) < 0.5, np.round(rng.normal(0, 1, n), 3), rng.normal(0, 1, n)),
        "-0.0 in decimals": np.where(rng.random(n) < 0.01, -0.0, np.round(rng.normal(0, 1, n), 2)),
        "huge ints": rng.integers(-(2 ** 62), 2 ** 62, n).astype(np.float64),
        "empty": np.empty(0),
    }
    for name, a in cases.items():
        key = {"size": 1, "mtime_ns": 2, "sha256": "x"}
        data = logcols.dumps(key, a, a[::-1].copy(), a, ["t", "T1", "T2"])
        log_path = str(tmp_path / f"{len(name)}.csv")
        with open(log_path, "wb") as f:
            f.write(data)                             # any bytes: the companion keys on them
        with open(log_path, "rb") as f:
            raw, st = f.read(), os.fstat(f.fileno())
        data = logcols.dumps(logcols.key_of(raw, st), a, a[::-1].copy(), a, ["t", "T1", "T2"])
        with open(logcols.companion_path(log_path), "wb") as f:
            f.write(data)
        got = logcols.load(log_path, raw, st)
        assert got is not None, name
        assert got[0].tobytes() == a.tobytes() and got[1].tobytes() == a[::-1].tobytes(), name
        assert got[0].flags.writeable and got[0].dtype == np.float64


def _unchanged_read(path, ref):
    assert _from_companion(path) is None
    assert _same(logio.read_log(path, with_meta=False), ref)


def test_a_stale_companion_is_ignored(recorded, tmp_path):
    folder = str(tmp_path / "t")
    shutil.copytree(os.path.dirname(recorded), folder)
    path = os.path.join(folder, LOG_NAME)
    cp = logcols.companion_path(path)
    assert _from_companion(path) is not None
    with open(path, "rb") as f:
        orig = f.read()
    st = os.stat(path)
    # appended to (a test continued): more rows, the companion's are not served
    with open(path, "ab") as f:
        f.write(gzip.compress(b"99999.0000,0.25,0.5,0,0,0,1,0,nan,nan\n", mtime=0))
    ref = _parsed(path)
    assert ref[0][-1] == 99999.0 and ref[0].size > 0
    _unchanged_read(path, ref)
    # rewritten with other bytes of the same size, mtime_ns set back: the hash tells (here the
    # first gzip member's MTIME field: the same rows, other bytes)
    other = orig[:4] + b"\x01\x02\x03\x04" + orig[8:]
    assert len(other) == len(orig) and other != orig
    with open(path, "wb") as f:
        f.write(other)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(path).st_size == st.st_size and os.stat(path).st_mtime_ns == st.st_mtime_ns
    ref = _parsed(path)
    _unchanged_read(path, ref)
    # the original bytes back, but touched (mtime differs): ignored too (the key is the triple)
    with open(path, "wb") as f:
        f.write(orig)
    assert _from_companion(path) is None
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))             # exactly as it was: valid again
    assert _from_companion(path) is not None
    assert os.path.exists(cp)                                       # a reader never deletes or rewrites it


def test_a_damaged_companion_is_ignored(recorded, tmp_path):
    folder = str(tmp_path / "t")
    shutil.copytree(os.path.dirname(recorded), folder)
    path = os.path.join(folder, LOG_NAME)
    cp = logcols.companion_path(path)
    with open(cp, "rb") as f:
        good = f.read()
    ref = _parsed(path)
    rng = random.Random(3)
    damaged = [good[:len(good) // 2], good[:-1], good + b"\0", b"", b"HWCOLS2\n", os.urandom(4096),
               b"\0" * len(good)]
    for _ in range(12):                                             # one flipped bit anywhere
        i = rng.randrange(len(good))
        damaged.append(good[:i] + bytes([good[i] ^ (1 << rng.randrange(8))]) + good[i + 1:])
    for bad in damaged:
        with open(cp, "wb") as f:
            f.write(bad)
        _unchanged_read(path, ref)
    os.remove(cp)
    os.mkdir(cp)                                                    # not even a file
    _unchanged_read(path, ref)


def test_no_companion_in_a_read_only_folder_or_on_a_disk_short_of_space(recorded, tmp_path, caplog):
    with small_tmpfs(tmp_path / "fs", size="64m") as fs:
        folder = os.path.join(fs, "t")
        shutil.copytree(os.path.dirname(recorded), folder)
        path = os.path.join(folder, LOG_NAME)
        os.remove(logcols.companion_path(path))
        # a 64 MB file system is always below the reserve (1 GiB): skipped, one info line
        assert logio.write_companion(path).startswith("skipped: the disk is short of space")
        assert not os.path.exists(logcols.companion_path(path))
        # a read-only folder (root ignores modes: the file system is remounted read-only)
        subprocess.run(["mount", "-o", "remount,ro", fs], check=True, capture_output=True)
        try:
            old = logcols.RESERVE_BYTES, logcols.RESERVE_FRACTION
            logcols.RESERVE_BYTES, logcols.RESERVE_FRACTION = 0, 0.0
            try:
                with caplog.at_level(logging.INFO, logger="hookwatch.logcols"):
                    assert logio.write_companion_later(path) is True       # queued, no exception
                    assert logcols.wait_idle(60)
            finally:
                logcols.RESERVE_BYTES, logcols.RESERVE_FRACTION = old
            lines = [r for r in caplog.records if r.name == "hookwatch.logcols"]
            assert len(lines) == 1 and "companion not written" in lines[0].getMessage()
            assert "read-only" in lines[0].getMessage().lower()
            assert sorted(os.listdir(folder)) == ["events.jsonl", "log.csv.gz", "log.meta.yaml", "result.json"]
            # the analysis of a log in a read-only folder still works, from the text
            code, out = _analyze(path)
            assert code == 0 and '"mu' in out
        finally:
            subprocess.run(["mount", "-o", "remount,rw", fs], capture_output=True)


def test_a_real_recorder_on_a_small_disk_closes_normally_without_a_companion(tmp_path, caplog):
    with small_tmpfs(tmp_path / "fs", size="16m") as fs:
        with caplog.at_level(logging.INFO, logger="hookwatch.logcols"):
            path = _record(os.path.join(fs, "t"))
        assert os.path.exists(os.path.join(fs, "t", "result.json"))
        assert not os.path.exists(logcols.companion_path(path))
        msgs = [r.getMessage() for r in caplog.records if r.name == "hookwatch.logcols"]
        assert len(msgs) == 1 and "short of space" in msgs[0]
        assert logio.read_log(path).t.size > logcols.MIN_ROWS


def test_a_log_that_does_not_parse_is_one_warning_line(tmp_path, caplog, monkeypatch):
    monkeypatch.setattr(logcols, "MIN_ROWS", 1)             # handed to the child with the reserve
    path = str(tmp_path / LOG_NAME)
    with open(path, "wb") as f:
        f.write(gzip.compress(b"t,T1,T2\n0.0,0.3,0.6\n0.02,zero,0.6\n", mtime=0))
    with caplog.at_level(logging.INFO, logger="hookwatch.logcols"):
        assert logio.write_companion_later(path) is True
        assert logcols.wait_idle(60)
    msgs = [r.getMessage() for r in caplog.records if r.name == "hookwatch.logcols"]
    assert len(msgs) == 1 and "companion not written" in msgs[0] and "line 3" in msgs[0], msgs
    assert sorted(os.listdir(tmp_path)) == [LOG_NAME]


def test_a_full_writer_drops_the_oldest_waiting_log_and_keeps_the_newest(tmp_path, caplog):
    """The writer is fed through the project's one bounded hand-over (a Mailbox): submitting never
    blocks the recorder; with MAX_PENDING logs waiting, each further log pushes out the OLDEST
    waiting one (one warning line naming it; its text stays, only the companion is not made), the
    newest are built in order, and the writer goes idle with nothing left."""
    extra = 4
    paths = []
    for i in range(logcols.MAX_PENDING + extra):
        os.makedirs(tmp_path / str(i))
        p = str(tmp_path / str(i) / "log.csv")
        with open(p, "w") as f:
            f.write("t,T1,T2\n0.0,0.3,0.6\n")           # a short test: skipped without a child
        paths.append(p)
    w = logcols.CompanionWriter()
    with caplog.at_level(logging.INFO, logger="hookwatch.logcols"):
        for p in paths:                                   # the thread is not started yet: all wait
            w.submit(p)
        assert len(w.box) == logcols.MAX_PENDING and w.box.dropped == extra
        dropped = [r.getMessage() for r in caplog.records if r.name == "hookwatch.logcols"]
        assert dropped == [f"{logcols.companion_path(p)}: companion not written: {logcols.MAX_PENDING} newer "
                           "logs waiting" for p in paths[:extra]]
        assert not w.wait_idle(0)
        caplog.clear()
        w.start()
        assert w.wait_idle(60)
    done = [r.getMessage() for r in caplog.records if r.name == "hookwatch.logcols"]
    assert done == [f"{logcols.companion_path(p)}: skipped: {os.path.getsize(p)} bytes cannot hold "
                    f"{logcols.MIN_ROWS} rows" for p in paths[extra:]]
    assert len(w.box) == 0 and not any(os.path.exists(logcols.companion_path(p)) for p in paths)
