"""Issue 21: one station process (``hookwatch run STATION.yaml``) as deployed, under
``prlimit --nofile=512:512``, with the console, the metrics endpoint and a Modbus TCP port:
2,500 idle connections to the console and 800 to the metrics endpoint. The station keeps
recording (its log grows), its test ends and its result file is written (the recorder finds its
descriptors: the reserve), mbpoll reads, and once the flood reaches its request deadline the
console and the metrics endpoint answer again; no traceback in the log. On today's main the
console takes every descriptor."""
import os
import socket

import pytest
import yaml

from conftest import hookwatch_cmd
from kit.e2e import METER_MAP, SHORT_METHOD, test_dirs, virtual_station
from kit.northbound import mbpoll
from kit.proc import Proc
from kit.tools import connect_many, free_port, http_status, require_tool, wait_for, wait_port

NOFILE = 512


@pytest.mark.timeout(400)
def test_idle_floods_leave_a_station_process_its_reserve(tmp_path):
    require_tool("mbpoll")
    require_tool("prlimit")
    cport, mport, pport = free_port(), free_port(), free_port()
    flood: list[socket.socket] = []
    with virtual_station(tmp_path, "config/scenarios/quick.yaml") as (_sim, links):
        cfg = {"station": {"id": "st"}, "meter": {"port": links["meter"], "map": METER_MAP},
               "stm32": {"port": links["stm32"]}, "method": SHORT_METHOD,
               "control": {"dead_band_n": 0.01},
               "test": {"sample_id": "S-1", "t_set_n": 0.5, "t_end_s": 40, "autostart": True},
               "recorder": {"dir": str(tmp_path / "records")},
               "console": {"enabled": True, "listen": [f"127.0.0.1:{cport}"],
                           "users_file": str(tmp_path / "users.json"),
                           "connections": {"request_timeout_s": 2.0}},
               "metrics": {"enabled": True, "port": mport, "connections": {"request_timeout_s": 2.0}},
               "modbus_tcp": {"enabled": True, "port": pport, "writes": {"allowed_clients": ["127.0.0.1"]}}}
        path = tmp_path / "st.yaml"
        path.write_text(yaml.safe_dump(cfg))
        gw = Proc(["prlimit", f"--nofile={NOFILE}:{NOFILE}", "--", *hookwatch_cmd(), "run", str(path)],
                  str(tmp_path / "gw.log"))
        try:
            wait_port(cport, 30)
            wait_port(mport, 30)
            wait_for(lambda: len(test_dirs(tmp_path, "st")) == 1, 60, what="the test")
            (d,) = test_dirs(tmp_path, "st")
            log_gz = os.path.join(d, "log.csv.gz")
            flood += connect_many(cport, 2500)
            flood += connect_many(mport, 800, within_s=10)
            assert len(flood) > NOFILE
            assert gw.p.poll() is None, gw.log()
            size = os.path.getsize(log_gz)
            wait_for(lambda: os.path.getsize(log_gz) > size, 30, what="the log grows (recording)")
            rc, _v, err = mbpoll(pport, "-t", "3", "-r", "1", unit=1)
            assert rc == 0, err
            # the test ends: its result is written although the flood still holds its sockets
            wait_for(lambda: os.path.exists(os.path.join(d, "result.json")), 120,
                     what=f"result.json; log:\n{gw.log()}")
            wait_for(lambda: http_status(f"http://127.0.0.1:{cport}/api/fleet") == 200, 30, what="the console answers")
            wait_for(lambda: http_status(f"http://127.0.0.1:{mport}/metrics") == 200, 30, what="metrics answer")
            assert gw.p.poll() is None
            log = gw.log_all()
            assert "Traceback" not in log, log[-4000:]
        finally:
            for s in flood:
                s.close()
            gw.stop()
