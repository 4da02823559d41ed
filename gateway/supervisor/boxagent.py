"""What the supervisor of a site-managed box does for the site's configuration.

A box is site-managed when its supervisor runs ``hookwatch run STATE/config/current`` (the
symlink of :mod:`gateway.config.site.versions`). The supervisor (gateway/supervisor/supervisor.py) then keeps a
:class:`BoxAgent`, which

- writes ``supervisor.pid`` (where ``config apply`` sends its SIGHUP) and ``supervisor.json``, the
  status the apply's health gate and ``config plan`` read: per station the version it runs, the
  version it has been sent but not yet applied (``pending``: deferred while its test runs),
  whether it is in a test, whether its meter answered since it (re)started;
- repairs the folder at start (an apply killed half-way: back to the verified version) and, while
  it runs, finds an apply that died after its switch (``applying.json`` with the lock free) and
  repairs it too — the supervisor then reloads;
- watches the effective tree for hand edits (drift), every :data:`WATCH_S` seconds;
- carries the ``--interrupt-tests --by NAME`` of an apply to the stations it concerns;
- publishes the config report (:class:`.boxpublish.ReportPublisher`) and serves its figures to
  Prometheus (``hookwatch_config_info``, ``hookwatch_config_drift``).

The workers' own side is unchanged: a station that gets a new configuration during a test keeps
its parameters and applies it when the test ends (``Station.reload_requested``).
"""
from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass
from typing import Any

from .. import __version__
from ..config.site.boxreport import build_report
from ..config.site.versions import StateDir, read_json, write_atomic
from ..outputs.broker.settings import BrokerSettings
from ..outputs.prometheus.figures import set_config_source
from ..plumbing import safeout
from ..plumbing.safeyaml import YamlError, load
from .boxpublish import ReportPublisher
from .startgate import StartGate

__all__ = ["BoxAgent", "HubInfo"]

log = logging.getLogger("hookwatch.config")

#: the drift and dead-apply watch, and the status file, at most this often (s)
WATCH_S = 2.0
#: the status file is written again at least this often, changed or not (s)
STATUS_REFRESH_S = 10.0


@dataclass(frozen=True)
class HubInfo:
    """What the agent needs of one station of the supervisor."""
    name: str
    in_test: bool          # a test is starting or running (its worker's heartbeat: ``busy``)
    running: bool
    refused: str | None
    software: str | None = None       # the hookwatch version its worker runs
    pid: int | None = None            # its worker process


class _Track:
    __slots__ = ("version", "pending", "meter_ok")

    def __init__(self, version: str | None) -> None:
        self.version = version
        self.pending: str | None = None
        self.meter_ok = False


class BoxAgent:
    """See the module docstring. Called by the supervisor's main loop (``tick``, the reload path)
    and by the workers' reader threads (``config_reloaded``, ``heartbeat``)."""

    def __init__(self, state: StateDir) -> None:
        self.state = state
        self.version: str | None = None
        self._tracks: dict[str, _Track] = {}
        self._lock = threading.Lock()
        self._last_watch = 0.0
        self._last_status = 0.0
        self._status_key = ""
        self._drift: list[str] = []
        self._interrupt: dict[str, Any] | None = None
        self._interrupted_for: str | None = None
        self._restart_done: str | None = None
        self._reporter: ReportPublisher | None = None
        self._reporter_key: tuple[Any, ...] = ()
        self.report: dict[str, Any] = {}
        self._start_gate = StartGate(state)
        self._started = time.time()
        self._verified_seen: str | None = None

    @classmethod
    def for_folder(cls, folder: str) -> BoxAgent | None:
        """The agent of a fleet folder that is a box's ``STATE/config/current``, else None."""
        folder = os.path.abspath(folder)
        root = os.path.dirname(folder)
        if (os.path.basename(folder) != "current" or not os.path.islink(folder)
                or not os.path.isdir(os.path.join(root, "versions"))):
            return None
        return cls(StateDir(os.path.dirname(root)))

    # ------------------------------------------------------------------ start, reload, stop
    def at_start(self) -> None:
        """Before the folder is read: the pid file, and the repair of a half-applied version."""
        self.state.ensure()
        write_atomic(self.state.path("supervisor.pid"), f"{os.getpid()}\n".encode("ascii"))
        set_config_source(self.figures)
        # a restart asked of the supervisor before this one: its workers all start now, on the
        # software installed (never restarted once more for it)
        req = read_json(self.state.path("restart.json"))
        self._restart_done = req.get("id") if req and isinstance(req.get("id"), str) else None
        with self.state.try_lock() as held:
            if held:
                why = self.state.repair()
                if why:
                    log.error("configuration repaired at start: %s; running %s", why,
                              (self.state.current() or "nothing")[:12])
        self.folder_read()

    def folder_read(self) -> None:
        """The supervisor (re)read the folder: the version it now names."""
        self.version = self.state.current()
        log.info("site configuration: version %s", (self.version or "none")[:12])
        self._reporter_for_version()

    def stop(self) -> None:
        set_config_source(None)
        if self._reporter is not None:
            self._reporter.stop()
            self._reporter = None
        for n in ("supervisor.pid",):
            try:
                os.unlink(self.state.path(n))
            except OSError:
                pass

    # ------------------------------------------------------------------ per station
    def spawned(self, name: str) -> None:
        """A worker started: it read its file through ``current`` now."""
        with self._lock:
            self._tracks[name] = _Track(self.version)

    def unchanged(self, name: str) -> None:
        with self._lock:
            t = self._tracks.get(name)
            if t is not None and t.pending is None:
                t.version = self.version

    def reload_sent(self, name: str, in_test: bool) -> None:
        with self._lock:
            t = self._tracks.setdefault(name, _Track(None))
            t.pending = self.version
        if in_test:
            self.state.journal("deferred", station=name, version=self.version,
                               why="a test runs: applies when it ends")
            log.info("%s: a test runs; version %s deferred until it ends", name,
                     (self.version or "")[:12])

    def config_reloaded(self, name: str) -> None:
        """The station restarted with its new configuration (its ``config_reloaded`` event)."""
        with self._lock:
            t = self._tracks.setdefault(name, _Track(None))
            t.version, t.pending, t.meter_ok = t.pending or self.version, None, False
            v = t.version
        self.state.journal("station_applied", station=name, version=v)

    def heartbeat(self, name: str, body: dict[str, Any]) -> None:
        filled = body.get("filled")
        if isinstance(filled, int) and filled > 0:
            with self._lock:
                t = self._tracks.get(name)
                if t is not None:
                    t.meter_ok = True

    def removed(self, name: str) -> None:
        with self._lock:
            self._tracks.pop(name, None)

    def interrupt_by(self) -> str | None:
        """``--interrupt-tests --by NAME`` of the apply of the version just read, once."""
        ap = self.state.applying()
        if ap and ap.get("version") == self.version and isinstance(ap.get("interrupt_by"), str):
            if self._interrupted_for != self.version:
                self._interrupted_for = self.version
                return str(ap["interrupt_by"])
        return None

    def restart_requested(self) -> tuple[str | None, bool] | None:
        """``hookwatch config restart`` asked for new worker processes (``restart.json`` with an
        id not yet carried out): (the software version asked for, every worker or only those on
        another version), or None. Each worker concerned restarts once its station is idle."""
        req = read_json(self.state.path("restart.json"))
        rid = req.get("id") if req else None
        if not req or not isinstance(rid, str) or rid == self._restart_done:
            return None
        self._restart_done = rid
        sw = req.get("software") if isinstance(req.get("software"), str) else None
        every = bool(req.get("all"))
        self.state.journal("restart", id=rid, software=sw, all=every,
                           why="new software: each station's worker restarts once idle")
        log.info("restart asked for (software %s): each worker restarts once its station is idle", sw)
        return sw, every

    def interrupted(self, by: str, stations: list[str]) -> None:
        self._interrupt = {"by": by, "version": self.version, "stations": stations, "time": time.time()}
        self.state.journal("interrupted", by=by, version=self.version, stations=stations)
        log.warning("config apply by %s interrupts the tests of %s", by, ", ".join(stations) or "none")
        self._last_status = 0.0

    # ------------------------------------------------------------------ the watch
    def tick(self, hubs: list[HubInfo], now: float) -> bool:
        """Status, drift, a dead apply; True when the folder was repaired (the supervisor reloads)."""
        if now - self._last_watch < WATCH_S and self._last_status:
            return False
        self._last_watch = now
        repaired = self._dead_apply()
        drift = self.state.drift() if self.version else []
        if drift != self._drift:
            if drift:
                self.state.journal("drift", version=self.version, files=drift[:50])
                log.error("configuration drift: %s edited by hand (version %s)",
                          ", ".join(drift[:5]), (self.version or "")[:12])
            else:
                self.state.journal("drift_cleared", version=self.version)
            self._drift = drift
        stations = self._status(hubs, now)
        if self._start_gate.check(self.version, stations, now):
            repaired = True
        elif self.state.verified() == self.version and self._verified_seen != self.version:
            self._last_status = 0.0          # verified now: the report says so at the next look
        self._verified_seen = self.state.verified()
        return repaired

    def _dead_apply(self) -> bool:
        if self.state.applying() is None:
            return False
        with self.state.try_lock() as held:
            if not held or self.state.applying() is None:
                return False
            why = self.state.repair()
        log.error("configuration repaired: %s; back to %s", why, (self.state.current() or "none")[:12])
        return True

    def _status(self, hubs: list[HubInfo], now: float) -> dict[str, dict[str, Any]]:
        with self._lock:
            stations = {h.name: {"version": self._tracks[h.name].version if h.name in self._tracks else None,
                                 "pending": self._tracks[h.name].pending if h.name in self._tracks else None,
                                 "meter_ok": bool(h.name in self._tracks and self._tracks[h.name].meter_ok),
                                 "in_test": h.in_test, "running": h.running, "refused": h.refused,
                                 "software": h.software, "pid": h.pid}
                        for h in hubs}
        man = self.state.manifest(self.version) if self.version else None
        status = {"pid": os.getpid(), "software": __version__, "started": self._started,
                  "box": (man or {}).get("box"),
                  "site": (man or {}).get("site"),
                  "version": self.version, "stations": stations, "drift_files": self._drift[:50],
                  "last_interrupt": self._interrupt}
        key = safeout.dumps(status)
        if key == self._status_key and now - self._last_status < STATUS_REFRESH_S:
            return stations
        self._status_key, self._last_status = key, now
        try:
            write_atomic(self.state.path("supervisor.json"),
                         safeout.dumps(dict(status, time=time.time())).encode("utf-8"))
        except OSError as e:
            log.error("cannot write %s: %s", self.state.path("supervisor.json"), e.strerror)
        self.report = build_report(self.state, status, online=True)
        if self._reporter is not None:
            self._reporter.update(self.report)
        return stations

    # ------------------------------------------------------------------ the report's session
    def _reporter_for_version(self) -> None:
        cur = self.state.current()
        man = self.state.manifest(cur) if cur else None
        site_file = os.path.join(self.state.current_link, "site.yaml")
        broker: dict[str, Any] = {}
        try:
            b = load(site_file).data.get("broker")
            broker = b if isinstance(b, dict) else {}
        except (YamlError, OSError, UnicodeDecodeError):
            broker = {}
        key = (safeout.dumps(broker), (man or {}).get("site"), (man or {}).get("box"))
        if key == self._reporter_key:
            return
        self._reporter_key = key
        if self._reporter is not None:
            self._reporter.stop()
            self._reporter = None
        if not broker.get("host") or not man:
            return
        try:
            bs = BrokerSettings(host=str(broker["host"]), port=int(broker.get("port", 1883)),
                                username=broker.get("username"), password_file=broker.get("password_file"),
                                keepalive_s=int(broker.get("keepalive_s", 30)))
        except (TypeError, ValueError) as e:
            log.error("site.yaml broker: %s: no config report", e)
            return
        self._reporter = ReportPublisher(bs, str(broker.get("prefix") or "hookwatch"),
                                         str(man.get("site")), str(man.get("box")))
        self._reporter.start()
        self._last_status = 0.0

    def figures(self) -> dict[str, Any]:
        """For Prometheus: the version, its sha256, the box and site, and the drift."""
        man = self.state.manifest(self.version) if self.version else None
        return {"box": (man or {}).get("box"), "site": (man or {}).get("site"),
                "version": self.version, "sha256": (man or {}).get("sha256"),
                "verified": self.state.verified(), "drift": bool(self._drift),
                "deferred": len(self.report.get("deferred") or []),
                "rollbacks": 1 if self.state.last_rollback() else 0}
