"""One supervisor, one worker process per station (``hookwatch run FLEET_DIR``).

The supervisor reads the fleet folder (a broken or clashing station file refuses that station
alone), starts one worker per station (:mod:`gateway.supervisor.worker`) with one end of a Unix
socketpair, and then only supervises:

- **restart with exponential back-off**: a worker that exits (crash, ``kill -9``, OOM) is started
  again after ``backoff_s · 2^(n-1)`` s (n = crashes in a row, capped at ``backoff_max_s``); after
  ``hold_after`` crashes in a row it is *held back* for ``hold_s`` with an ERROR line and an event.
  A worker that ran ``stable_s`` counts as healthy again;
- **watchdog**: each worker sends a HEARTBEAT every 0.5 s from its station's own loop; one silent
  for ``watchdog_s`` (5 s: a stuck loop, a stopped process) is killed with SIGKILL and restarted —
  well within systemd's ``WatchdogSec=10s``, which guards the supervisor itself;
- **SIGHUP**: the folder is read again; only a worker whose effective configuration changed gets a
  RELOAD frame (its station decides on its own loop: idle → restarts with it, in a test → keeps its
  parameters); a broken file keeps its running station; new files start, removed files stop.

The restarts, the watchdog and the pace of starts are one part, :class:`WorkerWatch`, run on
every tick; :class:`Supervisor` reads the folder, holds the workers and hubs, releases the start
barrier, reloads and stops (the ``Runtime`` of ``hookwatch run``).

Per station the supervisor keeps a :class:`StationHub`: the latest state, the last slot summary,
a bounded stream of slot summaries and events, and a command path back to the station. The
outputs that stay in the supervisor process (the Modbus TCP ports with one unit per station, the
Sparkplug edge nodes with a device per station, the web console, the metrics endpoint) hang on
it through a station proxy (``hub.sink``, a :class:`~gateway.supervisor.remote.RemoteStation`):
see docs/runtime.md.
"""
from __future__ import annotations

import collections
import itertools
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

from ..compose import process_budget
from ..config import Issue
from ..core.command_rules import CODE, Rejection
from ..core.records import CommandReply
from ..plumbing import safeout
from ..plumbing.backoff import Backoff
from ..plumbing.doors import RateLog, budget
from ..plumbing.threadloop import Mailbox
from ..station.build import records_dir_ok
from .boxagent import BoxAgent, HubInfo
from .fleetcfg import FleetPlan, Refused, RunOptions, apply_overrides, fingerprint, plan_fleet
from .ipc import RESTART_EXIT, FrameDecoder, FrameType, ProtocolError, encode, read_frames

__all__ = ["StationHub", "Supervisor", "WorkerHandle", "WorkerWatch"]

log = logging.getLogger("hookwatch.supervisor")

#: how many stream items (slot summaries, events) a hub keeps for late subscribers
STREAM_LEN = 512
#: a gap between two ticks longer than this is a stall of the supervisor itself …
STALL_S = 2.0
#: … after which the worker watchdog waits this long (the readers catch up on the heartbeats)
GRACE_S = 2.0
#: a worker start that failed (EMFILE …) is tried again after this, doubling up to SPAWN_RETRY_MAX_S
SPAWN_RETRY_S = 0.5
SPAWN_RETRY_MAX_S = 30.0


class FrameSink(Protocol):
    """Where a hub hands every frame of its worker (on the worker's reader thread: O(1), never
    blocking) and the worker's ups and downs."""

    def on_frame(self, ftype: FrameType, body: dict[str, Any]) -> None: ...

    def on_worker(self, up: bool, restarts: int = 0) -> None: ...


class SharedOutputs(Protocol):
    """The outputs a fleet's supervisor runs for its stations
    (:class:`~gateway.supervisor.remote.RemoteFleet`): attached to the hubs at start (before the
    first worker, so they see every frame) and after each reload, stopped after the workers."""

    def attach(self, sup: Supervisor) -> None: ...

    def stop(self) -> None: ...


class StationHub:
    """Everything the supervisor process knows of one station: the hook point for shared outputs.

    - :attr:`state` — the latest STATE frame (a :class:`~gateway.core.records.StationState` mapping);
    - :attr:`last_slots` — the latest SLOTS frame (with ``last``: the latest slot record);
    - :attr:`stream` — the last :data:`STREAM_LEN` items ``(kind, body)``, kind ``"slots"``,
      ``"event"`` (station events) or ``"supervisor"`` (refused, exited, restarted, held back);
    - :meth:`subscribe` — a :class:`~gateway.plumbing.threadloop.Mailbox` fed with every new item, bounded
      (a slow consumer loses its oldest items, counted; it never delays the station or the hub);
    - :meth:`command` — a command to the station (``station.submit`` in its worker) with a timeout.

    Frames are dispatched on the worker's reader thread; subscribers drain on their own thread.
    """

    def __init__(self, name: str, path: str | None) -> None:
        self.name = name
        self.path = path
        self.state: dict[str, Any] | None = None
        self.last_slots: dict[str, Any] | None = None
        self.heartbeat: dict[str, Any] | None = None
        self.heartbeat_t = 0.0
        #: the hookwatch version its worker runs (its HELLO)
        self.software: str | None = None
        self.refused: str | None = None
        self.stream: collections.deque[tuple[str, dict[str, Any]]] = collections.deque(maxlen=STREAM_LEN)
        self.results: list[dict[str, Any]] = []
        self.stats: dict[str, Any] | None = None
        self.worker: WorkerHandle | None = None
        #: the station proxy of the supervisor's shared outputs (gateway/supervisor/remote.py):
        #: gets every frame on the reader thread (:class:`FrameSink`), or None
        self.sink: FrameSink | None = None
        self._subs: list[Mailbox[tuple[str, dict[str, Any]]]] = []
        self._lock = threading.Lock()

    def subscribe(self, maxlen: int = 1024) -> Mailbox[tuple[str, dict[str, Any]]]:
        box: Mailbox[tuple[str, dict[str, Any]]] = Mailbox(maxlen)
        with self._lock:
            self._subs.append(box)
        return box

    def unsubscribe(self, box: Mailbox[tuple[str, dict[str, Any]]]) -> None:
        with self._lock:
            if box in self._subs:
                self._subs.remove(box)

    def publish(self, kind: str, body: dict[str, Any]) -> None:
        """Never blocks: the stream and each subscriber's mailbox drop their oldest item."""
        item = (kind, body)
        with self._lock:
            self.stream.append(item)
            subs = list(self._subs)
        for box in subs:
            box.put_nowait(item)

    def snapshot(self) -> dict[str, Any]:
        """The station's latest state as the supervisor knows it (for a console or metrics)."""
        w = self.worker
        return {"station": self.name, "file": self.path, "refused": self.refused,
                "running": bool(w is not None and w.running), "state": self.state,
                "slots": self.last_slots, "heartbeat": self.heartbeat,
                "restarts": w.restarts if w else 0}

    def command(self, kind: str, args: dict[str, Any] | None = None, source: str = "supervisor",
                request_id: str | None = None, timeout: float = 5.0) -> CommandReply:
        """Send a command (start, stop, ack, setpoint) to the station and wait for its reply."""
        w = self.worker
        if w is None or not w.running:
            return Rejection(False, f"station {self.name} is not running", request_id, CODE["NO_STATION"])
        return w.command({"kind": kind, "args": args or {}, "source": source,
                          "request_id": request_id}, timeout)

    def _sink(self, ftype: FrameType, body: dict[str, Any]) -> None:
        sink = self.sink
        if sink is not None:
            try:
                sink.on_frame(ftype, body)
            except Exception:  # a broken shared output must not take the worker's link down
                log.exception("%s: shared outputs failed on a %s frame", self.name, ftype.name)

    def _worker(self, up: bool) -> None:
        sink, w = self.sink, self.worker
        if sink is not None:
            try:
                sink.on_worker(up, w.restarts if w is not None else 0)
            except Exception:
                log.exception("%s: shared outputs failed on a worker %s", self.name, "up" if up else "down")

    @property
    def in_test(self) -> bool:
        hb = self.heartbeat
        return bool(hb and hb.get("in_test"))

    @property
    def busy(self) -> bool:
        """A test is starting or running (a new configuration waits for its end)."""
        hb = self.heartbeat
        return bool(hb and (hb.get("busy") or hb.get("in_test")))


class WorkerHandle:
    """One worker process and its end of the socketpair."""
    _ids = itertools.count(1)

    def __init__(self, sup: Supervisor, hub: StationHub, path: str, phase: float) -> None:
        self.sup = sup
        self.hub = hub
        self.path = path
        self.phase = phase
        self.proc: subprocess.Popen[bytes] | None = None
        self.sock: socket.socket | None = None
        self.reader: threading.Thread | None = None
        self.hello = False               # loaded (HELLO), waiting for GO
        self.go_t = 0.0                  # when GO was sent (the station runs from then on)
        self.started_at = 0.0
        self.next_start = 0.0
        #: the restart back-off of this worker (crashes in a row) and of its failed starts
        self.restart = sup.watch.restart_backoff()
        self.spawn_retry = Backoff(SPAWN_RETRY_S, SPAWN_RETRY_MAX_S)
        self.spawned = 0
        self.restarts = 0
        #: starts that failed (EMFILE …), in all
        self.spawn_failures = 0
        self.stopping = False
        self.fingerprint = ""
        #: what the supervisor serves for this station (Modbus TCP unit, Sparkplug device, console, metrics)
        self.served: frozenset[str] = frozenset()
        self._send_lock = threading.Lock()
        self._pending: dict[int, tuple[threading.Event, list[dict[str, Any]]]] = {}

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def spawn(self) -> None:
        """Start the worker. An OSError (EMFILE, ENFILE, EAGAIN, ENOMEM: out of descriptors or
        processes) leaves nothing open behind and is raised for :meth:`Supervisor.tick`, which
        makes it a state (retry with back-off, one log line with a count)."""
        parent, child = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self._spawn(parent, child)
        except BaseException:
            parent.close()
            raise

    def _spawn(self, parent: socket.socket, child: socket.socket) -> None:
        sup = self.sup
        argv = [sys.executable, "-m", "gateway.supervisor.worker", self.path,
                "--fd", str(child.fileno()), "--fleet-file", sup.plan.fleet_file or "",
                "--phase", f"{self.phase:.4f}", "--options", sup.opts_json,
                "--summary-every", str(sup.summary_every),
                "--served-by-supervisor", ",".join(sorted(self.served))]
        try:
            # systemd's notify socket is the supervisor's alone (NotifyAccess=main)
            env = {k: v for k, v in os.environ.items()
                   if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID")}
            # its own session: a Ctrl-C on the terminal reaches the supervisor only, which stops
            # the workers in order (systemd's KillMode=mixed still SIGKILLs leftovers)
            self.proc = subprocess.Popen(argv, pass_fds=(child.fileno(),), stdin=subprocess.DEVNULL,
                                         env=env, start_new_session=True)
        finally:
            child.close()
        self.sock = parent
        self.spawned += 1
        self.hello = False
        self.go_t = 0.0
        self.started_at = time.monotonic()
        self.hub.heartbeat = None
        self.hub.heartbeat_t = 0.0
        self.reader = threading.Thread(target=self._read, args=(parent,), daemon=True,
                                       name=f"ipc-{self.hub.name}")
        self.reader.start()
        log.info("%s: worker started (pid %d)", self.hub.name, self.proc.pid)
        if sup.agent is not None:
            sup.agent.spawned(self.hub.name)

    def _read(self, sock: socket.socket) -> None:
        dec = FrameDecoder()
        hub = self.hub
        try:
            while True:
                frames = read_frames(sock, dec)
                if frames is None:
                    break
                for ftype, body in frames:
                    hub._sink(ftype, body)
                    if ftype == FrameType.HEARTBEAT:
                        hub.heartbeat = body
                        hub.heartbeat_t = time.monotonic()
                        if self.sup.agent is not None:
                            self.sup.agent.heartbeat(hub.name, body)
                    elif ftype == FrameType.SLOTS:
                        hub.last_slots = body
                        hub.publish("slots", body)
                    elif ftype == FrameType.EVENT:
                        hub.publish("event", body)
                        if body.get("type") == "config_reloaded" and self.sup.agent is not None:
                            self.sup.agent.config_reloaded(hub.name)
                    elif ftype == FrameType.STATE:
                        hub.state = body
                    elif ftype == FrameType.REPLY:
                        p = self._pending.get(body.get("id"))     # type: ignore[arg-type]
                        if p is not None:
                            p[1].append(body)
                            p[0].set()
                    elif ftype == FrameType.HELLO:
                        self.hello = True
                        sw = body.get("software")
                        hub.software = sw if isinstance(sw, str) else None
                        hub._worker(True)
                        if not self.sup.barrier:
                            self.go()
                    elif ftype == FrameType.FINAL:
                        hub.results.extend(body.get("results") or [])
                        hub.stats = body.get("stats")
                    elif ftype == FrameType.SITE and self.sup.on_site is not None:
                        t, p = body.get("topic"), body.get("payload")
                        if isinstance(t, str) and isinstance(p, str):
                            self.sup.on_site(t, p.encode("utf-8"))
        except (OSError, ProtocolError) as e:
            log.error("%s: worker link broken: %s", hub.name, e)
        finally:
            for ev, _ in list(self._pending.values()):
                ev.set()
            hub._worker(False)

    def send(self, ftype: FrameType, body: dict[str, Any]) -> bool:
        s = self.sock
        if s is None:
            return False
        try:
            with self._send_lock:
                s.sendall(encode(ftype, body))
            return True
        except OSError:
            return False

    def go(self) -> None:
        """Let the loaded worker run its station."""
        self.go_t = time.monotonic()
        self.send(FrameType.GO, {})

    def command(self, body: dict[str, Any], timeout: float) -> CommandReply:
        fid = next(self._ids)
        ev: threading.Event = threading.Event()
        slot: list[dict[str, Any]] = []
        self._pending[fid] = (ev, slot)
        rid = body.get("request_id")
        try:
            if not self.send(FrameType.COMMAND, {"id": fid, **body}):
                return Rejection(False, f"station {self.hub.name}: worker link down", rid, CODE["NO_STATION"])
            ev.wait(timeout)
        finally:
            self._pending.pop(fid, None)
        if not slot:
            return Rejection(False, f"station {self.hub.name} did not answer within {timeout:g} s", rid,
                             CODE["NO_STATION"])
        r = slot[0]
        if r.get("ok"):
            return CommandReply(True, str(r.get("reason") or ""), r.get("request_id"))
        code = r.get("code")
        return Rejection(False, str(r.get("reason") or ""), r.get("request_id"),
                         int(code) if isinstance(code, int) and code else CODE["BAD_REQUEST"])

    def terminate(self) -> None:
        self.stopping = True
        if self.running and self.proc is not None:
            self.proc.send_signal(signal.SIGTERM)

    def reap(self) -> None:
        """After the process ended: let the reader take the last frames, close the socket."""
        if self.reader is not None:
            self.reader.join(5)
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class WorkerWatch:
    """The supervision of a fleet's workers, once per tick: starts paced (at most ``max_starting``
    loading at a time), a worker that exits restarted after ``backoff_s · 2^(n-1)`` s (n = crashes
    in a row, capped at ``backoff_max_s``; a run of ``stable_s`` resets n) or held back ``hold_s``
    after ``hold_after`` crashes in a row, one silent for ``watchdog_s`` (``startup_s`` while it
    loads) killed, a start that fails (EMFILE …) retried with its own back-off. A stall of the
    supervisor itself (> STALL_S between ticks) pauses the watchdog GRACE_S."""

    def __init__(self, rlog: RateLog, *, watchdog_s: float, backoff_s: float, backoff_max_s: float,
                 hold_after: int, hold_s: float, stable_s: float, startup_s: float) -> None:
        self.rlog = rlog
        self.watchdog_s = watchdog_s
        self.backoff_s = backoff_s
        self.backoff_max_s = backoff_max_s
        self.hold_after = hold_after
        self.hold_s = hold_s
        self.stable_s = stable_s
        self.startup_s = startup_s
        self.max_starting = max(1, os.cpu_count() or 1)
        #: worker starts that failed (EMFILE, ENFILE …), all stations
        self.spawn_failures = 0
        self._last_tick = 0.0
        #: no watchdog kill before this time (after a stall of the supervisor itself)
        self._grace_until = 0.0

    def restart_backoff(self) -> Backoff:
        """A worker's restart back-off (gateway/plumbing/backoff.py): ``backoff_s`` doubling to
        ``backoff_max_s``, a run of ``stable_s`` starting a new row."""
        return Backoff(self.backoff_s, self.backoff_max_s, self.stable_s)

    def tick(self, workers: list[WorkerHandle], now: float) -> None:
        if self._last_tick and now - self._last_tick > STALL_S:
            # the supervisor itself did not run (stopped, swapped out, starved): the workers'
            # heartbeats wait unread in the sockets; let the readers catch up before judging them
            log.warning("supervisor did not run for %.1f s; worker watchdog paused %.0f s",
                        now - self._last_tick, GRACE_S)
            self._grace_until = now + GRACE_S
        self._last_tick = now
        # workers start at most ``max_starting`` at a time: a worker's start-up (imports, port
        # opening) costs about a second of CPU, and N at once would starve the running stations
        starting = sum(1 for w in workers if w.running and not w.hello)
        for w in workers:
            name = w.hub.name
            if w.proc is None:
                if not w.stopping and now >= w.next_start and starting < self.max_starting:
                    starting += 1
                    try:
                        w.spawn()
                    except OSError as e:        # EMFILE, ENFILE, EAGAIN: a state, never the end
                        self._spawn_failed(w, e, now)
                        continue
                    w.spawn_retry.reset()
                    if w.spawned > 1:
                        w.restarts += 1
                        w.hub.publish("supervisor", {"type": "worker_restarted", "station": name,
                                                     "restarts": w.restarts, "time": time.time()})
                continue
            rc = w.proc.poll()
            if rc is not None:
                self._exited(w, rc, now)
                continue
            if w.hello and not w.go_t:
                continue                     # loaded, waiting at the start barrier
            age = now - max(w.hub.heartbeat_t, w.go_t, w.started_at)
            limit = self.watchdog_s if w.go_t else self.startup_s
            if age > limit and not w.stopping and now >= self._grace_until:
                log.error("%s: worker pid %d silent for %.1f s (stuck loop?): killed (SIGKILL)",
                          name, w.proc.pid, age)
                w.hub.publish("supervisor", {"type": "worker_stuck", "station": name,
                                             "silent_s": round(age, 1), "time": time.time()})
                w.proc.kill()

    def _spawn_failed(self, w: WorkerHandle, e: OSError, now: float) -> None:
        """A worker that cannot be started (no descriptor for its socketpair, no process): tried
        again after SPAWN_RETRY_S, doubling to SPAWN_RETRY_MAX_S; one log line a minute per
        station with the count; the running workers go on."""
        w.spawn_failures += 1
        delay = w.spawn_retry.failed()
        w.next_start = now + delay
        self.spawn_failures += 1
        self.rlog(logging.ERROR, f"spawn:{w.hub.name}", "%s: cannot start the worker: %s; "
                  "retrying in %.1f s (%d failed starts)", w.hub.name, e.strerror or e, delay,
                  w.spawn_failures)
        if w.spawn_retry.in_row == 1:
            w.hub.publish("supervisor", {"type": "worker_start_failed", "station": w.hub.name,
                                         "reason": str(e.strerror or e), "retry_in_s": delay,
                                         "time": time.time()})

    def _exited(self, w: WorkerHandle, rc: int, now: float) -> None:
        w.reap()
        w.proc = None
        w.hub.heartbeat = None
        name = w.hub.name
        if w.stopping:
            return
        if rc == RESTART_EXIT:          # asked for (new software), once idle: not a crash
            log.info("%s: worker ended for its restart (new software); starting it again", name)
            w.next_start = now
            return
        why = f"signal {-rc}" if rc < 0 else f"exit code {rc}"
        delay = w.restart.failed(now - w.started_at)
        n = w.restart.in_row
        if n >= self.hold_after:
            delay = self.hold_s
            log.error("%s: worker keeps crashing (%d times in a row, last: %s): held back for %.0f s",
                      name, n, why, delay)
            kind = "worker_held_back"
        else:
            log.error("%s: worker ended (%s); restarting in %.1f s", name, why, delay)
            kind = "worker_exited"
        w.next_start = now + delay
        w.hub.publish("supervisor", {"type": kind, "station": name, "reason": why,
                                     "crashes_in_row": n, "restart_in_s": delay, "time": time.time()})


class Supervisor:
    def __init__(self, folder: str, opts: RunOptions, *, watchdog_s: float = 5.0,
                 backoff_s: float = 1.0, backoff_max_s: float = 60.0, hold_after: int = 5,
                 hold_s: float = 300.0, stable_s: float = 60.0, startup_s: float = 60.0,
                 summary_every: int = 10,
                 served_for: Callable[[Any], frozenset[str]] | None = None,
                 shared: SharedOutputs | None = None,
                 on_site: Callable[[str, bytes], object] | None = None) -> None:
        self.folder = folder
        #: a site-managed box (``hookwatch run STATE/config/current``): versions, deferral, report
        self.agent = BoxAgent.for_folder(folder)
        #: removed stations whose test still runs: stopped when it ends
        self._retire_after_test: list[WorkerHandle] = []
        #: the console's site view (SITE frames of the worker that carries it), or None
        self.on_site = on_site
        #: the shared outputs (Modbus TCP units, Sparkplug devices, console, metrics), or None
        self.shared = shared
        #: what the supervisor's shared outputs serve for a station (its configuration → a subset
        #: of modbus, sparkplug, console, metrics): its worker then streams what they need and serves none
        self.served_for = served_for
        self.opts = opts
        self.opts_json = safeout.dumps(opts.as_dict())
        self.startup_s = startup_s
        self.summary_every = summary_every
        self.rlog = RateLog(log)
        #: restarts, hold-backs, the watchdog and the pace of starts
        self.watch = WorkerWatch(self.rlog, watchdog_s=watchdog_s, backoff_s=backoff_s,
                                 backoff_max_s=backoff_max_s, hold_after=hold_after, hold_s=hold_s,
                                 stable_s=stable_s, startup_s=startup_s)
        #: at start, loaded workers wait until all are loaded (then GO for all at once)
        self.barrier = True
        self.t_start = time.monotonic()
        self.plan = FleetPlan(None)
        self.hubs: dict[str, StationHub] = {}
        self.workers: dict[str, WorkerHandle] = {}        # by station file path
        self._retired: list[WorkerHandle] = []             # removed or renamed, stopping
        self._ready = False
        self._started_any = False

    # ------------------------------------------------------------ start
    def refuse(self, r: Refused, reload: bool = False) -> None:
        hub = self.hubs.get(r.name)
        if hub is None:
            hub = self.hubs[r.name] = StationHub(r.name, r.path)
        hub.refused = r.message()
        log.error("station %s refused (%s): %s; the other stations run", r.name, r.path, r.message())
        hub.publish("supervisor", {"type": "station_refused", "station": r.name, "file": r.path,
                                   "reason": r.message(), "time": time.time()})

    def start(self, spawn: bool = True) -> FleetPlan:
        """Read the fleet folder, make a hub per station and (``spawn``) start the first workers;
        with ``spawn`` False the first :meth:`tick` starts them (the caller attaches its shared
        outputs to the hubs in between, so they see every frame from the first HELLO on)."""
        self.t_start = time.monotonic()
        if self.agent is not None:
            self.agent.at_start()
        self.plan = plan = plan_fleet(self.folder)
        # the descriptor budget first: the soft limit raised, the reserve for the socketpairs of
        # worker (re)starts kept from the console, metrics and Modbus ports (gateway/plumbing/doors.py)
        if plan.accepted:
            process_budget(plan.accepted[0][1])
        else:
            budget()
        for path, cfg in list(plan.accepted):
            err = records_dir_ok(apply_overrides(cfg, self.opts).recorder.dir)
            if err:                       # a station that cannot record does not run
                plan.accepted.remove((path, cfg))
                plan.refused.append(Refused(path, cfg.station.id, [Issue("error", "recorder.dir", err, path)]))
        for r in plan.refused:
            self.refuse(r)
        n = max(1, len(plan.accepted))
        for i, (path, cfg) in enumerate(plan.accepted):
            self._add(path, cfg, i / n)
        if self.shared is not None and plan.accepted:
            self.shared.attach(self)
        if spawn:
            self.tick()
        return plan

    def _add(self, path: str, cfg: Any, phase: float) -> None:
        name = cfg.station.id
        hub = self.hubs.get(name)
        if hub is None:
            hub = self.hubs[name] = StationHub(name, path)
        hub.refused = None
        hub.path = path
        w = WorkerHandle(self, hub, path, phase)
        w.fingerprint = fingerprint(apply_overrides(cfg, self.opts))
        w.served = self.served_for(apply_overrides(cfg, self.opts)) if self.served_for else frozenset()
        hub.worker = w
        self.workers[path] = w          # started by tick(), a few at a time

    def all_up(self) -> bool:
        """Every worker runs its station (READY for systemd)."""
        return all(w.stopping or (w.running and w.go_t > 0) for w in self.workers.values())

    # ------------------------------------------------------------ the runtime (gateway.core.ports.Runtime)
    def alive(self) -> bool:
        """A station can run (not every station file was refused); workers are restarted."""
        return bool(self.workers)

    def ready(self) -> bool:
        """Every worker runs its station, or the start-up time is over (READY for systemd)."""
        if not self._ready and (self.all_up() or time.monotonic() - self.t_start > self.startup_s):
            self._ready = True
        return self._ready

    def status(self) -> str:
        n_run = sum(1 for w in self.workers.values() if w.running)
        refused = [h.name for h in self.hubs.values() if h.refused]
        return (f"{n_run} station worker(s) running"
                + (f"; refused: {', '.join(refused)}" if refused else ""))

    def tests_done(self) -> bool:
        """Every test started has ended, and no worker is starting or waiting for its restart."""
        return (self._started_any and not any(h.in_test for h in self.hubs.values())
                and not self.pending())

    def report(self) -> dict[str, dict[str, Any] | None]:
        out: dict[str, dict[str, Any] | None] = {}
        for name, h in self.hubs.items():
            if h.refused:
                out[name] = {"refused": h.refused}
                continue
            out[name] = dict(h.stats or {}, results=h.results,
                             restarts=h.worker.restarts if h.worker else 0)
        return out

    # ------------------------------------------------------------ supervision
    def tick(self, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        if any(h.in_test for h in self.hubs.values()):
            self._started_any = True
        if self.barrier and (now - self.t_start > self.startup_s or not any(
                w.proc is None or (w.running and not w.hello) for w in self.workers.values())):
            # every worker of the fleet has loaded (or the start-up time is over): all stations
            # start their slot loops now, after the start-up CPU of all of them is spent
            self.barrier = False
            for w in self.workers.values():
                if w.running and w.hello and not w.go_t:
                    w.go()
        self.watch.tick(list(self.workers.values()), now)
        for w in [w for w in self._retire_after_test if not w.hub.busy]:
            self._retire_after_test.remove(w)
            log.info("%s: its test ended: the removed station stops", w.hub.name)
            self._retire(w)
        if self.agent is not None and self.agent.tick(
                [HubInfo(h.name, h.busy, bool(h.worker and h.worker.running), h.refused, h.software,
                         h.worker.proc.pid if h.worker and h.worker.proc else None)
                 for h in self._current_hubs()], now):
            self.reload()

    def _current_hubs(self) -> list[StationHub]:
        """The stations of the folder as read last (refused ones too) and the removed ones whose
        test still runs — not the stations retired earlier."""
        live = {id(w) for w in self.workers.values()} | {id(w) for w in self._retire_after_test}
        return [h for h in self.hubs.values() if h.refused or (h.worker is not None and id(h.worker) in live)]

    @property
    def spawn_failures(self) -> int:
        """Worker starts that failed (EMFILE, ENFILE …), all stations."""
        return self.watch.spawn_failures

    def healthy(self, max_age_s: float = 3.0) -> bool:
        """Every running worker's station loop answered within ``max_age_s`` (systemd watchdog).
        A worker waiting for its restart or still starting (its own start-up limit applies) does
        not hold the others' watchdog back; one that went silent does, until it is killed."""
        now = time.monotonic()
        for w in self.workers.values():
            if (w.running and not w.stopping and w.go_t
                    and now - max(w.hub.heartbeat_t, w.go_t) > max_age_s):
                return False
        return True

    def pending(self) -> bool:
        """A worker is starting, has not run a slot yet, or waits for its restart."""
        for w in self.workers.values():
            hb = w.hub.heartbeat
            if not w.stopping and (w.proc is None or not w.go_t or not hb or not hb.get("slots")):
                return True
        return False

    # ------------------------------------------------------------ reload
    def reload(self) -> None:
        if self.agent is not None:
            self.agent.folder_read()
        try:
            plan = plan_fleet(self.folder)
        except OSError as e:
            log.error("reload refused, configuration kept: %s: %s", self.folder, e)
            return
        seen = set()
        changed: list[StationHub] = []
        for r in plan.refused:
            seen.add(r.path)
            if r.path in self.workers:
                log.error("reload refused, configuration kept: %s", r.message())
            else:
                self.refuse(r, reload=True)
        n = max(1, len(plan.accepted))
        for i, (path, cfg) in enumerate(plan.accepted):
            seen.add(path)
            fp = fingerprint(apply_overrides(cfg, self.opts))
            w = self.workers.get(path)
            if w is None:
                log.info("%s: new station file: starting its worker", cfg.station.id)
                self._add(path, cfg, i / n)
            elif w.hub.name != cfg.station.id:
                log.info("%s: station id changed to %s: worker replaced", w.hub.name, cfg.station.id)
                self._retire(w)
                self._add(path, cfg, i / n)
            elif fp != w.fingerprint:
                w.fingerprint = fp
                log.info("%s: %s changed: reload sent to its worker", w.hub.name, os.path.basename(path))
                changed.append(w.hub)
                if self.agent is not None:
                    self.agent.reload_sent(w.hub.name, w.hub.busy)
                if not w.send(FrameType.RELOAD, {}):
                    log.warning("%s: worker not running; it starts with the new file", w.hub.name)
            elif self.agent is not None:
                self.agent.unchanged(w.hub.name)
        for path, w in list(self.workers.items()):
            if path not in seen:
                if w.hub.busy and self.agent is not None:
                    log.info("%s: station file removed: its worker stops when its test ends", w.hub.name)
                    self.workers.pop(path, None)
                    self._retire_after_test.append(w)
                    continue
                log.info("%s: station file removed: its worker stops", w.hub.name)
                self._retire(w)
        req = self.agent.restart_requested() if self.agent is not None else None
        if req is not None:                      # new software: each worker restarts once idle
            for w in self.workers.values():
                if req[1] or w.hub.software != req[0]:
                    w.send(FrameType.RELOAD, {"restart": True})
        by = self.agent.interrupt_by() if self.agent is not None else None
        if by is not None:
            stopping = [h for h in changed if h.busy]
            self.agent.interrupted(by, [h.name for h in stopping])      # type: ignore[union-attr]
            for h in stopping:      # the test ends as aborted; its deferred configuration applies
                threading.Thread(target=h.command, args=("stop",), kwargs={"source": f"config:{by}"},
                                 daemon=True, name=f"interrupt-{h.name}").start()
        self.plan = plan
        if self.shared is not None:
            self.shared.attach(self)

    def _retire(self, w: WorkerHandle) -> None:
        w.terminate()
        self.workers.pop(w.path, None)
        self._retired.append(w)

    # ------------------------------------------------------------ stop
    def stop(self, timeout: float = 40.0) -> None:
        ws = list(self.workers.values()) + list(self._retired) + list(self._retire_after_test)
        for w in ws:
            w.terminate()
        t_end = time.monotonic() + timeout
        for w in ws:
            if w.proc is None:
                continue
            try:
                w.proc.wait(max(0.1, t_end - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.error("%s: worker did not stop within %.0f s: killed", w.hub.name, timeout)
                w.proc.kill()
                w.proc.wait()
            w.reap()
        if self.shared is not None:
            self.shared.stop()
        if self.agent is not None:
            self.agent.stop()
        self.rlog.close()               # the counts of the last window, and no timer after
