"""The box's configuration state folder (``STATE/config``)::

    versions/<sha>/            a staged effective tree (+ .hookwatch-version.json, its manifest)
    current -> versions/<sha>  the version the supervisor runs (``hookwatch run STATE/config/current``)
    verified                   the sha of the last version that passed its health gate
    applying.json              an apply under way (written before the switch, removed after the gate)
    rollback.json              the last rollback: from, to, why, when
    journal.jsonl              every apply, deferral, interruption, rollback and repair, one line each
    lock                       held (flock) by whoever changes the folder
    supervisor.json, .pid      written by the supervisor (gateway/config/site/boxagent.py)

Every change is a new file or folder fsynced and then renamed, and the switch is one ``rename`` of
a symlink: whatever instant the box dies at, ``current`` names a complete version. A version
switched to but not yet verified is named by ``applying.json``; :meth:`StateDir.repair` (at the
supervisor's start, and when the supervisor sees the lock free while ``applying.json`` is there:
the apply was killed) switches back to the verified version and says why.
"""
from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import shutil
import time
from collections.abc import Iterator
from typing import Any

from ...plumbing import safeout
from .repository import MANIFEST, Effective, read_tree, write_tree

__all__ = ["StateDir"]

#: the journal is cut to its newer half beyond this size
JOURNAL_MAX = 1024 * 1024
#: the versions kept besides current and verified (the older ones are removed after an apply)
KEEP_VERSIONS = 5


def write_atomic(path: str, data: bytes) -> None:
    """``path`` replaced by ``data`` whole or not at all (:func:`safeout.write_atomic`)."""
    safeout.write_atomic(path, data, make_dir=False, tmp_suffix=f".tmp-{os.getpid()}")


def read_json(path: str) -> dict[str, Any] | None:
    """A small JSON object file, or None (missing, unreadable, not an object)."""
    try:
        with open(path, "rb") as f:
            v = safeout.loads_strict(f.read(1024 * 1024))
    except (OSError, ValueError):
        return None
    return v if isinstance(v, dict) else None


class StateDir:
    """``STATE/config`` of one box."""

    def __init__(self, state_dir: str) -> None:
        self.root = os.path.join(os.path.abspath(state_dir), "config")
        self.versions = os.path.join(self.root, "versions")
        self.current_link = os.path.join(self.root, "current")

    def path(self, name: str) -> str:
        return os.path.join(self.root, name)

    def ensure(self) -> None:
        os.makedirs(self.versions, exist_ok=True)

    # ------------------------------------------------------------------ the lock
    @contextlib.contextmanager
    def lock(self) -> Iterator[None]:
        """Held while the folder is changed (one apply, rollback or repair at a time); released by
        the kernel when its holder dies (``kill -9``)."""
        self.ensure()
        fd = os.open(self.path("lock"), os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)

    @contextlib.contextmanager
    def try_lock(self) -> Iterator[bool]:
        """The lock if nobody holds it (True), else at once False: an ``applying.json`` found while
        holding it belongs to an apply that died."""
        try:
            self.ensure()
            fd = os.open(self.path("lock"), os.O_RDWR | os.O_CREAT, 0o644)
        except OSError:
            yield False
            return
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                yield False
                return
            yield True
        finally:
            os.close(fd)

    # ------------------------------------------------------------------ what is where
    def current(self) -> str | None:
        try:
            return os.path.basename(os.readlink(self.current_link))
        except OSError:
            return None

    def verified(self) -> str | None:
        try:
            with open(self.path("verified"), encoding="ascii") as f:
                v = f.read(100).strip()
        except (OSError, UnicodeDecodeError):
            return None
        return v or None

    def version_dir(self, sha: str) -> str:
        return os.path.join(self.versions, sha)

    def manifest(self, sha: str) -> dict[str, Any] | None:
        return read_json(os.path.join(self.version_dir(sha), MANIFEST))

    def complete(self, sha: str | None) -> bool:
        """The version is staged whole (its manifest is written last, before the rename)."""
        return bool(sha) and self.manifest(str(sha)) is not None

    def applying(self) -> dict[str, Any] | None:
        return read_json(self.path("applying.json"))

    def last_rollback(self) -> dict[str, Any] | None:
        return read_json(self.path("rollback.json"))

    def drift(self, sha: str | None = None) -> list[str]:
        """The files of the current (or ``sha``'s) tree that differ from what was staged: changed,
        added or removed by hand (empty: no drift)."""
        sha = sha or self.current()
        if not sha:
            return []
        man = self.manifest(sha)
        if man is None:
            return ["(no manifest)"]
        files = read_tree(self.version_dir(sha))
        staged = man.get("files") or {}
        got = {p: _sha(b) for p, b in files.items()}
        return sorted({p for p in set(staged) | set(got) if staged.get(p) != got.get(p)})

    # ------------------------------------------------------------------ changes
    def journal(self, kind: str, **data: Any) -> dict[str, Any]:
        entry = {"time": time.time(), "event": kind, **data}
        self.ensure()
        path = self.path("journal.jsonl")
        line = (safeout.dumps(entry) + "\n").encode("utf-8")
        with open(path, "ab") as f:
            f.write(line)
            f.flush()
            os.fsync(f.fileno())
        with contextlib.suppress(OSError):
            if os.path.getsize(path) > JOURNAL_MAX:
                with open(path, "rb") as f:
                    f.seek(-JOURNAL_MAX // 2, os.SEEK_END)
                    tail = f.read()
                write_atomic(path, tail[tail.find(b"\n") + 1:])
        return entry

    def read_journal(self, last: int = 50) -> list[dict[str, Any]]:
        try:
            with open(self.path("journal.jsonl"), "rb") as f:
                lines = f.read().splitlines()[-last:]
        except OSError:
            return []
        out = []
        for ln in lines:
            try:
                v = safeout.loads_strict(ln)
            except ValueError:
                continue
            if isinstance(v, dict):
                out.append(v)
        return out

    def stage(self, sha: str, eff: Effective, box: str) -> str:
        """``versions/<sha>`` with the tree (reused when already staged whole and unchanged)."""
        self.ensure()
        dest = self.version_dir(sha)
        digest = eff.digest
        man = self.manifest(sha)
        if man is not None and man.get("sha256") == digest and not self.drift(sha):
            return dest
        tmp = os.path.join(self.versions, f".tmp-{sha}-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        write_tree(eff.files, tmp)
        manifest = {"version": sha, "box": box, "site": eff.site.get("site"), "sha256": digest,
                    "files": {p: _sha(b) for p, b in eff.files.items()}, "staged_at": time.time()}
        write_atomic(os.path.join(tmp, MANIFEST), safeout.dumps(manifest).encode("utf-8"))
        if os.path.lexists(dest):          # a broken or drifted copy: set aside, then removed
            old = os.path.join(self.versions, f".old-{sha}-{os.getpid()}")
            os.replace(dest, old)
            shutil.rmtree(old, ignore_errors=True)
        os.replace(tmp, dest)
        safeout.fsync_dir(self.versions)
        return dest

    def switch(self, sha: str) -> None:
        """``current`` → ``versions/<sha>`` in one rename."""
        tmp = f"{self.current_link}.new-{os.getpid()}"
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        os.symlink(os.path.join("versions", sha), tmp)
        os.replace(tmp, self.current_link)
        safeout.fsync_dir(self.root)

    def mark_verified(self, sha: str) -> None:
        write_atomic(self.path("verified"), (sha + "\n").encode("ascii"))
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path("unverified.json"))

    def mark_unverified(self, sha: str, why: str, health_timeout_s: float) -> None:
        """``current`` switched to ``sha`` with no supervisor running: not verified until the
        supervisor's first start has passed its health gate (:mod:`gateway.supervisor.startgate`)."""
        write_atomic(self.path("unverified.json"), safeout.dumps(
            {"version": sha, "why": why, "health_timeout_s": health_timeout_s,
             "time": time.time()}).encode("utf-8"))

    def unverified(self) -> dict[str, Any] | None:
        """``unverified.json`` if it names the current version (a later switch made it stale)."""
        uv = read_json(self.path("unverified.json"))
        return uv if uv and uv.get("version") == self.current() else None

    def begin_apply(self, sha: str, previous: str | None, **data: Any) -> None:
        write_atomic(self.path("applying.json"), safeout.dumps(
            {"version": sha, "previous": previous, "pid": os.getpid(), "time": time.time(),
             **data}).encode("utf-8"))

    def end_apply(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path("applying.json"))
        safeout.fsync_dir(self.root)

    def record_rollback(self, frm: str | None, to: str | None, why: str) -> dict[str, Any]:
        rb = {"from": frm, "to": to, "why": why, "time": time.time()}
        write_atomic(self.path("rollback.json"), safeout.dumps(rb).encode("utf-8"))
        self.journal("rollback", **{k: v for k, v in rb.items() if k != "time"})
        return rb

    def rollback_target(self, fallback: str | None = None) -> str | None:
        """The last verified version if it is staged whole, else ``fallback`` if it is."""
        for sha in (self.verified(), fallback):
            if sha and self.complete(sha):
                return sha
        return None

    def repair(self) -> str | None:
        """Make the folder consistent (the caller holds the lock, or saw it free): leftovers of a
        staging removed; an apply that never passed its gate (``applying.json``) or a ``current``
        that names no complete version → back to the last verified version. Returns why, or None
        when nothing needed repair."""
        self.ensure()
        for n in os.listdir(self.versions):
            if n.startswith(".old-"):       # a version set aside for its restaging: back if it is gone
                sha = n[len(".old-"):].rsplit("-", 1)[0]
                if not os.path.lexists(self.version_dir(sha)):
                    os.replace(os.path.join(self.versions, n), self.version_dir(sha))
                    continue
            if n.startswith((".tmp-", ".old-")):
                shutil.rmtree(os.path.join(self.versions, n), ignore_errors=True)
        for n in os.listdir(self.root):
            if n.startswith(("current.new-", "verified.tmp-", "applying.json.tmp-")):
                with contextlib.suppress(OSError):
                    os.unlink(os.path.join(self.root, n))
        why = None
        cur = self.current()
        ap = self.applying()
        if ap is not None:
            why = (f"the apply of {str(ap.get('version'))[:12]} was interrupted before its health "
                   f"gate passed (process {ap.get('pid')} gone)")
            target = self.rollback_target(ap.get("previous"))
        elif cur is not None and not self.complete(cur):
            why = f"current names {cur[:12]}, which is not staged whole"
            target = self.rollback_target()
        else:
            return None
        if target is not None and target != cur:
            self.switch(target)
        self.record_rollback(cur, target if target else cur, why)
        self.journal("repaired", version=target, why=why)
        self.end_apply()
        return why

    def prune(self) -> None:
        """Keep current, verified and the newest :data:`KEEP_VERSIONS` others."""
        keep = {self.current(), self.verified()}
        try:
            names = [n for n in os.listdir(self.versions) if not n.startswith(".")]
        except OSError:
            return
        names.sort(key=lambda n: os.path.getmtime(os.path.join(self.versions, n)), reverse=True)
        for n in names[KEEP_VERSIONS:]:
            if n not in keep:
                shutil.rmtree(os.path.join(self.versions, n), ignore_errors=True)


def _sha(b: bytes) -> str:
    return hashlib.sha256(b).hexdigest()
