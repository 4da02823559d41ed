"""Issue 21, item 4: a flood of refused PLC writes and commands is a bounded number of log lines
and ``command_rejected`` events, each with its count (gateway/plumbing/ratelog.py, the station's refusal
gate in gateway/station/command_desk.py). 3,000 refused writes by `mbpoll` (the PLC) against a
running station: 1,500 `stop` commands the station refuses (no test running: code 2; once the
PLC's budget is spent — refused commands cost it too, issue 34 — code 14) and 1,500 setpoints out
of range (exception 03)."""
import logging
import re
import subprocess
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

from gateway.core.records import EventType
from gateway.outputs.plc import registers as R
from gateway.outputs.plc.server import ModbusOutput, ModbusSettings, shutdown_all
from gateway.plumbing import ratelog
from kit.fakes import Capture
from kit.northbound import LoopThread, RunningStation, make_station, mbpoll
from kit.tools import free_port, require_tool, wait_for

N = 1500            # of each kind
WINDOW_S = 5.0      # the refusal window of this test (60 s by default: HW_REFUSAL_WINDOW_S)
COUNT = re.compile(r"\(×(\d+)")


def _flood(port: int) -> list[tuple[int, str]]:
    """Every write once, by 4 PLC processes at a time: (exit code, what mbpoll said)."""
    exe = require_tool("mbpoll")
    base = [exe, "-m", "tcp", "-p", str(port), "-a", "7", "-0", "-1", "-o", "5"]
    stop = base + ["-t", "4", "-r", str(R.HR["command"].address), "127.0.0.1", str(R.COMMAND_CODE["stop"])]
    t_set = base + ["-t", "4:float", "-B", "-r", str(R.HR["t_set"].address), "127.0.0.1", "9.0"]

    def one(i: int) -> tuple[int, str]:
        p = subprocess.run(stop if i % 2 else t_set, capture_output=True, timeout=60, text=True)
        return p.returncode, p.stderr.strip()

    with ThreadPoolExecutor(4) as ex:
        return list(ex.map(one, range(2 * N)))


def test_3000_refused_plc_writes_are_a_few_log_lines_and_events_with_counts(tmp_path, caplog, monkeypatch):
    monkeypatch.setattr(ratelog, "WINDOW_S", WINDOW_S)
    port = free_port()
    lt = LoopThread()
    cap = Capture()
    s = make_station(tmp_path, [cap], station_id="st7")
    s.outputs.append(ModbusOutput(ModbusSettings("st7", port=port, unit_id=7, writes_enabled=True,
                                                 allowed_clients=("127.0.0.1",)), s))
    run = RunningStation(lt, s)
    caplog.set_level(logging.INFO, logger="hookwatch")
    try:
        wait_for(lambda: mbpoll(port, "-t", "3", "-r", "0", unit=7)[0] == 0, 20, what="the server")
        caplog.clear()
        t0 = time.monotonic()
        rcs = _flood(port)
        elapsed = time.monotonic() - t0
        assert len(rcs) == 2 * N and all(rc != 0 for rc, _ in rcs)     # every write refused
        # … by the gateway, with a Modbus exception (not a connection the door closed or a
        # timeout: each reached the server, so each is in the counts below)
        not_refused = Counter(err for _, err in rcs if "register failed: " not in err)
        assert not not_refused, not_refused

        def refusal_events():
            return [e for e in cap.events if e.type == EventType.COMMAND_REJECTED]

        def modbus_lines():     # this station's (a worker's earlier tests may log beside it)
            return [m for r in caplog.records if r.name == "hookwatch.modbus"
                    and (m := r.getMessage()).startswith("st7: ")]

        # the counts of the last windows come when they end
        # (bounds against a hang, not speed goals: 20 s once ran out with 4 test workers on 2 cores)
        wait_for(lambda: sum(e.data["count"] for e in refusal_events()) == N, WINDOW_S + 60,
                 what="the refused commands counted in events")
        def counted():
            return sum(int(COUNT.search(m).group(1)) for m in modbus_lines() if COUNT.search(m))
        try:
            wait_for(lambda: counted() == 2 * N, WINDOW_S + 60, what="the refused writes counted in log lines")
        except AssertionError as e:
            raise AssertionError(f"{e}: {counted()} of {2 * N}; {modbus_lines()}") from None
        evs = refusal_events()
        lines = modbus_lines()
        windows = elapsed / WINDOW_S + 2
        # per kind: one line (one event) as a window opens, one with the count as it ends; the
        # refused stops are two kinds (code 2, then 14 once the budget is spent)
        assert len(evs) <= 2 * 2 * windows and len(evs) < N / 10, len(evs)
        assert all(e.data["command"] == "stop" and e.data["code"] in (2, 14) and e.data["count"] >= 1
                   and e.data["source"] == "plc:127.0.0.1" for e in evs)
        # the first refusals of the burst were the station's state's (2), the rest the budget's
        assert sum(e.data["count"] for e in evs if e.data["code"] == 2) >= 20
        # the server's lines: three kinds (the t_set writes, the stops refused 2 and 14)
        assert len(lines) <= 2 * 3 * windows and len(lines) < N / 10, lines[:10]
        assert all(COUNT.search(m) for m in lines), [m for m in lines if not COUNT.search(m)][:3]
        assert any("t_set" in m for m in lines) and any("stop" in m for m in lines)
        # and the whole gateway log of the flood is bounded too (the station logs its events)
        assert len([r for r in caplog.records if r.name.startswith("hookwatch")]) < N / 5
        # the station still answers, and a good command is carried out
        assert s.monitor is None
        rc, _, err = mbpoll(port, "-t", "4:float", "-B", "-r", str(R.HR["t_set"].address), unit=7, values=[0.45])
        assert rc == 0, err
        wait_for(lambda: abs(s.default_plan.t_set - 0.45) < 1e-6, 10, what="the setpoint")
    finally:
        run.stop()
        lt.close()
        shutdown_all()
