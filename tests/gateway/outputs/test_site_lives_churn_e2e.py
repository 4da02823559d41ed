"""Issue 34 item 1 end to end: a flood of valid lives snapshots costs a station no command and no
slot. A box as deployed — `hookwatch run FLEET_DIR`, a supervisor and a worker process per
station — with two stations on virtual instruments (`hookwatch sim --count 2`) and a real
Mosquitto: `churned` shares the site's lives, `control` does not (`mqtt.share_lives: false`: it
never subscribes to them), so the control runs the same test at the same time on the same
machine without the lives. The MES (mosquitto_sub / mosquitto_pub) starts a test on both, sends
both a row of commands a second apart and stops them; meanwhile another station of the site floods
400 changing lives snapshots back to back and keeps publishing new ones (the churn attack: on the
code before issue 34 every snapshot rewrote `site_lives.json` and logged a line on the MQTT thread
— a stop answered after 97 s, 473 slots MISSING).

What must hold on any machine, however loaded (no duration is asserted): every command answered
exactly once and in the order sent; every slot of both tests recorded or counted MISSING (how many
MISSING beside the control is bench/bench_site_churn.py's figure); every snapshot the churned station
received checked or dropped unread because a newer one of its station came, and counted
(`lives_checked` + `lives_dropped` in the Prometheus counters = snapshots sent); the local copy
written far fewer times than snapshots came and holding the newest; one rate-limited log line
instead of one per snapshot."""
import json
import os
import threading
import time

import pytest
import yaml

from conftest import ROOT, hookwatch_cmd
from gateway.outputs.mqtt.sitelives import STORE_NAME
from kit.broker import Broker, Sub, pub
from kit.e2e import METER_MAP, SHORT_METHOD, assert_no_slot_lost, fleet_dir, read_json, run_gateway, test_dirs
from kit.proc import Proc
from kit.site_peer import SitePeer, mqtt_counters
from kit.tools import free_port, wait_for, wait_port

SITE = "hookwatch/lab/hall/l1"
NAMES = ("churned", "control")
ACKS = 8
BURST = 400
MORE = 200


def _sim(tmp_path) -> tuple[Proc, str]:
    """One `hookwatch sim --count 2` of the real-time life-I-0.5 plant (a test runs until stopped)."""
    with open(os.path.join(ROOT, "config", "scenarios", "life-I-0.5.yaml")) as f:
        sc = yaml.safe_load(f)
    sc["meter"] = {"map": METER_MAP}
    (tmp_path / "sc.yaml").write_text(yaml.safe_dump(sc))
    links = tmp_path / "links"
    # the twins stand for hardware, which the flood's other processes (the broker, the peer) do not
    # slow down: their loop under SCHED_FIFO 10 where permitted (below the gateway's 20), as in
    # tests/gateway/station/test_stall_e2e.py — the subject is the gateway, not a starved twin
    p = Proc(hookwatch_cmd() + ["sim", str(tmp_path / "sc.yaml"), "--count", "2", "--link-dir", str(links),
                                "--duration", "900", "--realtime", "10"], str(tmp_path / "sim.log"))
    p.readline_until("ready:")
    return p, str(links)


def _answered(sub, rid: str) -> bool:
    return any(m[2].get("request_id") == rid for m in sub.messages("reply"))


@pytest.mark.timeout(900)
def test_a_churn_of_lives_snapshots_costs_no_command_and_no_slot(tmp_path):
    mport = free_port()
    sim, links = _sim(tmp_path)
    gw = peer = None
    sent: dict[str, list[str]] = {n: [] for n in NAMES}
    newest: list[bytes] = []
    with Broker(tmp_path) as b:
        sub = Sub(b.port, f"{SITE}/+/reply")
        try:
            fleet = fleet_dir(tmp_path, method=SHORT_METHOD, control={"dead_band_n": 0.01},
                              test={"t_end_s": 3600, "sample_id": "S-1", "grade": "I"},
                              mqtt={"enabled": True, "port": b.port},
                              metrics={"enabled": True, "port": mport})
            for i, name in enumerate(NAMES):
                st = {"station": {"id": name}, "meter": {"port": os.path.join(links, f"sim{i + 1:02d}", "meter")},
                      "stm32": {"port": os.path.join(links, f"sim{i + 1:02d}", "stm32")}}
                if name == "control":
                    st["mqtt"] = {"share_lives": False}
                (fleet / "stations" / f"{name}.yaml").write_text(yaml.safe_dump(st))
            gw = run_gateway(tmp_path, str(fleet), name="gw")
            wait_port(mport, 60)
            for n in NAMES:
                wait_for(lambda n=n: mqtt_counters(mport, n).get("connects", 0) >= 1, 60, 0.5,
                         what=f"{n} connected")
            for n in NAMES:
                sent[n].append(f"{n}-start")
                pub(b.port, f"{SITE}/{n}/cmd/start", json.dumps({"sample_id": n.upper(), "grade": "I",
                                                                "t_set": 0.5, "request_id": sent[n][-1]}))
            for n in NAMES:
                wait_for(lambda n=n: test_dirs(tmp_path, n), 120, what=f"{n}'s test")
            peer = SitePeer(b.port, "peer", base=SITE)

            def churn() -> None:
                burst = peer.churn_payloads(BURST + MORE)
                peer.send_raw(burst[:BURST])              # 400 back to back
                for p in burst[BURST:]:                  # and more while the commands go on
                    peer.send_raw([p])
                    time.sleep(0.02)
                newest.append(burst[-1])

            flood = threading.Thread(target=churn, daemon=True)
            flood.start()
            for i in range(ACKS):
                time.sleep(1.0)                          # the commands spread over the tests
                for n in NAMES:
                    sent[n].append(f"{n}-ack-{i}")
                    pub(b.port, f"{SITE}/{n}/cmd/ack", json.dumps({"request_id": sent[n][-1]}))
                for n in NAMES:
                    wait_for(lambda n=n: _answered(sub, sent[n][-1]), 300, what=f"the answer to {sent[n][-1]}")
            flood.join(300)
            for n in NAMES:
                sent[n].append(f"{n}-stop")
                pub(b.port, f"{SITE}/{n}/cmd/stop", json.dumps({"request_id": sent[n][-1]}))
            dirs = {n: test_dirs(tmp_path, n)[0] for n in NAMES}
            for n in NAMES:
                wait_for(lambda n=n: os.path.exists(os.path.join(dirs[n], "result.json")), 300,
                         what=f"{n}'s result")
            # every snapshot the churned station received: checked, or dropped unread for a newer one
            total = BURST + MORE
            wait_for(lambda: (lambda c: c.get("lives_checked", 0) + c.get("lives_dropped", 0) >= total)(
                mqtt_counters(mport, "churned")), 300, 0.5, what="every snapshot checked or dropped")
            # the local copy holds the newest snapshot (the newest is never the one dropped)
            store = tmp_path / "records" / "churned" / STORE_NAME
            last = {r["test_id"] for r in json.loads(newest[0])["lives"]}

            def saved() -> set[str]:
                try:
                    return {r["test_id"] for r in read_json(store)["stations"].get("peer", [])}
                except (OSError, ValueError, AttributeError):
                    return set()
            wait_for(lambda: saved() == last, 120, 0.5, what="the newest snapshot saved")
            counters = {n: mqtt_counters(mport, n) for n in NAMES}
            for n in NAMES:
                wait_for(lambda n=n: _answered(sub, sent[n][-1]), 300, what=f"the answer to {sent[n][-1]}")
        finally:
            if peer is not None:
                peer.close()
            if gw is not None:
                gw.stop()
            sim.stop()
            sub.stop()
    assert peer.sent == total
    # every command answered once, in the order sent
    answered = [m[2]["request_id"] for m in sub.messages("reply")]
    for n in NAMES:
        assert [r for r in answered if r.startswith(f"{n}-")] == sent[n], answered
    replies = {m[2]["request_id"]: m[2] for m in sub.messages("reply")}
    for n in NAMES:
        assert replies[f"{n}-start"]["ok"] and replies[f"{n}-stop"]["ok"], replies
    # every slot recorded or counted MISSING (how many MISSING the churn costs against the control
    # is a figure of the loaded machine, measured by bench/bench_site_churn.py, not asserted here:
    # at load 2-17 the churned station had 1-7 slots more than the control in 10 of 18 runs)
    for n in NAMES:
        res = read_json(os.path.join(dirs[n], "result.json"))
        assert_no_slot_lost(dirs[n], res["method"])
    # what the snapshots cost the churned station: counted, dropped for newer ones, saved and
    # logged far less often; the control never took them
    c = counters["churned"]
    assert c["lives_checked"] + c["lives_dropped"] == total, c
    assert c["lives_dropped"] > 0 and c.get("lives_save_errors", 0) == 0, c
    assert 1 <= c["lives_saves"] and c["lives_saves"] * 10 <= total, c
    assert counters["control"].get("lives_checked", 0) == 0, counters["control"]
    log = gw.log_all()
    assert 1 <= log.count("churned: the site's lives:") and log.count("the site's lives:") * 20 <= total
    assert "Traceback" not in log, log[-3000:]
