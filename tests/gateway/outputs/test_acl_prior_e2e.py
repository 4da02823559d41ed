"""Issue 34 item 2 end to end: a forging box cannot poison another box's prior. Two boxes of one
site on a real Mosquitto whose permissions are generated from the site (gateway/outputs/acl/broker_acl.py, as
`hookwatch config acl` writes them). Box B poses as three stations it does not run — retained
lives of plausible failures at grade I, 0.5 N, the grade and T_set of box A's next test — and then
publishes its own station's true lives (grade II). The broker refuses the forgeries (PUBACK 0x87)
and takes B's own; box A's gateway keeps B's station's lives and nothing of the three, and its
test starts without a history prior. (Before, with `readwrite hookwatch/#` for every box, the
forged lives became the prior of A's next test: "the site: 60 tests from 2 stations".)"""
import json
import os

import yaml

from gateway.offline.history import read_history
from gateway.outputs.acl import broker_acl as A
from gateway.outputs.mqtt import schema as S
from gateway.outputs.mqtt.sitelives import STORE_NAME, lives_topic, snapshot
from kit.broker import ACCEPTED, NOT_AUTHORIZED, Broker, Publisher
from kit.e2e import QUICK_END, QUICK_METHOD, quick_scenario, run_gateway, station_yaml, virtual_station
from kit.tools import wait_for

SITE = "hookwatch/lab/test/l1"
USERS = {"box-a": "pw-a", "box-b": "pw-b", "mes": "pw-mes"}
POSED = ("z1", "z2", "z3")          # stations box B does not run


def _acl() -> str:
    site = A.SiteAcl((A.Box("box-a", (A.StationTopics("a", f"{SITE}/a"),)),
                      A.Box("box-b", (A.StationTopics("b", f"{SITE}/b"),))), (A.Commander("mes"),))
    return A.mosquitto(A.grants(site), ["test_acl_prior_e2e"])


def _lives(root, station: str, grade: str, failures: tuple[float, ...]) -> bytes:
    """A station's retained lives message: its recorded failures, as its gateway would send them."""
    for i, t_life in enumerate(failures):
        tid = f"2026030{i}T080000Z-{station}-{i}"
        d = root / station / tid
        d.mkdir(parents=True)
        (d / "result.json").write_text(json.dumps({
            "test_id": tid, "station": station, "test_status": "completed", "end_reason": "completed",
            "sample_id": f"{station}-{i}", "grade": grade, "t_set": 0.5, "ts": 0.02, "t_end": QUICK_END,
            "method": {"status": "failure", "t_life": t_life, "k_b": 400, "n_slots": round(t_life / 0.02) + 100,
                       "stop_reasons": None}}))
    doc = snapshot(station, read_history(str(root / station)), S.iso_ms(1772352000.0))
    return json.dumps({**doc, "seq": 1}).encode()


def _sidecar(station_dir):
    if not station_dir.exists():
        return None
    found = [station_dir / d / "log.meta.yaml" for d in sorted(os.listdir(station_dir))
             if (station_dir / d / "log.meta.yaml").exists()]
    return str(found[0]) if found else None


def _kept(path):
    try:
        with open(path) as f:
            return sorted(json.load(f)["stations"])
    except (OSError, ValueError, KeyError):
        return None


def test_a_box_posing_as_other_stations_never_reaches_a_prior(tmp_path):
    root_a, forged = tmp_path / "A" / "records", tmp_path / "forged"
    with Broker(tmp_path, users=USERS, acl=_acl()) as b:
        box_b = Publisher(b.port, "box-b", USERS["box-b"])
        try:
            for z in POSED:        # as the attacker did: plausible failures at the next test's grade and T_set
                msg = _lives(forged, z, "I", (20.0, 21.5, 23.0, 24.5, 26.0))
                assert box_b.publish(lives_topic(f"{SITE}/{z}"), msg, retain=True) == NOT_AUTHORIZED
            # box A's own station's lives topic: not B's either
            assert box_b.publish(lives_topic(f"{SITE}/a"), _lives(forged, "a", "I", (22.0,)),
                                 retain=True) == NOT_AUTHORIZED
            # B's own station: passes (B can still say what it likes of its own stations)
            assert box_b.publish(lives_topic(f"{SITE}/b"), _lives(forged, "b", "II", (30.0,)),
                                 retain=True) in ACCEPTED
        finally:
            box_b.close()
        (tmp_path / "pw-a").write_text(USERS["box-a"])
        gw = None
        try:
            with virtual_station(tmp_path, quick_scenario(tmp_path, "quick.yaml")) as (_sim, links):
                st_a = station_yaml(tmp_path, links, name="a", method=QUICK_METHOD, test={"t_end_s": QUICK_END},
                                    mqtt={"enabled": True, "port": b.port, "username": "box-a",
                                          "password_file": str(tmp_path / "pw-a")},
                                    extra={"recorder": {"dir": str(root_a)}})
                gw = run_gateway(tmp_path, st_a, name="gw-a")
                # B's own lives arrive (retained, like the forgeries would have): A keeps them
                wait_for(lambda: "b" in (_kept(root_a / "a" / STORE_NAME) or ()), 90, what="B's own lives kept by A")
                mes = Publisher(b.port, "mes", USERS["mes"])
                try:
                    assert mes.publish(S.command_topic(f"{SITE}/a", "start"),
                                       '{"sample_id": "A-1", "grade": "I", "t_set": 0.5}') in ACCEPTED
                finally:
                    mes.close()
                meta_path = wait_for(lambda: _sidecar(root_a / "a"), 90, what="A's test started")
                with open(meta_path) as f:
                    meta = yaml.safe_load(f)
                kept = _kept(root_a / "a" / STORE_NAME)
        finally:
            if gw is not None:
                gw.stop()
    assert meta.get("prior_source") != "history", meta.get("prior_from")
    assert kept == ["b"]
    assert not meta.get("prior_stations")
