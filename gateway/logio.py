"""Reading the log interchange format (METHOD.md §9) and its metadata sidecar.

A log is ``NAME.csv`` or ``NAME.csv.gz`` with a header line and columns ``t``, ``T1``, ``T2``
(further columns are ignored); its metadata is ``NAME.meta.yaml`` beside it.
"""
from __future__ import annotations

import csv
import io
import math
import os
import threading
import warnings
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import logcache, safeyaml
from .method.prior import NO_PRIOR, SOURCE_CONFIG, SOURCE_HISTORY, Prior

#: a log file smaller than this is never looked up in the cache (cannot hold MIN_ROWS rows)
_CACHE_MIN_BYTES = 256 << 10

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


def _read_raw(path: str) -> bytes:
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except FileNotFoundError:
        raise LogError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise LogError(f"{path}: is a directory, not a log file") from None
    except OSError as e:
        raise LogError(f"{path}: cannot read: {e.strerror or e}") from None
    return raw


def _decompress(path: str, raw: bytes) -> bytes:
    if raw[:2] == b"\x1f\x8b":
        # the recorder writes one gzip member per flush; a log cut off by kill -9 (older
        # recorders: one stream) has no trailer: keep what decompresses
        out, rest = [], raw
        try:
            while rest[:2] == b"\x1f\x8b":
                d = zlib.decompressobj(16 + zlib.MAX_WBITS)
                out.append(d.decompress(rest))
                rest = d.unused_data
        except zlib.error as e:
            raise LogError(f"{path}: corrupt gzip data: {e}") from None
        raw = b"".join(out)
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
    ``method.prior_sd``, and beside them ``prior_source`` (``config``, ``history`` or nothing) and
    ``prior_n``. Lenient, as the method reads a log: a prior with an SD ≤ 0, only half of one, or
    values that are not numbers is no prior (source and n are then dropped too)."""
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
    n = meta.get("prior_n")
    return Prior(m, sd, src if src in (SOURCE_CONFIG, SOURCE_HISTORY) else None,
                 n if isinstance(n, int) and not isinstance(n, bool) and n > 0 else None)


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


def _parse_fast(body: str, ncols: int, cols: list[int]) -> np.ndarray | None:
    """The common case, fast: every row has exactly ``ncols`` numeric fields. Returns None when
    that does not hold (the careful parser then finds what is wrong)."""
    body = body.rstrip()
    nrows = body.count("\n") + 1
    n_values = nrows * ncols
    flat = None
    # fork only from a single-threaded process (forking a threaded one can deadlock the child)
    if (len(body) > PARALLEL_PARSE_BYTES and hasattr(os, "fork") and (os.cpu_count() or 1) > 1
            and threading.active_count() == 1):
        flat = _parse_forked(body, n_values)
    if flat is None:
        flat = _fromstring(body)
    if flat is None or flat.size != n_values:
        return None
    return flat.reshape(nrows, ncols)[:, cols]


def _read_bytes(path: str) -> bytes:
    return _decompress(path, _read_raw(path))


def _recorded_here(path: str, meta: dict) -> bool:
    """True when the log's sidecar says hookwatch recorded it (``software: hookwatch …``)."""
    if not meta:
        try:
            meta = read_meta(path)
        except Exception:  # noqa: BLE001 - no readable sidecar: not one of ours
            return False
    return str(meta.get("software", "")).startswith("hookwatch")


def read_log(path: str, with_meta: bool = True) -> Log:
    """The log at ``path``: columns t, T1, T2 as float64 arrays (every complete row; see
    :mod:`gateway.logcache` for the validated binary cache used for large logs)."""
    raw = _read_raw(path)
    key = None
    if logcache.enabled() and len(raw) >= _CACHE_MIN_BYTES:
        try:
            key = logcache.source_key(path, raw)
        except OSError:
            key = None
        hit = logcache.load(path, key) if key is not None else None
        if hit is not None:
            t, t1, t2, columns = hit
            meta = read_meta(path) if with_meta else {}
            return Log(path=path, t=t, t1=t1, t2=t2, meta=meta, columns=columns)
    raw = _decompress(path, raw)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise LogError(f"{path}: not a text CSV file (byte {e.start} is not UTF-8)") from None
    nl = text.find("\n")
    header_line = (text if nl < 0 else text[:nl]).strip().lstrip("\ufeff")
    if not header_line:
        raise LogError(f"{path}: empty file; expected a header line with columns t,T1,T2")
    columns = [c.strip() for c in header_line.split(",")]
    missing = [c for c in REQUIRED_COLUMNS if c not in columns]
    if missing:
        raise LogError(f"{path}: missing column {missing[0]!r} in header {header_line[:80]!r}; "
                       f"required: t,T1,T2")
    cols = [columns.index(c) for c in REQUIRED_COLUMNS]
    body = "" if nl < 0 else text[nl + 1:]
    # a file cut off mid-row (kill -9 during a write) keeps every complete row
    if body and not body.endswith("\n"):
        cut = body.rfind("\n")
        last = body[cut + 1:]
        if len(last.split(",")) < len(columns):
            body = body[: cut + 1]
    data: np.ndarray | None
    if not body.strip():
        data = np.empty((0, 3))
    else:
        data = _parse_fast(body, len(columns), cols)
        if data is None:
            try:
                data = np.loadtxt(io.StringIO(body), delimiter=",", usecols=cols, ndmin=2,
                                  dtype=np.float64, comments=None)
            except ValueError:
                raise LogError(_locate_bad_row(path, text, cols, len(columns))) from None
    meta = read_meta(path) if with_meta else {}
    lg = Log(path=path, t=data[:, 0].copy(), t1=data[:, 1].copy(), t2=data[:, 2].copy(),
             meta=meta, columns=columns)
    # the cache goes only beside logs that hookwatch recorded (their sidecar names the software):
    # a log from elsewhere (a colleague's share, the method vectors) is read, never written beside
    if key is not None and lg.t.size >= logcache.MIN_ROWS and _recorded_here(path, meta):
        logcache.store(path, key, lg.t, lg.t1, lg.t2, columns)
    return lg


def finite_or_none(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x
