"""The site repository and a box's effective tree.

The repository (deploy/site-example/, docs/deploy.md "A site of many boxes")::

    site.yaml                       site: NAME; broker: where every box publishes its config report
    defaults/fleet.yaml             the fleet-wide defaults (a fleet.yaml: ``defaults:`` …)
    boxes/<box>/box.yaml            the box's overrides, fleet.yaml-shaped, deep-merged over them
    boxes/<box>/stations/<id>.yaml  the box's station files
    maps/<name>.yaml                meter maps

A box runs its *effective tree*, a fleet folder: ``fleet.yaml`` (the merge), ``stations/``,
``maps/`` and ``site.yaml``. It is what ``config check`` validates, what ``config apply`` stages,
and what the sha256 of the config report and the drift watch are taken over. Relative paths are
as on the box: ``maps/x.yaml`` from the fleet defaults, ``../maps/x.yaml`` from a station file.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import os
import re
import subprocess
import tarfile
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import yaml

from ...plumbing.safeout import fsync_dir
from ...plumbing.safeyaml import YamlError, load
from ..loader import FLEET_KEYS, _merge

__all__ = ["BOX_NAME_RE", "MANIFEST", "Effective", "GitError", "boxes", "build", "checkout", "commit_of",
           "read_tree", "tree_digest", "write_tree"]

#: a box name: one path level, a topic level, a folder name
BOX_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
#: the file a staged version carries about itself (not part of the effective tree)
MANIFEST = ".hookwatch-version.json"
#: the most files and bytes an effective tree may hold (every input bounded)
MAX_FILES = 2000
MAX_BYTES = 64 * 1024 * 1024
#: the keys of site.yaml and of its broker
SITE_KEYS = ("site", "broker")
BROKER_KEYS = ("host", "port", "username", "password_file", "prefix", "keepalive_s")


class GitError(Exception):
    """The site repository cannot be read at that version (no such commit, not a repository)."""


@dataclass
class Effective:
    """A box's effective tree, with where each part came from in the repository."""
    box: str
    files: dict[str, bytes] = field(default_factory=dict)      # tree path → content
    origin: dict[str, str] = field(default_factory=dict)       # tree path → repository file
    fleet_lines: dict[int, str] = field(default_factory=dict)  # line of fleet.yaml → "FILE:LINE"
    problems: list[str] = field(default_factory=list)          # "FILE:LINE: message"
    site: dict[str, Any] = field(default_factory=dict)

    @property
    def digest(self) -> str:
        return tree_digest(self.files)


def boxes(root: str) -> list[str]:
    d = os.path.join(root, "boxes")
    if not os.path.isdir(d):
        return []
    return sorted(n for n in os.listdir(d) if os.path.isdir(os.path.join(d, n)) and BOX_NAME_RE.match(n))


def _rel(root: str, path: str) -> str:
    return os.path.relpath(path, root)


def _load(root: str, rel: str, problems: list[str]) -> Any:
    path = os.path.join(root, rel)
    try:
        return load(path)
    except YamlError as e:
        problems.append(f"{rel}:{e.line or 1}: {e.msg}")
    except (OSError, UnicodeDecodeError) as e:
        problems.append(f"{rel}:1: cannot read: {getattr(e, 'strerror', None) or e}")
    return None


def _site(root: str, eff: Effective) -> None:
    rel = "site.yaml"
    if not os.path.isfile(os.path.join(root, rel)):
        eff.problems.append(f"{rel}:1: missing: the site repository names its site (site: NAME)")
        return
    doc = _load(root, rel, eff.problems)
    if doc is None:
        return
    for k in doc.data:
        if k not in SITE_KEYS:
            eff.problems.append(f"{rel}:{doc.pos[(k,)].line}: {k}: unknown key; site.yaml has: "
                                f"{', '.join(SITE_KEYS)}")
    site = doc.data.get("site")
    if not isinstance(site, str) or not BOX_NAME_RE.match(site):
        line = doc.pos[("site",)].line if ("site",) in doc.pos else 1
        eff.problems.append(f"{rel}:{line}: site: a name (letters, digits, _ . -) is required")
    broker = doc.data.get("broker") or {}
    if not isinstance(broker, dict):
        eff.problems.append(f"{rel}:{doc.pos[('broker',)].line}: broker: a mapping (host, port, …)")
        broker = {}
    for k in broker:
        if k not in BROKER_KEYS:
            eff.problems.append(f"{rel}:{doc.pos[('broker', k)].line}: broker.{k}: unknown key; "
                                f"allowed: {', '.join(BROKER_KEYS)}")
    port = broker.get("port", 1883)
    if not isinstance(port, int) or isinstance(port, bool) or not 1 <= port <= 65535:
        eff.problems.append(f"{rel}:{doc.pos.get(('broker', 'port'), doc.pos[('broker',)]).line}: "
                            "broker.port: 1 … 65535")
    eff.site = {"site": site, "broker": broker}
    with open(os.path.join(root, rel), "rb") as f:
        eff.files["site.yaml"] = f.read()
    eff.origin["site.yaml"] = rel


def _fleet(root: str, eff: Effective) -> None:
    """fleet.yaml: boxes/<box>/box.yaml deep-merged over defaults/fleet.yaml; every line of the
    result remembers the repository line it came from."""
    docs = []
    for rel in ("defaults/fleet.yaml", f"boxes/{eff.box}/box.yaml"):
        if os.path.isfile(os.path.join(root, rel)):
            doc = _load(root, rel, eff.problems)
            if doc is None:
                return
            for k in doc.data:
                if k not in FLEET_KEYS:
                    eff.problems.append(f"{rel}:{doc.pos[(k,)].line}: {k}: unknown key; it has: "
                                        f"{', '.join(FLEET_KEYS)} (written like a station file's sections)")
            docs.append((rel, doc))
    merged: dict[str, Any] = {}
    for _, doc in docs:
        merged = _merge(merged, doc.data)
    text = ("# the effective fleet.yaml of box " + eff.box + ": "
            + " over ".join(r for r, _ in reversed(docs)) + "\n"
            + yaml.safe_dump(merged, sort_keys=False, allow_unicode=True))
    eff.files["fleet.yaml"] = text.encode("utf-8")
    eff.origin["fleet.yaml"] = docs[-1][0] if docs else "defaults/fleet.yaml"
    try:
        out = load("fleet.yaml", text)
    except YamlError:            # not reached: the text was just dumped from plain data
        return
    for kp, p in out.pos.items():
        for rel, doc in reversed(docs):
            src = doc.pos.get(kp)
            if src is not None:
                eff.fleet_lines[p.line] = f"{rel}:{src.line}"
                break


def _copy(root: str, eff: Effective, src_dir: str, dest_dir: str) -> None:
    d = os.path.join(root, src_dir)
    if not os.path.isdir(d):
        return
    for n in sorted(os.listdir(d)):
        p = os.path.join(d, n)
        if not (n.endswith((".yaml", ".yml")) and os.path.isfile(p)):
            continue
        if os.path.islink(p):          # a link could reach outside the repository
            eff.problems.append(f"{src_dir}/{n}:1: a symbolic link; the site repository holds files")
            continue
        if len(eff.files) >= MAX_FILES:
            eff.problems.append(f"{src_dir}/{n}:1: more than {MAX_FILES} files in one box's tree")
            return
        with open(p, "rb") as f:
            eff.files[f"{dest_dir}/{n}"] = f.read(MAX_BYTES + 1)
        eff.origin[f"{dest_dir}/{n}"] = f"{src_dir}/{n}"


def build(root: str, box: str) -> Effective:
    """The effective tree of ``box`` from a repository checkout at ``root`` (never raises for bad
    content: :attr:`Effective.problems`)."""
    eff = Effective(box)
    if not BOX_NAME_RE.match(box):
        eff.problems.append(f"boxes/{box}:1: not a box name (letters, digits, _ . -)")
        return eff
    if not os.path.isdir(os.path.join(root, "boxes", box)):
        eff.problems.append(f"boxes/{box}:1: no such box in the site repository (boxes: "
                            f"{', '.join(boxes(root)) or 'none'})")
        return eff
    _site(root, eff)
    _fleet(root, eff)
    _copy(root, eff, f"boxes/{box}/stations", "stations")
    _copy(root, eff, "maps", "maps")
    if sum(len(b) for b in eff.files.values()) > MAX_BYTES:
        eff.problems.append(f"boxes/{box}:1: the tree is larger than {MAX_BYTES // 2**20} MiB")
    return eff


def tree_digest(files: dict[str, bytes]) -> str:
    """sha256 over the tree: each file's path and sha256, in path order."""
    h = hashlib.sha256()
    for path in sorted(files):
        h.update(path.encode("utf-8") + b"\0" + hashlib.sha256(files[path]).hexdigest().encode() + b"\n")
    return h.hexdigest()


def read_tree(folder: str) -> dict[str, bytes]:
    """The files of a staged tree (its manifest left out), bounded like a built one."""
    out: dict[str, bytes] = {}
    total = 0
    for dirpath, dirnames, filenames in os.walk(folder):
        dirnames.sort()
        for n in sorted(filenames):
            rel = os.path.relpath(os.path.join(dirpath, n), folder)
            if rel == MANIFEST:
                continue
            if len(out) >= MAX_FILES or total > MAX_BYTES:
                out["…"] = b"too many files"
                return out
            try:
                with open(os.path.join(dirpath, n), "rb") as f:
                    out[rel] = f.read(MAX_BYTES + 1)
            except OSError as e:
                out[rel] = f"unreadable: {e.strerror}".encode()
            total += len(out[rel])
    return out


def write_tree(files: dict[str, bytes], dest: str) -> None:
    """Write a tree into the new folder ``dest``, every file and folder fsynced."""
    dirs = {dest}
    for rel, data in files.items():
        path = os.path.join(dest, rel)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        dirs.add(os.path.dirname(path))
        with open(path, "xb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    for d in sorted(dirs, key=len, reverse=True):
        fsync_dir(d)


def _git_bytes(root: str, *args: str) -> bytes:
    try:
        p = subprocess.run(["git", "-C", root, *args], capture_output=True, timeout=60,
                           stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired) as e:
        raise GitError(f"git {args[0]}: {e}") from None
    if p.returncode != 0:
        raise GitError(p.stderr.decode("utf-8", "replace").strip().splitlines()[-1:][0]
                       if p.stderr.strip() else f"git {args[0]} failed ({p.returncode})")
    return p.stdout


def _git(root: str, *args: str) -> str:
    return _git_bytes(root, *args).decode("utf-8", "replace")


def commit_of(root: str, version: str) -> str:
    """The full sha of the commit ``version`` names in the repository at ``root`` (GitError)."""
    if not version or version.startswith("-") or len(version) > 200:
        raise GitError(f"{version!r}: not a version")
    return _git(root, "rev-parse", "--verify", "--quiet", f"{version}^{{commit}}").strip()


@contextlib.contextmanager
def checkout(root: str, version: str | None) -> Iterator[str]:
    """The repository's files: its working tree (``version`` None) or the commit's tree read out
    of Git into a temporary folder (GitError)."""
    if version is None:
        yield root
        return
    sha = commit_of(root, version)
    data = _git_bytes(root, "archive", "--format=tar", sha)
    with tempfile.TemporaryDirectory(prefix="hookwatch-site-") as tmp:
        try:
            with tarfile.open(fileobj=io.BytesIO(data)) as tf:
                _extract_plain(tf, tmp)
        except (tarfile.TarError, OSError, ValueError) as e:      # a link, a device, a path out …
            raise GitError(f"{sha[:12]}: its tree cannot be read safely: {e}") from None
        yield tmp


def _extract_plain(tf: tarfile.TarFile, dest: str) -> None:
    """Write a commit's tree (``git archive``) under ``dest``: folders and regular files only, each
    inside ``dest``, files 0644. A site repository holds YAML; a link, a device or a path that
    leaves the folder is refused (ValueError), never followed. This is what ``extractall(filter=
    "data")`` does, written out because Debian 12's Python (3.11.2) predates that filter (3.11.4)."""
    top = os.path.realpath(dest)
    for m in tf.getmembers():
        if m.type == tarfile.XGLTYPE or m.name == "pax_global_header":
            continue                                  # git archive's commit id header
        path = os.path.realpath(os.path.join(top, m.name))
        if os.path.isabs(m.name) or not (path == top or path.startswith(top + os.sep)):
            raise ValueError(f"{m.name}: a path out of the repository")
        if m.isdir():
            os.makedirs(path, mode=0o755, exist_ok=True)
        elif m.isfile():
            src = tf.extractfile(m)
            if src is None:
                raise ValueError(f"{m.name}: not readable")
            os.makedirs(os.path.dirname(path), mode=0o755, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
            with os.fdopen(fd, "wb") as out, src:
                while chunk := src.read(1 << 16):
                    out.write(chunk)
        else:
            kind = "a symbolic link" if m.issym() else "a hard link" if m.islnk() else "not a file"
            raise ValueError(f"{m.name}: {kind}")
