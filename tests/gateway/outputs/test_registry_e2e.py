"""Issue 35 item 1 end to end: a new output is ONE row of the output registry. A toy plug-in
output (tests/kit/toy_output.py, ``HOOKWATCH_OUTPUTS=kit.toy_output``: its module registers its
row, its section ``toy:`` comes with it) runs in a real ``hookwatch run`` against ``hookwatch
sim``: in one process (a station file) and in a fleet (a supervisor and a worker process, the
supervisor serving the toy for the station's proxy). Either way it gets every slot record, is
rebuilt on SIGHUP when its section changes, and ``hookwatch check --probe`` checks its door
(free before the gateway runs, in use while it does)."""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess

import yaml

from conftest import ROOT, hookwatch_cmd
from kit.e2e import fleet_dir, station_yaml, virtual_station
from kit.proc import Proc
from kit.tools import free_port, wait_for

SCENARIO = "config/scenarios/quick.yaml"


def _env() -> dict[str, str]:
    return {**os.environ, "HOOKWATCH_OUTPUTS": "kit.toy_output",
            "PYTHONPATH": os.pathsep.join([os.path.join(ROOT, "tests"), os.environ.get("PYTHONPATH", "")])}


def _ask(port: int) -> dict | None:
    """What the toy output tells on its door (None while nothing listens there)."""
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            f = s.makefile("rb")
            line = f.readline()
    except OSError:
        return None
    return json.loads(line) if line else None


def _probe(path: str) -> str:
    """``hookwatch check --probe`` of a station file or fleet folder, as a user runs it."""
    p = subprocess.run(hookwatch_cmd() + ["check", "--probe", path], capture_output=True, text=True,
                       cwd=ROOT, env=_env(), timeout=120)
    return p.stdout + p.stderr


def _retag(path, tag: str) -> None:
    with open(path) as f:
        doc = yaml.safe_load(f)
    doc["toy"]["tag"] = tag
    with open(path, "w") as f:
        yaml.safe_dump(doc, f)


def _slots_then_reload(gw: Proc, port: int, station_file, pid: int) -> None:
    """The toy output, built in process ``pid``, counts the station's slot records with none
    missing (none lost on their way to it); a change of its section and SIGHUP rebuild it."""
    first = wait_for(lambda: (r := _ask(port)) and r["n"] >= 100 and r, timeout=60,
                     what="the toy's first 100 slot records")
    assert first["pid"] == pid and first["tag"] == "one", (first, gw.log())
    assert first["gaps"] == first["lost"] == 0, first
    assert first["last"] - first["first"] + 1 == first["n"], first
    _retag(station_file, "two")
    gw.p.send_signal(signal.SIGHUP)
    second = wait_for(lambda: (r := _ask(port)) and r["tag"] == "two" and r["n"] >= 50 and r,
                      timeout=60, what="the toy rebuilt with its new section")
    assert second["pid"] == pid and second["instance"] > first["instance"], (first, second)
    # (in a fleet the worker's station restarts with the new file too: its slots count from 0 again)
    assert second["gaps"] == second["lost"] == 0, second


def test_a_toy_output_in_one_row_runs_in_one_process(tmp_path):
    port = free_port()
    with virtual_station(tmp_path, SCENARIO) as (_sim, links):
        st = station_yaml(tmp_path, links, name="toy1",
                          extra={"toy": {"enabled": True, "port": port, "tag": "one"}})
        out = _probe(st)
        assert f"toy.port: 127.0.0.1:{port} is free to listen on." in out, out
        gw = Proc(hookwatch_cmd() + ["run", st], str(tmp_path / "gw.log"), env=_env())
        try:
            _slots_then_reload(gw, port, st, gw.p.pid)
            out = _probe(st)
            assert f"toy.port: 127.0.0.1:{port} is already in use" in out, out
        finally:
            gw.stop()


def test_a_toy_output_in_one_row_is_served_by_a_fleet_supervisor(tmp_path):
    """In a fleet the supervisor builds the toy for the station's proxy (the row says ``box``),
    and the worker streams every slot record to it (``slot_rows``); its section's change
    rebuilds it there on SIGHUP (``reload``)."""
    port = free_port()
    fleet = fleet_dir(tmp_path)
    with virtual_station(tmp_path, SCENARIO) as (_sim, links):
        st = fleet / "stations" / "toy2.yaml"
        st.write_text(yaml.safe_dump({"station": {"id": "toy2"}, "meter": {"port": links["meter"]},
                                      "stm32": {"port": links["stm32"]},
                                      "toy": {"enabled": True, "port": port, "tag": "one"}}))
        gw = Proc(hookwatch_cmd() + ["run", str(fleet)], str(tmp_path / "gw.log"), env=_env())
        try:
            _slots_then_reload(gw, port, st, gw.p.pid)
        finally:
            gw.stop()
