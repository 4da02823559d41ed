"""hookwatch's offline release: its manifest and its installer (standard library only).

    release.py manifest DIR                  (scripts/build-release) write DIR/SHA256SUMS: the SHA-256
                                             of every file of the release; print its fingerprint
    release.py install [--root R] [--expect SHA256]
    release.py uninstall [--root R] [--purge]
                                             (install.sh runs these, with `python3 -I -S -B`)

The manifest, SHA256SUMS, is checked first: well-formed (`<sha-256>  <relative path>` per line, as
`sha256sum -c` reads it), no path outside the release, and the release's own parts listed. Then
every file of the unpacked release must be listed with its hash, and every listed file present:
anything else (an extra wheel, a symlink, a changed unit) refuses the whole install, naming it.
The listed files are then copied into a private stage and hashed again as they are copied; the
install uses only that copy.

Everything is prepared beside what runs — the new venv (`pip --no-index --require-hashes` from the
verified wheels only), its smoke test, the units, udev rules, sysusers/tmpfiles, logrotate, the
default configuration — and committed with a journal: any failure, up to the last step, puts every
file back and removes the new venv. The last step is the one switch: /opt/hookwatch/venv, a
symlink, renamed to point at the new venv. An upgrade that fails changes nothing.

Files under /etc are the administrator's once installed: one the administrator has edited is kept
(the release's version and the diff are shown, with the command that takes it); one as the last
release left it is updated, and the change is shown. docs/deploy.md §1.2.
"""
from __future__ import annotations

import argparse
import difflib
import fcntl
import functools
import hashlib
import os
import re
import shutil
import stat
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field

MANIFEST = "SHA256SUMS"
# the release's own parts: a manifest that does not list them is not a release
REQUIRED = ("install.sh", "release.py", "VERSION")
_LINE = re.compile(r"([0-9a-f]{64})  (.+)")
_WHEEL = re.compile(r"([A-Za-z0-9_.]+)-([A-Za-z0-9_.!+]+)(-\d[^-]*)?-[^-]+-[^-]+-[^-]+\.whl")
_VERSION = re.compile(r"[0-9A-Za-z][0-9A-Za-z.+_-]{0,63}")
_CHUNK = 1 << 20
# /etc files the package owns: (source in the release, destination under the root)
ETC_FILES = (
    ("deploy/systemd/hookwatch-fleet.service", "etc/systemd/system/hookwatch-fleet.service"),
    ("deploy/systemd/hookwatch@.service", "etc/systemd/system/hookwatch@.service"),
    ("deploy/sysusers.d/hookwatch.conf", "etc/sysusers.d/hookwatch.conf"),
    ("deploy/tmpfiles.d/hookwatch.conf", "etc/tmpfiles.d/hookwatch.conf"),
    ("deploy/logrotate/hookwatch", "etc/logrotate.d/hookwatch"),
)
# how to take the release's version of a kept file
_APPLY = {"etc/systemd/": "systemctl daemon-reload", "etc/udev/": "udevadm control --reload"}
BIN = "usr/local/bin/hookwatch"
BIN_TARGET = "../../../opt/hookwatch/venv/bin/hookwatch"   # relative: right under --root too


class Refused(Exception):
    """The release or the box is not fit to install: nothing was changed."""


def say(msg: str) -> None:
    print(f"hookwatch install: {msg}", file=sys.stderr, flush=True)


def sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def safe_relpath(rel: str) -> bool:
    """A path inside the release: relative, no `..`, no empty part, nothing sha256sum would escape."""
    if not rel or rel.startswith("/") or any(c in rel for c in "\\\n\r\0"):
        return False
    return all(part not in ("", ".", "..") for part in rel.split("/"))


# ----------------------------------------------------------------------------------- the manifest

def write_manifest(top: str) -> str:
    """Write top/SHA256SUMS over every file under top (build side); return its own SHA-256."""
    entries = []
    for dirpath, dirnames, filenames in os.walk(top):
        dirnames.sort()
        for name in filenames:
            path = os.path.join(dirpath, name)
            rel = os.path.relpath(path, top).replace(os.sep, "/")
            if rel == MANIFEST:
                continue
            if not safe_relpath(rel):
                raise SystemExit(f"release.py: {rel!r}: a file name with a backslash or a line break")
            if not stat.S_ISREG(os.lstat(path).st_mode):
                raise SystemExit(f"release.py: {rel}: not a regular file (a release holds files only)")
            entries.append((rel, sha256_file(path)))
    missing = [r for r in REQUIRED if r not in dict(entries)]
    if missing:
        raise SystemExit(f"release.py: the release lacks {', '.join(missing)}")
    text = "".join(f"{digest}  {rel}\n" for rel, digest in sorted(entries))
    temp = os.path.join(top, f".{MANIFEST}.new")
    with open(temp, "w", encoding="utf-8", newline="\n") as f:
        f.write(text)
    os.replace(temp, os.path.join(top, MANIFEST))     # a new file: never one shared with another copy
    return hashlib.sha256(text.encode()).hexdigest()


def read_manifest(top: str, expect: str | None) -> tuple[dict[str, str], str]:
    """The manifest, checked before anything it lists is trusted: {relative path: sha-256}."""
    path = os.path.join(top, MANIFEST)
    try:
        st = os.lstat(path)
        if not stat.S_ISREG(st.st_mode):
            raise Refused(f"{MANIFEST} is not a regular file")
        if st.st_size > 1 << 20:
            raise Refused(f"{MANIFEST} is {st.st_size} bytes: not a manifest")
        with open(path, "rb") as f:
            raw = f.read()
    except FileNotFoundError:
        raise Refused(f"no {MANIFEST} in {top}: not a hookwatch release") from None
    fingerprint = hashlib.sha256(raw).hexdigest()
    if expect is not None and expect.lower() != fingerprint:
        raise Refused(f"{MANIFEST} has the fingerprint {fingerprint}, not the expected {expect}: "
                      "not the release that was signed off")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise Refused(f"{MANIFEST} is not UTF-8 text") from None
    listed: dict[str, str] = {}
    for n, line in enumerate(text.split("\n")[:-1] if text.endswith("\n") else text.split("\n"), 1):
        m = _LINE.fullmatch(line)
        if m is None or not safe_relpath(m.group(2)):
            raise Refused(f"{MANIFEST} line {n} is not `<sha-256>  <path inside the release>`: {line[:120]!r}")
        if m.group(2) in listed or m.group(2) == MANIFEST:
            raise Refused(f"{MANIFEST} line {n} lists {m.group(2)!r} twice")
        listed[m.group(2)] = m.group(1)
    missing = [r for r in REQUIRED if r not in listed]
    if missing:
        raise Refused(f"{MANIFEST} does not list {', '.join(missing)}: not a hookwatch release")
    if not any(r.startswith("wheels/") and r.endswith(".whl") for r in listed):
        raise Refused(f"{MANIFEST} lists no wheel: not a hookwatch release")
    return listed, fingerprint


def verify_tree(top: str, listed: dict[str, str]) -> None:
    """Every file of the release listed with its hash, every listed file there: or refuse, naming each."""
    problems: list[str] = []
    seen: set[str] = set()
    for dirpath, dirnames, filenames in os.walk(top):
        for name in sorted(dirnames + filenames):
            path = os.path.join(dirpath, name)
            rel = os.path.relpath(path, top).replace(os.sep, "/")
            mode = os.lstat(path).st_mode
            if stat.S_ISDIR(mode):
                continue
            if rel == MANIFEST:
                continue
            if not stat.S_ISREG(mode):
                problems.append(f"{rel!r} is not a regular file (a symlink or a device): refused")
            elif rel not in listed:
                problems.append(f"{rel!r} is in the release but not in {MANIFEST}: an unlisted file is "
                                "never installed")
            else:
                seen.add(rel)
                if sha256_file(path) != listed[rel]:
                    problems.append(f"{rel!r} does not match its SHA-256 in {MANIFEST}: a damaged or "
                                    "changed copy")
    problems += [f"{rel!r} is listed in {MANIFEST} but missing" for rel in sorted(set(listed) - seen)]
    if problems:
        shown = problems[:20] + ([f"… and {len(problems) - 20} more"] if len(problems) > 20 else [])
        raise Refused("the release does not match its manifest, nothing was installed:\n  " + "\n  ".join(shown))


def copy_verified(top: str, listed: dict[str, str], stage: str) -> None:
    """Copy every listed file into stage, hashing what is copied: the install reads only this copy."""
    for rel, digest in sorted(listed.items()):
        dst = os.path.join(stage, *rel.split("/"))
        os.makedirs(os.path.dirname(dst), exist_ok=True)
        h = hashlib.sha256()
        fd = os.open(os.path.join(top, *rel.split("/")), os.O_RDONLY | os.O_NOFOLLOW)
        with os.fdopen(fd, "rb") as src, open(dst, "xb") as out:
            while chunk := src.read(_CHUNK):
                h.update(chunk)
                out.write(chunk)
        if h.hexdigest() != digest:
            raise Refused(f"{rel!r} changed while it was being copied: refused")
        os.chmod(dst, 0o755 if rel == "install.sh" else 0o644)


# ------------------------------------------------------------------------------------- the journal

@dataclass
class Journal:
    """What the commit has done, undone in reverse order if any later step fails."""
    undo: list[Callable[[], None]] = field(default_factory=list)
    after: list[Callable[[], None]] = field(default_factory=list)   # after the switch: clean-up

    def rollback(self) -> None:
        for fn in reversed(self.undo):
            try:
                fn()
            except OSError as e:
                say(f"rollback: {e}")
        self.undo.clear()

    def replace(self, temp: str, dst: str, tag: str) -> None:
        """Move temp over dst (one rename); the old dst kept until the switch has happened."""
        backup = f"{dst}.hookwatch-old-{tag}"
        if os.path.lexists(dst):
            os.rename(dst, backup)
            self.undo.append(lambda: os.replace(backup, dst))
            self.after.append(lambda: _remove(backup))
        else:
            self.undo.append(lambda: _remove(dst))
        os.rename(temp, dst)

    def makedirs(self, path: str) -> None:
        missing = []
        p = path
        while not os.path.isdir(p):
            missing.append(p)
            p = os.path.dirname(p)
        for d in reversed(missing):
            os.mkdir(d, 0o755)
            self.undo.append(functools.partial(os.rmdir, d))


def _remove(path: str) -> None:
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path, ignore_errors=True)
    elif os.path.lexists(path):
        os.unlink(path)


# ------------------------------------------------------------------------------------ the install

@dataclass
class Box:
    root: str   # "" for the live system

    @property
    def live(self) -> bool:
        return self.root == ""

    def at(self, rel: str) -> str:
        return f"{self.root}/{rel}"

    @property
    def opt(self) -> str:
        return self.at("opt/hookwatch")

    @property
    def record(self) -> str:          # what the package put under /etc, with the hashes it put there
        return os.path.join(self.opt, "MANIFEST")

    def read_record(self) -> dict[str, str | None]:
        """{path under the root: sha-256 installed, or None (a record of an older installer)}"""
        out: dict[str, str | None] = {}
        try:
            with open(self.record, encoding="utf-8") as f:
                for line in f:
                    line = line.rstrip("\n")
                    m = re.fullmatch(r"([0-9a-f]{64})  /(.+)", line)
                    if m:
                        out[m.group(2)] = m.group(1)
                    elif line.startswith("/"):
                        out[line[1:]] = None
        except FileNotFoundError:
            pass
        return out


def _systemd_running(box: Box) -> bool:
    return box.live and shutil.which("systemctl") is not None and os.path.isdir("/run/systemd/system")


def _run(argv: list[str], what: str, env: dict[str, str] | None = None) -> str:
    r = subprocess.run(argv, capture_output=True, text=True, env=env, stdin=subprocess.DEVNULL)
    if r.returncode != 0:
        tail = (r.stderr or r.stdout).strip().splitlines()[-15:]
        raise Refused(f"{what} failed (exit {r.returncode}):\n  " + "\n  ".join(tail))
    return r.stdout


def _wheel_requirements(stage: str, listed: dict[str, str]) -> str:
    """One `name==version --hash=sha256:…` per listed wheel: pip installs exactly these."""
    lines = []
    for rel, digest in sorted(listed.items()):
        if not (rel.startswith("wheels/") and rel.endswith(".whl")):
            continue
        m = _WHEEL.fullmatch(rel[len("wheels/"):])
        if m is None or "/" in rel[len("wheels/"):]:
            raise Refused(f"{rel!r} is not a wheel's file name")
        lines.append(f"{m.group(1)}=={m.group(2)} --hash=sha256:{digest}")
    names = [ln.split("==")[0].lower().replace("_", "-").replace(".", "-") for ln in lines]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise Refused(f"the release holds more than one wheel of {', '.join(twice)}")
    return "\n".join(lines) + "\n"


def _clean_env() -> dict[str, str]:
    """pip and Python with no site configuration of the box (no PIP_*, PYTHON*, pip.conf)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PIP_", "PYTHON"))}
    env["PIP_CONFIG_FILE"] = os.devnull
    env["PYTHONNOUSERSITE"] = "1"
    return env


def _diff(old: str, new: str, a: str, b: str) -> str:
    try:
        with open(old, encoding="utf-8", errors="replace") as f:
            lo = f.readlines()
        with open(new, encoding="utf-8", errors="replace") as f:
            ln = f.readlines()
    except OSError as e:
        return f"    (no diff: {e})\n"
    lines = list(difflib.unified_diff(lo, ln, a, b))
    if len(lines) > 80:
        lines = lines[:80] + [f"… {len(lines) - 80} more lines: diff {old} {new}\n"]
    return "".join("    " + (ln if ln.endswith("\n") else ln + "\n") for ln in lines)


def install(top: str, box: Box, expect: str | None) -> None:
    listed, fingerprint = read_manifest(top, expect)
    verify_tree(top, listed)
    with open(os.path.join(top, "VERSION"), encoding="utf-8") as f:
        want = f.read().strip()
    if not _VERSION.fullmatch(want):
        raise Refused(f"VERSION {want[:40]!r} is not a version")
    say(f"release {want} verified: every file matches {MANIFEST} (fingerprint {fingerprint})")

    created_opt = not os.path.exists(box.opt)
    os.makedirs(box.opt, exist_ok=True)
    lock = open(os.path.join(box.opt, ".lock"), "w")   # noqa: SIM115 (held to the end)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        raise Refused(f"another install.sh is running on {box.opt}") from None
    tag = f"{time.strftime('%Y%m%d%H%M%S')}-{os.getpid()}"
    stage = os.path.join(box.opt, f".stage-{tag}")
    venvs = os.path.join(box.opt, "venvs")
    new = os.path.join(venvs, f"{want}-{tag}")
    link = os.path.join(box.opt, "venv")
    journal = Journal()
    temps: list[str] = []
    old: str | None = None
    try:
        old = _installed_version(link)
        # 1. the verified copy
        copy_verified(top, listed, stage)
        # 2. the venv, from the verified wheels only
        os.makedirs(venvs, exist_ok=True)
        env = _clean_env()
        _run([sys.executable, "-m", "venv", new], "python3 -m venv (Debian: apt-get install python3-venv)", env)
        req = os.path.join(stage, "requirements.txt")
        with open(req, "w", encoding="utf-8") as f:
            f.write(_wheel_requirements(stage, listed))
        _run([os.path.join(new, "bin", "python"), "-m", "pip", "install", "-q", "--no-index", "--no-deps",
              "--require-hashes", "--only-binary", ":all:", "--disable-pip-version-check",
              "--find-links", os.path.join(stage, "wheels"), "-r", req],
             "installing the verified wheels", env)
        out = _run([os.path.join(new, "bin", "hookwatch"), "--version"], "the new hookwatch --version", env)
        if want not in out:
            raise Refused(f"the new venv says {out.strip()[:80]!r}, not {want}")
        # 3. the release's files (examples, scenarios, units, this installer) inside the new release
        share = os.path.join(new, "share", "hookwatch")
        for rel in sorted(listed):
            if rel.startswith("wheels/"):
                continue
            dst = os.path.join(share, *rel.split("/"))
            os.makedirs(os.path.dirname(dst), exist_ok=True)
            shutil.copy2(os.path.join(stage, *rel.split("/")), dst)
        shutil.copy2(os.path.join(top, MANIFEST), os.path.join(share, MANIFEST))

        # 4. what goes under /etc, decided and written beside its place (nothing replaced yet)
        record = box.read_record()
        new_record: dict[str, str] = {}
        notes: list[str] = []
        plan: list[tuple[str, str]] = []          # (temp file, destination)
        etc = list(ETC_FILES) + [(r, "etc/udev/rules.d/" + r.rsplit("/", 1)[1]) for r in sorted(listed)
                                 if r.startswith("deploy/udev/") and r.endswith(".rules") and r.count("/") == 2]
        for src_rel, dst_rel in etc:
            if src_rel not in listed:
                raise Refused(f"the release lacks {src_rel}")
            src = os.path.join(share, *src_rel.split("/"))
            dst = box.at(dst_rel)
            shipped = listed[src_rel]
            new_record[dst_rel] = shipped
            if os.path.lexists(dst) and not stat.S_ISREG(os.lstat(dst).st_mode):
                raise Refused(f"/{dst_rel} is not a regular file: move it away first")
            current = sha256_file(dst) if os.path.exists(dst) else None
            if current == shipped:
                continue
            if current is not None and current != record.get(dst_rel):
                apply = next((v for k, v in _APPLY.items() if dst_rel.startswith(k)), "")
                installed_src = f"/opt/hookwatch/share/{src_rel}"
                notes.append(
                    f"KEPT /{dst_rel}: it was changed on this box, and this release's differs. Yours stays;"
                    f" to take the release's:\n      install -m 644 {installed_src} /{dst_rel}"
                    + (f" && {apply}" if apply else "") + "\n" + _diff(dst, src, f"/{dst_rel} (yours)",
                                                                       f"{installed_src} (this release)"))
                continue
            if current is not None:
                notes.append(f"UPDATED /{dst_rel} (this release changes it):\n"
                             + _diff(dst, src, f"/{dst_rel} (before)", f"/{dst_rel} (now)"))
            temp = f"{dst}.hookwatch-new-{tag}"
            journal.makedirs(os.path.dirname(dst))
            shutil.copyfile(src, temp)
            os.chmod(temp, 0o644)
            temps.append(temp)
            plan.append((temp, dst))
        # the default configuration: the administrator's, written only where there is none
        etc_dir = box.at("etc/hookwatch")
        conf_temp = None
        conf_msg = "configuration in /etc/hookwatch kept"
        if not os.path.exists(os.path.join(etc_dir, "fleet.yaml")):
            conf_msg = ("default configuration written to /etc/hookwatch (add one stations/<id>.yaml per "
                        "loom: docs/deploy.md §1.4)")
            conf_temp = box.at(f"etc/.hookwatch-new-{tag}")
            journal.makedirs(os.path.dirname(conf_temp))
            temps.append(conf_temp)
            os.makedirs(os.path.join(conf_temp, "stations"))
            shutil.copytree(os.path.join(share, "config", "meters"), os.path.join(conf_temp, "meters"))
            shutil.copy2(os.path.join(share, "config", "fleet.yaml"), os.path.join(conf_temp, "fleet.yaml"))
            shutil.copyfile(os.path.join(share, "deploy", "secrets.env.example"),
                            os.path.join(conf_temp, "secrets.env"))
            os.chmod(os.path.join(conf_temp, "secrets.env"), 0o600)
        rec_temp = f"{box.record}.new-{tag}"
        temps.append(rec_temp)
        with open(rec_temp, "w", encoding="utf-8") as f:
            f.writelines(f"{digest}  /{rel}\n" for rel, digest in sorted(new_record.items()))

        # 5. commit, journalled: every later failure undoes all of it
        for temp, dst in plan:
            journal.replace(temp, dst, tag)
        if conf_temp is not None:
            if os.path.isdir(etc_dir):       # a folder without fleet.yaml: fill in what is missing
                for dirpath, _dirs, files in os.walk(conf_temp):
                    for name in files:
                        src = os.path.join(dirpath, name)
                        dst = os.path.join(etc_dir, os.path.relpath(src, conf_temp))
                        if not os.path.lexists(dst):
                            journal.makedirs(os.path.dirname(dst))
                            journal.replace(src, dst, tag)
                journal.makedirs(os.path.join(etc_dir, "stations"))
            else:
                journal.replace(conf_temp, etc_dir, tag)
        journal.replace(rec_temp, box.record, tag)
        _link(journal, os.path.join(box.opt, "share"), "venv/share/hookwatch", tag)
        bin_path = box.at(BIN)
        if not os.path.lexists(bin_path) or (os.path.islink(bin_path) and os.readlink(bin_path) == BIN_TARGET):
            journal.makedirs(os.path.dirname(bin_path))
            _link(journal, bin_path, BIN_TARGET, tag)
        else:
            notes.append(f"/{BIN} exists and is not hookwatch's link: left alone; run "
                         "/opt/hookwatch/venv/bin/hookwatch")
        _apply_system(box, listed)
        # 6. the switch, last: one rename of the symlink
        if os.path.isdir(link) and not os.path.islink(link):      # a venv of an old installer
            moved = os.path.join(venvs, f"pre-symlink-{tag}")
            os.rename(link, moved)
            journal.undo.append(functools.partial(os.rename, moved, link))
        tmp_link = f"{link}.new-{tag}"
        os.symlink(os.path.relpath(new, box.opt), tmp_link)
        temps.append(tmp_link)
        os.replace(tmp_link, link)
    except BaseException as e:
        journal.rollback()
        for t in temps:
            _remove(t)
        _remove(new)
        _remove(stage)
        if created_opt:
            _remove(box.opt)
        if journal.after and _systemd_running(box):
            subprocess.run(["systemctl", "daemon-reload"], check=False)
        if isinstance(e, Refused | OSError):
            state = "nothing was installed" if old is None else f"{old} is still installed and active"
            raise Refused(f"{e}\n  {state}: nothing was changed") from e
        raise
    finally:
        lock.close()
    # after the switch: the old venvs, backups and the stage go (a failure here is only said)
    for fn in journal.after:
        try:
            fn()
        except OSError as e:
            say(f"clean-up: {e}")
    for v in os.listdir(venvs):
        if os.path.join(venvs, v) != new:
            _remove(os.path.join(venvs, v))
    for t in [*temps, stage]:
        _remove(t)
    say(conf_msg)
    for note in notes:
        say(note.rstrip("\n"))
    if any(n.startswith("UPDATED /etc/systemd") for n in notes):
        say("the units changed: systemctl daemon-reload was run"
            if _systemd_running(box) else "the units changed: run systemctl daemon-reload")
    say(f"`hookwatch` on PATH: /{BIN} -> /opt/hookwatch/venv/bin/hookwatch")
    say(f"upgraded {old} -> {want}; restart the service to run it (docs/deploy.md §1.10)" if old
        else f"installed {want} under /opt/hookwatch")


def _link(journal: Journal, path: str, target: str, tag: str) -> None:
    if os.path.islink(path) and os.readlink(path) == target:
        return
    temp = f"{path}.new-{tag}"
    os.symlink(target, temp)
    journal.replace(temp, path, tag)


def _installed_version(link: str) -> str | None:
    py = os.path.join(link, "bin", "python")
    if not os.path.exists(py):
        return None
    r = subprocess.run([py, "-c", "import importlib.metadata as m; print(m.version('hookwatch'))"],
                       capture_output=True, text=True, env=_clean_env(), stdin=subprocess.DEVNULL)
    return r.stdout.strip() or None if r.returncode == 0 else None


def _apply_system(box: Box, listed: dict[str, str]) -> None:
    """sysusers and tmpfiles applied, systemd and udev told: before the switch (a failure undoes all)."""
    sysusers, tmpfiles = box.at("etc/sysusers.d/hookwatch.conf"), box.at("etc/tmpfiles.d/hookwatch.conf")
    if box.live:
        if shutil.which("systemd-sysusers"):
            _run(["systemd-sysusers", sysusers], "systemd-sysusers")
        if shutil.which("systemd-tmpfiles"):
            _run(["systemd-tmpfiles", "--create", tmpfiles], "systemd-tmpfiles")
        if _systemd_running(box):
            _run(["systemctl", "daemon-reload"], "systemctl daemon-reload")
        if shutil.which("udevadm"):
            subprocess.run(["udevadm", "control", "--reload"], capture_output=True, check=False)
    else:
        if shutil.which("systemd-sysusers"):
            _run(["systemd-sysusers", f"--root={box.root}", sysusers], "systemd-sysusers --root")
        if shutil.which("systemd-tmpfiles"):
            _run(["systemd-tmpfiles", f"--root={box.root}", "--create", tmpfiles], "systemd-tmpfiles --root")


def uninstall(box: Box, purge: bool) -> None:
    if not os.path.exists(box.record):
        raise Refused(f"nothing installed under {box.root or ''}/ (no {box.record})")
    if _systemd_running(box):
        subprocess.run(["systemctl", "disable", "--now", "hookwatch-fleet.service"], capture_output=True, check=False)
    for rel in box.read_record():
        _remove(box.at(rel))
    bin_path = box.at(BIN)
    if os.path.islink(bin_path) and os.readlink(bin_path) == BIN_TARGET:
        os.unlink(bin_path)
    shutil.rmtree(box.opt)
    if purge:
        for rel in ("etc/hookwatch", "var/lib/hookwatch", "var/log/hookwatch"):
            _remove(box.at(rel))
        say("removed, with the configuration and the records (--purge)")
    else:
        say(f"removed; kept the configuration ({box.at('etc/hookwatch')}) and the records "
            f"({box.at('var/lib/hookwatch')})")
    if _systemd_running(box):
        subprocess.run(["systemctl", "daemon-reload"], check=False)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="release.py")
    sub = ap.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("manifest")
    m.add_argument("dir")
    for name in ("install", "uninstall"):
        p = sub.add_parser(name)
        p.add_argument("--root", default="/")
        if name == "install":
            p.add_argument("--expect", metavar="SHA256", help="the manifest's fingerprint, as build-release printed it")
        else:
            p.add_argument("--purge", action="store_true")
    a = ap.parse_args(argv)
    if a.cmd == "manifest":
        print(write_manifest(a.dir))
        return 0
    root = os.path.realpath(a.root).rstrip("/")
    box = Box(root)
    try:
        if a.cmd == "install":
            install(os.path.dirname(os.path.realpath(__file__)), box, a.expect)
        else:
            uninstall(box, a.purge)
    except Refused as e:
        say(f"refused: {e}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
