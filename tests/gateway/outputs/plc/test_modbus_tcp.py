"""Issue 12, item 6 (and 10: holding register 0): the own Modbus TCP server in layers — the MBAP
framer and the PDU codec as pure functions, then raw sockets against a real server: pipelined
requests in one segment, a request split over segments, function 0x15, count 0, unknown
functions, connection caps and the idle timeout, 1,100 idle sockets against a server whose
process has a low file-descriptor limit (`ulimit -n`), networks in `allowed_clients`."""
import dataclasses
import logging
import os
import resource
import socket
import struct
import subprocess
import sys
import time

import pytest

from conftest import HERE
from gateway.outputs.plc import registers as R
from gateway.outputs.plc.modbus_tcp import tcp_server as S
from gateway.outputs.plc.modbus_tcp.framer import FrameError, Framer, encode
from gateway.outputs.plc.modbus_tcp.pdu import Exc, decode
from gateway.outputs.plc.server import ModbusOutput, ModbusSettings, shutdown_all
from kit.northbound import LoopThread, RunningStation, make_station, mbpoll
from kit.tools import free_port, require_tool, wait_for

IR, HR = R.IR, R.HR


# ------------------------------------------------------------------ pure layers
def test_framer_splits_pipelined_frames_and_joins_split_ones():
    a, b = encode(1, 3, b"\x04\x00\x00\x00\x02"), encode(2, 3, b"\x03\x00\x00\x00\x01")
    f = Framer()
    assert [(x.tid, x.unit, x.pdu) for x in f.feed(a + b)] == [(1, 3, a[7:]), (2, 3, b[7:])]
    out = []
    for i in range(len(a + b)):
        out += f.feed((a + b)[i:i + 1])
    assert [x.tid for x in out] == [1, 2] and f.pending == 0
    with pytest.raises(FrameError):
        Framer().feed(struct.pack(">HHHB", 1, 7, 6, 1) + b"\x03\x00\x00\x00\x01")
    with pytest.raises(FrameError):
        Framer().feed(struct.pack(">HHHB", 1, 0, 60000, 1))


def test_pdu_serves_only_the_documented_functions_with_standard_codes():
    for fc in (1, 2, 5, 8, 15, 17, 20, 21, 22, 24, 43, 0x41, 0x83):
        assert decode(bytes([fc]) + b"\x00" * 6) == Exc.ILLEGAL_FUNCTION, fc
    assert decode(b"\x03\x00\x00\x00\x00") == Exc.ILLEGAL_VALUE               # count 0
    assert decode(b"\x04\x00\x00\x00\x7e") == Exc.ILLEGAL_VALUE               # count 126
    assert decode(b"\x03\x00\x00") == Exc.ILLEGAL_VALUE                       # short
    assert decode(b"\x10\x00\x00\x00\x02\x03\x00\x01\x00") == Exc.ILLEGAL_VALUE   # byte count
    r = decode(b"\x10\x00\x01\x00\x02\x04\x00\x01\x00\x02")
    assert (r.fc, r.write_addr, r.values) == (16, 1, (1, 2))
    r = decode(b"\x17\x00\x00\x00\x02\x00\x03\x00\x01\x02\x00\x05")
    assert (r.read_addr, r.read_count, r.write_addr, r.values) == (0, 2, 3, (5,))


def test_allowed_clients_match_networks():
    o = ModbusOutput(ModbusSettings("x", writes_enabled=True,
                                    allowed_clients=("10.10.5.0/24", "192.168.1.7", "fd00::/8")))
    assert o.may_write("10.10.5.77") and o.may_write("192.168.1.7") and o.may_write("fd00::1")
    assert not o.may_write("10.10.6.1") and not o.may_write("192.168.1.8") and not o.may_write(None)
    assert o.may_write("::ffff:10.10.5.1")
    assert not ModbusOutput(ModbusSettings("y", writes_enabled=False,
                                           allowed_clients=("0.0.0.0/0",))).may_write("10.0.0.1")


# ------------------------------------------------------------------ a real server, raw sockets
@pytest.fixture(scope="module")
def server():
    require_tool("mbpoll")
    import tempfile
    tmp = tempfile.mkdtemp(prefix="hw-mbtcp-")
    port = free_port()
    lt = LoopThread()
    from pathlib import Path
    s = make_station(Path(tmp), [], station_id="st3")
    s.outputs.append(ModbusOutput(ModbusSettings("st3", port=port, unit_id=3, writes_enabled=True,
                                                 allowed_clients=("127.0.0.0/30",)), s))
    run = RunningStation(lt, s)
    wait_for(lambda: mbpoll(port, "-t", "3", "-r", str(IR["map_version"].address), unit=3)[0] == 0, 20,
             what="server up")
    yield port, s
    run.stop()
    lt.close()
    shutdown_all()


def _req(tid, unit, pdu):
    return encode(tid, unit, pdu)


def _recv_frames(sock, n, timeout=5.0):
    sock.settimeout(timeout)
    f, out = Framer(), []
    while len(out) < n:
        data = sock.recv(4096)
        if not data:
            break
        out += f.feed(data)
    return out


def _ask(port, pdu, unit=3, src="127.0.0.1"):
    with socket.create_connection(("127.0.0.1", port), timeout=5, source_address=(src, 0)) as s:
        s.sendall(_req(7, unit, pdu))
        fr, = _recv_frames(s, 1)
        return fr.pdu


def test_pipelined_requests_in_one_segment_are_answered_in_order(server):
    port, _ = server
    reqs = b"".join(_req(100 + i, 3, struct.pack(">BHH", 4, IR["map_version"].address, 1 + i % 3))
                    for i in range(20))
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        s.sendall(reqs)                       # one segment (loopback MSS ≫ 240 bytes)
        frames = _recv_frames(s, 20)
    assert [f.tid for f in frames] == list(range(100, 120))
    assert all(f.pdu[0] == 4 and f.pdu[1] == 2 * (1 + i % 3) for i, f in enumerate(frames))
    assert struct.unpack(">H", frames[0].pdu[2:4])[0] == R.MAP_VERSION


def test_a_request_split_over_segments_is_answered(server):
    port, _ = server
    req = _req(9, 3, struct.pack(">BHH", 4, IR["map_version"].address, 1))
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        for part in (req[:3], req[3:8], req[8:]):
            s.sendall(part)
            time.sleep(0.05)
        fr, = _recv_frames(s, 1)
    assert fr.tid == 9 and struct.unpack(">H", fr.pdu[2:4])[0] == R.MAP_VERSION


def test_exception_codes_and_no_traceback_for_malformed_0x15(server, caplog):
    port, st = server
    caplog.set_level(logging.DEBUG, logger="hookwatch.modbus")
    assert _ask(port, b"\x03\x00\x00\x00\x00") == b"\x83\x03"            # count 0
    assert _ask(port, b"\x04\x00\x00\x00\x00") == b"\x84\x03"
    assert _ask(port, b"\x41\x00\x00") == b"\xc1\x01"                     # unknown function
    for fc in (0x08, 0x2B, 0x11, 0x01, 0x05):                               # diagnostics, identification, coils
        assert _ask(port, bytes([fc]) + b"\x00\x00\x00\x01") == bytes([0x80 | fc, 1])
    # write file record (0x15): malformed and well-formed, from a client that may write or not
    for body in (b"\x15\x03\x06", b"\x15\x09\x06\x00\x01\x00\x00\x00\x01\x12\x34"):
        for src in ("127.0.0.1", "127.0.0.9"):
            assert _ask(port, body, src=src) == b"\x95\x01"
    assert _ask(port, b"\x03\x00\x00\x00\x01", unit=99) == b"\x83\x0b"    # unknown unit
    assert _ask(port, struct.pack(">BHH", 4, R.INPUT_SIZE - 1, 2)) == b"\x84\x02"
    # a write from an address outside allowed_clients (127.0.0.0/30): refused with 01
    assert _ask(port, b"\x06\x00\x00\x00\x03", src="127.0.0.9") == b"\x86\x01"
    assert not any(r.exc_info for r in caplog.records)
    assert "Traceback" not in caplog.text


def test_holding_register_0_reads_back_0_after_a_command(server):
    port, st = server
    # ack without an alarm: the station refuses for its state (exception 03, reason code in last_result)
    assert _ask(port, b"\x06\x00\x00\x00\x03") == b"\x86\x03"
    assert _ask(port, b"\x03\x00\x00\x00\x01") == b"\x03\x02\x00\x00"
    rc, v, err = mbpoll(port, "-t", "3", "-r", str(IR["last_command"].address), "-c", "2", unit=3)
    assert rc == 0 and v[IR["last_command"].address] == 3 and v[IR["last_command"].address + 1] == 3


def test_connection_caps_and_idle_timeout(server, monkeypatch):
    port, _ = server
    srv = None
    from gateway.outputs.plc.server import _SERVERS
    srv = next(s for (h, p), s in _SERVERS.items() if p == port).server
    monkeypatch.setattr(srv.door, "limits", dataclasses.replace(srv.door.limits, idle_timeout_s=1.0))
    idle = [socket.create_connection(("127.0.0.1", port), timeout=5, source_address=("127.0.0.2", 0))
            for _ in range(S.MAX_PER_CLIENT + 5)]
    try:
        wait_for(lambda: srv.connections >= S.MAX_PER_CLIENT, 5, what="connections")
        time.sleep(0.3)
        assert srv.connections == S.MAX_PER_CLIENT       # the rest were closed at once
        # another client address is still served
        assert _ask(port, b"\x04\x00\x01\x00\x01")[:2] == b"\x04\x02"
        wait_for(lambda: srv.connections == 0, 10, what="idle connections closed")
    finally:
        for s in idle:
            s.close()


CHILD = r"""
import resource, sys, time
sys.path.insert(0, sys.argv[2])
resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))
from pathlib import Path
from gateway.outputs.plc.server import ModbusOutput, ModbusSettings
from kit.northbound import LoopThread, RunningStation, make_station
lt = LoopThread()
s = make_station(Path(sys.argv[3]), [], station_id="fd")
s.outputs.append(ModbusOutput(ModbusSettings("fd", port=int(sys.argv[1]), unit_id=1), s))
RunningStation(lt, s)
print("ready", flush=True)
time.sleep(600)
"""


def test_1100_idle_sockets_under_a_low_fd_limit_do_not_lock_out_the_plc(tmp_path):
    require_tool("mbpoll")
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < 1300:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(max(hard, 1300), hard), hard))
    if resource.getrlimit(resource.RLIMIT_NOFILE)[0] < 1200:
        pytest.skip("cannot open 1,100 sockets in the test process")
    port = free_port()
    env = dict(os.environ)
    p = subprocess.Popen([sys.executable, "-c", CHILD, str(port), HERE, str(tmp_path)],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    socks = []
    try:
        assert p.stdout.readline().strip() == "ready", p.stderr.read()
        wait_for(lambda: mbpoll(port, "-t", "3", "-r", "1", unit=1)[0] == 0, 20, what="server up")
        for i in range(1100):
            try:
                socks.append(socket.create_connection(("127.0.0.1", port), timeout=2,
                                                      source_address=(f"127.0.{1 + i // 250}.{2 + i % 250}", 0)))
            except OSError:
                pass
        time.sleep(1.5)                  # idle long enough to be evicted for a new connection
        assert p.poll() is None
        # the PLC gets in (on a loaded machine the server may still be accepting the last idle
        # sockets, which evict the PLC's fresh connection in turn: it tries again, as a PLC does)
        wait_for(lambda: mbpoll(port, "-t", "3", "-r", "1", unit=1)[0] == 0, 30, 0.5,
                 what="the PLC served among 1,100 idle sockets")
        for _ in range(3):
            rc, v, err = mbpoll(port, "-t", "3", "-r", str(IR["map_version"].address), unit=1)
            assert rc == 0 and v[IR["map_version"].address] == R.MAP_VERSION, err
    finally:
        for s in socks:
            s.close()
        p.kill()
        p.wait()
        p.stdout.close()
        p.stderr.close()


def test_the_allowed_plc_finds_room_against_busy_connections_and_a_trickler_is_closed(tmp_path):
    """Issue 21: 72 connections from other addresses that keep reading (busy, never idle) hold
    every slot they can get; mbpoll, as the PLC in ``allowed_clients``, still reads (slots kept for
    the allow-list). A client that trickles one byte of a request every 0.4 s is closed at the
    request deadline although it never stops sending."""
    import threading

    from gateway.plumbing.doors import DoorLimits
    require_tool("mbpoll")
    port = free_port()
    lt = LoopThread()
    s = make_station(tmp_path, [], station_id="plc")
    s.outputs.append(ModbusOutput(ModbusSettings("plc", port=port, unit_id=1, allowed_clients=("127.0.0.1",),
                                                 door=DoorLimits(64, request_timeout_s=2.0, idle_timeout_s=3.0)), s))
    run = RunningStation(lt, s)
    busy: list[socket.socket] = []
    stop = threading.Event()
    try:
        wait_for(lambda: mbpoll(port, "-t", "3", "-r", "1", unit=1)[0] == 0, 20, what="server up")
        from gateway.outputs.plc.server import _SERVERS
        srv = _SERVERS[("127.0.0.1", port)].server
        req = _req(1, 1, struct.pack(">BHH", 4, IR["map_version"].address, 1))
        for i in range(72):
            try:
                c = socket.create_connection(("127.0.0.1", port), timeout=5,
                                             source_address=(f"127.0.1.{10 + i // 9}", 0))
            except OSError:
                continue
            busy.append(c)

        def keep_busy():
            while not stop.is_set():
                for c in list(busy):
                    try:
                        c.sendall(req)
                        c.settimeout(1.0)
                        if not c.recv(64):
                            busy.remove(c)
                            c.close()
                    except OSError:
                        busy.remove(c)
                        c.close()
                stop.wait(0.02)
        t = threading.Thread(target=keep_busy, daemon=True)
        t.start()
        time.sleep(2.0)                   # every slot the others may take is taken, and busy
        served = sum(1 for _ in busy)
        assert srv.connections >= 64 - S.RESERVED_FOR_ALLOWED, srv.connections
        assert served <= 64 - S.RESERVED_FOR_ALLOWED < 72
        for _ in range(3):
            rc, v, err = mbpoll(port, "-t", "3", "-r", str(IR["map_version"].address), unit=1)
            assert rc == 0 and v[IR["map_version"].address] == R.MAP_VERSION, err
        assert len(busy) >= 64 - S.RESERVED_FOR_ALLOWED - 1    # the busy ones were not thrown out for it
        stop.set()
        t.join(5)
        for c in busy:
            c.close()
        busy.clear()
        # a trickler: one byte of a request every 0.4 s is closed at the 2 s request deadline
        with socket.create_connection(("127.0.0.1", port), timeout=5, source_address=("127.0.2.1", 0)) as tr:
            t0 = time.monotonic()
            closed_at = None
            for i in range(40):
                try:
                    tr.sendall(req[i % len(req):i % len(req) + 1])
                    tr.settimeout(0.4)
                    if tr.recv(64) == b"":
                        closed_at = time.monotonic() - t0
                        break
                except TimeoutError:
                    continue
                except OSError:
                    closed_at = time.monotonic() - t0
                    break
            # closed by the server (its request timeout: how soon is the machine's, not asserted)
            assert closed_at is not None, closed_at
        assert srv.store.counters["request_timeouts"] >= 1
    finally:
        stop.set()
        for c in busy:
            c.close()
        run.stop()
        lt.close()
        shutdown_all()
