"""The health gate of a version applied while no supervisor ran (issue 37).

``hookwatch config apply`` on a box whose supervisor is not running switches ``current`` and can
run no health gate: nothing reads the new version yet. The version is then *not* verified; the
apply records it as ``unverified.json`` (``{version, why, health_timeout_s}``; the config report's
``unverified``), and the supervisor's first start on it runs the gate the apply would have run:
within ``health_timeout_s`` every station runs the version with its meter read (or keeps a test
running with it deferred). Passed: the version is ``verified`` (journaled ``verified``). Failed (a
station refused, or the bound passed): back to the last verified version, as an apply's failed
gate does (``rollback.json`` says why); with no verified version to go back to (the box's first
version), the box stays on it, still unverified, and the report says why.

Decided under the state folder's lock (an apply under way is never raced: the gate waits for the
next look), from the supervisor's own view of its stations (:class:`.boxagent.BoxAgent`).
"""
from __future__ import annotations

import logging
from typing import Any

from ..config.site.versions import StateDir

__all__ = ["StartGate", "unhealthy"]

log = logging.getLogger("hookwatch.config")

#: the gate's bound when ``unverified.json`` names none (the box file's default)
DEFAULT_TIMEOUT_S = 60.0


def unhealthy(version: str, stations: dict[str, dict[str, Any]]) -> tuple[bool, str | None]:
    """(failed for good, why not yet healthy): None when every station runs ``version`` with its
    meter read, or is deferred in its test; a refused station fails at once."""
    waiting = []
    for name, s in sorted(stations.items()):
        if s.get("refused"):
            return True, f"{name}: refused: {s['refused']}"
        if s.get("version") == version and s.get("running") and s.get("meter_ok"):
            continue
        if s.get("pending") == version and s.get("in_test"):
            continue
        waiting.append(f"{name}: " + ("still on its old version" if s.get("version") != version
                                      else "its worker is not running" if not s.get("running")
                                      else "no meter reading"))
    return False, "; ".join(waiting) or None


class StartGate:
    """See the module docstring; :meth:`check` on every look of the supervisor's agent."""

    def __init__(self, state: StateDir) -> None:
        self.state = state
        self._t0: float | None = None
        self._failed_for: str | None = None

    def check(self, version: str | None, stations: dict[str, dict[str, Any]], now: float) -> bool:
        """One look; True when the box went back to its verified version (the supervisor reloads)."""
        uv = self.state.unverified()
        if uv is None or version is None or uv.get("version") != version or self._failed_for == version:
            return False
        if self._t0 is None:
            self._t0 = now
        t = uv.get("health_timeout_s")
        timeout = float(t) if isinstance(t, (int, float)) and 1 <= t <= 3600 else DEFAULT_TIMEOUT_S
        failed, why = unhealthy(version, stations)
        if not failed and why is not None and now - self._t0 < timeout:
            return False
        with self.state.try_lock() as held:
            if not held or self.state.unverified() is None:
                return False
            if why is None:
                self.state.mark_verified(version)
                self.state.journal("verified", version=version,
                                   why="the supervisor's first start on it: health gate passed")
                log.info("version %s verified: its health gate passed at the supervisor's start", version[:12])
                return False
            why = f"health gate at the supervisor's start ({timeout:g} s): {why}"
            target = self.state.rollback_target()
            if target is not None and target != version:
                self.state.switch(target)
                self.state.record_rollback(version, target, why)
                log.error("version %s: %s; back to %s", version[:12], why, target[:12])
                return True
            self._failed_for = version
            self.state.mark_unverified(version, why, timeout)
            self.state.journal("unverified", version=version, why=why)
            log.error("version %s stays unverified (no verified version to go back to): %s",
                      version[:12], why)
        return False
