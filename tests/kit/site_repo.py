"""A site repository (real Git, commits signed with a real OpenSSH key) and boxes on this machine
(each its box file, state folder and supervisor process) for the issue-37 tests."""
from __future__ import annotations

import json
import os
import shutil
import subprocess

import yaml

from conftest import ROOT, hookwatch_cmd
from kit.e2e import METER_MAP, QUICK_METHOD
from kit.proc import Proc


def git(repo, *args, check=True) -> subprocess.CompletedProcess:
    env = {**os.environ, "GIT_AUTHOR_NAME": "site", "GIT_AUTHOR_EMAIL": "site@example.org",
           "GIT_COMMITTER_NAME": "site", "GIT_COMMITTER_EMAIL": "site@example.org",
           "GIT_CONFIG_GLOBAL": os.devnull, "GIT_CONFIG_NOSYSTEM": "1"}
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, env=env,
                          check=check, timeout=60)


def ssh_key(folder, name="signer"):
    """An ed25519 key made by ssh-keygen: (private key file, allowed-signers line)."""
    key = os.path.join(str(folder), name)
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", name, "-f", key],
                   check=True, capture_output=True, timeout=30)
    with open(key + ".pub") as f:
        pub = f.read().split()
    return key, f'{name}@example.org namespaces="git" {pub[0]} {pub[1]}'


class SiteRepo:
    """deploy/site-example's layout, with virtual stations and a test broker."""

    def __init__(self, path, broker_port: int | None, defaults: dict | None = None):
        self.path = path
        path.mkdir()
        git(path, "init", "-q", "-b", "main")
        (path / "maps").mkdir()
        shutil.copy(METER_MAP, path / "maps" / "zn-s.yaml")
        site = {"site": "lab"}
        if broker_port:
            site["broker"] = {"host": "127.0.0.1", "port": broker_port, "prefix": "hookwatch"}
        self.write("site.yaml", site)
        base = {
            "station": {"site": "lab", "area": "hall", "line": "l1"},
            "meter": {"map": "maps/zn-s.yaml"},
            "method": dict(QUICK_METHOD),
            "test": {"t_set_n": 0.5, "t_end_s": 70},
            "mqtt": {"enabled": False}, "modbus_tcp": {"enabled": False},
        }
        for k, v in (defaults or {}).items():
            base[k] = {**base.get(k, {}), **v}
        self.write("defaults/fleet.yaml", {"defaults": base})

    def box(self, name: str, records_dir, **defaults) -> None:
        """boxes/NAME/box.yaml: the box's records folder (and further defaults by section)."""
        self.write(f"boxes/{name}/box.yaml", {"defaults": {"recorder": {"dir": str(records_dir)}, **defaults}})
        (self.path / "boxes" / name / "stations").mkdir(parents=True, exist_ok=True)

    def write(self, rel: str, data) -> None:
        p = self.path / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))

    def read(self, rel: str):
        return yaml.safe_load((self.path / rel).read_text())

    def edit(self, rel: str, fn) -> None:
        d = self.read(rel)
        fn(d)
        self.write(rel, d)

    def station(self, box: str, sid: str, links: dict, **sections) -> None:
        self.write(f"boxes/{box}/stations/{sid}.yaml", {
            "station": {"id": sid}, "meter": {"port": links["meter"]}, "stm32": {"port": links["stm32"]},
            "test": {"sample_id": f"S-{sid}"}, **sections})

    def commit(self, msg: str, key: str | None = None) -> str:
        git(self.path, "add", "-A")
        if key:
            git(self.path, "-c", "gpg.format=ssh", "-c", f"user.signingkey={key}", "commit", "-q", "-S",
                "-m", msg)
        else:
            git(self.path, "commit", "-q", "-m", msg)
        return git(self.path, "rev-parse", "HEAD").stdout.strip()


class Box:
    """One box: its box file, state folder, records folder; `hookwatch config …` and its supervisor."""

    def __init__(self, tmp_path, name: str, allowed_signers_line: str | None, allow_unsigned=False,
                 health_timeout_s: float = 60):
        self.name = name
        self.dir = tmp_path / name
        self.dir.mkdir()
        self.state = self.dir / "state"
        self.records = self.dir / "records"
        signers = self.dir / "allowed_signers"
        if allowed_signers_line:
            signers.write_text(allowed_signers_line + "\n")
        self.file = self.dir / "box.yaml"
        self.file.write_text(yaml.safe_dump({"name": name, "state_dir": str(self.state),
                                             "allowed_signers": str(signers),
                                             "allow_unsigned": allow_unsigned,
                                             "health_timeout_s": health_timeout_s}))
        self.sup: Proc | None = None
        self._n = 0

    @property
    def config_dir(self):
        return self.state / "config"

    @property
    def current_dir(self):
        return self.config_dir / "current"

    def config(self, *args, timeout=300) -> subprocess.CompletedProcess:
        return subprocess.run(hookwatch_cmd() + ["config", *args, "--box-file", str(self.file)],
                              capture_output=True, text=True, cwd=ROOT, timeout=timeout)

    def config_popen(self, *args) -> subprocess.Popen:
        return subprocess.Popen(hookwatch_cmd() + ["config", *args, "--box-file", str(self.file)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)

    def current(self) -> str | None:
        try:
            return os.path.basename(os.readlink(self.current_dir))
        except OSError:
            return None

    def verified(self) -> str | None:
        try:
            return (self.config_dir / "verified").read_text().strip()
        except OSError:
            return None

    def status(self) -> dict:
        try:
            return json.loads((self.config_dir / "supervisor.json").read_text())
        except (OSError, ValueError):
            return {}

    def journal(self) -> list[dict]:
        try:
            return [json.loads(x) for x in (self.config_dir / "journal.jsonl").read_text().splitlines() if x]
        except OSError:
            return []

    def start(self, *args) -> Proc:
        self._n += 1
        self.sup = Proc(hookwatch_cmd() + ["run", str(self.current_dir), *args],
                        str(self.dir / f"supervisor-{self._n}.log"))
        return self.sup

    def stop(self) -> int | None:
        if self.sup is None:
            return None
        rc = self.sup.stop()
        return rc
