"""Reading the log interchange format (METHOD.md §9) and its metadata sidecar; the bounded tail
of a JSON-lines record file (:func:`tail_jsonl`: events.jsonl, hooks.jsonl).

A log is ``NAME.csv`` or ``NAME.csv.gz`` with a header line and columns ``t``, ``T1``, ``T2``
(further columns are ignored); its metadata is ``NAME.meta.yaml`` beside it.

Reading never writes anything beside a log (issue 22): a large log is parsed fast instead of
cached. Gunzip runs in ISA-L (``isal``: ≈ 2× zlib's inflate, same bytes; a cut-off or corrupt file
goes through the lenient member loop, and on any ISA-L error zlib inflates it again, whose result
and message are the reference) and the three columns are parsed by Arrow's multi-threaded CSV
reader (``pyarrow.csv``, 3–9× numpy here; its float conversion is correctly rounded —
bit-identical to ``float()`` of the decimal text, checked on 820 k awkward tokens incl. exact
halfway cases; tests/gateway/offline/test_logio_fast.py compares it with the reference parse on every
method vector and a recorder-written log). Anything Arrow will not take exactly as numpy does (a
quoted field, ragged rows, an empty field, ``nan(…)``, non-UTF-8 text, a missing package) falls
back to the reference parser (numpy's loadtxt, forked over two cores for large bodies), which
also finds and names the bad row.

A log the station recorded gets a compact columnar companion ``NAME.cols`` when its test closes
(:mod:`gateway.offline.logcols`: written once, by the recorder's background writer, from this module's
parse of the finished log): :func:`read_log` takes t, T1, T2 from it — bit-identical, ≈ 5× faster
than gunzip + parse of a 10-hour recorder log — when it matches the log's size, mtime_ns and
SHA-256 (and its own CRC); otherwise (none, stale, damaged) it parses the text. Readers never
write one. A ``NAME.colcache`` left by older versions is ignored (never read, never deleted:
deleting it is safe).
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
import sys
import threading
import warnings
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.method.prior import NO_PRIOR, SOURCE_CONFIG, SOURCE_HISTORY, Prior
from ..plumbing import safeyaml
from . import logcols

REQUIRED_COLUMNS = ("t", "T1", "T2")


class LogError(ValueError):
    """Bad log input; the message names the file and the problem."""


@dataclass
class Log:
    path: str
    t: np.ndarray
    t1: np.ndarray
    t2: np.ndarray
    meta: dict[str, Any]
    columns: list[str]


def log_stem(path: str) -> str:
    for ext in (".csv.gz", ".csv"):
        if path.endswith(ext):
            return path[: -len(ext)]
    return path


def sidecar_path(path: str) -> str:
    return log_stem(path) + ".meta.yaml"


#: compressed bytes handed to the inflater at a time by the lenient member loop: what is left of a
#: chunk after a member ends is copied once per member, so it must be small (a recorder log has
#: one member per flush: 36 000 members in 10 hours, ≈ 1.5 kB each)
_INFLATE_CHUNK = 16 << 10


def _inflate_members(raw: bytes, mod: Any) -> bytes:
    """Every gzip member of ``raw``, in order; a member without its end (a log cut off by kill -9)
    gives what it holds; zero bytes between members are skipped (as gzip and ISA-L's reader do);
    anything else after the last member that is not a gzip header is ignored.
    ``mod`` is ``zlib`` or ``isal.isal_zlib``. Linear in the size: the input goes in small chunks
    (handing the whole remainder to each member copies it once per member — quadratic, minutes
    for a 10-hour recorder log)."""
    out: list[bytes] = []
    mv = memoryview(raw)
    n = len(raw)
    pos = 0
    data: bytes | memoryview = b""
    while True:
        while True:
            while len(data) < 2 and pos < n:   # enough for the magic (a chunk may split it)
                data = bytes(data) + mv[pos:pos + _INFLATE_CHUNK]
                pos += _INFLATE_CHUNK
            if bytes(data[:1]) != b"\x00":
                break
            # zero padding between members, skipped as gzip does (a power cut can leave
            # zero-filled blocks; the members after them are kept)
            data = bytes(data).lstrip(b"\x00")
            if not data and pos >= n:
                break
        if bytes(data[:2]) != b"\x1f\x8b":
            break
        d = mod.decompressobj(16 + mod.MAX_WBITS)
        while True:
            out.append(d.decompress(data))
            if d.eof:
                data = d.unused_data
                break
            if pos >= n:                       # member cut off: keep what it held
                return b"".join(out)
            data = mv[pos:pos + _INFLATE_CHUNK]
            pos += _INFLATE_CHUNK
    return b"".join(out)


def _decompress(path: str, raw: bytes) -> bytes:
    if raw[:2] == b"\x1f\x8b":
        try:
            from isal import igzip, isal_zlib  # ISA-L inflate: ≈ 2-3× zlib, same bytes
        except ImportError:
            pass
        else:
            try:
                # a complete file (the common case): members read in C; trailing zeros allowed
                return igzip.decompress(raw)
            except Exception:  # noqa: BLE001 - cut-off member, trailing bytes, corrupt: lenient loop
                pass
            try:
                return _inflate_members(raw, isal_zlib)
            except Exception:  # noqa: BLE001 - corrupt data: zlib below gives the reference message
                pass
        try:
            raw = _inflate_members(raw, zlib)
        except zlib.error as e:
            raise LogError(f"{path}: corrupt gzip data: {e}") from None
    return raw


def read_meta(path: str) -> dict[str, Any]:
    """The sidecar of a log, or {} when there is none (read within :data:`safeyaml.SIDECAR`)."""
    sp = sidecar_path(path)
    if not os.path.exists(sp):
        return {}
    try:
        meta = safeyaml.read(sp, limits=safeyaml.SIDECAR).data
    except safeyaml.YamlError as e:
        raise LogError(f"{sp}: {e.detail()}") from None
    except OSError as e:
        raise LogError(f"{sp}: cannot read: {e.strerror or e}") from None
    if meta is None:
        return {}
    if not isinstance(meta, dict):
        raise LogError(f"{sp}: expected a mapping of metadata keys, got {type(meta).__name__}")
    method = meta.get("method")
    if method is not None and not isinstance(method, dict):
        raise LogError(f"{sp}: method: expected a mapping of parameter names, got {method!r}")
    return meta


def sidecar_prior(meta: dict[str, Any]) -> Prior:
    """The life prior a sidecar records (METHOD.md §5b, §7a): ``method.prior_mean`` and
    ``method.prior_sd``, and beside them ``prior_source`` (``config``, ``history`` or nothing),
    ``prior_n``, ``prior_n_censored`` and ``prior_n_early``. Lenient, as the method reads a log: a prior with an
    SD ≤ 0, only half of one, or values that are not numbers is no prior (source and counts are
    then dropped too)."""
    raw = meta.get("method")
    method: dict[str, Any] = raw if isinstance(raw, dict) else {}

    def num(v: Any) -> float | None:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            return None
        return float(v)

    m, sd = num(method.get("prior_mean")), num(method.get("prior_sd"))
    if m is None or sd is None or not sd > 0:
        return NO_PRIOR
    src = meta.get("prior_source")
    n, nc, ne = meta.get("prior_n"), meta.get("prior_n_censored"), meta.get("prior_n_early")

    def count(v: Any, least: int) -> int | None:
        return v if isinstance(v, int) and not isinstance(v, bool) and v >= least else None

    return Prior(m, sd, src if src in (SOURCE_CONFIG, SOURCE_HISTORY) else None,
                 count(n, 1), count(nc, 0), count(ne, 0))


def _locate_bad_row(path: str, text: str, cols: list[int], ncols: int) -> str:
    """Slow path for a clear message: the first row (file line number) that does not parse."""
    rd = csv.reader(io.StringIO(text))
    for lineno, row in enumerate(rd, start=1):
        if lineno == 1:
            continue
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) < max(cols) + 1:
            return (f"{path}: line {lineno}: expected at least {max(cols) + 1} columns, got {len(row)}: "
                    f"{','.join(row)[:80]!r}")
        for c in cols:
            try:
                float(row[c])
            except ValueError:
                return f"{path}: line {lineno}: column {c + 1} value {row[c][:40]!r} is not a number"
    return f"{path}: unparsable data"


def _fromstring(chunk: str) -> np.ndarray | None:
    """All numbers of a block of complete CSV rows, row by row, flat; None if any field is not a
    number or the rows do not all have the same number of fields. (numpy's C loadtxt parser: a
    third faster than np.fromstring, and correctly rounded like float().)"""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            a = np.loadtxt(io.StringIO(chunk), delimiter=",", dtype=np.float64, ndmin=2,
                           comments=None, encoding=None)
        except (ValueError, UserWarning):
            return None
    return a.ravel()


def _parse_forked(body: str, n_values: int) -> np.ndarray | None:
    """Parse the second half of a large body in a forked child (its result lands in shared
    memory) while this process parses the first half: the text parser holds the GIL, so
    threads would not help. Returns None if anything goes wrong (the caller parses serially)."""
    import mmap

    mid = body.find("\n", len(body) // 2)
    if mid < 0:
        return None
    first, second = body[:mid], body[mid + 1:]
    n2 = second.count(",") + second.count("\n") + 1
    n1 = n_values - n2
    shm = mmap.mmap(-1, max(1, n2 * 8))
    try:
        pid = os.fork()
    except OSError:
        return None
    if pid == 0:  # child: parse, copy into the shared buffer, leave without cleanup
        code = 1
        try:
            a = _fromstring(second)
            if a is not None and a.size == n2:
                np.frombuffer(shm, dtype=np.float64, count=n2)[:] = a
                code = 0
        finally:
            os._exit(code)
    a1 = _fromstring(first)
    _, status = os.waitpid(pid, 0)
    if a1 is None or a1.size != n1 or not os.WIFEXITED(status) or os.WEXITSTATUS(status) != 0:
        return None
    out = np.empty(n_values, dtype=np.float64)
    out[:n1] = a1
    out[n1:] = np.frombuffer(shm, dtype=np.float64, count=n2)
    return out


#: bodies larger than this are parsed on two cores
PARALLEL_PARSE_BYTES = 8 << 20


def _may_fork() -> bool:
    """Fork only from a single-threaded process (forking a threaded one can deadlock the child);
    Arrow's thread pool, once started, is invisible to `threading`: no fork after it either."""
    return (hasattr(os, "fork") and (os.cpu_count() or 1) > 1 and threading.active_count() == 1
            and "pyarrow" not in sys.modules)


def _parse_fast(body: str, ncols: int, cols: list[int]) -> np.ndarray | None:
    """The common case, fast: every row has exactly ``ncols`` numeric fields. Returns None when
    that does not hold (the careful parser then finds what is wrong)."""
    body = body.rstrip()
    nrows = body.count("\n") + 1
    n_values = nrows * ncols
    flat = None
    if len(body) > PARALLEL_PARSE_BYTES and _may_fork():
        flat = _parse_forked(body, n_values)
    if flat is None:
        flat = _fromstring(body)
    if flat is None or flat.size != n_values:
        return None
    return flat.reshape(nrows, ncols)[:, cols]


def _read_raw_stat(path: str) -> tuple[bytes, os.stat_result]:
    """The file's bytes and the fstat of the same open file (the key a companion must match)."""
    try:
        with open(path, "rb") as f:
            st = os.fstat(f.fileno())
            raw = f.read()
    except FileNotFoundError:
        raise LogError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise LogError(f"{path}: is a directory, not a log file") from None
    except OSError as e:
        raise LogError(f"{path}: cannot read: {e.strerror or e}") from None
    return raw, st


def _read_bytes(path: str) -> bytes:
    return _decompress(path, _read_raw_stat(path)[0])


#: field text Arrow reads as a number where the reference parser does not (``nan(123)``)
_ARROW_UNSAFE = b"("


def _arrow_owned(pa: Any, raw: bytes, start: int, end: int) -> Any:
    """``raw[start:end]`` copied into memory of Arrow's own (one memcpy, a few ms for a 10-hour
    log). Never a buffer over Python's bytes (``pa.py_buffer``): Arrow's worker threads may drop
    the last reference to their input after ``read_csv`` returned, and releasing a Python buffer
    needs the GIL — at interpreter exit that thread is ended inside a C++ ``std::thread``, which
    aborts the process (SIGABRT, "terminate called without an active exception"; seen in
    ``hookwatch analyze`` on a loaded box, Arrow's PyBuffer destructor in the core dump)."""
    buf = pa.allocate_buffer(end - start)
    memoryview(buf).cast("B")[:] = memoryview(raw)[start:end]
    return buf


def _parse_arrow(raw: bytes, start: int, end: int, ncols: int, cols: list[int]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """t, T1, T2 of the complete rows ``raw[start:end]`` by Arrow's CSV reader (threads on every core, no
    fork), or None whenever it might not equal the reference parse (the caller then runs it).

    Arrow is configured to accept exactly what numpy's loadtxt accepts for these columns: no
    quoting, no null values (an empty field is an error), every row exactly ``ncols`` fields,
    float64 from the decimal text, correctly rounded."""
    if end <= start or raw.find(_ARROW_UNSAFE, start, end) >= 0:
        return None
    try:
        import pyarrow as pa
        import pyarrow.csv as pcsv
    except ImportError:
        return None
    names = [f"c{i}" for i in range(ncols)]
    want = [names[c] for c in cols]
    try:
        tab = pcsv.read_csv(
            _arrow_owned(pa, raw, start, end),
            read_options=pcsv.ReadOptions(column_names=names, block_size=4 << 20),
            parse_options=pcsv.ParseOptions(quote_char=False, escape_char=False, double_quote=False,
                                            newlines_in_values=False, ignore_empty_lines=True),
            convert_options=pcsv.ConvertOptions(
                include_columns=want, column_types={n: pa.float64() for n in want}, null_values=[],
                true_values=[], false_values=[], strings_can_be_null=False,
                quoted_strings_can_be_null=False))
    except (pa.ArrowException, ValueError):
        return None
    out = []
    for n in want:
        col = tab.column(n)
        if col.null_count:
            return None
        parts = [c.to_numpy(zero_copy_only=False) for c in col.chunks]
        out.append(np.concatenate(parts) if parts else np.empty(0))   # a fresh, writable array
    return out[0], out[1], out[2]


def read_log(path: str, with_meta: bool = True) -> Log:
    """The log at ``path``: columns t, T1, T2 as float64 arrays (every complete row). From its
    companion (:mod:`gateway.offline.logcols`) when one was made from exactly these bytes, else parsed.
    Reads only: nothing is ever written beside the log."""
    raw, st = _read_raw_stat(path)
    got = logcols.load(path, raw, st)
    t, t1, t2, columns = got if got is not None else parse_raw(path, raw)
    meta = read_meta(path) if with_meta else {}
    return Log(path=path, t=t, t1=t1, t2=t2, meta=meta, columns=columns)


def parse_raw(path: str, raw: bytes) -> logcols.Columns:
    """t, T1, T2 and the header columns of the log file's bytes ``raw`` (the text, never a
    companion); LogError names what is wrong."""
    raw = _decompress(path, raw)
    if not raw.isascii():
        try:
            raw.decode("utf-8")
        except UnicodeDecodeError as e:
            raise LogError(f"{path}: not a text CSV file (byte {e.start} is not UTF-8)") from None
    nl = raw.find(b"\n")
    header_line = (raw if nl < 0 else raw[:nl]).decode("utf-8").strip().lstrip("\ufeff")
    if not header_line:
        raise LogError(f"{path}: empty file; expected a header line with columns t,T1,T2")
    columns = [c.strip() for c in header_line.split(",")]
    missing = [c for c in REQUIRED_COLUMNS if c not in columns]
    if missing:
        raise LogError(f"{path}: missing column {missing[0]!r} in header {header_line[:80]!r}; "
                       f"required: t,T1,T2")
    cols = [columns.index(c) for c in REQUIRED_COLUMNS]
    start, end = (len(raw), len(raw)) if nl < 0 else (nl + 1, len(raw))
    # a file cut off mid-row (kill -9 during a write) keeps every complete row
    if end > start and raw[end - 1:end] != b"\n":
        cut = raw.rfind(b"\n", start)
        last = raw[(start if cut < 0 else cut + 1):end]
        if last.count(b",") + 1 < len(columns):
            end = start if cut < 0 else cut + 1
    parsed = _parse_arrow(raw, start, end, len(columns), cols)
    if parsed is not None:
        t, t1, t2 = parsed
    else:
        data = _parse_reference(path, raw.decode("utf-8"), raw[start:end].decode("utf-8"), columns, cols)
        t, t1, t2 = data[:, 0].copy(), data[:, 1].copy(), data[:, 2].copy()
    return t, t1, t2, columns


def write_companion(path: str) -> str:
    """Write the companion of the finished log at ``path`` from the parse of its bytes (so its
    values are exactly what a parse gives). Returns what was done; raises on an I/O error or a
    log that does not parse (the background writer makes that one log line)."""
    raw, st = _read_raw_stat(path)
    if logcols.load(path, raw, st) is not None:
        return "already current"
    t, t1, t2, columns = parse_raw(path, raw)
    if t.size < logcols.MIN_ROWS:
        return f"skipped: {t.size} rows parse fast (fewer than {logcols.MIN_ROWS})"
    key = logcols.key_of(raw, st)
    data = logcols.dumps(key, t, t1, t2, columns)
    now = os.stat(path)
    if now.st_size != st.st_size or now.st_mtime_ns != st.st_mtime_ns:
        return "skipped: the log changed while it was read"
    if not logcols.store(path, data):
        return "skipped: the disk is short of space"
    return f"written ({t.size} rows, {len(data)} bytes)"


def write_companion_later(path: str) -> bool:
    """:func:`write_companion` in the process's one background writer, in a child interpreter
    (the recorder calls this when a test closes). Never blocks, never raises."""
    return logcols.write_in_background(path)


def _parse_reference(path: str, text: str, body: str, columns: list[str], cols: list[int]) -> np.ndarray:
    """The reference parse (numpy): rows × 3 float64, or LogError naming the first bad row."""
    data: np.ndarray | None
    if not body.strip():
        return np.empty((0, 3))
    data = _parse_fast(body, len(columns), cols)
    if data is None:
        try:
            data = np.loadtxt(io.StringIO(body), delimiter=",", usecols=cols, ndmin=2,
                              dtype=np.float64, comments=None)
        except ValueError:
            raise LogError(_locate_bad_row(path, text, cols, len(columns))) from None
    return data


def finite_or_none(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


#: last lines read of a file kept as JSON lines (events.jsonl, hooks.jsonl)
TAIL_LINES = 10_000
#: longest line read of such a file (hooks.jsonl lines are ≤ 4 KiB; events are small)
TAIL_LINE_BYTES = 16 * 1024


def tail_jsonl(path: str, max_lines: int = TAIL_LINES,
               max_line_bytes: int = TAIL_LINE_BYTES) -> tuple[list[dict[str, Any]], int]:
    """The last ``max_lines`` lines of a JSON-lines file as objects, oldest first, and how many
    lines were damaged (not JSON, not an object, longer than ``max_line_bytes``: skipped). Reads
    at most ``max_lines × max_line_bytes`` bytes from the end; a missing file is ``([], 0)``."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            budget = max_lines * (max_line_bytes + 1)
            start = max(0, size - budget)
            f.seek(start)
            data = f.read(size - start)
    except FileNotFoundError:
        return [], 0
    lines = data.split(b"\n")
    if start > 0:
        lines = lines[1:]            # the first line is cut by the read window
    lines = [ln for ln in lines if ln.strip()][-max_lines:]
    out, bad = [], 0
    for ln in lines:
        if len(ln) > max_line_bytes:
            bad += 1
            continue
        try:
            v = json.loads(ln.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            bad += 1
            continue
        if isinstance(v, dict):
            out.append(v)
        else:
            bad += 1
    return out, bad
