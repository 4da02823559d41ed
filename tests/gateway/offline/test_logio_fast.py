"""The fast log parse (gateway/offline/logio.py: ISA-L gunzip + Arrow's CSV reader) gives columns
bit-identical to the reference parse (Python's float() of every field, and numpy's loadtxt path
that read_log falls back to), and reading a log never writes anything beside it."""
import contextlib
import glob
import gzip
import math
import os
import subprocess
import zlib

import numpy as np
import pyarrow as pa
import pyarrow.csv as pcsv
import pytest

from conftest import ROOT, hookwatch_cmd
from conftest import VECTORS as VECTOR_DIR
from gateway.core.records import SlotRecord
from gateway.offline import logio
from gateway.station import recorder as rec_mod

VECTORS = sorted(glob.glob(os.path.join(VECTOR_DIR, "*.csv*")))
assert VECTORS, VECTOR_DIR


def _float_reference(path):
    """Independent reference: every gzip member inflated by zlib, each field through float()."""
    with open(path, "rb") as f:
        raw = f.read()
    if raw[:2] == b"\x1f\x8b":
        out, rest = [], raw
        while rest[:2] == b"\x1f\x8b":
            d = zlib.decompressobj(16 + zlib.MAX_WBITS)
            out.append(d.decompress(rest))
            rest = d.unused_data
        raw = b"".join(out)
    lines = raw.decode().split("\n")
    header = [c.strip() for c in lines[0].lstrip("\ufeff").split(",")]
    idx = [header.index(c) for c in ("t", "T1", "T2")]
    rows = [ln.split(",") for ln in lines[1:] if ln.strip()]
    if rows and len(rows[-1]) < len(header):
        rows.pop()  # cut off mid-row
    return [np.array([float(r[i]) for r in rows], dtype=np.float64) for i in idx]


def _reference_read(path, monkeypatch):
    """read_log through the numpy reference parser only (the fast path switched off)."""
    with monkeypatch.context() as m:
        m.setattr(logio, "_parse_arrow", lambda *a: None)
        try:
            return logio.read_log(path, with_meta=False)
        except logio.LogError as e:
            return str(e)


def _same(lg, cols):
    return all(a.dtype == np.float64 and a.tobytes() == b.tobytes()
               for a, b in zip((lg.t, lg.t1, lg.t2), cols))


@pytest.mark.parametrize("path", VECTORS, ids=os.path.basename)
def test_vectors_parse_bit_identical(path, monkeypatch):
    calls = []
    real = logio._parse_arrow
    monkeypatch.setattr(logio, "_parse_arrow", lambda *a: calls.append(1) or real(*a))
    lg = logio.read_log(path, with_meta=False)
    assert calls and real(*_body_args(path)) is not None, "the fast path was not taken"
    assert _same(lg, _float_reference(path))
    ref = _reference_read(path, monkeypatch)
    assert _same(lg, (ref.t, ref.t1, ref.t2))


def _body_args(path):
    raw = logio._read_bytes(path)
    nl = raw.index(b"\n")
    cols = [c.strip() for c in raw[:nl].decode().split(",")]
    return raw, nl + 1, len(raw), len(cols), [cols.index(c) for c in ("t", "T1", "T2")]


def _record(k, t1, t2, t=None):
    return SlotRecord(k=k, t=k * 0.02 if t is None else t, present=True, t1=t1, t2=t2, q=1, mask=0,
                      ratio=None, mu=0.26, mean_filt=0.5, speed_cmd=100.0, speed_act=math.nan,
                      saturated=False)


def _awkward_values(n, seed=3):
    """What the recorder can be handed: float32-derived meter values (long reprs), values that
    repr in exponent form, subnormals, huge values, -0.0, NaN (a MISSING value kept as a row),
    ±inf, None (written as nan), ordinary 3-decimal readings."""
    rng = np.random.default_rng(seed)
    vals = []
    special = [math.nan, math.inf, -math.inf, -0.0, 0.0, 5e-324, 2.2250738585072014e-308, 1e-05,
               1.7976931348623157e308, 1e22, 1e23, 0.1 + 0.2, None]
    for i in range(n):
        r = i % 5
        if r == 0:
            v = float(np.float32(rng.uniform(0.05, 2.0)))
        elif r == 1:
            v = round(float(rng.uniform(0.05, 2.0)), 3)
        elif r == 2:
            v = float(rng.standard_normal() * 10.0 ** int(rng.integers(-12, 12)))
        elif r == 3:
            v = special[i // 5 % len(special)]
        else:
            v = float(rng.uniform(0.05, 2.0))
        vals.append(v)
    return vals


def test_recorder_log_with_awkward_values(tmp_path, monkeypatch):
    """A log written by the real recorder (10 columns, T1/T2 as repr, NaN rows, several gzip
    members) reads back bit-identical to float() of its text and to the reference parse."""
    d = str(tmp_path / "test")
    r = rec_mod.TestRecorder(d, {"software": "hookwatch test", "method": {"t_set": 0.5}},
                             flush_interval_s=0.0)
    a, b = _awkward_values(3000), _awkward_values(3000, seed=4)
    for k in range(3000):
        r.on_record(_record(k, a[k], b[k], t=float(np.float32(k * 0.02)) if k % 7 else None))
    r.close({"status": "complete"})
    p = os.path.join(d, rec_mod.LOG_NAME)
    with open(p, "rb") as f:
        assert f.read().count(b"\x1f\x8b\x08") > 3      # many members
    ref = _float_reference(p)
    assert ref[0].size == 3000 and np.isnan(ref[1]).any() and np.isinf(ref[2]).any()
    lg = logio.read_log(p, with_meta=False)
    assert _same(lg, ref)
    old = _reference_read(p, monkeypatch)
    assert _same(lg, (old.t, old.t1, old.t2))
    assert logio._parse_arrow(*_body_args(p)) is not None


ODD_BODIES = {
    "crlf": "t,T1,T2\r\n0.0,0.25,0.5\r\n0.02,0.25,0.5\r\n",
    "blank_lines": "t,T1,T2\n0.0,0.25,0.5\n\n0.02,0.26,0.5\n\n",
    "bom_spaces": "\ufeff t , T1 ,T2\n 0.0 ,0.25, 0.5\n0.02,0.26,0.5 \n",
    "reordered_extra": "q,T2,x,t,T1\nok,0.5,a,0.0,0.25\nbad,0.6,b,0.02,0.26\n",
    "cut_mid_row": "t,T1,T2\n0.0,0.25,0.5\n0.02,0.2",
    "cut_last_field": "t,T1,T2\n0.0,0.25,0.5\n0.02,0.25,0.4",
    "no_newline_at_all": "t,T1,T2",
    "header_only": "t,T1,T2\n",
    "whitespace_body": "t,T1,T2\n   \n",
    "nan_inf_forms": "t,T1,T2\n0,nan,-inf\n1,NaN,+Infinity\n2,-nan,1e-400\n3,1e400,+1.5\n",
    "nan_payload": "t,T1,T2\n0,nan(1),0.5\n",
    "quoted": 't,T1,T2\n0,"0.25",0.5\n',
    "empty_field": "t,T1,T2\n0,,0.5\n",
    "ragged": "t,T1,T2\n0,0.25,0.5\n1,0.25,0.5,9\n",
    "short_row": "t,T1,T2\n0,0.25,0.5\n1,0.25\n2,0.25,0.5\n",
    "text_value": "t,T1,T2\n0,0.25,0.5\n1,abc,0.5\n",
    "hex": "t,T1,T2\n0,0x10,0.5\n",
    "missing_col": "t,T1\n0,0.25\n",
    "utf8_extra": "t,T1,T2,note\n0,0.25,0.5,grün\n",
    "leading_dot_exp": "t,T1,T2\n.5,5.,1E5\n",
}


@pytest.mark.parametrize("name", sorted(ODD_BODIES))
@pytest.mark.parametrize("gz", [False, True])
def test_odd_logs_same_as_reference(tmp_path, monkeypatch, name, gz):
    """Every odd input gives what the reference parser gives: the same columns or the same
    error message (the fast path falls back wherever it might differ)."""
    p = str(tmp_path / ("x.csv.gz" if gz else "x.csv"))
    data = ODD_BODIES[name].encode()
    with open(p, "wb") as f:
        f.write(gzip.compress(data) if gz else data)
    ref = _reference_read(p, monkeypatch)
    try:
        got = logio.read_log(p, with_meta=False)
    except logio.LogError as e:
        assert str(e) == ref
        return
    assert not isinstance(ref, str), ref
    assert _same(got, (ref.t, ref.t1, ref.t2)) and got.columns == ref.columns
    for a in (got.t, got.t1, got.t2):
        a[:0] = 0  # writable, like the reference's arrays
        assert a.flags.writeable


def test_non_utf8_and_corrupt_gzip_same_as_reference(tmp_path, monkeypatch):
    p = str(tmp_path / "x.csv")
    with open(p, "wb") as f:
        f.write(b"t,T1,T2,note\n0,0.25,0.5,\xff\xfe\n")
    with pytest.raises(logio.LogError) as e:
        logio.read_log(p, with_meta=False)
    assert str(e.value) == _reference_read(p, monkeypatch) and "UTF-8" in str(e.value)
    g = str(tmp_path / "y.csv.gz")
    blob = bytearray(gzip.compress(b"t,T1,T2\n" + b"0,0.25,0.5\n" * 5000))
    blob[40] ^= 0x55
    with open(g, "wb") as f:
        f.write(bytes(blob))
    with pytest.raises(logio.LogError) as e:
        logio.read_log(g, with_meta=False)
    assert "corrupt gzip" in str(e.value)


@contextlib.contextmanager
def _read_only_folder(path):
    """The folder made immutable (chattr +i; tests run as root), or else a read-only bind mount."""
    if subprocess.run(["chattr", "+i", path], capture_output=True).returncode == 0:
        try:
            yield "chattr"
        finally:
            subprocess.run(["chattr", "-i", path], check=True)
        return
    src = path + ".src"
    os.rename(path, src)
    os.mkdir(path)
    ok = subprocess.run(["mount", "--bind", src, path], capture_output=True).returncode == 0
    ok = ok and subprocess.run(["mount", "-o", "remount,bind,ro", path],
                               capture_output=True).returncode == 0
    if not ok:
        pytest.fail("cannot make a read-only folder (neither chattr +i nor a read-only bind mount)")
    try:
        yield "bind"
    finally:
        subprocess.run(["umount", path], check=True)


def _listing(folder):
    return sorted((e.name, e.stat().st_size, e.stat().st_mtime_ns) for e in os.scandir(folder))


def test_analyze_in_read_only_folder_writes_nothing(tmp_path):
    """A recorded log big enough for the old column cache (a 2-hour log, 360 k rows, sidecar
    naming hookwatch) analyses in a read-only folder, and analysing it in a writable one leaves
    the folder exactly as it was (no derived file, no temp file)."""
    import sys
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    from gen_long_log import generate

    folder = tmp_path / "records"
    folder.mkdir()
    p = generate(str(folder / "long.csv.gz"), hours=2.0)
    before = _listing(folder)
    cmd = hookwatch_cmd() + ["analyze", p, "--json"]
    writable = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert writable.returncode == 0, writable.stderr
    assert _listing(folder) == before
    with _read_only_folder(str(folder)):
        with pytest.raises(OSError):
            open(os.path.join(folder, "probe"), "w").close()
        ro = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert ro.returncode == 0, ro.stderr
        assert _listing(folder) == before
    assert ro.stdout == writable.stdout and '"mu' in ro.stdout


def test_leftover_colcache_is_ignored(tmp_path):
    """A NAME.colcache from older versions is never read (a wrong one cannot change a result)
    and never touched."""
    p = str(tmp_path / "a.csv")
    with open(p, "w") as f:
        f.write("t,T1,T2\n0.0,0.25,0.5\n0.02,0.25,0.5\n")
    cp = str(tmp_path / "a.colcache")
    with open(cp, "wb") as f:
        f.write(b"HWCOLS1\n" + b"\0" * 200)
    st = os.stat(cp)
    lg = logio.read_log(p, with_meta=False)
    assert lg.t.tolist() == [0.0, 0.02] and lg.t1.tolist() == [0.25, 0.25]
    assert os.stat(cp).st_mtime_ns == st.st_mtime_ns and os.path.getsize(cp) == 208


def _members(n_rows=20000, per=50):
    rows = [f"{i * 0.02:.4f},{0.25 + i % 7 * 1e-3!r},0.5\n".encode() for i in range(n_rows)]
    return b"".join(rows), [gzip.compress(b"".join(rows[i:i + per]), mtime=0)
                            for i in range(0, n_rows, per)]


@pytest.mark.parametrize("case", ["members", "cut_mid_member", "zeros_between", "trailing_zeros",
                                  "trailing_garbage", "one_member", "magic_split_at_chunk"])
def test_gzip_members_all_read_the_same_way(case):
    """One member per recorder flush (thousands per log): ISA-L's reader, the lenient loop with
    ISA-L and with zlib give the same bytes; a cut-off member keeps what it holds."""
    from isal import isal_zlib

    full, mems = _members()
    raw = {
        "members": b"".join(mems),
        "cut_mid_member": b"".join(mems)[:-700],
        "zeros_between": b"".join(mems[:100]) + b"\0" * 5000 + b"".join(mems[100:]),
        "trailing_zeros": b"".join(mems) + b"\0" * 100,
        "trailing_garbage": b"".join(mems) + b"garbage",
        "one_member": gzip.compress(full),
        "magic_split_at_chunk": mems[0] + b"\0" * (logio._INFLATE_CHUNK - len(mems[0]) - 1)
        + b"".join(mems[1:]),
    }[case]
    got = logio._decompress("x.csv.gz", raw)
    assert got == logio._inflate_members(raw, zlib) == logio._inflate_members(raw, isal_zlib)
    if case == "cut_mid_member":
        assert full.startswith(got) and len(full) - 20000 < len(got) < len(full)
    else:
        assert got == full


def test_many_members_read_in_linear_time():
    """A 10-hour recorder log has ≈ 36 000 members; handing each member the whole remainder made
    the read quadratic (minutes). Counted, not timed: the bytes copied stay linear."""
    full, mems = _members(40000, 5)   # 8000 members
    raw = b"".join(mems)
    seen = []

    class Counting:
        MAX_WBITS = zlib.MAX_WBITS

        @staticmethod
        def decompressobj(w):
            d = zlib.decompressobj(w)

            class D:
                def decompress(self, data):
                    seen.append(len(data))
                    return d.decompress(data)

                eof = property(lambda self: d.eof)
                unused_data = property(lambda self: d.unused_data)
            return D()

    assert logio._inflate_members(raw, Counting) == full
    assert sum(seen) <= 2 * len(raw) + len(mems) * logio._INFLATE_CHUNK
    assert max(seen) <= logio._INFLATE_CHUNK + 1   # + a byte carried over (a split magic)


def test_arrow_reads_memory_of_its_own_never_a_python_buffer(tmp_path, monkeypatch):
    """Arrow's CSV reader is given a copy in Arrow's own memory, never a buffer over Python's
    bytes: its worker threads may drop the last reference after ``read_csv`` returned, and a
    Python buffer released then needs the GIL — at interpreter exit that aborts the process
    (SIGABRT in ``hookwatch analyze``; Arrow's PyBuffer destructor in the core dump)."""
    seen = []
    real = pcsv.read_csv

    def spy(src, *a, **kw):
        seen.append((isinstance(src, pa.Buffer), src.size, pa.total_allocated_bytes()))
        return real(src, *a, **kw)
    monkeypatch.setattr(pcsv, "read_csv", spy)
    body = "".join(f"{k * 0.02:.2f},0.3,0.6\n" for k in range(5000))
    p = tmp_path / "log.csv"
    p.write_text("t,T1,T2\n" + body)
    t, t1, t2, _ = logio.parse_raw(str(p), p.read_bytes())
    assert t.size == 5000 and t1[0] == 0.3 and t2[-1] == 0.6
    (is_buffer, size, allocated), = seen
    assert is_buffer and size == len(body) and allocated >= size, seen
