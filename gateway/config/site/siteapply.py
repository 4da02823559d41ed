"""``hookwatch config apply`` and ``rollback``: a version reaches the box, or goes.

Apply, under the state folder's lock (one at a time; released by the kernel if the process dies):

1. the folder is repaired first (:meth:`.versions.StateDir.repair`);
2. the same version again, staged whole, verified and without drift: nothing to do (exit 0);
3. the commit's signature (:mod:`.signing`), unless the box allows unsigned commits;
4. ``config check`` of the commit's tree (one validation) — a refusal changes nothing (exit 4);
5. ``applying.json`` (the version, the previous one, ``--interrupt-tests --by``), the tree staged
   under ``versions/<sha>`` (fsync), ``current`` switched in one rename, the supervisor's SIGHUP;
6. the health gate: every changed or new station runs the new version and reads its meter — or
   keeps its test running with the new version deferred — within the bound; the supervisor's
   ``supervisor.json`` says so (gateway/supervisor/boxagent.py);
7. passed: ``verified`` = the version, ``applying.json`` removed (exit 3). Failed: ``current``
   back to the verified version, SIGHUP, ``rollback.json`` says why (exit 5). No supervisor
   running: no gate can run; the version is ``unverified.json`` (exit 3) until the supervisor's
   first start on it has passed the gate (gateway/supervisor/startgate.py).

Killed anywhere in between, the box is consistent: before the switch ``current`` is untouched;
after it ``applying.json`` is there, and the supervisor (while it runs, seeing the lock free) or
its next start switches back to the verified version.
"""
from __future__ import annotations

import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ...plumbing import safeout
from .boxreport import supervisor_alive
from .boxsettings import BoxSettings
from .repository import GitError, checkout, commit_of
from .signing import verify_commit
from .siteplan import Plan, make_plan
from .versions import StateDir, read_json, write_atomic

__all__ = ["EXIT", "Outcome", "apply_version", "restart", "rollback"]

EXIT = {"nothing": 0, "error": 1, "changed": 3, "refused": 4, "rolled_back": 5, "waiting": 6}
#: how often the health gate reads the supervisor's status (s)
GATE_POLL_S = 0.25


@dataclass
class Outcome:
    code: int
    version: str | None = None
    changed: bool = False
    stations: dict[str, str] = field(default_factory=dict)
    deferred: list[str] = field(default_factory=list)
    rolled_back: bool = False
    why: str | None = None
    errors: list[str] = field(default_factory=list)
    plan: Plan | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"version": self.version, "changed": self.changed, "stations": self.stations,
                "deferred": self.deferred, "rolled_back": self.rolled_back, "why": self.why,
                "exit": self.code, "errors": self.errors}


def reload_supervisor(state: StateDir) -> bool:
    """SIGHUP to the box's supervisor; False when none runs."""
    pid = supervisor_alive(state)
    if pid is None:
        return False
    try:
        os.kill(pid, signal.SIGHUP)
    except OSError:
        return False
    return True


def _gate(state: StateDir, sha: str, plan: Plan, timeout: float) -> tuple[bool, str | None, list[str]]:
    """Every changed or new station on ``sha`` with its meter read, or deferred in its test:
    (passed, why not, the deferred stations)."""
    watch = [s.station for s in plan.stations if s.status in ("new", "apply-now", "deferred")]
    t_end = time.monotonic() + timeout
    why = "the supervisor did not read the new version"
    while True:
        st = read_json(state.path("supervisor.json")) or {}
        raw = st.get("stations")
        stations: dict[str, Any] = raw if isinstance(raw, dict) else {}
        if supervisor_alive(state) is None:
            return False, "the supervisor is not running", []
        if st.get("version") == sha:
            deferred, waiting = [], []
            for name in watch:
                s = stations.get(name)
                if not isinstance(s, dict):
                    waiting.append(f"{name}: not started")
                elif s.get("refused"):
                    return False, f"{name}: refused: {s['refused']}", []
                elif s.get("version") == sha and s.get("running") and s.get("meter_ok"):
                    continue
                elif s.get("pending") == sha and s.get("in_test"):
                    deferred.append(name)
                elif s.get("version") != sha:
                    waiting.append(f"{name}: still on its old version")
                elif not s.get("running"):
                    waiting.append(f"{name}: its worker is not running")
                else:
                    waiting.append(f"{name}: no meter reading")
            if not waiting:
                return True, None, deferred
            why = "; ".join(waiting)
        if time.monotonic() > t_end:
            return False, f"health gate ({timeout:g} s): {why}", []
        time.sleep(GATE_POLL_S)


def apply_version(root: str, version: str, box: str, settings: BoxSettings, state: StateDir, *,
                  interrupt_by: str | None = None, health_timeout: float | None = None,
                  say: Callable[[str], None] = lambda s: None) -> Outcome:
    """Apply commit ``version`` of the site repository at ``root`` to ``box`` (see the module doc)."""
    try:
        sha = commit_of(root, version)
    except GitError as e:
        return Outcome(EXIT["error"], why=f"{version}: {e}")
    with state.lock():
        why = state.repair()
        if why:
            say(f"repaired first: {why}")
        cur, ver = state.current(), state.verified()
        if sha == cur == ver and state.complete(sha) and not state.drift(sha):
            return Outcome(EXIT["nothing"], sha, why="already applied")
        if not settings.allow_unsigned:
            v = verify_commit(root, sha, settings.allowed_signers)
            if not v.ok:
                state.journal("refused", version=sha, why=v.why)
                return Outcome(EXIT["refused"], sha, why=v.why)
            say(f"signature: {v.why}")
        else:
            say("unsigned commits allowed on this box (allow_unsigned)")
        try:
            with checkout(root, sha) as tree:
                plan = make_plan(tree, box, state, sha)
                if plan.errors:
                    state.journal("refused", version=sha, why="config check failed",
                                  errors=plan.errors[:20])
                    return Outcome(EXIT["refused"], sha, why="config check failed",
                                   errors=plan.errors, plan=plan)
                eff = plan.eff
        except GitError as e:
            return Outcome(EXIT["error"], sha, why=str(e))
        assert eff is not None                  # a plan without errors has its tree
        state.begin_apply(sha, cur, interrupt_by=interrupt_by)
        state.stage(sha, eff, box)
        state.switch(sha)
        state.journal("switched", version=sha, previous=cur, by=interrupt_by)
        stations = {s.station: s.status for s in plan.stations}
        timeout = health_timeout if health_timeout is not None else settings.health_timeout_s
        if not reload_supervisor(state):
            # no health gate can run: unverified until the supervisor's first start has passed
            # it (gateway/supervisor/startgate.py), never marked verified unchecked
            why = "no supervisor running: unverified until its first start passes the health gate"
            state.mark_unverified(sha, why, timeout)
            state.end_apply()
            state.journal("applied", version=sha, checked=False, why=why)
            return Outcome(EXIT["changed"], sha, True, stations, why=why, plan=plan)
        ok, why, deferred = _gate(state, sha, plan, timeout)
        if ok:
            state.mark_verified(sha)
            state.end_apply()
            state.journal("applied", version=sha, deferred=deferred)
            state.prune()
            return Outcome(EXIT["changed"], sha, True, stations, deferred, plan=plan)
        target = state.rollback_target(cur)
        if target is not None:
            state.switch(target)
        state.record_rollback(sha, target, str(why))
        state.end_apply()
        reload_supervisor(state)
        return Outcome(EXIT["rolled_back"], sha, True, stations, rolled_back=True, why=why, plan=plan)


def rollback(state: StateDir, to: str | None = None) -> Outcome:
    """Back to the last verified version (or ``to``, staged under versions/), by hand."""
    with state.lock():
        state.repair()
        cur = state.current()
        target = to or state.verified()
        if not target or not state.complete(target):
            return Outcome(EXIT["error"], target, why=f"{target or 'no verified version'}: not staged")
        if target == cur:
            return Outcome(EXIT["nothing"], target, why="already the current version")
        state.switch(target)
        state.mark_verified(target)
        state.record_rollback(cur, target, "by hand (hookwatch config rollback)")
        reload_supervisor(state)
        return Outcome(EXIT["nothing"], target, True, rolled_back=True, why="by hand")


def restart(state: StateDir, software: str, *, every: bool = False, wait: float = 0.0,
            request: str | None = None) -> Outcome:
    """New software installed: ask the box's supervisor for a new worker process per station
    (every one, or those not on ``software``), each once its station is idle — at once, or when
    its test ends, never before. Waits up to ``wait`` s for every station to run ``software`` in a
    new worker: exit 0 done, 6 still waiting (``deferred``: the stations in a test), 1 no
    supervisor.

    ``request`` names the request: asked again with the same name (a retry of Ansible's
    ``until`` loop), the request already made is awaited, never made again — with ``every``, a
    second request would restart the workers again, and a station that began a new test on the
    new worker (autostart) would hold the retry until that test ends too. A worker counts as
    restarted when its process is not one of those running when the request was first made."""
    if supervisor_alive(state) is None:
        return Outcome(EXIT["error"], why="the supervisor is not running")
    req = read_json(state.path("restart.json")) if request else None
    if not (req and req.get("id") == request and req.get("software") == software
            and bool(req.get("all")) == every and isinstance(req.get("pids"), dict)):
        before = read_json(state.path("supervisor.json")) or {}
        raw = before.get("stations")
        pids = {n: s.get("pid") for n, s in (raw if isinstance(raw, dict) else {}).items()
                if isinstance(s, dict)}
        rid = request or f"{time.time():.6f}-{os.getpid()}"
        req = {"id": rid, "software": software, "all": every, "time": time.time(), "pids": pids}
        write_atomic(state.path("restart.json"), safeout.dumps(req).encode("utf-8"))
        state.journal("restart_requested", id=rid, software=software, all=every)
        reload_supervisor(state)
    old_pids = req["pids"]
    t0 = float(req.get("time") or 0.0)
    t_end = time.monotonic() + max(0.0, wait)
    while True:
        st = read_json(state.path("supervisor.json")) or {}
        raw = st.get("stations")
        stations: dict[str, Any] = raw if isinstance(raw, dict) else {}
        behind = {}
        for n, s in stations.items():
            if not isinstance(s, dict) or s.get("refused"):
                continue
            if (s.get("software") != software or not s.get("running")
                    or (every and s.get("pid") == old_pids.get(n))):
                behind[n] = s
        fresh = isinstance(st.get("time"), (int, float)) and st["time"] > t0
        if fresh and not behind:
            return Outcome(EXIT["nothing"], software, True, {n: "restarted" for n in stations})
        if time.monotonic() >= t_end:
            deferred = sorted(n for n, s in behind.items() if s.get("in_test"))
            return Outcome(EXIT["waiting"], software, True, {n: "waiting" for n in behind}, deferred,
                           why=f"{len(behind)} station(s) not yet on {software}"
                               + (f" ({', '.join(deferred)} in a test: when it ends)" if deferred else ""))
        time.sleep(GATE_POLL_S)
