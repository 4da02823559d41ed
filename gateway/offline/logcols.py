"""A compact columnar companion of a finished log: ``NAME.cols`` beside ``NAME.csv[.gz]``.

Written ONCE, by the recorder when a test closes (:func:`gateway.offline.logio.write_companion_later`),
by one background writer per process; read by :func:`gateway.offline.logio.read_log` (so by
``hookwatch analyze``, reports, recovery) instead of gunzipping and parsing the text — **only when
it was made from exactly the bytes on disk now**: it records the log's size, ``mtime_ns`` and
SHA-256, and a companion whose key differs (the log appended to, rewritten, touched, copied
without its mtime) or that is damaged (any bit: a CRC-32 covers everything after the magic; each
column is a checked deflate stream of the exact expected length) is ignored, never trusted, and
never rewritten by a reader. Readers never write anything beside a log.

The values are the float64 columns t, T1, T2 that the parse of the finished log gives (the writer
builds it from that parse), so a read from the companion is bit-identical to a parse of the text.

Encoding, per column, whichever exact candidate deflates smallest on a sample of the column (each
is verified bit for bit against the whole column before it is chosen, NaN payloads and signed
zeros included):

* ``dec`` — every value is ``i / 10**k`` for integers ``i`` (the recorder's ``t``: ``%.4f``):
  the integers delta-coded (int32 when they fit, else int64), byte-shuffled, deflated;
* ``f32`` — every value is a float32 widened (the meter's T1/T2, written as ``repr``): the
  float32 bits byte-shuffled, deflated;
* ``f64`` — anything: the float64 bits byte-shuffled, deflated.

On a 10-hour recorder log that is 3.96 bytes per row (t ``dec4`` 0.95, T1/T2 ``f32`` 1.39/1.62;
plain shuffled float64 would be 7.8 B/row, the ``.csv.gz`` is 31.3 B/row), decoded in ≈ 0.1 s;
see bench/README.md.

File layout (little-endian): ``b"HWCOLS2\\n"`` | uint32 header length H | H bytes JSON header |
the column streams | uint32 CRC-32 of everything between the magic and it. The header holds the
log's key (``size``, ``mtime_ns``, ``sha256``), ``rows``, the log's header ``columns`` and, per
column, its encoding and stream length.

Writing is bounded: one writer thread per process, which builds one companion at a time in a child
interpreter at nice 10 (the station's interpreter never runs the build: no GIL taken from the slot
loop), each within :data:`BUILD_TIMEOUT_S`, fed through a :class:`~gateway.plumbing.threadloop.Mailbox` of
at most :data:`MAX_PENDING` logs (when full, the oldest waiting log is skipped with a log line: it
keeps its text, only the companion is not made); nothing is written that would leave less than
:data:`RESERVE_BYTES` or :data:`RESERVE_FRACTION` of the file system free; any failure (read-only
folder, full disk, a log that does not parse) is one log line, never an exception into the
caller. ``HOOKWATCH_LOG_COLS=0`` switches writing off (a companion already written is still used).
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import struct
import subprocess
import sys
import threading
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np

from ..plumbing.safeout import write_atomic
from ..plumbing.threadloop import Mailbox

_inflater: Any = zlib
try:
    from isal import isal_zlib  # ISA-L inflate: same bytes as zlib, ≈ 2× faster
    _inflater = isal_zlib
except ImportError:  # pragma: no cover - isal is a dependency; zlib reads the same streams
    pass

log = logging.getLogger("hookwatch.logcols")

MAGIC = b"HWCOLS2\n"
SUFFIX = ".cols"
#: the free space a companion must leave on the file system (the records folder of a gateway must
#: never fill up with derived files): at least this many bytes …
RESERVE_BYTES = 1 << 30
#: … and at least this fraction of the file system
RESERVE_FRACTION = 0.10
#: logs with fewer rows get no companion (10 minutes at 50 Hz: they parse in tens of milliseconds)
MIN_ROWS = 30_000
#: logs waiting for their companion in one process; beyond, the oldest is skipped (one log line each)
MAX_PENDING = 16
#: a companion header larger than this is not one
MAX_HEADER = 64 << 10
#: seconds one companion may take to build (a 10-hour log: ≈ 4 s); then its child is killed
BUILD_TIMEOUT_S = 600.0
#: deflate level of the column streams (decoding speed does not depend on it)
LEVEL = 6
_COLS = ("t", "T1", "T2")
Columns = tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]


def companion_path(log_path: str) -> str:
    for ext in (".csv.gz", ".csv"):
        if log_path.endswith(ext):
            return log_path[: -len(ext)] + SUFFIX
    return log_path + SUFFIX


def writing_enabled() -> bool:
    return os.environ.get("HOOKWATCH_LOG_COLS", "1").strip().lower() not in ("0", "no", "off", "false")


def key_of(raw: bytes, st: os.stat_result) -> dict[str, Any]:
    """What a companion must match: the log file's size, mtime_ns and SHA-256 (of ``raw``, the
    file's bytes as read, ``st`` its fstat)."""
    return {"size": len(raw), "mtime_ns": st.st_mtime_ns, "sha256": hashlib.sha256(raw).hexdigest()}


# -- encoding -------------------------------------------------------------------------------------

def _shuffle(a: np.ndarray) -> bytes:
    w = a.dtype.itemsize
    return np.ascontiguousarray(a).view(np.uint8).reshape(-1, w).T.tobytes()


def _unshuffle(b: bytes, n: int, dtype: str) -> np.ndarray:
    w = np.dtype(dtype).itemsize
    return np.frombuffer(b, np.uint8).reshape(w, n).T.copy().view(dtype).ravel()


def _dec_values(ints: np.ndarray, k: int) -> np.ndarray:
    return ints.astype(np.float64) / (10.0 ** k)


def _candidates(a: np.ndarray) -> list[tuple[dict[str, Any], bytes]]:
    """(description, raw stream before deflate) of every exact encoding of ``a``."""
    out: list[tuple[dict[str, Any], bytes]] = []
    ref = a.tobytes()
    if a.size and bool(np.isfinite(a).all()):
        for k in range(10):
            s = np.rint(a * 10.0 ** k)
            if float(np.abs(s).max()) >= 2.0 ** 53:
                break
            ints = s.astype(np.int64)
            if _dec_values(ints, k).tobytes() != ref:
                continue
            d = np.diff(ints, prepend=np.int64(0))
            dt = "<i4" if d.size == 0 or (int(d.min()) >= -(2 ** 31) and int(d.max()) < 2 ** 31) else "<i8"
            out.append(({"enc": "dec", "k": k, "dtype": dt}, _shuffle(d.astype(dt))))
            break
    f32 = a.astype("<f4")
    if f32.astype(np.float64).tobytes() == ref:
        out.append(({"enc": "f32", "dtype": "<f4"}, _shuffle(f32)))
    out.append(({"enc": "f64", "dtype": "<f8"}, _shuffle(a.astype("<f8"))))
    return out


def _encode(a: np.ndarray) -> tuple[dict[str, Any], bytes]:
    with np.errstate(all="ignore"):               # overflow in a candidate only rules it out
        cands = _candidates(np.ascontiguousarray(a, dtype=np.float64))
    if len(cands) > 1 and a.size:
        # the smallest on a sample (every 16th block of 4096 values), then only that one in full
        n = a.size

        def sample(desc: dict[str, Any], stream: bytes) -> int:
            w = np.dtype(desc["dtype"]).itemsize
            planes = np.frombuffer(stream, np.uint8).reshape(w, n)
            idx = np.concatenate([np.arange(i, min(i + 4096, n)) for i in range(0, n, 16 * 4096)])
            return len(zlib.compress(planes[:, idx].tobytes(), 1))
        cands.sort(key=lambda c: sample(*c))
    desc, stream = cands[0]
    return desc, zlib.compress(stream, LEVEL)


def _decode(desc: dict[str, Any], blob: bytes, n: int) -> np.ndarray | None:
    enc, dt = desc.get("enc"), desc.get("dtype")
    if dt not in ("<i4", "<i8", "<f4", "<f8"):
        return None
    want = n * np.dtype(dt).itemsize
    d = _inflater.decompressobj()
    raw = d.decompress(blob, want + 1)       # bounded: never more than the expected length
    if len(raw) != want or not d.eof or d.unused_data:
        return None
    vals = _unshuffle(raw, n, dt)
    if enc == "dec" and dt in ("<i4", "<i8"):
        k = desc.get("k")
        if not isinstance(k, int) or not 0 <= k < 10:
            return None
        return _dec_values(np.cumsum(vals, dtype=np.int64), k)
    if enc == "f32" and dt == "<f4":
        return vals.astype(np.float64)
    if enc == "f64" and dt == "<f8":
        return vals.astype(np.float64)       # a fresh, writable, native array
    return None


def dumps(key: dict[str, Any], t: np.ndarray, t1: np.ndarray, t2: np.ndarray, columns: list[str]) -> bytes:
    """The companion file's bytes for the parsed columns of a log with ``key``."""
    n = int(t.size)
    encs, blobs = [], []
    for name, a in zip(_COLS, (t, t1, t2)):
        if a.size != n:
            raise ValueError("columns of different lengths")
        desc, z = _encode(a)
        encs.append({"name": name, **desc, "len": len(z)})
        blobs.append(z)
    hdr = json.dumps({**key, "rows": n, "columns": list(columns), "enc": encs}).encode()
    body = struct.pack("<I", len(hdr)) + hdr + b"".join(blobs)
    return MAGIC + body + struct.pack("<I", zlib.crc32(body))


def load(log_path: str, raw: bytes, st: os.stat_result) -> Columns | None:
    """t, T1, T2 and the header columns from the companion of ``log_path`` if it exists, is
    intact and was made from exactly ``raw`` (the log file's bytes now, ``st`` their fstat);
    None otherwise. Never raises, never writes."""
    cp = companion_path(log_path)
    try:
        with open(cp, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            if size < len(MAGIC) + 8 or size > 4 * len(raw) + (1 << 20):
                return None
            data = f.read(size + 1)
    except OSError:
        return None
    try:
        if len(data) != size or data[:len(MAGIC)] != MAGIC:
            return None
        body = data[len(MAGIC):-4]
        if struct.unpack("<I", data[-4:])[0] != zlib.crc32(body):
            return None                               # damaged
        (hlen,) = struct.unpack("<I", body[:4])
        if hlen > MAX_HEADER or 4 + hlen > len(body):
            return None
        hdr = json.loads(body[4:4 + hlen].decode())
        if not isinstance(hdr, dict) or hdr.get("size") != len(raw) or hdr.get("mtime_ns") != st.st_mtime_ns:
            return None                               # stale: the log changed
        n, columns, encs = hdr.get("rows"), hdr.get("columns"), hdr.get("enc")
        if (not isinstance(n, int) or n < 0 or not isinstance(columns, list)
                or not all(isinstance(c, str) for c in columns)
                or not isinstance(encs, list) or len(encs) != 3 or not all(isinstance(e, dict) for e in encs)):
            return None
        lens = [e.get("len") for e in encs]
        if not all(isinstance(x, int) and x >= 0 for x in lens) or 4 + hlen + sum(lens) != len(body):
            return None
        # the hash (≈ 50 ms for a 10-hour log) runs beside the decoding: both release the GIL
        digest: list[str] = []
        hasher = threading.Thread(target=lambda: digest.append(hashlib.sha256(raw).hexdigest()),
                                  name="logcols-sha256", daemon=True)
        hasher.start()
        out: list[np.ndarray] = []
        pos = 4 + hlen
        for e, ln in zip(encs, lens):
            a = _decode(e, body[pos:pos + ln], n)
            if a is None:
                break
            out.append(a)
            pos += ln
        hasher.join()
        if len(out) != 3 or digest != [hdr.get("sha256")]:
            return None                               # damaged, or same size and mtime, other bytes
    except (ValueError, TypeError, KeyError, UnicodeDecodeError, zlib.error, struct.error, MemoryError):
        return None
    except Exception:  # noqa: BLE001 - isal's errors: a companion is never trusted, never fatal
        return None
    return out[0], out[1], out[2], [str(c) for c in columns]


def room_for(folder: str, nbytes: int) -> bool:
    """True if writing ``nbytes`` leaves at least :data:`RESERVE_BYTES` and
    :data:`RESERVE_FRACTION` of the file system free."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return False
    free = st.f_bavail * st.f_frsize
    total = st.f_blocks * st.f_frsize
    return free - nbytes >= max(RESERVE_BYTES, RESERVE_FRACTION * total)


def store(log_path: str, data: bytes) -> bool:
    """Write the companion of ``log_path`` atomically (:func:`safeout.write_atomic`). False if the
    disk is short of space; an I/O error is raised (the temporary file is removed)."""
    cp = companion_path(log_path)
    folder = os.path.dirname(cp) or "."
    if not room_for(folder, len(data)):
        return False
    write_atomic(cp, data, make_dir=False, tmp_suffix=f".{os.getpid()}.tmp")
    return True


# -- the one background writer of a process ------------------------------------------------------
#
# The thread only waits: the build (gunzip, parse, encode: ≈ 4 s of CPU for a 10-hour log) runs in
# a child interpreter at nice 10. In-thread it would hold the GIL in many short C calls (copies,
# casts, the text checks) and delay the station's slot loop by up to 50 ms (measured); a child
# cannot touch the station's interpreter at all.

#: the child's code: ``argv`` is the log, then this process's limits (one definition: here)
_CHILD = ("import sys; from gateway.offline import logcols, logio; "
          "sys.exit(logcols.child_main(sys.argv[1:], logio.write_companion))")


def child_main(argv: list[str], build: Callable[[str], str]) -> int:
    """The child's main: ``LOG RESERVE_BYTES RESERVE_FRACTION MIN_ROWS``; prints what was done,
    or one line on stderr and exit 1."""
    global RESERVE_BYTES, RESERVE_FRACTION, MIN_ROWS
    with contextlib.suppress(OSError):
        os.nice(10)                                   # below every station thread
    try:
        path = argv[0]
        RESERVE_BYTES, RESERVE_FRACTION, MIN_ROWS = int(argv[1]), float(argv[2]), int(argv[3])
        print(build(path))
        return 0
    except Exception as e:  # noqa: BLE001 - the parent logs this one line
        msg = getattr(e, "strerror", None) or str(e) or type(e).__name__
        print(f"{type(e).__name__}: {msg}".replace("\n", " ")[:300], file=sys.stderr)
        return 1


def _build_in_child(path: str) -> tuple[bool, str]:
    size = os.path.getsize(path)
    if size < MIN_ROWS:               # a row takes more than one byte even deflated: a short test
        return True, f"skipped: {size} bytes cannot hold {MIN_ROWS} rows"
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = dict(os.environ)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    p = subprocess.run([sys.executable, "-P", "-c", _CHILD, path, str(RESERVE_BYTES), repr(RESERVE_FRACTION),
                        str(MIN_ROWS)], stdin=subprocess.DEVNULL, capture_output=True, text=True,
                       errors="replace", env=env, timeout=BUILD_TIMEOUT_S, check=False)
    if p.returncode == 0:
        return True, (p.stdout.strip().splitlines() or ["done"])[-1][:300]
    return False, (p.stderr.strip().splitlines() or [f"exit status {p.returncode}"])[-1][:300]


class CompanionWriter:
    """The background writer of a process: one thread that builds one companion at a time, fed
    through a :class:`~gateway.plumbing.threadloop.Mailbox` of at most ``max_pending`` logs.

    What waits may be dropped: a companion is derived from its log, which stays on disk whatever
    happens here (a reader without one parses the text). So the producer (the recorder closing a
    test, on the station's thread) never waits: when ``max_pending`` logs already wait, the
    mailbox drops the oldest of them (one warning line naming it) and keeps the newest, the one a
    report or ``hookwatch analyze`` will read next."""

    def __init__(self, max_pending: int = MAX_PENDING) -> None:
        self.box: Mailbox[str] = Mailbox(max_pending, on_drop=self._skipped)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._busy = 0                        # logs waiting or being built
        self._idle = threading.Event()
        self._idle.set()

    def _skipped(self, path: str) -> None:
        log.warning("%s: companion not written: %d newer logs waiting", companion_path(path), self.box.maxlen)

    def start(self) -> None:
        """Start the writer thread if it does not run (raises if no thread can be started)."""
        with self._lock:
            if self._thread is None or not self._thread.is_alive():
                self._thread = threading.Thread(target=self._run, name="logcols", daemon=True)
                self._thread.start()

    def submit(self, log_path: str) -> None:
        """Queue ``log_path``; never blocks (when full, the oldest waiting log is dropped)."""
        with self._lock:
            if self.box.put_nowait(log_path):
                self._busy += 1               # else one went out for this one: as many as before
            self._idle.clear()

    def _run(self) -> None:
        while True:
            self.box.wait()
            for path in self.box.take():
                try:
                    ok, what = _build_in_child(path)
                    if ok:
                        log.info("%s: %s", companion_path(path), what)
                    else:
                        log.warning("%s: companion not written: %s", companion_path(path), what)
                except Exception as e:  # noqa: BLE001 - one line, never an exception into the station
                    log.warning("%s: companion not written: %s", companion_path(path),
                                (getattr(e, "strerror", None) or str(e) or type(e).__name__)[:200])
                finally:
                    with self._lock:
                        self._busy -= 1
                        if self._busy == 0:
                            self._idle.set()

    def wait_idle(self, timeout: float) -> bool:
        """Wait until no companion is queued or being written."""
        return self._idle.wait(timeout)


_writer = CompanionWriter()


def write_in_background(log_path: str) -> bool:
    """Queue the log for the process's one writer thread (which builds its companion in a child
    interpreter, :func:`gateway.offline.logio.write_companion`). Never blocks, never raises; False if it
    was not queued (writing switched off, or no thread can be started)."""
    if not writing_enabled():
        return False
    try:
        _writer.start()
        _writer.submit(log_path)
        return True
    except Exception as e:  # noqa: BLE001 - e.g. no thread can be started: the log stays as it is
        log.warning("%s: companion not written: %s", companion_path(log_path), e)
    return False


def wait_idle(timeout: float) -> bool:
    """Wait until no companion is queued or being written (tests, a clean shutdown)."""
    return _writer.wait_idle(timeout)
