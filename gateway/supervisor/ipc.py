"""The supervisor ↔ worker IPC: length-prefixed JSON frames over a Unix socketpair.

One frame on the wire::

    +----------------+---------+------------------------------------+
    | length: u32 BE | type: u8| body: UTF-8 JSON object (length-1) |
    +----------------+---------+------------------------------------+

``length`` counts the type byte and the body (so an empty body is length 1). A body is at most
:data:`MAX_BODY` bytes; a longer (or undecodable) frame is a protocol violation and the peer closes
the connection (the supervisor then treats the worker as crashed). Floats that are not finite are
sent as ``null`` (strict JSON). No pickled objects: either side can be read by any JSON decoder.

Worker → supervisor (the stream; see :class:`FrameChannel` for how it is bounded):

====  ===========  ============================================================================
type  name         body
====  ===========  ============================================================================
1     HELLO        ``{station, pid, proto, software}`` once the worker has loaded (imports,
                   configuration; ``software``: the hookwatch version it runs);
                   it then waits for GO
2     HEARTBEAT    ``{slots, filled, in_test, results, dropped, crashes}`` every 0.5 s, produced
                   *on the station's loop* (a stuck loop sends none: the supervisor's watchdog)
3     STATE        the :class:`~gateway.core.records.StationState` as a mapping (enum → value)
4     SLOTS        a summary of the last ``n`` slots: ``{k, n, filled, valid, mu_mean, t_mean,
                   lateness_ms_max, rtt_ms_max, last: <the last SlotRecord as a mapping>}``;
                   when the supervisor serves outputs for the station (Modbus TCP, console) also
                   ``rows``: every one of those ``n`` slot records as a list of the
                   :data:`SLOT_COLUMNS` values, oldest first (no gap within a frame; a gap between
                   frames means frames were dropped); then a frame is also sent before each EVENT
                   and STATE with the slots so far (``n`` < 10), so records, events and states
                   arrive in the order the station produced them
8     METRICS      the station's metrics snapshot (``gateway/outputs/metrics.py``, shape
                   ``SNAPSHOT_VERSION``) once a second, when the fleet has a metrics endpoint
5     EVENT        :meth:`~gateway.core.records.Event.as_dict`
6     REPLY        ``{id, ok, reason, code, request_id}`` to a COMMAND (``code``: the rejection
                   code of gateway/core/command_rules.py, 0 when accepted)
7     FINAL        ``{stats, results}`` when the worker stops cleanly
9     SITE         ``{topic, payload}``: a retained state/status of a station of the site, for the
                   supervisor's console (its site view, gateway/outputs/console/site.py), from the one
                   worker that carries it (``site`` in ``--served-by-supervisor``); ``payload``
                   is the message's text, cut to the site view's bound + 1 byte (the console
                   refuses it, counted)
====  ===========  ============================================================================

Supervisor → worker (commands flow back):

====  ===========  ============================================================================
16    COMMAND      ``{id, kind, source, args, request_id}`` → ``station.submit`` → REPLY ``id``
17    RELOAD       ``{}``: re-read the station file; the station decides on its own loop;
                   ``{restart: true}``: stop once idle (now, or when its test ends) and exit with
                   75 for a new worker process (new software installed: ``hookwatch config restart``)
18    GO           ``{}``: run the station (at start, once every worker of the fleet has loaded,
                   so no station's slots compete with another worker's start-up)
====  ===========  ============================================================================
"""
from __future__ import annotations

import enum
import json
import math
import operator
import socket
import struct
import threading
from dataclasses import fields
from typing import Any

from ..core.records import Event, EventType, SlotRecord, StationState, TestState
from ..plumbing import safeout
from ..plumbing.threadloop import Mailbox

PROTO = 2
#: the columns of a SLOTS frame's ``rows``: the fields of :class:`~gateway.core.records.SlotRecord`
SLOT_COLUMNS = tuple(f.name for f in fields(SlotRecord))
HEADER = struct.Struct(">IB")
MAX_BODY = 1 << 20


#: the exit code of a worker that ended for the restart the supervisor asked for (new software,
#: RELOAD ``{restart: true}``): started again at once, not counted as a crash (EX_TEMPFAIL)
RESTART_EXIT = 75

class FrameType(enum.IntEnum):
    HELLO = 1
    HEARTBEAT = 2
    STATE = 3
    SLOTS = 4
    EVENT = 5
    REPLY = 6
    FINAL = 7
    METRICS = 8
    SITE = 9
    COMMAND = 16
    RELOAD = 17
    GO = 18


#: SlotRecord fields that are floats (NaN on the wire is ``null``, and back)
_NAN_FIELDS = frozenset(f.name for f in fields(SlotRecord)
                        if f.type in ("float",) and f.name not in ("t",))
_row_of = operator.attrgetter(*SLOT_COLUMNS)
_STATE_FIELDS = frozenset(f.name for f in fields(StationState))


def slot_row(rec: SlotRecord) -> tuple:
    """One slot record as the values of :data:`SLOT_COLUMNS` (a SLOTS frame's ``rows``)."""
    return _row_of(rec)


def slot_from_row(row: list[Any]) -> SlotRecord:
    """The slot record of one ``rows`` entry (``null`` floats back to NaN). Raises ValueError."""
    if len(row) != len(SLOT_COLUMNS):
        raise ValueError(f"slot row of {len(row)} values, expected {len(SLOT_COLUMNS)}")
    d = dict(zip(SLOT_COLUMNS, row))
    for name in _NAN_FIELDS:
        if d[name] is None:
            d[name] = math.nan
    return SlotRecord(**d)


def event_from_dict(d: dict[str, Any]) -> Event:
    """The :class:`Event` of an EVENT frame (``Event.as_dict``). Raises ValueError/KeyError."""
    data = {k: v for k, v in d.items() if k not in ("type", "station", "time", "test_id", "k")}
    return Event(EventType(d["type"]), str(d["station"]), float(d["time"]), d.get("test_id"),
                 d.get("k"), data)


def state_from_dict(d: dict[str, Any]) -> StationState:
    """The :class:`StationState` of a STATE frame (unknown keys are ignored: a newer worker)."""
    kw = {k: v for k, v in d.items() if k in _STATE_FIELDS}
    kw["state"] = TestState(int(kw.get("state", 0)))
    if kw.get("elapsed_s") is None:
        kw["elapsed_s"] = 0.0
    return StationState(**kw)


class ProtocolError(Exception):
    """A frame that breaks the format (too long, unknown type, not a JSON object)."""


def encode(ftype: FrameType, body: dict[str, Any]) -> bytes:
    """One frame: header + strict JSON body (non-finite floats → null)."""
    data = safeout.dumps(body).encode("utf-8")
    if len(data) > MAX_BODY:
        raise ProtocolError(f"frame body of {len(data)} bytes exceeds {MAX_BODY}")
    return HEADER.pack(len(data) + 1, int(ftype)) + data


class FrameDecoder:
    """Incremental decoder: :meth:`feed` bytes, get the complete frames."""

    def __init__(self) -> None:
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[tuple[FrameType, dict[str, Any]]]:
        self._buf += data
        out = []
        while len(self._buf) >= HEADER.size:
            length, t = HEADER.unpack_from(self._buf)
            if length < 1 or length - 1 > MAX_BODY:
                raise ProtocolError(f"frame length {length} out of range")
            if len(self._buf) < HEADER.size - 1 + length:
                break
            body = bytes(self._buf[HEADER.size:HEADER.size - 1 + length])
            del self._buf[:HEADER.size - 1 + length]
            try:
                ftype = FrameType(t)
            except ValueError:
                raise ProtocolError(f"unknown frame type {t}") from None
            try:
                obj = json.loads(body) if body else {}
            except ValueError as e:
                raise ProtocolError(f"frame {ftype.name}: bad JSON: {e}") from None
            if not isinstance(obj, dict):
                raise ProtocolError(f"frame {ftype.name}: body is not a JSON object")
            out.append((ftype, obj))
        return out


def read_frames(sock: socket.socket, decoder: FrameDecoder, bufsize: int = 65536):
    """Blocking: the next batch of frames from ``sock``; [] at EOF (raises ProtocolError)."""
    while True:
        data = sock.recv(bufsize)
        if not data:
            return None
        frames = decoder.feed(data)
        if frames:
            return frames


class FrameChannel:
    """The sending side of one socket: a bounded queue and a writer thread.

    :meth:`send` never blocks and never fails (it is called on a station's slot loop): frames wait
    in a :class:`~gateway.plumbing.threadloop.Mailbox` of ``maxlen`` frames; when the peer does not read
    (a stalled supervisor, a full socket buffer) the oldest frames are dropped and counted in
    :attr:`dropped`. The writer thread sends them in order with blocking ``sendall``."""

    def __init__(self, sock: socket.socket, maxlen: int = 256, name: str = "ipc-writer") -> None:
        self.sock = sock
        self.box: Mailbox[bytes] = Mailbox(maxlen)
        self.sent = 0
        self.closed = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def dropped(self) -> int:
        return self.box.dropped

    def send(self, ftype: FrameType, body: dict[str, Any]) -> bool:
        """Queue a frame; False when an older frame had to be dropped (or the channel is closed)."""
        if self.closed.is_set():
            return False
        return self.box.put_nowait(encode(ftype, body))

    def _run(self) -> None:
        while not self.closed.is_set():
            self.box.wait(0.5)
            for frame in self.box.drain():
                try:
                    self.sock.sendall(frame)
                except OSError:
                    self.closed.set()
                    return
                self.sent += 1

    def flush(self, timeout: float = 2.0) -> None:
        """Send what is queued now from the calling thread (at exit), then stop the writer."""
        self.closed.set()
        self.box.wake()
        self._thread.join(timeout)
        self.sock.settimeout(timeout)
        try:
            for frame in self.box.drain():
                self.sock.sendall(frame)
        except OSError:
            pass

    def send_now(self, ftype: FrameType, body: dict[str, Any], timeout: float = 2.0) -> bool:
        """Send one frame synchronously (after :meth:`flush`; the FINAL frame)."""
        try:
            self.sock.settimeout(timeout)
            self.sock.sendall(encode(ftype, body))
            return True
        except OSError:
            return False
