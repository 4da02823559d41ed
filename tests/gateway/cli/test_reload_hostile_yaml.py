"""Issue 12 item 5: a SIGHUP reload with a hostile file — a NUL byte, then a billion-laughs alias
bomb — is refused with the reader's one line and the running configuration kept; the gateway
neither ends nor grows (the bomb is refused without being expanded)."""
import contextlib
import os
import signal

import yaml

from conftest import ROOT
from kit.e2e import fleet_dir, run_gateway, virtual_station, wait_log

LAUGHS = "a: &a [lol,lol,lol,lol,lol,lol,lol,lol,lol]\n" + "".join(
    f"{chr(98 + i)}: &{chr(98 + i)} [" + ",".join([f"*{chr(97 + i)}"] * 9) + "]\n" for i in range(8))


def _rss_kb(pid):
    with open(f"/proc/{pid}/status") as f:
        return next(int(ln.split()[1]) for ln in f if ln.startswith("VmRSS:"))


def test_sighup_with_nul_byte_and_alias_bomb_is_refused_and_the_gateway_runs_on(tmp_path):
    fleet = fleet_dir(tmp_path)
    sc = os.path.join(ROOT, "config", "scenarios", "quick.yaml")
    with contextlib.ExitStack() as stack:
        _p, links = stack.enter_context(virtual_station(tmp_path, sc))
        f = fleet / "stations" / "idle.yaml"
        good = yaml.safe_dump({"station": {"id": "idle"}, "meter": {"port": links["meter"]},
                               "stm32": {"port": links["stm32"]}})
        f.write_text(good)
        gw = run_gateway(tmp_path, str(fleet))
        try:
            wait_log(gw, "open at 115200 baud")
            rss0 = _rss_kb(gw.p.pid)
            f.write_bytes(good.encode() + b"test: {sample_id: a\x00b}\n")
            gw.p.send_signal(signal.SIGHUP)
            wait_log(gw, "reload refused, configuration kept")
            line = gw.log().split("reload refused", 1)[1]
            assert "a NUL byte" in line, line
            f.write_text(good + LAUGHS)
            gw.p.send_signal(signal.SIGHUP)
            wait_log(gw, "once the aliases are expanded")
            assert gw.p.poll() is None
            assert _rss_kb(gw.p.pid) < rss0 + 50_000      # the bomb took 1.6 GB before
            # a good file reloads again (a changed one: an unchanged file is nothing to reload for
            # the fleet supervisor, which compares the effective configuration)
            f.write_text(good + "test: {sample_id: S-after}\n")
            gw.p.send_signal(signal.SIGHUP)
            wait_log(gw, "idle: configuration reloaded")
        finally:
            assert gw.stop() == 0, gw.log()
    assert "Traceback" not in gw.log()
