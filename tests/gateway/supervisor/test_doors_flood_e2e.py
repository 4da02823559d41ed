"""Issue 21: the descriptor budget of a fleet supervisor as deployed. ``hookwatch run FLEET_DIR``
under ``prlimit --nofile=512:512`` (soft = hard: nothing to raise) with the console, the metrics
endpoint and a Modbus TCP port; 2,500 idle connections to the console, 800 to the metrics endpoint
and 100 to the PLC port from other addresses. Then: the supervisor lives, a killed worker
restarts (its socketpair finds a descriptor: the reserve), the restarted station starts a new test
and writes its log, mbpoll (the allowed PLC) reads, and once the idle connections reach their
request deadline the console and the metrics endpoint answer again. On today's main the console
takes every descriptor and the supervisor dies at the worker's restart (``socketpair``: EMFILE)."""
import os
import signal
import socket

import pytest
import yaml

from conftest import hookwatch_cmd
from kit.e2e import fleet_dir, test_dirs, virtual_station, worker_pids
from kit.northbound import mbpoll
from kit.proc import Proc
from kit.tools import connect_many, free_port, http_status, require_tool, wait_for, wait_port

NOFILE = 512


@pytest.mark.timeout(400)
def test_idle_floods_leave_the_supervisor_its_reserve(tmp_path):
    require_tool("mbpoll")
    require_tool("prlimit")
    mport, pport = free_port(), free_port()
    fleet = fleet_dir(tmp_path, control={"dead_band_n": 0.01},
                      test={"t_end_s": 70, "autostart": True},
                      console={"enabled": True, "listen": ["127.0.0.1:0"],
                               "users_file": str(tmp_path / "users.json"),
                               "connections": {"request_timeout_s": 2.0}},
                      metrics={"enabled": True, "port": mport,
                               "connections": {"request_timeout_s": 2.0}},
                      modbus_tcp={"enabled": True, "port": pport,
                                  "writes": {"allowed_clients": ["127.0.0.1"]}})
    flood: list[socket.socket] = []
    with virtual_station(tmp_path, "config/scenarios/quick.yaml") as (_sim, links):
        (fleet / "stations" / "fl.yaml").write_text(yaml.safe_dump({
            "station": {"id": "fl"}, "meter": {"port": links["meter"]},
            "stm32": {"port": links["stm32"]}, "test": {"sample_id": "S-fl"}}))
        gw = Proc(["prlimit", f"--nofile={NOFILE}:{NOFILE}", "--", *hookwatch_cmd(), "run", str(fleet)],
                  str(tmp_path / "gw.log"))
        try:
            url = gw.readline_until("console:", timeout=30).rstrip("/")
            wait_port(mport, 30)
            wait_for(lambda: len(test_dirs(tmp_path, "fl")) == 1, 60, what="the first test")
            (pid,) = worker_pids(gw, "fl")
            cport = int(url.rsplit(":", 1)[1])

            flood += connect_many(cport, 2500)
            flood += connect_many(mport, 800, within_s=10)
            flood += connect_many(pport, 100, src="127.0.3", within_s=10)
            assert len(flood) > NOFILE                 # more than the process could ever hold
            assert gw.p.poll() is None, gw.log()

            # a killed worker restarts: the supervisor's socketpair finds its descriptors
            os.kill(pid, signal.SIGKILL)
            wait_for(lambda: len(worker_pids(gw, "fl")) == 2, 60, what=f"worker restarted; log:\n{gw.log()}")
            assert gw.p.poll() is None

            # the restarted station starts a new test and writes its log
            wait_for(lambda: len(test_dirs(tmp_path, "fl")) == 2, 60, what="a new test")
            new = test_dirs(tmp_path, "fl")[-1]
            log_gz = os.path.join(new, "log.csv.gz")
            wait_for(lambda: os.path.exists(log_gz) and os.path.getsize(log_gz) > 0, 30, what="its log")
            size = os.path.getsize(log_gz)
            wait_for(lambda: os.path.getsize(log_gz) > size, 30, what="the log grows (recording)")

            # the PLC (allowed client) reads
            for _ in range(3):
                rc, v, err = mbpoll(pport, "-t", "3", "-r", "1", unit=1)
                assert rc == 0, err

            # the flood's idle connections reach their deadline: console and metrics answer again
            wait_for(lambda: http_status(url + "/api/fleet") == 200, 30, what="the console answers")
            wait_for(lambda: http_status(f"http://127.0.0.1:{mport}/metrics") == 200, 30, what="metrics answer")
            log = gw.log_all()
            assert "Traceback" not in log
            assert log.count("refused") < 40, log[-4000:]          # rate-limited lines, not one per socket
            assert gw.p.poll() is None
        finally:
            for s in flood:
                s.close()
            gw.stop()
