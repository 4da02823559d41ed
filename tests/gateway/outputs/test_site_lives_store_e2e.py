"""Issue 34 items 3 and 7 end to end: what a gateway keeps of the site's lives, on a real Mosquitto
with real gateway processes, another station of the site being a paho client (kit.site_peer).

- a planted `site_lives.json.tmp` link is never written through (an outside file stays as it
  was; before: overwritten);
- a station that never ran a test keeps the site's lives on disk from the first minute (its
  records folder made; before: "No such file or directory", kept in memory only), in a fleet
  (supervisor and worker process), and reads them back after a restart while the broker is down;
- a test id that two stations claim with different lives is refused from both and logged once;
  the same life claimed twice counts once; the history prior names its stations in the sidecar
  (`prior_station_ids`, `prior_from`) and in the state the console's station page shows."""
import json
import os

import pytest
import yaml

from gateway.core.method.prior import history_prior
from gateway.outputs.mqtt.sitelives import STORE_NAME
from kit.broker import Broker, Sub, pub
from kit.e2e import (
    QUICK_END,
    QUICK_METHOD,
    fleet_dir,
    quick_scenario,
    run_gateway,
    station_yaml,
    virtual_station,
    wait_log,
)
from kit.site_peer import SITE_BASE, SitePeer, failure
from kit.tools import wait_for


def _absent(tmp_path) -> dict:
    """Instruments that are not there (a state, not a crash): the station runs, never a test."""
    dev = tmp_path / "absent"
    return {"meter": str(dev / "meter"), "stm32": str(dev / "stm32")}


def _kept(path) -> dict:
    try:
        with open(path) as f:
            return json.load(f)["stations"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def _sidecar(station_dir):
    if not station_dir.exists():
        return None
    found = [station_dir / d / "log.meta.yaml" for d in sorted(os.listdir(station_dir))
             if (station_dir / d / "log.meta.yaml").exists()]
    return str(found[0]) if found else None


PEER_LIVES = [failure("peer", f"P-{i}", 20.0 + i) for i in range(5)]


def test_a_planted_tmp_link_is_never_written_through(tmp_path):
    folder = tmp_path / "records" / "b"
    folder.mkdir(parents=True)
    outside, outside2 = tmp_path / "outside.txt", tmp_path / "outside2.txt"
    outside.write_text("precious\n")
    outside2.write_text("precious too\n")
    os.symlink(outside, folder / (STORE_NAME + ".tmp"))      # the temporary file, planted
    os.symlink(outside2, folder / STORE_NAME)                # and the file itself
    with Broker(tmp_path) as b:
        st = station_yaml(tmp_path, _absent(tmp_path), name="b", mqtt={"enabled": True, "port": b.port})
        gw = run_gateway(tmp_path, st, name="gw-b")
        peer = SitePeer(b.port, "peer")
        try:
            wait_log(gw, "connected to 127.0.0.1", 60)
            peer.publish(PEER_LIVES)
            wait_for(lambda: len(_kept(folder / STORE_NAME).get("peer", [])) == 5
                     and not os.path.islink(folder / STORE_NAME), 60, what="the site's lives saved")
        finally:
            peer.close()
            gw.stop()
    assert outside.read_text() == "precious\n" and outside2.read_text() == "precious too\n"
    assert not os.path.islink(folder / STORE_NAME) and not os.path.lexists(folder / (STORE_NAME + ".tmp"))
    assert "Traceback" not in gw.log_all()


def test_a_station_that_never_ran_a_test_keeps_the_sites_lives_on_disk_in_a_fleet(tmp_path):
    store = tmp_path / "records" / "fresh" / STORE_NAME
    with Broker(tmp_path) as b:
        fleet = fleet_dir(tmp_path, mqtt={"enabled": True, "port": b.port})
        absent = _absent(tmp_path)
        (fleet / "stations" / "fresh.yaml").write_text(yaml.safe_dump({
            "station": {"id": "fresh"}, "meter": {"port": absent["meter"]}, "stm32": {"port": absent["stm32"]},
            # the outbox elsewhere: nothing else makes the station's records folder
            "mqtt": {"outbox": {"path": str(tmp_path / "outbox-fresh.sqlite")}}}))
        assert not (tmp_path / "records").exists()
        gw = run_gateway(tmp_path, str(fleet), name="gw")
        peer = SitePeer(b.port, "peer", base="hookwatch/lab/hall/l1")
        try:
            wait_log(gw, "fresh: worker started", 60)
            wait_for(lambda: os.path.exists(tmp_path / "outbox-fresh.sqlite"), 60, what="the station's outbox")
            peer.publish(PEER_LIVES)
            wait_for(lambda: len(_kept(store).get("peer", [])) == 5, 60, what="the site's lives on disk")
        finally:
            peer.close()
            gw.stop()
    # restarted while the broker is down: the lives come from the disk
    gw2 = run_gateway(tmp_path, str(fleet), name="gw2")
    try:
        wait_log(gw2, "fresh: the site's lives: 5 tests of 1 stations from", 60)
    finally:
        gw2.stop()
    assert not [d for d in os.listdir(tmp_path / "records" / "fresh") if (tmp_path / "records" / "fresh" / d).is_dir()]
    assert "cannot be saved" not in gw.log_all() + gw2.log_all()


@pytest.mark.timeout(300)
def test_contested_lives_are_refused_from_both_and_the_prior_names_its_stations(tmp_path):
    x = failure("p1", "X-1", 20.0)                 # p1 and p2 disagree on X-1: refused from both
    same = failure("p1", "S-1", 23.0)              # both claim S-1 with the same life: once
    p1 = [x, same, failure("p1", "P1-a", 26.5), failure("p1", "P1-b", 24.0)]
    p2 = [failure("p2", "X-1", 22.0), failure("p2", "S-1", 23.0), failure("p2", "P2-a", 25.0)]
    expected = history_prior([23.0, 26.5, 24.0, 25.0], [])
    root = tmp_path / "records"
    with Broker(tmp_path) as b, virtual_station(tmp_path, quick_scenario(tmp_path, "quick.yaml")) as (_sim, links):
        mes = Sub(b.port, f"{SITE_BASE}/b/state")
        st = station_yaml(tmp_path, links, name="b", method=QUICK_METHOD, test={"t_end_s": QUICK_END},
                          mqtt={"enabled": True, "port": b.port})
        gw = run_gateway(tmp_path, st, name="gw-b")
        peers = {n: SitePeer(b.port, n) for n in ("p1", "p2")}
        try:
            wait_log(gw, "connected to 127.0.0.1", 60)
            peers["p1"].publish(p1)
            wait_for(lambda: len(_kept(root / "b" / STORE_NAME).get("p1", [])) == 4, 60, what="p1's lives")
            # p2 again and again, each snapshot with one more test of another grade: the
            # contested id is logged once, however often it comes
            for k in range(4):
                peers["p2"].publish(p2 + [failure("p2", f"P2-II-{j}", 30.0, grade="II") for j in range(k)])
                wait_for(lambda k=k: len(_kept(root / "b" / STORE_NAME).get("p2", [])) == 3 + k, 60,
                         what="p2's lives")
            pub(b.port, f"{SITE_BASE}/b/cmd/start", '{"sample_id": "B-1", "grade": "I", "t_set": 0.5}')
            meta_path = wait_for(lambda: _sidecar(root / "b"), 60, what="B's test started")
            with open(meta_path) as f:
                meta = yaml.safe_load(f)
            state = mes.wait(lambda s: [m for m in s.messages("state")
                                        if (m[2].get("prior_source") or "").startswith("history:")], 60,
                             what="the state with the prior")
        finally:
            for p in peers.values():
                p.close()
            gw.stop()
            mes.stop()
    words = "the site: 4 tests from 2 stations (0 of this station; p1 3, p2 1)"
    assert meta["prior_source"] == "history" and (meta["prior_n"], meta["prior_n_censored"]) == (4, 0)
    assert meta["prior_stations"] == 2 and meta["prior_station_ids"] == ["p1", "p2"]
    assert meta["prior_from"] == words
    assert meta["method"]["prior_mean"] == pytest.approx(expected[0], rel=1e-12)
    assert meta["method"]["prior_sd"] == pytest.approx(expected[1], rel=1e-12)
    assert state[-1][2]["prior_source"] == f"history:4 ({words})"
    log = gw.log_all()
    assert log.count("claimed by two or more stations with different lives") == 1, log[-3000:]
    assert "'X-1' claimed by 'p1', 'p2'" in log
