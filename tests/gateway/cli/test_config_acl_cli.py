"""`hookwatch config acl`: a box's fleet folder or a site description in, the broker's permissions
out; every bad input a clear error with its exit code, nothing written. `hookwatch config` is a
table of subcommands (gateway/cli/config.py). The console command itself runs twice (its
help, and a box); the other cases go through its entry point, `gateway.cli.main`, in process."""
from __future__ import annotations

import os
import shutil
import subprocess

import pytest
import yaml

from conftest import ROOT, hookwatch_cmd
from gateway import cli
from gateway.cli import config as config_cmd


def _cmd(*args: str) -> subprocess.CompletedProcess:
    """The console command a user runs."""
    return subprocess.run(hookwatch_cmd() + ["config", *args], capture_output=True, text=True, timeout=120)


@pytest.fixture
def run(capsys):
    """``hookwatch config ARGS`` through its entry point: (exit code, stdout, stderr)."""
    def _run(*args: str) -> tuple[int, str, str]:
        try:
            code = cli.main(["config", *args])
        except SystemExit as e:         # argparse: usage
            code = int(e.code or 0)
        out = capsys.readouterr()
        return code, out.out, out.err
    return _run


def _box(root, name: str, stations: dict[str, dict], **mqtt) -> str:
    """A fleet folder: fleet.yaml (site, MQTT) + one station file per entry (its own keys)."""
    d = root / name
    (d / "stations").mkdir(parents=True)
    (d / "fleet.yaml").write_text(yaml.safe_dump({"defaults": {
        "station": {"site": "plant-a", "area": "hall", "line": name},
        "recorder": {"dir": str(root / "records")},
        "mqtt": {"enabled": True, "username": "hookwatch-edge", "password_env": "X", **mqtt}}}))
    for sid, extra in stations.items():
        (d / "stations" / f"{sid}.yaml").write_text(yaml.safe_dump({
            "station": {"id": sid}, "meter": {"port": f"/dev/hw/{sid}-m"},
            "stm32": {"port": f"/dev/hw/{sid}-s"}, **extra}))
    return str(d)


def test_config_lists_its_subcommands_from_one_table(run):
    r = _cmd("--help")
    assert r.returncode == 0
    for s in config_cmd.SUBCOMMANDS:
        assert s.name in r.stdout and " ".join(s.help.split()[:4]) in " ".join(r.stdout.split())
    code, _, err = run()
    assert code == 2 and "SUBCOMMAND" in err
    code, out, _ = run("acl", "--help")
    assert code == 0 and "--commander" in out and "--format" in out


def test_a_box_gets_its_stations_under_its_user_name(tmp_path, run):
    box = _box(tmp_path, "b1", {"st-1": {}, "st-2": {"mqtt": {"command_doors": ["panel"]}}})
    r = _cmd("acl", box, "--commander", "mes", "--commander", "op=panel", "--reader", "telegraf")
    assert r.returncode == 0, r.stderr
    acl = r.stdout
    assert "\nuser hookwatch-edge\n" in acl and "\nuser mes\n" in acl and "\nuser telegraf\n" in acl
    assert "topic write hookwatch/plant-a/hall/b1/st-1/lives\n" in acl
    assert "topic write hookwatch/plant-a/hall/b1/st-2/cmd/panel/+\n" in acl
    assert "topic write hookwatch/plant-a/hall/b1/st-1/cmd/panel/+\n" not in acl
    assert "readwrite hookwatch/#" not in acl
    # another identity, and the RabbitMQ form (a shell script sh reads)
    out = tmp_path / "perms.sh"
    code, _, err = run("acl", box, "--identity", "edge-box07", "--commander", "mes", "--format", "rabbitmq",
                       "-o", str(out))
    assert code == 0 and f"{out}: rabbitmq permissions written" in err
    text = out.read_text()
    assert "set_topic_permissions -p \"$VHOST\" 'edge-box07' 'amq.topic'" in text
    assert subprocess.run(["sh", "-n", str(out)]).returncode == 0


def test_a_site_description_names_its_boxes(tmp_path, run):
    _box(tmp_path, "b1", {"st-1": {}})
    _box(tmp_path, "b2", {"st-9": {}})
    site = tmp_path / "site.yaml"
    site.write_text("boxes:\n  edge-1: b1\n  edge-2: b2\ncommanders:\n  mes: default\nreaders: [tg]\n")
    code, out, err = run("acl", str(site), "--bridges")
    assert code == 0, err
    assert "\nuser edge-1\n" in out and "\nuser edge-2\n" in out and "\nuser tg\n" in out
    assert "topic write hookwatch/_bridge/edge-2/state\n" in out


def test_bad_input_is_a_clear_error_and_writes_nothing(tmp_path, run):
    _box(tmp_path, "b1", {"st-1": {}})
    _box(tmp_path, "dup", {"st-1": {"station": {"id": "st-1", "line": "b1"}}})
    out = tmp_path / "acl"

    def fails(args, code, *says):
        got, stdout, err = run("acl", *args, "-o", str(out))
        assert got == code, (args, got, err)
        assert stdout == "" and not out.exists()
        for s in says:
            assert s in err, (s, err)

    site = tmp_path / "site.yaml"
    site.write_text("boxes:\n  edge-1: b1\ncomanders:\n  mes: default\n")
    fails([str(site)], 1, f"{site}:3: unknown key `comanders`")
    site.write_text("boxes:\n  edge-1: b1\n  edge-2: dup\n")
    fails([str(site)], 1, "station 'st-1' (hookwatch/plant-a/hall/b1/st-1) is in box 'edge-1' and in box 'edge-2'")
    site.write_text("boxes:\n  edge-1: nowhere\n")
    fails([str(site)], 1, "nowhere: no such file or folder")
    site.write_text("boxes: [b1]\n")
    fails([str(site)], 1, f"{site}:1: `boxes` must map")
    site.write_text("boxes:\n  edge 1: b1\n")
    fails([str(site)], 1, "box identity 'edge 1'")
    fails([str(tmp_path / "b1"), "--commander", "op=nodoor"], 1, "no station of the site listens on it")
    fails([str(tmp_path / "b1"), "--commander", "op=start"], 1, "is a command's name")
    # a broken station file: the station's own errors, as `hookwatch check` says them
    (tmp_path / "b1" / "stations" / "st-1.yaml").write_text(
        "station: {id: st-1}\nmeter: {port: /dev/hw/m}\nstm32: {port: /dev/hw/s}\nmqtt: {command_doors: [a.b]}\n")
    fails([str(tmp_path / "b1")], 1, "the stations cannot run", "mqtt.command_doors", "'a.b'")
    (tmp_path / "b1" / "stations" / "st-1.yaml").write_text("station: {id: st-1}\n")
    fails([str(tmp_path / "b1")], 1, "the stations cannot run", "meter.port")
    # no user name: which identity?
    _box(tmp_path, "anon", {"st-5": {}}, username=None, password_env=None)
    fails([str(tmp_path / "anon")], 2, "give --identity NAME")
    fails([str(tmp_path / "missing")], 1, "no such file or folder")


def test_the_shipped_example_site_reads_the_same_from_anywhere(tmp_path, run):
    """The example site's box folders are relative to its own file."""
    here = run("acl", os.path.join(ROOT, "deploy", "site-acl", "site.yaml"))
    copy = tmp_path / "repo"
    shutil.copytree(os.path.join(ROOT, "deploy", "site-acl"), copy / "deploy" / "site-acl")
    shutil.copytree(os.path.join(ROOT, "config"), copy / "config")
    there = run("acl", str(copy / "deploy" / "site-acl" / "site.yaml"))
    assert here[0] == there[0] == 0, here[2] + there[2]
    assert here[1].split("\n", 1)[1] == there[1].split("\n", 1)[1]      # the first line names the path
