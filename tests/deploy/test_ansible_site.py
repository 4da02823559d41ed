"""Issue 37 items 8–9: the site rolled out by the real ``ansible-playbook`` (deploy/ansible/) to
three boxes on this machine (tests/kit/site_lab.py: each its own settings, state folder,
configuration, ports and supervisor process; one virtual station each; one Mosquitto; the
``local`` connection with per-host variables in an inventory the test writes), from a Git site
repository whose commits are signed with an OpenSSH key.

(a) a fleet-default change reaches every box; box 2's station, in a test, defers it and applies it
    when the test ends (the test's parameters and result unchanged, online == offline); check
    mode prints each box's plan and changes nothing; a Vault-encrypted secret reaches every box;
(b) a change that fails ``config check`` stops the play before any box: no box changed;
(c) a change that passes the check but fails the canary's health gate (a serial port that does not
    exist) rolls back on the canary and stops the play;
(d) an unsigned commit is refused by the canary; the play stops;
(e) a hand edit on box 3 is reported as drift (the time it takes: the core's bench_site_config.py);
(h) the console's Boxes page in chromium shows every box's version and box 2's deferred station
    (from the boxes' own retained config reports on the site's broker);
(g) an offline release (scripts/build-release) installed in waves by release.yml: every station's
    worker restarted on it, box 2's only once its test has ended (the test's result unchanged);
(f) ``kill -9`` of an apply: the box starts on one consistent version, and the next run applies.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import signal
import subprocess
import tarfile
import threading

import pytest
import yaml

from conftest import ROOT, hookwatch_cmd
from gateway.outputs.mqtt import schema as mqtt_schema
from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
from kit.broker import pub
from kit.browser import wait_js
from kit.console_helpers import start_console
from kit.e2e import analyze_cli, read_json, test_dirs, wait_log
from kit.northbound import LoopThread
from kit.site_lab import SiteLab, ansible_playbook, recap, restart_command
from kit.tools import wait_for

#: a bound against a hang: a run of ansible-playbook over three boxes took 100–260 s at load 15–20
pytestmark = pytest.mark.timeout(1800)

#: box 2's station runs a test from its start, longer than any rollout on a loaded machine; the
#: test ends it with the station's stop command (MQTT) once the rollout has passed box 2
BOX2_TEST = {"autostart": True, "t_end_s": 1800}
BOX2_CMD = "hookwatch/lab/hall/l1/loom-21/cmd/stop"


@pytest.fixture
def lab(tmp_path, broker):
    box2 = {"test": BOX2_TEST, "mqtt": {"enabled": True, "port": broker.port, "telemetry_interval_s": 5}}
    lab = SiteLab(tmp_path, broker.port, stations={"box-2": box2}, health_timeout_s=60)
    try:
        yield lab.make()
    finally:
        lab.stop()


def _bootstrap(lab: SiteLab) -> str:
    """The first version applied to every box by the playbook (no supervisor runs yet: the switch
    alone), then each box's supervisor started on it; its sha."""
    v1 = lab.head()
    r = lab.playbook()
    assert r.returncode == 0, r.stdout + r.stderr
    for b in lab.boxes:
        assert b.current() == v1, b.name
        lab.start_box(b)
    for b in lab.boxes:
        wait_for(lambda b=b: _runs(b, v1), timeout=90, interval=0.5, what=f"{b.name} running {v1[:12]}")
    # applied while no supervisor ran: verified only once its first start has passed the gate
    for b in lab.boxes:
        wait_for(lambda b=b: b.status()["verified"] == v1, timeout=90, interval=0.5,
                 what=f"{b.name}: {v1[:12]} verified at the supervisor's start")
    return v1


def _station(b, status: dict | None = None) -> dict:
    st = (status or b.status()).get("stations") or {}
    return st.get(b.station) or {}


def _runs(b, version: str) -> bool:
    s = _station(b)
    return s.get("version") == version and bool(s.get("running"))


def _plan_lines(run: subprocess.CompletedProcess, box: str) -> str:
    """The plan task's output for one box (``ok: [box-N] => {hookwatch_plan.stdout_lines: …}``)."""
    out = [c.split("TASK [", 1)[0] for c in run.stdout.split("TASK [hookwatch_site : The plan of this box]")[1:]]
    return "\n".join(c for c in out if f"ok: [{box}]" in c)


def test_a_fleet_default_reaches_every_box_and_box_2_applies_it_when_its_test_ends(lab, tmp_path, broker, browser):
    # a secret for every box, encrypted with Ansible Vault on the controller (never in the site
    # repository, which only names its path on the box)
    vault_pw = tmp_path / "vault-pass"
    vault_pw.write_text("lab-vault-password\n")
    secret = tmp_path / "mqtt.pass"
    secret.write_text("s3cret-of-the-site\n")
    vault = os.path.join(os.path.dirname(ansible_playbook()), "ansible-vault")
    subprocess.run([vault, "encrypt", "--vault-password-file", str(vault_pw), str(secret)],
                   check=True, capture_output=True, env=dict(os.environ, ANSIBLE_HOME=str(tmp_path / "ansible-home")))
    assert "s3cret" not in secret.read_text() and secret.read_text().startswith("$ANSIBLE_VAULT")
    vault_args = ["--vault-password-file", str(vault_pw)]
    secrets = {"hookwatch_secret_files": [{"src": str(secret), "dest": "{{ hookwatch_state_dir }}/../mqtt.pass",
                                           "mode": "0600"}]}

    v1 = lab.head()
    r = lab.playbook("site.yml", *vault_args, **secrets)
    assert r.returncode == 0, r.stdout + r.stderr
    for b in lab.boxes:
        assert b.current() == v1
        st = b.status()          # no supervisor runs yet: applied, not verified (no health gate ran)
        assert st["verified"] is None and st["unverified"]["version"] == v1, st
        assert (b.dir / "mqtt.pass").read_text() == "s3cret-of-the-site\n"
        assert oct((b.dir / "mqtt.pass").stat().st_mode & 0o777) == "0o600"
        lab.start_box(b)
    box1, box2, box3 = lab.boxes
    wait_log(box2.proc, f"{box2.station}: test_started", timeout=90)
    for b in lab.boxes:
        wait_for(lambda b=b: _runs(b, v1), timeout=90, interval=0.5, what=f"{b.name} on {v1[:12]}")

    # a fleet-wide default changes (one file, every box)
    fleet = lab.read("defaults/fleet.yaml")
    fleet["defaults"]["method"]["delta"] = 0.3
    lab.write("defaults/fleet.yaml", fleet)
    v2 = lab.commit("defaults: delta 0.3 for every loom", push=True)

    # check mode: each box's plan printed, nothing changed anywhere
    chk = lab.playbook("site.yml", "--check", *vault_args, **secrets)
    (tmp_path / "check-mode.txt").write_text(chk.stdout)
    assert chk.returncode == 0, chk.stdout + chk.stderr
    for b in lab.boxes:
        plan = _plan_lines(chk, b.name)
        assert b.station in plan and "delta" in plan, (b.name, plan)
        assert ("deferred" in plan) == (b is box2), (b.name, plan)
        assert b.current() == v1 and _station(b)["version"] == v1
    assert recap(chk)["box-1"]["failed"] == 0

    # the rollout: every box takes v2; box 2's station keeps v1 for its running test
    r = lab.playbook("site.yml", *vault_args, **secrets)
    assert r.returncode == 0, r.stdout + r.stderr
    rc = recap(r)
    for b in lab.boxes:
        assert rc[b.name]["failed"] == 0 and rc[b.name]["changed"] >= 1, (b.name, rc)
        assert b.current() == v2, b.name
    for b in (box1, box3):
        wait_for(lambda b=b: _runs(b, v2), timeout=90, interval=0.5, what=f"{b.name} on {v2[:12]}")
    s2 = _station(box2)
    assert s2["in_test"] and s2["version"] == v1 and s2["pending"] == v2, s2
    assert box2.station in box2.status()["deferred"]
    # (h) the console's Boxes page, on the site's broker, shows every box on v2, box 2's deferral
    _boxes_page(browser, tmp_path, broker.port, v2, {"box-2": box2.station})

    # box 2's test ends (the operator's stop); then its station applies v2 (and, autostart,
    # begins another test on it)
    pub(broker.port, BOX2_CMD, '{"request_id": "end-of-test"}')
    wait_log(box2.proc, f"{box2.station}: test_ended", timeout=60)
    wait_for(lambda: _runs(box2, v2), timeout=90, interval=0.5, what="box-2's station on v2")
    first = test_dirs(box2.dir, box2.station)[0]
    with open(os.path.join(first, "log.meta.yaml")) as f:
        meta = yaml.safe_load(f)
    assert meta["method"]["delta"] == 0.25          # the parameters the test started with
    res = read_json(os.path.join(first, "result.json"))
    assert res["end_reason"] == "stopped by command", res
    assert analyze_cli(os.path.join(first, "log.csv.gz")) == res["method"]       # online == offline

    # the same version again changes nothing on any box
    again = lab.playbook("site.yml", *vault_args, **secrets)
    assert again.returncode == 0, again.stdout + again.stderr
    assert all(recap(again)[b.name]["changed"] == 0 for b in lab.boxes), again.stdout


def test_b_c_d_a_bad_change_stops_at_the_canary_and_no_other_box_changes(lab):
    v1 = _bootstrap(lab)
    box1, box2, box3 = lab.boxes

    def unchanged(run):
        for b in lab.boxes:
            assert b.current() == v1, (b.name, run.stdout[-3000:])
            # (a rolled-back station is back on v1 once it has restarted on it)
            wait_for(lambda b=b: _runs(b, v1), timeout=90, interval=0.5, what=f"{b.name} on v1")
        # the boxes after the canary were never reached by the waves
        assert "[box-2]" not in run.stdout.split("PLAY [The boxes, in waves]", 1)[-1].split("PLAY RECAP")[0]

    # (b) a change that fails `config check`: the whole site is checked once, before any box
    good = lab.read(f"boxes/box-3/stations/{box3.station}.yaml")
    lab.write(f"boxes/box-3/stations/{box3.station}.yaml", {**good, "station": {"id": box1.station}})
    lab.commit("box-3: a station id another box has", push=True)
    r = lab.playbook()
    assert r.returncode != 0
    assert "Check the whole site repository once" in r.stdout and box1.station in r.stdout, r.stdout
    unchanged(r)
    lab.write(f"boxes/box-3/stations/{box3.station}.yaml", good)

    # (c) passes the check, fails the canary's health gate: a meter port that does not exist
    st1 = lab.read(f"boxes/box-1/stations/{box1.station}.yaml")
    lab.write(f"boxes/box-1/stations/{box1.station}.yaml",
              {**st1, "meter": {"port": "/dev/hookwatch-lab-no-such-port"}})
    lab.commit("box-1: a meter port that is not there", push=True)
    r = lab.playbook()
    assert r.returncode != 0
    assert "box-1: hookwatch config apply exit 5 (rolled back): health gate" in r.stdout, r.stdout
    unchanged(r)
    rb = box1.status()["last_rollback"]
    assert rb and rb.get("why"), box1.status()
    lab.write(f"boxes/box-1/stations/{box1.station}.yaml", st1)

    # (d) an unsigned commit: refused by the canary's own check of the signature
    unsigned = lab.commit("everything fixed, but not signed", signed=False, push=True)
    r = lab.playbook()
    assert r.returncode != 0
    assert "box-1: hookwatch config apply exit 4 (refused)" in r.stdout, r.stdout
    unchanged(r)

    # (e) a hand edit on box 3: its report says drift, naming the file
    edited = box3.state / "config" / "current" / "stations" / f"{box3.station}.yaml"
    assert not box3.status()["drift"]
    with open(edited, "a") as f:
        f.write("# edited by hand on the box\n")
    st3 = wait_for(lambda: (s := box3.status())["drift"] and s, timeout=60, interval=0.5,
                   what="box-3's drift")
    assert any(box3.station in f for f in st3["drift_files"]), st3

    # the same tree signed: every box takes it (box 3's hand edit replaced by the version)
    lab.write("README.md", "signed again\n")
    v2 = lab.commit("signed", push=True)
    assert v2 != unsigned
    r = lab.playbook()
    assert r.returncode == 0, r.stdout + r.stderr
    for b in lab.boxes:
        assert b.current() == v2
    wait_for(lambda: not box3.status()["drift"], timeout=60, interval=0.5, what="box-3 without drift")
    assert not [ln for ln in box1.proc.log_all().splitlines() if "Traceback" in ln]


def test_f_an_apply_killed_mid_way_leaves_one_consistent_version_and_the_next_run_applies(lab):
    v1 = _bootstrap(lab)
    box1 = lab.boxes[0]
    fleet = lab.read("defaults/fleet.yaml")
    fleet["defaults"]["method"]["delta"] = 0.35
    lab.write("defaults/fleet.yaml", fleet)
    v2 = lab.commit("defaults: delta 0.35", push=True)
    subprocess.run(["git", "-C", str(box1.dir / "site"), "fetch", "-q", "origin"], check=True)
    # the apply, as the role runs it, killed once it has begun to switch (its journal says so)
    ap = subprocess.Popen(hookwatch_cmd() + [
        "config", "apply", str(box1.dir / "site"), "--version", v2, "--box-file", str(box1.box_file),
        "--state-dir", str(box1.state), "--json"], cwd=ROOT, stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL)
    journal = box1.state / "config" / "journal.jsonl"

    def begun():
        with contextlib.suppress(OSError):
            return v2 in journal.read_text()
        return False
    wait_for(begun, timeout=60, interval=0.01, what="the apply's journal entry")
    ap.send_signal(signal.SIGKILL)
    ap.wait(10)
    # the box started again (the supervisor too is gone: a power cut)
    box1.proc.p.send_signal(signal.SIGKILL)
    box1.proc.stop()
    lab.start_box(box1)
    wait_for(lambda: box1.current() in (v1, v2) and _station(box1).get("running")
             and _station(box1).get("version") == box1.current(), timeout=90, interval=0.5,
             what="box-1 on one consistent version")
    st = box1.status()
    assert st["applying"] is None, st
    assert st["version"] in (v1, v2) and st["stations"][box1.station]["version"] == st["version"]
    # the next run applies v2 everywhere
    r = lab.playbook()
    assert r.returncode == 0, r.stdout + r.stderr
    for b in lab.boxes:
        assert b.current() == v2
    for b in (lab.boxes[0], lab.boxes[2]):
        wait_for(lambda b=b: _runs(b, v2), timeout=90, interval=0.5, what=f"{b.name} on v2")
    s2 = _station(lab.boxes[1])          # box 2's station: in its test, v2 waits for its end
    assert s2["in_test"] and s2["pending"] == v2, s2


def _boxes_page(browser, tmp_path, port: int, version: str, deferred: dict[str, str]) -> None:
    """A console whose site view rides on a real MQTT output of site `lab` on the lab's broker:
    its Boxes page in chromium lists the lab's boxes (their retained config reports)."""
    lt = LoopThread()
    srv = out = None
    try:
        srv, url, _outs, _dirs = start_console(tmp_path)
        base = mqtt_schema.base_topic("hookwatch", "lab", "hall", "l1", "console-lab")
        out = MqttOutput(MqttSettings(station_id="console-lab", base_topic=base, port=port,
                                      outbox_path=str(tmp_path / "console-lab.sqlite"),
                                      reconnect_min_s=0.2, reconnect_max_s=1.0))
        assert srv.attach_site("console-lab", base, out.pump.add_site_feed)
        lt.call(out.start())
        ctx = browser.new_context(viewport={"width": 1500, "height": 900}, bypass_csp=True)
        page = ctx.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url + "/#/boxes")
        wait_js(page, "window.hw.boxes && window.hw.boxes.length === 3")
        assert page.evaluate("window.hw.boxes") == ["box-1", "box-2", "box-3"]

        def cell(box, cls):
            return page.locator(f'#boxes tr[data-box="{box}"] td.{cls}').inner_text()
        for box in ("box-1", "box-2", "box-3"):
            # (a box whose deferred station has not taken it yet says "… (applying …)")
            assert cell(box, "version").startswith(version[:12]), (box, cell(box, "version"))
            assert cell(box, "online") == "online" and cell(box, "drift") == "no", box
            assert cell(box, "deferred") == deferred.get(box, "none"), box
        page.screenshot(path=str(tmp_path / "boxes.png"), full_page=True)
        assert not errors, errors
        ctx.close()
    finally:
        if out is not None:
            lt.call(out.stop())
        closer = threading.Thread(target=lt.close)
        closer.start()
        closer.join(30)
        if srv is not None:
            srv.stop()


@pytest.fixture
def lab_g(tmp_path, broker):
    """The lab of (g): box 2's test is started by the MES (no autostart: a station whose worker
    restarts on the new software would otherwise begin another test at once, and the service's
    own restart waits for no test)."""
    box2 = {"test": {"t_end_s": 1800}, "mqtt": {"enabled": True, "port": broker.port, "telemetry_interval_s": 5}}
    lab = SiteLab(tmp_path, broker.port, stations={"box-2": box2}, health_timeout_s=60)
    try:
        yield lab.make()
    finally:
        lab.stop()


def test_g_a_release_in_waves_restarts_each_station_only_when_its_test_has_ended(lab_g, broker, tmp_path,
                                                                                  tmp_path_factory):
    if os.geteuid() != 0:
        pytest.skip("install.sh --root applies sysusers/tmpfiles to the box's root as root")
    from deploy.test_release import _built_once  # the run's one release build
    lab = lab_g
    tarball = _built_once(tmp_path_factory)
    with tarfile.open(tarball) as t:
        sums = next(m for m in t.getmembers() if m.name.endswith("/SHA256SUMS"))
        fingerprint = hashlib.sha256(t.extractfile(sums).read()).hexdigest()
    v1 = lab.head()
    r = lab.playbook()
    assert r.returncode == 0, r.stdout + r.stderr
    for b in lab.boxes:                 # each box's supervisor under its service manager
        lab.start_box(b, service=True)
    for b in lab.boxes:
        wait_for(lambda b=b: _runs(b, v1), timeout=90, interval=0.5, what=f"{b.name} running {v1[:12]}")
    box1, box2, box3 = lab.boxes
    pub(broker.port, BOX2_CMD.replace("/cmd/stop", "/cmd/start"),
        '{"sample_id": "S-box-2", "t_set": 0.5, "request_id": "g-start"}')
    wait_log(box2.proc, f"{box2.station}: test_started", timeout=90)
    pids = {b.name: _station(b)["pid"] for b in lab.boxes}
    sups = {b.name: b.status()["supervisor"]["pid"] for b in lab.boxes}
    release = {"hookwatch_release_tarball": tarball, "hookwatch_release_fingerprint": fingerprint,
               # the new release's own hookwatch asks for the restarts (the software it runs)
               "hookwatch_cmd": "{{ hookwatch_root }}/usr/local/bin/hookwatch",
               # the lab's supervisors are this checkout's; a rebuilt release of the same version:
               # every worker restarts on it
               "hookwatch_restart_all": True,
               # then the service itself, as systemctl restart does (the lab's service manager)
               "hookwatch_restart_service": True, "hookwatch_restart_command": restart_command()}
    done: list[subprocess.CompletedProcess] = []
    runner = threading.Thread(target=lambda: done.append(lab.playbook("release.yml", **release)))
    runner.start()
    journal2 = box2.state / "config" / "journal.jsonl"
    try:
        # box 1 (the canary) restarted at once; box 2's restart waits for its running test
        wait_for(lambda: _station(box1).get("pid") not in (None, pids["box-1"]), timeout=600, interval=1,
                 what="box-1's worker on the release")
        # box 2's supervisor has taken the release's request (its journal: `restart`, the id the
        # role gives: the fingerprint), and the role has asked again since (`restart_requested`
        # is written once, the retries await it): its test goes on, its worker too
        wait_for(lambda: journal2.exists() and f'"event":"restart","id":"{fingerprint}"'
                 in journal2.read_text().replace(" ", ""), timeout=600, interval=0.5,
                 what="box-2's supervisor took the restart request")
        s2 = _station(box2)
        assert s2["in_test"] and s2["pid"] == pids["box-2"], s2
        assert runner.is_alive()                                        # the wave waits for it
        pub(broker.port, BOX2_CMD, '{"request_id": "end-of-test"}')
    finally:
        runner.join(900)
    (r,) = done
    assert r.returncode == 0, r.stdout + r.stderr
    waited = r.stdout.split("TASK [hookwatch_site : Each station's worker on the new software")[2]
    assert "FAILED - RETRYING: [box-2]" in waited.split("TASK [", 1)[0], waited
    # as the play ends, each box runs a NEW supervisor process (the role waited for it, not for
    # the old one still answering), on the release, with its station's worker running on it
    for b in lab.boxes:
        st = b.status()
        assert st["online"] and st["supervisor"]["pid"] != sups[b.name], (b.name, st)
        s = st["stations"][b.station]
        assert s["running"] and s["software"] == st["supervisor"]["software"], (b.name, st)
        assert _station(b)["pid"] != pids[b.name], b.name
        assert (b.dir / "release" / "installed").read_text().strip() == fingerprint
        hw = b.dir / "root" / "usr" / "local" / "bin" / "hookwatch"
        assert subprocess.run([str(hw), "--version"], capture_output=True, text=True).stdout.startswith("hookwatch ")
        assert b.current() == v1
        # each worker restarted once for the release (the role's retries asked for it once)
        assert b.proc.log_all().count("worker ended for its restart") == 1, b.name
    # box 2's test ended by its operator, not by the release; nothing of it lost
    first = test_dirs(box2.dir, box2.station)[0]
    res = read_json(os.path.join(first, "result.json"))
    assert res["end_reason"] == "stopped by command", res
    assert analyze_cli(os.path.join(first, "log.csv.gz")) == res["method"]
    # the same release again installs nothing
    again = lab.playbook("release.yml", **release)
    assert again.returncode == 0, again.stdout + again.stderr
    assert all(recap(again)[b.name]["changed"] == 0 for b in lab.boxes), again.stdout
