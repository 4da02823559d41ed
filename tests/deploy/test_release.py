"""The offline release (issue 22 item 5): `scripts/build-release` makes one tarball; its
`install.sh` installs it with the network cut (`unshare -n`: a namespace with nothing but a
loopback), into a scratch root as if it were /: units, udev rules, sysusers/tmpfiles, logrotate, the
default configuration under /etc, a venv from the bundled wheels. The installed copy then checks a
station and runs a short test against the installed `hookwatch sim`, still without a network; an
upgrade in place keeps the configuration and the records; uninstalling removes the rest."""
from __future__ import annotations

import base64
import fcntl
import glob
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import zipfile

import pytest
import yaml

from conftest import ROOT
from kit.tools import require_tool


def _sh(argv, **kw):
    kw.setdefault("timeout", 900)
    r = subprocess.run(argv, capture_output=True, text=True, **kw)
    assert r.returncode == 0, f"{argv}: {r.returncode}\n{r.stdout}\n{r.stderr}"
    return r


def _offline(script: str, **kw):
    """Run a shell script with no network at all (a fresh network namespace: only lo, brought up)."""
    return _sh([require_tool("unshare"), "-n", "sh", "-ec", "ip link set lo up\n" + script], **kw)


#: what the module's build made (the release fixture fills it)
_BUILT: dict[str, int] = {}


def _extract(tarball: str, dest: str) -> None:
    """Unpack the tarball, refusing members that would land outside ``dest`` (absolute paths, ``..``,
    links out). ``extractall(filter="tar")`` does this but is Python 3.11.4+; Debian 12 ships 3.11.2."""
    top = os.path.realpath(dest)
    with tarfile.open(tarball) as t:
        members = t.getmembers()
        for m in members:
            target = os.path.realpath(os.path.join(top, m.name))
            assert target == top or target.startswith(top + os.sep), f"{m.name} leaves the tarball's folder"
            if m.issym() or m.islnk():
                base = top if m.islnk() else os.path.dirname(target)
                link = os.path.realpath(os.path.join(base, m.linkname))
                assert link.startswith(top + os.sep), f"{m.name} links out of the tarball's folder: {m.linkname}"
            assert not (m.ischr() or m.isblk() or m.isfifo()), f"{m.name} is a device or fifo"
        if hasattr(tarfile, "tar_filter"):      # 3.11.4+ (3.12+ warns without a filter)
            t.extractall(top, members, filter="tar")
        else:
            t.extractall(top, members)


def _built_once(tmp_path_factory) -> str:
    """The tarball, built once per run: the run's xdist workers share one build (the first to take
    the lock builds it, the others wait for it and take it), in the run's own temporary folder — a
    new one every run, so nothing is carried over from an earlier run. Each test once rebuilt it on
    its own worker (45–67 s each, four times a run)."""
    base = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        base = base.parent          # pytest-N/ of this run, above its workers' popen-gwK/
    dist = base / "release-dist"
    with open(base / "release-dist.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)            # released when the file is closed
        built = dist / "BUILT"
        if not built.is_file():
            shutil.rmtree(dist, ignore_errors=True)      # a failed build's leftovers
            dist.mkdir()
            r = _sh([os.path.join(ROOT, "scripts", "build-release"), str(dist)])
            (tarball,) = glob.glob(str(dist / "hookwatch-*.tar.gz"))
            assert r.stdout.strip() == tarball
            built.write_text(tarball)
        return built.read_text()


@pytest.fixture(scope="session")
def release(tmp_path_factory):
    """The release, unpacked once per worker. A test that changes it works on its own copy
    (`_variant`, or a full copy), never on this folder."""
    if os.geteuid() != 0:
        pytest.skip("unshare -n needs root (CI runs as root)")
    require_tool("ip")
    tarball = _built_once(tmp_path_factory)
    _BUILT["tarball_bytes"] = os.path.getsize(tarball)
    unpacked = tmp_path_factory.mktemp("unpacked")
    _extract(tarball, str(unpacked))
    (top,) = os.listdir(unpacked)
    return os.path.join(unpacked, top)


def _on_path(root: str) -> str | None:
    """Where a shell with Debian's PATH (inside root) finds `hookwatch`."""
    path = ":".join(os.path.join(root, d) for d in ("usr/local/sbin", "usr/local/bin", "usr/sbin", "usr/bin"))
    return shutil.which("hookwatch", path=path)


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
    # `hookwatch` is on PATH (Debian's PATH has /usr/local/bin): a link through the one switch
    on_path = _on_path(root)
    assert on_path == os.path.join(root, "usr", "local", "bin", "hookwatch")
    assert os.path.realpath(on_path) == os.path.realpath(hw)
    assert _sh([on_path, "--version"]).stdout.strip().startswith("hookwatch ")

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
    assert _on_path(root) is None and not os.path.lexists(os.path.join(root, "usr/local/bin/hookwatch"))
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


# --- issue 27 item 6: the release verifies everything it installs ---------------------------------

def _variant(release: str, dest: str) -> str:
    """A copy of the unpacked release (hard links: a file to be changed is rewritten, never edited)."""
    shutil.copytree(release, dest, copy_function=os.link)
    return dest


def _rewrite(path: str, data: str | bytes) -> None:
    """Replace a file by a new one (its hard-linked original in the fixture stays as it was)."""
    if os.path.lexists(path):
        os.unlink(path)
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "wb") as f:
        f.write(data.encode() if isinstance(data, str) else data)


def _read(path: str) -> str:
    with open(path, encoding="utf-8") as f:
        return f.read()


def _remanifest(top: str) -> None:
    """SHA256SUMS made anew, as scripts/build-release makes it: a properly built next release."""
    _sh([sys.executable, os.path.join(ROOT, "packaging", "release.py"), "manifest", top])


def _install(top: str, root: str, *extra: str, prefix: tuple[str, ...] = ()) -> subprocess.CompletedProcess:
    return subprocess.run([*prefix, require_tool("unshare"), "-n", os.path.join(top, "install.sh"), "--root", root,
                           *extra], capture_output=True, text=True, timeout=900)


def _evil_wheel(path: str, marker: str) -> None:
    """pyarrow 99.0 (newer than any real one, so pip would prefer it) with a .pth: Python runs it at
    every start of the venv's interpreter — as root during an install."""
    files = {
        "pyarrow_evil.pth": f"import os; open({marker!r}, 'w').write(str(os.geteuid()))\n",
        "pyarrow/__init__.py": "",
        "pyarrow-99.0.dist-info/METADATA": "Metadata-Version: 2.1\nName: pyarrow\nVersion: 99.0\n",
        "pyarrow-99.0.dist-info/WHEEL":
            "Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n",
    }
    record = []
    with zipfile.ZipFile(path, "w") as z:
        for name, text in files.items():
            data = text.encode()
            z.writestr(name, data)
            digest = base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b"=").decode()
            record.append(f"{name},sha256={digest},{len(data)}")
        z.writestr("pyarrow-99.0.dist-info/RECORD", "\n".join(record) + "\npyarrow-99.0.dist-info/RECORD,,\n")


def _state(root: str) -> dict[str, str | None]:
    """What an install leaves on the box: every file's content hash and every link's target."""
    out: dict[str, str | None] = {}
    for dirpath, dirnames, filenames in os.walk(root):
        if os.path.relpath(dirpath, root).startswith(os.path.join("opt", "hookwatch", "venvs") + os.sep):
            dirnames.clear()      # a venv is named by its folder (listed below); its insides are pip's
        for name in dirnames + filenames:
            p = os.path.join(dirpath, name)
            rel = os.path.relpath(p, root)
            if os.path.islink(p):
                out[rel] = "-> " + os.readlink(p)
            elif os.path.isfile(p):
                with open(p, "rb") as f:
                    out[rel] = hashlib.sha256(f.read()).hexdigest()
            else:
                out[rel] = None
    return out


def test_an_unlisted_wheel_is_refused_and_nothing_runs(release, tmp_path):
    """An extra wheel that SHA256SUMS does not list (pyarrow 99.0 with a .pth) is refused by name
    before anything is written; its code never runs. A manifest that is not the signed-off one
    (--expect) and a unit changed in the tarball are refused the same way."""
    bad = _variant(release, str(tmp_path / "bad"))
    marker = str(tmp_path / "pth-ran")
    _evil_wheel(os.path.join(bad, "wheels", "pyarrow-99.0-py3-none-any.whl"), marker)
    root = str(tmp_path / "root")
    r = _install(bad, root)
    assert r.returncode != 0, r.stderr
    assert "'wheels/pyarrow-99.0-py3-none-any.whl' is in the release but not in SHA256SUMS" in r.stderr, r.stderr
    assert not os.path.exists(marker), "the unlisted wheel's code ran"
    assert not os.path.exists(root), "a refused release wrote something"

    # a unit changed in the tarball (SHA256SUMS left as built): refused, named
    bad2 = _variant(release, str(tmp_path / "bad2"))
    unit = os.path.join(bad2, "deploy", "systemd", "hookwatch-fleet.service")
    _rewrite(unit, _read(unit).replace("User=hookwatch\n", "User=root\n"))
    r = _install(bad2, root)
    assert r.returncode != 0 and "'deploy/systemd/hookwatch-fleet.service' does not match its SHA-256" in r.stderr, \
        r.stderr
    assert not os.path.exists(root)

    # the release as built, but not the one signed off: its manifest's fingerprint differs
    r = _install(release, root, "--expect", "0" * 64)
    assert r.returncode != 0 and "not the release that was signed off" in r.stderr, r.stderr
    assert not os.path.exists(root)


def test_a_configuration_name_with_a_space_installs(release, tmp_path):
    top = _variant(release, str(tmp_path / "rel"))
    loom = _read(os.path.join(top, "config", "stations", "loom-01.yaml")).replace("loom-01", "loom-05")
    _rewrite(os.path.join(top, "config", "stations", "loom 05.yaml"), loom)
    meter = _read(os.path.join(top, "config", "meters", "zn-s.yaml"))
    _rewrite(os.path.join(top, "config", "meters", "zn-s custom.yaml"), meter)
    _remanifest(top)
    root = str(tmp_path / "root")
    r = _install(top, root)
    assert r.returncode == 0, r.stderr
    share = os.path.join(root, "opt", "hookwatch", "share", "config")
    assert _read(os.path.join(share, "stations", "loom 05.yaml")) == loom
    assert _read(os.path.join(root, "etc", "hookwatch", "meters", "zn-s custom.yaml")) == meter
    assert "installed" in r.stderr
    _sh([os.path.join(root, "usr", "local", "bin", "hookwatch"), "--version"])


def test_a_failing_upgrade_changes_nothing(release, tmp_path):
    """The old release stays active and working whatever step of an upgrade fails: a wheel whose
    hash does not match (found first), and a file that cannot be replaced half-way through the
    commit (a bind mount: the kernel refuses to rename it) after a unit was already replaced."""
    root = str(tmp_path / "root")
    r = _install(release, root)
    assert r.returncode == 0, r.stderr
    hw = os.path.join(root, "usr", "local", "bin", "hookwatch")
    version = _sh([hw, "--version"]).stdout
    before = _state(root)
    assert any(k.startswith(os.path.join("opt", "hookwatch", "venvs", "")) for k in before)

    # 1. a damaged wheel in the upgrade
    bad = _variant(release, str(tmp_path / "bad"))
    (whl,) = glob.glob(os.path.join(bad, "wheels", "hookwatch-*.whl"))
    with open(whl, "rb") as f:
        data = bytearray(f.read())
    data[100:104] = b"XXXX"
    _rewrite(whl, bytes(data))
    r = _install(bad, root)
    assert r.returncode != 0 and "does not match its SHA-256 in SHA256SUMS" in r.stderr, r.stderr
    assert _state(root) == before
    assert _sh([hw, "--version"]).stdout == version

    # 2. a next release that changes a unit, the logrotate file and the udev rules; the installed
    # logrotate file is a mount point, so its replacement fails after the unit was replaced
    nxt = _variant(release, str(tmp_path / "next"))
    for rel, line in (("deploy/systemd/hookwatch-fleet.service", "# next release\n"),
                      ("deploy/logrotate/hookwatch", "# next release\n"),
                      ("deploy/udev/99-hookwatch.rules", "# next release\n")):
        p = os.path.join(nxt, *rel.split("/"))
        _rewrite(p, _read(p) + line)
    _remanifest(nxt)
    busy = os.path.join(root, "etc", "logrotate.d", "hookwatch")
    script = f'mount --bind "{busy}" "{busy}"\nexec "{nxt}/install.sh" --root "{root}"\n'
    r = subprocess.run([require_tool("unshare"), "-n", "-m", "sh", "-ec", script],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode != 0, r.stderr
    assert "nothing was changed" in r.stderr and "still installed and active" in r.stderr, r.stderr
    after = _state(root)
    assert after == before, {k: (before.get(k), after.get(k)) for k in set(before) | set(after)
                             if before.get(k) != after.get(k)}
    assert _sh([hw, "--version"]).stdout == version
    # the old release still works: it checks a station file
    demo = os.path.join(root, "opt", "hookwatch", "share", "config", "demo", "station.yaml")
    assert "1 OK" in _sh([hw, "check", demo]).stdout


def test_a_changed_unit_is_reported_never_replaced_silently(release, tmp_path):
    """An upgrade that changes a unit shows the change (a diff); a unit the administrator edited is
    kept, and the release's version and the command that takes it are shown."""
    root = str(tmp_path / "root")
    r = _install(release, root)
    assert r.returncode == 0, r.stderr
    units = os.path.join(root, "etc", "systemd", "system")
    edited = _read(os.path.join(units, "hookwatch@.service")).replace(
        "ExecStart=/opt/hookwatch/venv/bin/hookwatch run", "ExecStart=/opt/hookwatch/venv/bin/hookwatch run -v")
    _rewrite(os.path.join(units, "hookwatch@.service"), edited)

    nxt = _variant(release, str(tmp_path / "next"))
    for unit in ("hookwatch-fleet.service", "hookwatch@.service"):
        p = os.path.join(nxt, "deploy", "systemd", unit)
        text = _read(p)
        assert "TimeoutStartSec=60s\n" in text
        _rewrite(p, text.replace("TimeoutStartSec=60s\n", "TimeoutStartSec=90s\n"))
    _remanifest(nxt)
    r = _install(nxt, root)
    assert r.returncode == 0, r.stderr
    # the unchanged-on-site unit: replaced, and the change shown
    assert "UPDATED /etc/systemd/system/hookwatch-fleet.service" in r.stderr, r.stderr
    assert "-TimeoutStartSec=60s" in r.stderr and "+TimeoutStartSec=90s" in r.stderr, r.stderr
    assert "TimeoutStartSec=90s\n" in _read(os.path.join(units, "hookwatch-fleet.service"))
    # the edited one: kept, the difference and the way to take the release's shown
    assert "KEPT /etc/systemd/system/hookwatch@.service" in r.stderr, r.stderr
    assert "install -m 644 /opt/hookwatch/share/deploy/systemd/hookwatch@.service" in r.stderr, r.stderr
    assert _read(os.path.join(units, "hookwatch@.service")) == edited
    assert "TimeoutStartSec=90s" in _read(os.path.join(root, "opt", "hookwatch", "share", "deploy", "systemd",
                                                       "hookwatch@.service"))
    # once taken, the next upgrade treats it as the release's again (no note)
    shutil.copyfile(os.path.join(root, "opt", "hookwatch", "share", "deploy", "systemd", "hookwatch@.service"),
                    os.path.join(units, "hookwatch@.service"))
    r = _install(nxt, root)
    assert r.returncode == 0 and "KEPT" not in r.stderr and "UPDATED" not in r.stderr, r.stderr


def test_the_documented_tarball_size_is_the_measured_one(release):
    """docs/deploy.md §1.2 states the size of the tarball: within a fifth of what was just built."""
    doc = _read(os.path.join(ROOT, "docs", "deploy.md"))
    m = re.search(r"hookwatch-<version>-py311-<arch>\.tar\.gz \((\d+) MB measured", doc)
    assert m, "docs/deploy.md §1.2 does not state the tarball's measured size"
    built_mb = _BUILT["tarball_bytes"] / 1e6
    assert abs(int(m.group(1)) - built_mb) <= 0.2 * built_mb, (m.group(1), built_mb)
