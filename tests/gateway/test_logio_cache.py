"""The binary column cache beside large logs (gateway/logcache.py): used only when it matches the
log's bytes, bit-identical to a parse of the text, never a reason for a read to fail."""
import gzip
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from gateway import logcache, logio

ROWS = 1200


@pytest.fixture
def small_cache(monkeypatch):
    """Cache logs of any size in these tests (the real thresholds are for 100 k rows)."""
    monkeypatch.setattr(logcache, "MIN_ROWS", 10)
    monkeypatch.setattr(logio, "_CACHE_MIN_BYTES", 0)
    monkeypatch.delenv("HOOKWATCH_LOG_CACHE", raising=False)


def _write_log(path, seed=1, extra_cols=False, recorded=True):
    rng = np.random.default_rng(seed)
    t = np.arange(ROWS) * 0.02 + rng.uniform(-0.004, 0.004, ROWS)
    t1 = rng.uniform(0.1, 0.3, ROWS)
    t2 = t1 * np.exp(0.26 * 1.83)
    head = "t,T1,T2,q\n" if extra_cols else "t,T1,T2\n"
    lines = [head] + [f"{a!r},{b!r},{c!r}" + (",0" if extra_cols else "") + "\n"
                      for a, b, c in zip(t.tolist(), t1.tolist(), t2.tolist())]
    opener = gzip.open if path.endswith(".gz") else open
    with opener(path, "wt") as f:
        f.write("".join(lines))
    if recorded:   # the sidecar of a log hookwatch recorded names the software
        with open(logio.sidecar_path(path), "w") as f:
            f.write("software: hookwatch test\nmethod:\n  t_set: 0.5\n")
    return t, t1, t2


def _no_parse(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("the text was parsed although a valid cache exists")
    monkeypatch.setattr(logio, "_decompress", boom)


@pytest.mark.parametrize("name", ["a.csv.gz", "a.csv"])
def test_cache_written_then_used_bit_identical(tmp_path, small_cache, monkeypatch, name):
    p = str(tmp_path / name)
    t, t1, t2 = _write_log(p, extra_cols=True)
    first = logio.read_log(p, with_meta=False)
    assert os.path.exists(logcache.cache_path(p))
    _no_parse(monkeypatch)
    second = logio.read_log(p, with_meta=False)
    for a, b, ref in ((first.t, second.t, t), (first.t1, second.t1, t1), (first.t2, second.t2, t2)):
        assert a.tobytes() == b.tobytes() == ref.tobytes()
    assert second.columns == first.columns == ["t", "T1", "T2", "q"]


def test_no_cache_beside_a_log_hookwatch_did_not_record(tmp_path, small_cache):
    """A log from elsewhere (no sidecar, or one that does not name hookwatch) is read, and nothing
    is written beside it (e.g. a shared folder of reference logs)."""
    p = str(tmp_path / "foreign.csv.gz")
    t, _, _ = _write_log(p, recorded=False)
    assert logio.read_log(p, with_meta=False).t.tobytes() == t.tobytes()
    assert not os.path.exists(logcache.cache_path(p))
    with open(logio.sidecar_path(p), "w") as f:
        f.write("sample_id: x\nmethod:\n  t_set: 0.5\n")
    logio.read_log(p)
    assert not os.path.exists(logcache.cache_path(p))


def test_stale_cache_same_size_and_mtime_is_not_used(tmp_path, small_cache):
    p = str(tmp_path / "a.csv")
    _write_log(p, seed=1)
    logio.read_log(p, with_meta=False)
    st = os.stat(p)
    # same length, same mtime, one digit changed: only the hash can tell
    with open(p) as f:
        text = f.read()
    i = text.index("\n") + 3
    digit = "1" if text[i] != "1" else "2"
    text = text[:i] + digit + text[i + 1:]
    with open(p, "w") as f:
        f.write(text)
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert os.stat(p).st_size == st.st_size and os.stat(p).st_mtime_ns == st.st_mtime_ns
    lg = logio.read_log(p, with_meta=False)
    assert lg.t[0] == float(text.split("\n")[1].split(",")[0])
    # and the cache was rewritten for the new content
    with open(p, "rb") as f:
        key = logcache.source_key(p, f.read())
    assert logcache.load(p, key) is not None


def test_log_still_being_written_gets_a_fresh_read(tmp_path, small_cache):
    p = str(tmp_path / "a.csv")
    _write_log(p)
    n0 = logio.read_log(p, with_meta=False).t.size
    with open(p, "a") as f:
        f.write("9999.0,0.2,0.4\n")
    lg = logio.read_log(p, with_meta=False)
    assert lg.t.size == n0 + 1 and lg.t[-1] == 9999.0


@pytest.mark.parametrize("damage", ["truncate", "garbage", "empty"])
def test_damaged_cache_is_ignored(tmp_path, small_cache, damage):
    p = str(tmp_path / "a.csv.gz")
    t, _, _ = _write_log(p)
    logio.read_log(p, with_meta=False)
    cp = logcache.cache_path(p)
    with open(cp, "rb") as f:
        data = f.read()
    with open(cp, "wb") as f:
        f.write({"truncate": data[:-100], "garbage": b"x" * len(data), "empty": b""}[damage])
    lg = logio.read_log(p, with_meta=False)
    assert lg.t.tobytes() == t.tobytes()


def test_cache_switched_off(tmp_path, small_cache, monkeypatch):
    monkeypatch.setenv("HOOKWATCH_LOG_CACHE", "0")
    p = str(tmp_path / "a.csv.gz")
    _write_log(p)
    logio.read_log(p, with_meta=False)
    assert not os.path.exists(logcache.cache_path(p))


def test_small_logs_leave_no_cache(tmp_path, monkeypatch):
    monkeypatch.delenv("HOOKWATCH_LOG_CACHE", raising=False)
    p = str(tmp_path / "a.csv.gz")
    _write_log(p)
    logio.read_log(p, with_meta=False)
    assert not os.path.exists(logcache.cache_path(p))


def test_unwritable_cache_place_does_not_fail_the_read(tmp_path, small_cache):
    p = str(tmp_path / "a.csv")
    t, _, _ = _write_log(p)
    os.mkdir(logcache.cache_path(p))  # a directory where the cache file would go
    assert logio.read_log(p, with_meta=False).t.tobytes() == t.tobytes()
    assert logio.read_log(p, with_meta=False).t.tobytes() == t.tobytes()


def test_analyze_cli_same_result_cold_and_warm(tmp_path):
    """End to end through the CLI with the real thresholds (a 2-hour log, 360 k rows)."""
    from conftest import ROOT

    sys.path.insert(0, os.path.join(ROOT, "bench"))
    from gen_long_log import generate

    p = generate(str(tmp_path / "long.csv.gz"), hours=2.0)
    exe = os.path.join(os.path.dirname(sys.executable), "hookwatch")
    env = {**os.environ}
    env.pop("HOOKWATCH_LOG_CACHE", None)
    cold = subprocess.run([exe, "analyze", p, "--json"], capture_output=True, text=True, env=env)
    assert cold.returncode == 0, cold.stderr
    assert os.path.exists(logcache.cache_path(p))
    warm = subprocess.run([exe, "analyze", p, "--json"], capture_output=True, text=True, env=env)
    off = subprocess.run([exe, "analyze", p, "--json"], capture_output=True, text=True,
                         env={**env, "HOOKWATCH_LOG_CACHE": "0"})
    assert warm.returncode == 0 and off.returncode == 0
    assert json.loads(cold.stdout) == json.loads(warm.stdout) == json.loads(off.stdout)


def test_no_cache_when_the_disk_would_fall_below_its_reserve(tmp_path, small_cache, monkeypatch):
    st = os.statvfs(tmp_path)
    # a reserve larger than the whole file system (not just what is free now: other processes
    # free space meanwhile): the cache is skipped, the read still succeeds
    monkeypatch.setattr(logcache, "RESERVE_BYTES", st.f_blocks * st.f_frsize + 1)
    p = str(tmp_path / "a.csv.gz")
    t, _, _ = _write_log(p)
    assert logio.read_log(p, with_meta=False).t.tobytes() == t.tobytes()
    assert not os.path.exists(logcache.cache_path(p))
