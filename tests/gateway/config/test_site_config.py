"""Issue 37, without processes of the gateway: `hookwatch config check` on a site repository (the
whole site, one box, a commit), `config plan` on an empty box, the box's state folder (staging,
the atomic switch, the repair of a half-applied version), signatures with a real OpenSSH key."""
from __future__ import annotations

import json
import os
import shutil
import subprocess

from conftest import ROOT, hookwatch_cmd
from gateway.config.site.repository import build
from gateway.config.site.signing import verify_commit
from gateway.config.site.versions import StateDir
from kit.site_repo import Box, SiteRepo, git, ssh_key

LINKS = {"meter": "/dev/ttyS-hw-meter-{}", "stm32": "/dev/ttyS-hw-stm32-{}"}


def _links(i):
    return {k: v.format(i) for k, v in LINKS.items()}


def _site(tmp_path):
    repo = SiteRepo(tmp_path / "site", None)
    for b in ("b1", "b2"):
        repo.box(b, tmp_path / b / "records")
    repo.station("b1", "st-1", _links(1), modbus_tcp={"unit_id": 1})
    repo.station("b1", "st-2", _links(2), modbus_tcp={"unit_id": 2})
    repo.station("b2", "st-3", _links(3))
    return repo


def test_the_shipped_site_example_checks_clean():
    p = subprocess.run(hookwatch_cmd() + ["config", "check", os.path.join(ROOT, "deploy", "site-example"),
                                          "--site"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "3 box(es), 6 station(s): ok" in p.stderr


def test_check_names_file_and_line_in_the_repository_and_ids_across_the_site(tmp_path):
    repo = _site(tmp_path)
    b1 = Box(tmp_path, "b1-box", None)
    assert b1.config("check", str(repo.path), "--site").returncode == 0
    # a fleet default broken in one box's overrides, a serial port twice on one box, an id twice
    # in the site
    repo.edit("boxes/b1/box.yaml", lambda d: d["defaults"].update(meter={"baud": 12345}))
    repo.edit("boxes/b2/stations/st-3.yaml", lambda d: d["station"].update(id="st-1"))
    repo.station("b2", "st-4", _links(3))
    p = b1.config("check", str(repo.path), "--site")
    assert p.returncode == 1, p.stdout + p.stderr
    lines = p.stdout.splitlines()
    box_yaml = (repo.path / "boxes/b1/box.yaml").read_text().splitlines()
    baud_line = next(i for i, t in enumerate(box_yaml, 1) if "baud" in t)
    assert f"boxes/b1/box.yaml:{baud_line}: meter.baud: 12345 is not allowed" in p.stdout, lines
    assert any(ln.startswith("boxes/b2/stations/st-4.yaml:") and "meter.port" in ln
               and "boxes/b2/stations/st-3.yaml:" in ln for ln in lines), lines
    assert any(ln.startswith("boxes/b2/stations/st-3.yaml:") and "'st-1' is also a station of box b1" in ln
               for ln in lines), lines
    # one box only: the rule across boxes is not its business
    p1 = b1.config("check", str(repo.path), "--box", "b2")
    assert p1.returncode == 1 and "also a station of box" not in p1.stdout and "meter.port" in p1.stdout
    assert b1.config("check", str(repo.path), "--box", "nope").returncode == 1


def _line(repo, rel, needle):
    return next(i for i, t in enumerate((repo.path / rel).read_text().splitlines(), 1) if needle in t)


def test_check_site_one_site_name_across_site_yaml_box_yaml_stations_and_topics(tmp_path):
    """The site's name: site.yaml's, every station's station.site (wherever it is set: the
    defaults, a box's box.yaml, a station file) and the MQTT topic prefix of site.yaml's broker
    (a station publishing elsewhere is not on the site's topics) — each error FILE:LINE."""
    repo = _site(tmp_path)
    b1 = Box(tmp_path, "b1-box", None)
    repo.write("site.yaml", {"site": "lab", "broker": {"host": "127.0.0.1", "prefix": "plant"}})
    repo.edit("defaults/fleet.yaml", lambda d: d["defaults"].update(mqtt={"enabled": True, "prefix": "plant"}))
    p = b1.config("check", str(repo.path), "--site")
    assert p.returncode == 0, p.stdout + p.stderr
    # box b2's box.yaml names another site; st-2's own file another; st-1 publishes under the
    # default prefix `hookwatch`, not the site's `plant`
    repo.edit("boxes/b2/box.yaml", lambda d: d["defaults"].update(station={"site": "lab-old"}))
    repo.edit("boxes/b1/stations/st-2.yaml", lambda d: d["station"].update(site="plant-b"))
    repo.edit("boxes/b1/stations/st-1.yaml", lambda d: d.update(mqtt={"prefix": "hookwatch"}))
    p = b1.config("check", str(repo.path), "--site")
    assert p.returncode == 1, p.stdout + p.stderr
    out = p.stdout
    assert (f"boxes/b2/box.yaml:{_line(repo, 'boxes/b2/box.yaml', 'lab-old')}: station.site: "
            "'lab-old' is not the site 'lab'") in out, out
    assert (f"boxes/b1/stations/st-2.yaml:{_line(repo, 'boxes/b1/stations/st-2.yaml', 'plant-b')}: "
            "station.site: 'plant-b' is not the site 'lab'") in out, out
    assert (f"boxes/b1/stations/st-1.yaml:{_line(repo, 'boxes/b1/stations/st-1.yaml', 'prefix')}: "
            "mqtt.prefix: 'hookwatch': the station would publish under hookwatch/lab/") in out, out
    assert "st-3" not in out.replace("boxes/b2/box.yaml", ""), out      # b2's one error, once
    # a station without MQTT may keep any prefix; the site's name is still its own
    repo.edit("boxes/b1/stations/st-1.yaml", lambda d: d["mqtt"].update(enabled=False))
    p = b1.config("check", str(repo.path), "--box", "b1")
    assert "mqtt.prefix" not in p.stdout and "plant-b" in p.stdout, p.stdout


def test_check_and_plan_of_a_commit_and_exit_codes(tmp_path):
    repo = _site(tmp_path)
    sha = repo.commit("first")
    box = Box(tmp_path, "b1", None)
    repo.edit("boxes/b1/stations/st-1.yaml", lambda d: d.update(meter={"port": 5}))   # not committed
    assert box.config("check", str(repo.path), "--version", sha).returncode == 0
    assert box.config("check", str(repo.path)).returncode == 1
    p = box.config("plan", str(repo.path), "--version", sha, "--json")
    assert p.returncode == 3, p.stdout + p.stderr
    plan = json.loads(p.stdout)
    assert {s["station"]: s["status"] for s in plan["stations"]} == {"st-1": "new", "st-2": "new"}
    assert plan["changed"] and plan["version"] == sha
    bad = box.config("plan", str(repo.path), "--json")
    assert bad.returncode == 1 and "boxes/b1/stations/st-1.yaml:" in bad.stderr
    assert box.config("plan", str(repo.path), "--version", "no-such-ref").returncode == 1


def test_staging_switch_and_repair_of_a_half_applied_version(tmp_path):
    repo = _site(tmp_path)
    st = StateDir(str(tmp_path / "state"))
    e1 = build(str(repo.path), "b1")
    assert not e1.problems
    st.stage("a" * 40, e1, "b1")
    st.switch("a" * 40)
    st.mark_verified("a" * 40)
    repo.edit("defaults/fleet.yaml", lambda d: d["defaults"]["method"].update(delta=0.3))
    e2 = build(str(repo.path), "b1")
    assert e2.digest != e1.digest
    # killed after the switch, before the gate: applying.json names it
    st.begin_apply("b" * 40, "a" * 40)
    st.stage("b" * 40, e2, "b1")
    st.switch("b" * 40)
    # and a staging cut off half-way
    os.makedirs(os.path.join(st.versions, ".tmp-" + "c" * 40 + "-1"))
    assert st.current() == "b" * 40
    why = st.repair()
    assert why and "interrupted" in why
    assert st.current() == "a" * 40 and st.applying() is None
    assert not [n for n in os.listdir(st.versions) if n.startswith(".")]
    assert st.last_rollback()["from"] == "b" * 40 and st.last_rollback()["to"] == "a" * 40
    assert st.repair() is None                      # consistent now: nothing to do
    # current naming a version that is not staged whole (its manifest missing)
    st.switch("b" * 40)
    os.unlink(os.path.join(st.versions, "b" * 40, ".hookwatch-version.json"))
    assert "not staged whole" in st.repair()
    assert st.current() == "a" * 40
    # drift: a hand edit of the current tree is named
    assert st.drift() == []
    with open(os.path.join(st.current_link, "stations", "st-1.yaml"), "a") as f:
        f.write("# edited by hand\n")
    assert st.drift() == ["stations/st-1.yaml"]
    # killed while the drifted current version was set aside for its restaging: put back
    os.replace(st.version_dir("a" * 40), os.path.join(st.versions, ".old-" + "a" * 40 + "-77"))
    st.repair()
    assert st.current() == "a" * 40 and st.complete("a" * 40)
    st.stage("a" * 40, e1, "b1")                   # the restaging itself repairs the drift
    assert st.drift() == [] and not [n for n in os.listdir(st.versions) if n.startswith(".")]
    shutil.rmtree(str(tmp_path / "state"))


def test_signed_by_an_allowed_key_only(tmp_path):
    repo = _site(tmp_path)
    key, line = ssh_key(tmp_path, "alice")
    other, other_line = ssh_key(tmp_path, "mallory")
    signers = tmp_path / "allowed_signers"
    signers.write_text(line + "\n")
    good = repo.commit("signed", key)
    repo.edit("defaults/fleet.yaml", lambda d: d["defaults"]["method"].update(delta=0.3))
    bad = repo.commit("signed by an unknown key", other)
    repo.edit("defaults/fleet.yaml", lambda d: d["defaults"]["method"].update(delta=0.35))
    unsigned = repo.commit("unsigned")
    v = verify_commit(str(repo.path), good, str(signers))
    assert v.ok and v.signed, v
    v = verify_commit(str(repo.path), bad, str(signers))
    assert not v.ok and v.signed and "not by an allowed signer" in v.why
    v = verify_commit(str(repo.path), unsigned, str(signers))
    assert not v.ok and not v.signed and "not signed" in v.why
    assert not verify_commit(str(repo.path), good, str(tmp_path / "none")).ok
    assert git(repo.path, "cat-file", "-t", good).stdout.strip() == "commit"


def test_a_link_out_of_the_repository_is_refused(tmp_path):
    repo = _site(tmp_path)
    secret = tmp_path / "secret.yaml"
    secret.write_text("password: hunter2\n")
    os.symlink(str(secret), repo.path / "maps" / "stolen.yaml")
    box = Box(tmp_path, "b1", None)
    p = box.config("check", str(repo.path))
    assert p.returncode == 1 and "maps/stolen.yaml:1: a symbolic link" in p.stdout, p.stdout + p.stderr
    sha = repo.commit("a link")
    p = box.config("plan", str(repo.path), "--version", sha)
    assert p.returncode == 1 and "hunter2" not in p.stdout + p.stderr, p.stdout + p.stderr


def test_the_start_gate_of_a_version_applied_while_no_supervisor_ran(tmp_path):
    """gateway/supervisor/startgate.py, on a real state folder: unverified until every station
    runs the version with its meter read; a station that never reads it within the bound and no
    verified version to go back to: still unverified, saying why; a refused station fails it at
    once; healthy at a later start: verified, and the report says so."""
    from gateway.config.site.boxreport import build_report
    from gateway.supervisor.startgate import StartGate
    a, old = "a" * 40, "b" * 40
    st = StateDir(str(tmp_path / "state"))
    st.ensure()
    st.switch(a)
    st.mark_unverified(a, "no supervisor running", 5)
    assert build_report(st)["unverified"] == {"version": a, "why": "no supervisor running"}
    s1 = {"version": a, "running": True, "meter_ok": False, "in_test": False, "refused": None}
    gate = StartGate(st)
    assert not gate.check(a, {"s1": s1}, 100.0) and st.verified() is None        # within its bound
    assert not gate.check(a, {"s1": s1}, 105.5) and st.verified() is None and st.current() == a
    why = build_report(st)["unverified"]["why"]
    assert why == "health gate at the supervisor's start (5 s): s1: no meter reading", why
    assert [e["event"] for e in st.read_journal()][-1] == "unverified"
    assert not gate.check(a, {"s1": s1}, 200.0)                     # decided once per start
    # a refused station fails the gate at once, without waiting for the bound
    gate = StartGate(st)
    assert not gate.check(a, {"s1": dict(s1, refused="meter.port: no such device")}, 0.0)
    assert "s1: refused: meter.port" in build_report(st)["unverified"]["why"]
    # the next start, every station healthy (one deferred in its test): verified
    gate = StartGate(st)
    s2 = {"version": old, "pending": a, "in_test": True, "running": True, "meter_ok": True, "refused": None}
    assert not gate.check(a, {"s1": dict(s1, meter_ok=True), "s2": s2}, 0.0)
    assert st.verified() == a and build_report(st)["unverified"] is None
    assert st.read_journal()[-1]["event"] == "verified"
    # an unverified.json of another version than current is stale: nothing to gate
    st.mark_unverified(old, "no supervisor running", 5)
    assert st.unverified() is None and not StartGate(st).check(a, {}, 0.0)
