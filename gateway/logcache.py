"""A binary column cache beside a large log: ``NAME.colcache`` next to ``NAME.csv[.gz]``.

Parsing a 10-hour log (1.8 M rows, 5.4 M decimal numbers) costs about a second; reading the same
three columns back from a binary file costs a few milliseconds. :func:`gateway.logio.read_log`
writes the cache after it has parsed a large log (``MIN_ROWS`` rows or more) and uses it on the
next read **only when it was made from exactly the bytes on disk now**: the cache records the
log's size, modification time and SHA-256, and a cache whose size, mtime or hash differs is
ignored (and rewritten). The hash is always checked (it costs ~10 ms for a 10-hour ``.csv.gz``),
so a log rewritten within the same mtime tick or copied with its mtime kept is never served stale.

Format (versioned by its magic, little-endian; one file, so it is replaced atomically together
with its validation key):

    8 bytes magic ``b"HWCOLS1\\n"`` | 4 bytes header length L (uint32 LE) | L bytes JSON header |
    zero padding to a multiple of 64 | n float64 ``t`` | n float64 ``T1`` | n float64 ``T2``

The JSON header holds ``size``, ``mtime_ns``, ``sha256`` of the source log, ``rows`` and the
log's header ``columns``. The values are the parsed float64 columns, so a read from the cache is
bit-identical to a parse of the text.

Trade-off (bench/README.md): 24 bytes per row on disk (≈ 43 MB beside a 9.4 MB 10-hour
``.csv.gz``), written once per log (≈ 50 ms), for an analysis that skips gunzip and the parse.
A cache that cannot be written (read-only folder, full disk) is simply not written: the read
still succeeds from the text; nor is one written that would leave less than 1 GiB or 10 % of the
file system free (the records folder of a gateway must not fill up with derived files).
``HOOKWATCH_LOG_CACHE=0`` switches the cache off entirely.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import struct
import tempfile

import numpy as np

log = logging.getLogger("hookwatch.logcache")

MAGIC = b"HWCOLS1\n"
#: logs with fewer rows are parsed every time (small logs parse in milliseconds; no clutter)
MIN_ROWS = 100_000
_ALIGN = 64
#: free space a cache write must leave on the file system
RESERVE_BYTES = 1 << 30
RESERVE_FRACTION = 0.10


def enabled() -> bool:
    return os.environ.get("HOOKWATCH_LOG_CACHE", "1").strip().lower() not in ("0", "no", "off", "false")


def cache_path(log_path: str) -> str:
    for ext in (".csv.gz", ".csv"):
        if log_path.endswith(ext):
            return log_path[: -len(ext)] + ".colcache"
    return log_path + ".colcache"


def source_key(path: str, raw: bytes) -> dict:
    """What a cache must match: size, mtime and content hash of the log file as read."""
    st = os.stat(path)
    return {"size": len(raw), "mtime_ns": st.st_mtime_ns, "sha256": hashlib.sha256(raw).hexdigest()}


def load(path: str, key: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]] | None:
    """The columns (t, T1, T2) and header columns from the cache of ``path`` if it exists and
    matches ``key``; None otherwise (missing, stale, truncated, or not a cache)."""
    cp = cache_path(path)
    try:
        with open(cp, "rb") as f:
            head = f.read(12)
            if len(head) != 12 or head[:8] != MAGIC:
                return None
            (hlen,) = struct.unpack("<I", head[8:])
            if hlen > 1 << 20:
                return None
            hdr = json.loads(f.read(hlen).decode("utf-8"))
            if not isinstance(hdr, dict) or any(hdr.get(k) != v for k, v in key.items()):
                return None
            n = int(hdr["rows"])
            columns = [str(c) for c in hdr["columns"]]
            off = _data_offset(hlen)
            f.seek(off)
            data = np.fromfile(f, dtype="<f8", count=3 * n)
    except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError):
        return None
    if data.size != 3 * n:
        return None  # truncated cache
    data = data.reshape(3, n)
    return data[0], data[1], data[2], columns


def _data_offset(hlen: int) -> int:
    return -(-(12 + hlen) // _ALIGN) * _ALIGN


def _room_for(folder: str, nbytes: int) -> bool:
    """True if writing nbytes leaves at least ``RESERVE_BYTES`` and ``RESERVE_FRACTION`` of the
    file system free (a cache must never be what fills a gateway's disk)."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    free = st.f_bavail * st.f_frsize
    total = st.f_blocks * st.f_frsize
    return free - nbytes >= max(RESERVE_BYTES, RESERVE_FRACTION * total)


def store(path: str, key: dict, t: np.ndarray, t1: np.ndarray, t2: np.ndarray,
          columns: list[str]) -> bool:
    """Write the cache beside ``path`` atomically (temp file + rename). False if it could not be
    written; never raises for an I/O problem."""
    cp = cache_path(path)
    need = 3 * 8 * int(t.size) + 4096
    if not _room_for(os.path.dirname(cp) or ".", need):
        log.debug("%s: column cache not written: the disk would fall below its reserve", cp)
        return False
    hdr = json.dumps({**key, "rows": int(t.size), "columns": list(columns)}).encode("utf-8")
    pad = _data_offset(len(hdr)) - 12 - len(hdr)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=".cols-", suffix=".tmp", dir=os.path.dirname(cp) or ".")
        os.chmod(tmp, 0o644)  # readable like the log beside it (mkstemp makes 0600)
        with os.fdopen(fd, "wb") as f:
            f.write(MAGIC + struct.pack("<I", len(hdr)) + hdr + b"\0" * pad)
            for col in (t, t1, t2):
                np.ascontiguousarray(col, dtype="<f8").tofile(f)
        os.replace(tmp, cp)
        tmp = None
        return True
    except OSError as e:
        log.debug("%s: column cache not written: %s", cp, e)
        return False
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass
