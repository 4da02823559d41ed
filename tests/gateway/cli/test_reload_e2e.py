"""Issue 6: SIGHUP reloads the configuration of stations that are not in a test; a running test
keeps the parameters it started with (they are in its sidecar); a broken file is refused and the
running configuration kept."""
import contextlib
import os
import signal

import yaml

from conftest import ROOT
from kit.e2e import fleet_dir, run_gateway, test_dirs, virtual_station, wait_log


def test_sighup_reloads_idle_stations_and_keeps_a_running_test(tmp_path):
    # the busy station's test only has to outlast the two reloads (a few seconds from its start)
    fleet = fleet_dir(tmp_path, test={"t_end_s": 12})
    sc = os.path.join(ROOT, "config", "scenarios", "quick.yaml")
    with contextlib.ExitStack() as stack:
        files = {}
        for name, autostart in (("busy", True), ("idle", False)):
            sub = tmp_path / name
            sub.mkdir()
            _p, links = stack.enter_context(virtual_station(sub, sc))
            files[name] = fleet / "stations" / f"{name}.yaml"
            files[name].write_text(yaml.safe_dump({
                "station": {"id": name}, "meter": {"port": links["meter"]},
                "stm32": {"port": links["stm32"]},
                "test": {"sample_id": f"S-{name}", "autostart": autostart}}))
        gw = run_gateway(tmp_path, str(fleet))
        try:
            wait_log(gw, "busy: test_started")
            # change both stations' parameters, then SIGHUP
            for name in ("busy", "idle"):
                d = yaml.safe_load(files[name].read_text())
                d["method"] = {"delta": 0.5}
                files[name].write_text(yaml.safe_dump(d))
            gw.p.send_signal(signal.SIGHUP)
            wait_log(gw, "idle: configuration reloaded")
            wait_log(gw, "busy: in a test; keeps the parameters it started with")
            # a broken file: refused, named, and the stations run on
            files["idle"].write_text("station: {id: idle\nmeter: [")
            gw.p.send_signal(signal.SIGHUP)
            wait_log(gw, "reload refused, configuration kept")
            assert "idle.yaml" in gw.log().split("reload refused", 1)[1].splitlines()[0]
            wait_log(gw, "busy: test_ended", timeout=60)
        finally:
            assert gw.stop() == 0, gw.log()
    d = test_dirs(tmp_path, "busy")[0]
    with open(os.path.join(d, "log.meta.yaml")) as f:
        meta = yaml.safe_load(f)
    assert meta["method"]["delta"] == 0.25          # the parameters it started with
    assert "Traceback" not in gw.log()
