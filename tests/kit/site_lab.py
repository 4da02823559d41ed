"""A site of boxes on this machine, rolled out by the real ``ansible-playbook`` (issue 37 item 9).

- **the site repository**: a bare Git repository (``site.git``, the one every box fetches from)
  and the author's clone (``work/``), whose commits are signed with an OpenSSH key made here
  (``ssh-keygen``; ``git -c gpg.format=ssh commit -S``); the boxes' allowed signers list that key;
- **N boxes**, each with its own settings file (written by the role from the inventory), state
  folder, configuration, ports and supervisor process (``hookwatch run STATE/config/current``,
  started again by :meth:`SiteLab.start_box` as systemd would, with ``--realtime 20``);
- **one virtual station per box** from one ``hookwatch sim --count N`` (links ``simNN/``);
- **the inventory** the test writes: the ``local`` connection, per-host variables (box name, box
  file, state folder, the hookwatch command), the canary pause 0, and the playbook run with
  ``ANSIBLE_HOME`` under the test's folder (nothing shared with another run).
Also used by ``bench/bench_rollout.py`` (the time from ``git push`` to every box applied)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from conftest import ROOT, hookwatch_cmd
from kit.e2e import METER_MAP, QUICK_METHOD, sim_fleet
from kit.proc import Proc
from kit.tools import require_tool

ANSIBLE_DIR = os.path.join(ROOT, "deploy", "ansible")
#: what the signer's key is called in the allowed signers (and the author of the commits)
SIGNER = "ops@site-lab"


def _run(argv: list[str], cwd: str | Path | None = None, check: bool = True, **kw: Any) -> subprocess.CompletedProcess:
    r = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=kw.pop("timeout", 120), **kw)
    if check and r.returncode != 0:
        raise AssertionError(f"{argv}: exit {r.returncode}\n{r.stdout}\n{r.stderr}")
    return r


def ansible_playbook() -> str:
    """The venv's ansible-playbook (ansible-core, the test extras), else the one on PATH."""
    exe = os.path.join(os.path.dirname(sys.executable), "ansible-playbook")
    return exe if os.path.exists(exe) else require_tool("ansible-playbook")


@dataclass
class Box:
    name: str
    dir: Path            # the box's folder: box.yaml, allowed_signers, state/, records/
    station: str         # its one station's id
    sim: str             # its virtual station (links/<sim>/meter, stm32)
    proc: Proc | None = None

    @property
    def state(self) -> Path:
        return self.dir / "state"

    @property
    def box_file(self) -> Path:
        return self.dir / "box.yaml"

    @property
    def records(self) -> Path:
        return self.dir / "records"

    def current(self) -> str | None:
        """The version the box's current symlink points at (None before the first apply)."""
        link = self.state / "config" / "current"
        return os.path.basename(os.readlink(link)) if os.path.islink(link) else None

    def status(self) -> dict[str, Any]:
        """``hookwatch config status --json`` of the box."""
        r = _run(hookwatch_cmd() + ["config", "status", "--box-file", str(self.box_file),
                                    "--state-dir", str(self.state), "--json"], cwd=ROOT)
        return json.loads(r.stdout)


class SiteLab:
    """The site repository, the boxes, their virtual stations and the playbook runs."""

    def __init__(self, tmp_path: Path, broker_port: int, n_boxes: int = 3, *,
                 stations: dict[str, dict[str, Any]] | None = None, health_timeout_s: float = 60):
        for tool in ("git", "ssh-keygen"):
            require_tool(tool)
        self.tmp = tmp_path
        self.broker_port = broker_port
        self.health_timeout_s = health_timeout_s
        self.boxes = [Box(f"box-{i}", tmp_path / "boxes" / f"box-{i}", f"loom-{i}1", f"sim{i:02d}")
                      for i in range(1, n_boxes + 1)]
        #: per box name, sections merged into its station's file (e.g. `test: {autostart: true}`)
        self.station_extra = stations or {}
        self.origin = tmp_path / "site.git"
        self.work = tmp_path / "work"
        self.keys = tmp_path / "keys"
        self.sim: Proc | None = None
        self.links = ""
        self.runs: list[subprocess.CompletedProcess] = []

    # ------------------------------------------------------------------ the site repository
    def make(self) -> SiteLab:
        """Keys, the bare repository and the author's clone, the virtual stations, the first
        signed commit pushed (nothing applied yet)."""
        self.keys.mkdir()
        key = self.keys / "ops"
        _run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", SIGNER, "-f", str(key)])
        pub = (self.keys / "ops.pub").read_text().split()
        (self.keys / "allowed_signers").write_text(f'{SIGNER} namespaces="git" {pub[0]} {pub[1]}\n')
        _run(["git", "init", "-q", "--bare", "-b", "main", str(self.origin)])
        _run(["git", "init", "-q", "-b", "main", str(self.work)])
        for k, v in (("user.name", "Site Ops"), ("user.email", SIGNER), ("gpg.format", "ssh"),
                     ("user.signingkey", str(key)), ("commit.gpgsign", "false")):
            _run(["git", "config", k, v], cwd=self.work)
        _run(["git", "remote", "add", "origin", str(self.origin)], cwd=self.work)
        for b in self.boxes:
            (b.dir / "state").mkdir(parents=True)
            b.records.mkdir()
        self.sim, self.links = sim_fleet(self.tmp, len(self.boxes))
        self._write_site()
        self.commit("site: the first version", push=True)
        return self

    def _write_site(self) -> None:
        w = self.work
        (w / "site.yaml").write_text(yaml.safe_dump(
            {"site": "lab", "broker": {"host": "127.0.0.1", "port": self.broker_port}}))
        (w / "maps").mkdir()
        shutil.copy(METER_MAP, w / "maps" / "zn-s.yaml")
        (w / "defaults").mkdir()
        self.write("defaults/fleet.yaml", {"defaults": {
            "station": {"site": "lab", "area": "hall", "line": "l1"},
            "meter": {"map": "maps/zn-s.yaml"},
            "method": dict(QUICK_METHOD),
            "test": {"t_set_n": 0.5, "t_end_s": 120},
            "mqtt": {"enabled": False}, "modbus_tcp": {"enabled": False}}})
        for b in self.boxes:
            self.write(f"boxes/{b.name}/box.yaml", {"defaults": {"recorder": {"dir": str(b.records)}}})
            link = os.path.join(self.links, b.sim)
            extra = self.station_extra.get(b.name, {})
            self.write(f"boxes/{b.name}/stations/{b.station}.yaml", {
                "station": {"id": b.station},
                "meter": {"port": os.path.join(link, "meter")},
                "stm32": {"port": os.path.join(link, "stm32")},
                **extra,
                "test": {"sample_id": f"S-{b.name}", **extra.get("test", {})}})

    def write(self, rel: str, data: Any) -> None:
        p = self.work / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(data if isinstance(data, str) else yaml.safe_dump(data, sort_keys=False))

    def read(self, rel: str) -> Any:
        return yaml.safe_load((self.work / rel).read_text())

    def commit(self, message: str, *, signed: bool = True, push: bool = False) -> str:
        """Everything of the author's clone committed (signed with the lab's key unless
        ``signed=False``); the commit's full sha."""
        _run(["git", "add", "-A"], cwd=self.work)
        _run(["git", "commit", "-q", *(["-S"] if signed else []), "-m", message], cwd=self.work)
        sha = _run(["git", "rev-parse", "HEAD"], cwd=self.work).stdout.strip()
        if push:
            self.push()
        return sha

    def head(self) -> str:
        """The full sha of the author's last commit."""
        return _run(["git", "rev-parse", "HEAD"], cwd=self.work).stdout.strip()

    def push(self) -> None:
        _run(["git", "push", "-q", "origin", "HEAD:main"], cwd=self.work)

    # ------------------------------------------------------------------ Ansible
    def inventory(self, **extra: Any) -> Path:
        """The inventory: every box a host on the ``local`` connection with its own variables."""
        hosts = {}
        for b in self.boxes:
            hosts[b.name] = {
                "hookwatch_box_name": b.name,
                "hookwatch_box_file": str(b.box_file),
                "hookwatch_state_dir": str(b.state),
                "hookwatch_site_checkout": str(b.dir / "site"),
                "hookwatch_allowed_signers": str(b.dir / "allowed_signers"),
                "hookwatch_release_dir": str(b.dir / "release"),
                "hookwatch_root": str(b.dir / "root"),          # install.sh --root (release.yml)
            }
        inv = {"hookwatch_boxes": {"hosts": hosts, "vars": {
            "ansible_connection": "local",
            "ansible_python_interpreter": sys.executable,
            "hookwatch_cmd": hookwatch_cmd()[0],
            "hookwatch_controller_cmd": hookwatch_cmd()[0],
            "hookwatch_site_repo": f"file://{self.origin}",
            "hookwatch_controller_checkout": str(self.tmp / "controller" / "site"),
            "hookwatch_allowed_signers_src": str(self.keys / "allowed_signers"),
            "hookwatch_owner": "", "hookwatch_group": "",
            "hookwatch_health_timeout_s": self.health_timeout_s,
            "hookwatch_canary_pause_s": 0,
            **extra}}}
        path = self.tmp / "inventory.yml"
        path.write_text(yaml.safe_dump(inv, sort_keys=False))
        return path

    def playbook(self, playbook: str = "site.yml", *args: str, timeout: float = 600,
                 **extra: Any) -> subprocess.CompletedProcess:
        """``ansible-playbook -i INVENTORY PLAYBOOK ARGS`` from deploy/ansible (its ansible.cfg),
        with its own ANSIBLE_HOME; the completed run (also kept in ``runs``)."""
        inv = self.inventory(**extra)
        home = self.tmp / "ansible-home"
        env = dict(os.environ, ANSIBLE_HOME=str(home), ANSIBLE_LOCAL_TEMP=str(home / "tmp"),
                   ANSIBLE_NOCOLOR="1", ANSIBLE_FORCE_COLOR="0",
                   ANSIBLE_CONFIG=os.path.join(ANSIBLE_DIR, "ansible.cfg"),
                   PATH=os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", ""))
        t0 = time.monotonic()
        r = subprocess.run([ansible_playbook(), "-i", str(inv), playbook, *args], cwd=ANSIBLE_DIR,
                           capture_output=True, text=True, timeout=timeout, env=env)
        self.runs.append(r)
        (self.tmp / f"ansible-{len(self.runs)}.log").write_text(
            f"# {' '.join(args)}: {time.monotonic() - t0:.1f} s\n" + r.stdout + "\n--- stderr\n" + r.stderr)
        return r

    # ------------------------------------------------------------------ the boxes' processes
    def start_box(self, b: Box, *, service: bool = False) -> Proc:
        """The box's supervisor on its current version, as the fleet unit runs it; ``service``:
        under :data:`SERVICE`, which starts it again whenever it ends (``Restart=always``), so
        that :func:`restart_command` restarts it as ``systemctl restart`` does."""
        n = sum(1 for p in self.tmp.glob(f"{b.name}-run*.log"))
        argv = hookwatch_cmd() + ["run", str(b.state / "config" / "current"), "--realtime", "20"]
        b.proc = Proc(["sh", "-c", SERVICE, "service", *argv] if service else argv,
                      str(self.tmp / f"{b.name}-run{n + 1}.log"),
                      env=dict(os.environ, HOOKWATCH_BOX_FILE=str(b.box_file)))
        return b.proc

    def stop(self) -> None:
        for b in self.boxes:
            if b.proc is not None:
                b.proc.stop()
        if self.sim is not None:
            self.sim.stop()


#: the box's service manager in the lab (systemd's ``Restart=always``): the supervisor started
#: again whenever it ends; SIGTERM to the manager stops it and its supervisor
SERVICE = ('trap \'kill -TERM "$child" 2>/dev/null; wait "$child"; exit 0\' TERM INT; '
           'while :; do "$@" & child=$!; wait "$child"; sleep 0.2; done')


def restart_command() -> list[str]:
    """``hookwatch_restart_command`` of a lab box run under :data:`SERVICE` (an inventory template:
    the box's own state folder): its supervisor ended by SIGTERM, as ``systemctl restart`` does,
    and started again by the lab's service manager."""
    return ["sh", "-c", 'kill -TERM "$(cat "$1"/config/supervisor.pid)"', "restart",
            "{{ hookwatch_state_dir }}"]


def recap(run: subprocess.CompletedProcess) -> dict[str, dict[str, int]]:
    """PLAY RECAP of an ansible-playbook run: host → {ok, changed, failed, skipped, ...}."""
    out: dict[str, dict[str, int]] = {}
    lines = run.stdout.split("PLAY RECAP", 1)[-1].splitlines()
    for ln in lines[1:]:
        if ":" not in ln:
            continue
        host, _, rest = ln.partition(":")
        kv = dict(x.split("=", 1) for x in rest.split() if "=" in x)
        out[host.strip()] = {k: int(v) for k, v in kv.items() if v.isdigit()}
    return out

