"""pymodbus' own Modbus RTU serial server as an independent slave (no code of this project on its
side), the way a commissioning engineer tests against a vendor's meter simulator or a virtual COM
port: ``socat`` joins two pseudo-terminals, pymodbus serves one end in a process of its own, the
gateway (or the probe) reads the other end. The bytes are not paced at any baud: a pty carries a
reply as fast as the server writes it.

``python -m kit.pymodbus_slave PORT UNIT CH1 CH2`` runs the server (holding registers 0–3: the two
channels as big-endian float32, the shipped ZN-S map); :func:`pymodbus_meter` starts socat and the
server and yields the path the gateway opens."""
from __future__ import annotations

import contextlib
import os
import struct
import subprocess
import sys
import time


def _regs(ch1: float, ch2: float) -> list[int]:
    a = struct.unpack(">2H", struct.pack(">f", ch1))
    b = struct.unpack(">2H", struct.pack(">f", ch2))
    return [*a, *b]


def serve(port: str, unit: int, ch1: float, ch2: float) -> None:
    from pymodbus.datastore import ModbusDeviceContext, ModbusSequentialDataBlock, ModbusServerContext
    from pymodbus.server import StartSerialServer

    regs = _regs(ch1, ch2)
    # pymodbus' device context adds 1 to a PDU address (its "register 1" numbering): the block
    # starts at 1 so that PDU address 0 is ch1's first word
    dev = ModbusDeviceContext(hr=ModbusSequentialDataBlock(1, regs + [0] * 12),
                              ir=ModbusSequentialDataBlock(1, regs + [0] * 12))
    print("serving", flush=True)
    StartSerialServer(ModbusServerContext(devices={unit: dev}, single=False), port=port,
                      baudrate=115200)


@contextlib.contextmanager
def pymodbus_meter(tmp_path, unit: int = 1, ch1: float = 0.5, ch2: float = 0.25):
    """socat's pty pair + pymodbus' serial server on one end; yields the other end's path."""
    d = tmp_path / "pymodbus"
    d.mkdir(exist_ok=True)
    server_end, meter_end = str(d / "server"), str(d / "meter")
    logs = [open(d / "socat.log", "w"), open(d / "server.log", "w")]
    socat = subprocess.Popen(["socat", f"pty,raw,echo=0,link={server_end}",
                              f"pty,raw,echo=0,link={meter_end}"],
                             stdout=subprocess.DEVNULL, stderr=logs[0])
    server = None
    try:
        t_end = time.monotonic() + 20
        while not (os.path.exists(server_end) and os.path.exists(meter_end)):
            assert socat.poll() is None and time.monotonic() < t_end, (d / "socat.log").read_text()
            time.sleep(0.05)
        here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        server = subprocess.Popen([sys.executable, "-m", "kit.pymodbus_slave", server_end, str(unit),
                                   repr(ch1), repr(ch2)], cwd=here, stdout=subprocess.PIPE,
                                  stderr=logs[1], text=True)
        assert server.stdout is not None
        line = server.stdout.readline()
        assert line.startswith("serving"), (d / "server.log").read_text()
        time.sleep(0.3)            # the server opens its port after saying so
        yield meter_end
    finally:
        for p in (server, socat):
            if p is not None and p.poll() is None:
                p.terminate()
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(10)
        if server is not None and server.stdout is not None:
            server.stdout.close()
        for f in logs:
            f.close()


if __name__ == "__main__":
    serve(sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4]))
