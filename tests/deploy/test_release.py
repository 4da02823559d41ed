"""The offline release (issue 22 item 5): `scripts/build-release` makes one tarball; its
`install.sh` installs it with the network cut (`unshare -n`: a namespace with nothing but a
loopback), into a scratch root as if it were /: units, udev rules, sysusers/tmpfiles, logrotate, the
default configuration under /etc, a venv from the bundled wheels. The installed copy then checks a
station and runs a short test against the installed `hookwatch sim`, still without a network; an
upgrade in place keeps the configuration and the records; uninstalling removes the rest."""
from __future__ import annotations

import glob
import json
import os
import shutil
import subprocess
import tarfile

import pytest
import yaml

from conftest import ROOT
from kit.tools import require_tool

pytestmark = pytest.mark.slow


def _sh(argv, **kw):
    kw.setdefault("timeout", 900)
    r = subprocess.run(argv, capture_output=True, text=True, **kw)
    assert r.returncode == 0, f"{argv}: {r.returncode}\n{r.stdout}\n{r.stderr}"
    return r


def _offline(script: str, **kw):
    """Run a shell script with no network at all (a fresh network namespace: only lo, brought up)."""
    return _sh([require_tool("unshare"), "-n", "sh", "-ec", "ip link set lo up\n" + script], **kw)


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    if os.geteuid() != 0:
        pytest.skip("unshare -n needs root (CI runs as root)")
    require_tool("ip")
    out = tmp_path_factory.mktemp("dist")
    r = _sh([os.path.join(ROOT, "scripts", "build-release"), str(out)])
    (tarball,) = glob.glob(str(out / "hookwatch-*.tar.gz"))
    assert r.stdout.strip() == tarball
    unpacked = tmp_path_factory.mktemp("unpacked")
    with tarfile.open(tarball) as t:
        t.extractall(unpacked, filter="tar")
    (top,) = os.listdir(unpacked)
    return os.path.join(unpacked, top)


def _station(root: str, links: str, records: str) -> str:
    etc = os.path.join(root, "etc", "hookwatch")
    cfg = {
        "station": {"id": "loom-t", "site": "lab", "area": "test", "line": "l1"},
        "meter": {"port": os.path.join(links, "meter"), "map": os.path.join(etc, "meters", "zn-s.yaml")},
        "stm32": {"port": os.path.join(links, "stm32")},
        "method": {"w_ss": 2, "w_hold": 8, "tau": 2},
        "test": {"sample_id": "REL-1", "grade": "I", "t_set_n": 0.5, "t_end_s": 4},
        "recorder": {"dir": records},
        "mqtt": {"enabled": False}, "modbus_tcp": {"enabled": False},
    }
    path = os.path.join(etc, "stations", "loom-t.yaml")
    with open(path, "w") as f:
        yaml.safe_dump(cfg, f, sort_keys=False)
    return path


def test_release_installs_runs_upgrades_and_uninstalls_offline(release, tmp_path):
    root = str(tmp_path / "root")
    _offline(f"{release}/install.sh --root {root}")
    opt = os.path.join(root, "opt", "hookwatch")
    hw = os.path.join(opt, "venv", "bin", "hookwatch")
    for f in ("etc/systemd/system/hookwatch-fleet.service", "etc/systemd/system/hookwatch@.service",
              "etc/sysusers.d/hookwatch.conf", "etc/tmpfiles.d/hookwatch.conf", "etc/logrotate.d/hookwatch",
              "etc/udev/rules.d/99-hookwatch.rules", "etc/hookwatch/fleet.yaml", "etc/hookwatch/meters/zn-s.yaml"):
        assert os.path.isfile(os.path.join(root, f)), f
    assert os.path.isdir(os.path.join(root, "var", "lib", "hookwatch", "records"))   # tmpfiles applied
    # the installed copy is the product alone: no test extras came with it
    py = os.path.join(opt, "venv", "bin", "python")
    assert _sh([py, "-c", "import importlib.util as u; print(u.find_spec('pytest') is None)"]).stdout.strip() == "True"

    # check + a short run against the installed simulator, no network
    links = str(tmp_path / "links")
    records = os.path.join(root, "var", "lib", "hookwatch", "records")
    station = _station(root, links, records)
    scenario = os.path.join(opt, "share", "config", "scenarios", "quick.yaml")
    _offline(f"""
{hw} sim {scenario} --link-dir {links} >{tmp_path}/sim.log 2>&1 &
sim=$!
for i in $(seq 100); do [ -e {links}/stm32 ] && break; sleep 0.1; done
{hw} check {station}
{hw} run {station} --start --exit-when-done --no-northbound --duration 120 >{tmp_path}/run.log 2>&1 \
  || {{ cat {tmp_path}/run.log; kill $sim; exit 1; }}
kill $sim; wait $sim || true
""", timeout=300)
    (res_path,) = glob.glob(os.path.join(records, "loom-t", "*", "result.json"))
    with open(res_path) as f:
        res = json.load(f)
    assert res["test_status"] == "completed", res
    # offline == online from the installed copy too
    (log,) = glob.glob(os.path.join(records, "loom-t", "*", "log.csv.gz"))
    off = json.loads(_sh([hw, "analyze", log, "--json"]).stdout)
    off.pop("log")
    assert off == res["method"]

    # an upgrade in place keeps the administrator's configuration and the records
    fleet = os.path.join(root, "etc", "hookwatch", "fleet.yaml")
    with open(fleet, "a") as f:
        f.write("# edited on site\n")
    old_target = os.readlink(os.path.join(opt, "venv"))
    r = _offline(f"{release}/install.sh --root {root}")
    assert "upgraded" in r.stderr and "kept" in r.stderr, r.stderr
    with open(fleet) as f:
        assert f.read().endswith("# edited on site\n")
    assert os.path.isfile(res_path) and os.path.isfile(station)
    assert os.readlink(os.path.join(opt, "venv")) != old_target
    assert not os.path.exists(os.path.join(opt, old_target))      # the old venv is gone, not piled up
    _sh([hw, "--version"])

    # uninstall: the software, units and rules go; configuration and records stay
    _offline(f"{release}/install.sh --root {root} --uninstall")
    assert not os.path.exists(opt)
    assert not os.path.exists(os.path.join(root, "etc/systemd/system/hookwatch-fleet.service"))
    assert not os.path.exists(os.path.join(root, "etc/udev/rules.d/99-hookwatch.rules"))
    assert os.path.isfile(fleet) and os.path.isfile(res_path)
    _offline(f"{release}/install.sh --root {root} --uninstall --purge || true")
    shutil.rmtree(root, ignore_errors=True)


def test_a_damaged_release_changes_nothing(release, tmp_path):
    """A wheel that does not match SHA256SUMS: refused before anything is written."""
    bad = str(tmp_path / "bad")
    shutil.copytree(release, bad)
    (whl,) = [w for w in glob.glob(os.path.join(bad, "wheels", "hookwatch-*.whl"))]
    with open(whl, "r+b") as f:
        f.seek(100)
        f.write(b"XXXX")
    root = str(tmp_path / "root")
    r = subprocess.run([require_tool("unshare"), "-n", os.path.join(bad, "install.sh"), "--root", root],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "SHA256SUMS" in r.stderr, r.stderr
    assert not os.path.exists(os.path.join(root, "opt"))
