"""The shipped systemd units set a file-descriptor limit that covers the connection caps of the
Modbus TCP server (issue 12), and docs/limits.md states the caps the code uses."""
import os
import re

from conftest import ROOT
from gateway.core.command_intake import MAX_DEPTH, MAX_PAYLOAD_BYTES
from gateway.outputs.broker.outbox_reserve import RESERVE_MAX_ROWS
from gateway.outputs.plc.modbus_tcp import tcp_server as S
from gateway.station.recorder import MAX_PENDING_ROWS

#: descriptors one station holds at most: 2 serial ports, outbox (db, wal, shm), recorder (log,
#: events, a result/sidecar being written), MQTT socket
PER_STATION = 2 + 3 + 3 + 1
#: what a box must handle: 64 stations, 4 Modbus TCP ports, the interpreter's own
BUDGET = 64 * PER_STATION + 4 * (S.MAX_CONNECTIONS + 1) + 64


def test_units_set_limitnofile_above_the_budget():
    for unit in ("hookwatch@.service", "hookwatch-fleet.service"):
        with open(os.path.join(ROOT, "deploy", "systemd", unit)) as f:
            text = f.read()
        m = re.search(r"^LimitNOFILE=(\d+)(?::(\d+))?$", text, re.M)
        assert m, f"{unit}: no LimitNOFILE"
        assert int(m.group(1)) >= BUDGET, (unit, m.group(1), BUDGET)


def test_limits_page_states_the_caps_the_code_uses():
    with open(os.path.join(ROOT, "docs", "limits.md")) as f:
        doc = f.read()
    for value in (f"| {S.MAX_CONNECTIONS} |", f"| {S.MAX_PER_CLIENT} |", f"{int(S.IDLE_TIMEOUT_S)} s",
                  f"{MAX_PAYLOAD_BYTES} bytes", f"{MAX_DEPTH} levels", f"{MAX_PENDING_ROWS:,}",
                  f"{RESERVE_MAX_ROWS:,}"):
        assert value in doc, value
