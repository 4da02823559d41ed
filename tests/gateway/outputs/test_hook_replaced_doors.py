"""`hook_replaced` (issue 20) from the MES (mosquitto_pub on cmd/hook_replaced, the reply and the
events seen by mosquitto_sub), from the PLC (mbpoll writes the new hook's sample id into the
holding registers, then command code 5) and from the CLI (`hookwatch hooks STATION.yaml
--replaced`, which also lists the life log), through the one intake: the running test ends with
end_reason hook_replaced, one line per replacement goes to hooks.jsonl with who did it, and a
hostile sample id is refused with a clear reason and changes nothing."""
import json
import os
import subprocess
import time

import yaml

from conftest import ROOT, hookwatch_cmd
from gateway.outputs.plc import registers as R
from gateway.station.command_desk import CODE
from gateway.station.hook_log import read_hooks
from kit.broker import pub, station_on_broker
from kit.northbound import mbpoll
from kit.tools import free_port, require_tool, wait_for

BASE = "hookwatch/lab/hall/l1/hr"
HR = R.HR


def test_hook_replaced_from_the_mes_and_the_plc(tmp_path):
    require_tool("mbpoll")
    mport = free_port()
    with station_on_broker(tmp_path, BASE, "hr", modbus_port=mport) as (_b, sub, st, lt):
        async def start():
            st.start_test(st.default_plan, "test")
        lt.call(start())
        wait_for(lambda: st.session is not None and st.state.elapsed_s > 0.2, 30, what="a running test")
        old_test = st.test_id

        # the MES, hostile first: refused with a reason, nothing changes
        pub(_b.port, f"{BASE}/cmd/hook_replaced", json.dumps({"sample_id": "A\u0000B", "request_id": "bad"}))
        bad = sub.wait(lambda s: [m for m in s.messages("reply") if m[2]["request_id"] == "bad"], 20,
                       what="the refusal")[0][2]
        assert not bad["ok"] and bad["code"] == CODE["SAMPLE_ID"] and "sample_id" in bad["reason"]
        assert st.test_id == old_test and read_hooks(str(tmp_path / "records" / "hr")) == []

        # … then the replacement: the test ends (its result says why), the replacement is logged
        pub(_b.port, f"{BASE}/cmd/hook_replaced", json.dumps({"sample_id": "S-2", "request_id": "r1"}))
        ok = sub.wait(lambda s: [m for m in s.messages("reply") if m[2]["request_id"] == "r1"], 20,
                      what="the reply")[0][2]
        assert ok["ok"], ok
        res = sub.wait(lambda s: s.messages("result"), 20, what="the result")[-1][2]
        assert res["test_id"] == old_test and res["end_reason"] == "hook_replaced"
        ev = sub.wait(lambda s: s.messages("event/hook_replaced"), 20, what="event/hook_replaced")[0][2]
        assert ev["data"]["old_sample_id"] == "S-0" and ev["data"]["new_sample_id"] == "S-2"
        assert ev["data"]["test_id"] == old_test and ev["data"]["logged"] is True

        # the PLC: the new hook's sample id into the holding registers, then code 5
        regs = R.encode_value(HR["sample_id"], "S-3")
        rc, _, err = mbpoll(mport, "-t", "4", "-r", str(HR["sample_id"].address), values=regs)
        assert rc == 0, err
        rc, _, err = mbpoll(mport, "-t", "4", "-r", str(HR["command"].address),
                            values=(R.COMMAND_CODE["hook_replaced"],))
        assert rc == 0, err
        wait_for(lambda: len(read_hooks(str(tmp_path / "records" / "hr"))) == 2, 20,
                 what="the PLC's replacement logged")
        rc, v, err = mbpoll(mport, "-t", "3", "-r", str(R.IR["last_result"].address))
        assert rc == 0 and v[R.IR["last_result"].address] == 0, (v, err)

        # the CLI: a refusal is a clear message and exit 1, then the replacement
        yml = tmp_path / "hr.yaml"
        yml.write_text(yaml.safe_dump({
            "station": {"id": "hr", "site": "lab", "area": "hall", "line": "l1"},
            "meter": {"port": "/dev/ttyHR0", "map": os.path.join(ROOT, "config", "meters", "zn-s.yaml")},
            "stm32": {"port": "/dev/ttyHR1"}, "recorder": {"dir": str(tmp_path / "records")},
            "mqtt": {"enabled": True, "port": _b.port}}))
        p = subprocess.run(hookwatch_cmd() + ["hooks", str(yml), "--replaced", "--grade", "nope"],
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 1 and "grade" in p.stderr and "refused" in p.stderr, p.stderr
        p = subprocess.run(hookwatch_cmd() + ["hooks", str(yml), "--replaced", "--sample-id", "S-4"],
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 0 and "hook replaced" in p.stdout, p.stdout + p.stderr
        time.sleep(0.5)
    p = subprocess.run(hookwatch_cmd() + ["hooks", str(yml)], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    assert [ln.split()[1:4] for ln in p.stdout.splitlines()] == [
        ["S-0", "→", "S-2"], ["S-2", "→", "S-3"], ["S-3", "→", "S-4"]], p.stdout
    hooks = read_hooks(str(tmp_path / "records" / "hr"))
    assert [(h["old_sample_id"], h["new_sample_id"]) for h in hooks] == [("S-0", "S-2"), ("S-2", "S-3"),
                                                                        ("S-3", "S-4")]
    assert hooks[0]["by"] == "mqtt" and hooks[1]["by"].startswith("plc:")
    assert hooks[0]["test_id"] == old_test and hooks[0]["life_s"] > 0
    assert hooks[1]["test_id"] is None and hooks[1]["life_s"] is None   # S-2 never ran a test
