"""One station in its own process: ``python -m gateway.supervisor.worker --fd N STATION.yaml``.

Started by the supervisor (``hookwatch run FLEET_DIR``) with one end of a Unix socketpair as
file descriptor ``N``. The station runs on a :class:`~gateway.station.fleet.StationRunner` (its own
loop, restarted after an exception, SIGHUP reloads decided on its loop), with its own MQTT client
and outbox when configured, plus an :class:`IpcOutput` that streams its state, slot summaries and
events to the supervisor (:mod:`gateway.supervisor.ipc`). Commands from the supervisor go to
``station.submit`` on the station's loop. SIGTERM/SIGINT, or the supervisor's end of the socket
closing, stop the station cleanly (a running test is closed as aborted).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import socket
import sys
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import asdict
from typing import Any

from .. import __version__
from ..compose import build_station
from ..config import ConfigError, load_station
from ..core.command_intake import intake
from ..core.command_rules import Rejection, reply_code
from ..core.records import CommandReply, Event, SlotRecord, StationState
from ..core.slotwindow import SlotWindow
from ..outputs.console.site import MAX_MESSAGE_BYTES
from ..outputs.console.site import filters as site_filters
from ..outputs.mqtt.output import MqttOutput
from ..outputs.prometheus import MetricsOutput
from ..outputs.registry import box_served, row_served
from ..plumbing.ratelog import safe
from ..plumbing.threadloop import submit_to
from ..station.fleet import StationRunner
from ..station.station import Station
from .fleetcfg import RunOptions, apply_overrides
from .ipc import PROTO, RESTART_EXIT, FrameChannel, FrameDecoder, FrameType, ProtocolError, read_frames, slot_row

log = logging.getLogger("hookwatch.worker")

#: one SLOTS frame per this many slots (0.2 s at 50 Hz)
SUMMARY_EVERY = 10
HEARTBEAT_S = 0.5
#: one METRICS frame per this many heartbeats (1 s)
METRICS_EVERY = 2


def served_words() -> tuple[str, ...]:
    """What a supervisor may serve for its workers' stations (``--served-by-supervisor``): the
    outputs of the registry it serves (gateway/outputs/registry.py, plug-in outputs included),
    and the site view."""
    return (*box_served(), "site")


class IpcOutput:
    """An :class:`~gateway.core.ports.Output` that sends a station's stream to the supervisor.
    O(1) per slot, never blocks: frames go to a bounded :class:`FrameChannel`. With ``rows``
    (the supervisor serves the station's Modbus TCP unit, the console or its Sparkplug device)
    every SLOTS frame also carries the slot records it summarises, as lists of values
    (``ipc.SLOT_COLUMNS``)."""

    def __init__(self, chan: FrameChannel, every: int = SUMMARY_EVERY, rows: bool = False) -> None:
        self.chan = chan
        self.every = max(1, int(every))
        self.rows = rows
        self._recs: list[SlotRecord] = []
        self._win = SlotWindow()

    async def start(self) -> None:
        pass

    async def stop(self) -> None:
        pass

    def on_record(self, rec: SlotRecord) -> None:
        w = self._win
        w.add(rec)
        if self.rows:
            self._recs.append(rec)
        if w.n >= self.every:
            self._flush(rec)

    def _flush(self, rec: SlotRecord) -> None:
        w = self._win
        body: dict[str, Any] = {
            "k": rec.k, "n": w.n, "filled": w.n_present, "valid": w.n_mu,
            "mu_mean": w.mu_mean, "t_mean": w.tension_mean,
            "lateness_ms_max": w.late_max * 1e3, "rtt_ms_max": w.rtt_max * 1e3,
            "last": asdict(rec)}
        if self.rows:
            body["rows"] = [slot_row(r) for r in self._recs]
            self._recs = []
        self.chan.send(FrameType.SLOTS, body)
        self._win = SlotWindow()

    def _in_order(self) -> None:
        # with rows, the supervisor's outputs must see records, events and states in the order
        # the station gave them (a test_started after its slot's records, not before the idle
        # slots of the same batch): the slots so far go first, as a shorter SLOTS frame
        if self.rows and self._recs:
            self._flush(self._recs[-1])

    def on_event(self, ev: Event) -> None:
        self._in_order()
        self.chan.send(FrameType.EVENT, ev.as_dict())

    def on_state(self, st: StationState) -> None:
        self._in_order()
        self.chan.send(FrameType.STATE, asdict(st))


class Worker:
    def __init__(self, sock: socket.socket, station_file: str, fleet_file: str | None,
                 opts: RunOptions, phase: float = 0.0, summary_every: int = SUMMARY_EVERY,
                 served: frozenset[str] = frozenset()) -> None:
        self.sock = sock
        self.station_file = station_file
        self.fleet_file = fleet_file
        self.opts = opts
        self.phase = phase
        #: what the supervisor serves for this station: Modbus TCP unit, console, metrics, Sparkplug device
        self.served = frozenset(served)
        self.chan = FrameChannel(sock, name="ipc-writer")
        self.out = IpcOutput(self.chan, summary_every, rows=bool(self.served & row_served()))
        self.stop = threading.Event()
        #: the exit code asked for (RESTART_EXIT), else None: 0 on a clean stop
        self.exit_code: int | None = None
        self.go = threading.Event()
        self.station: Station | None = None
        #: results of the station's earlier incarnations (before a reload or an in-process restart)
        self.earlier_results: list[dict[str, Any]] = []
        self.runner: StationRunner | None = None

    def load(self) -> Any:
        return apply_overrides(load_station(self.station_file, self.fleet_file or None), self.opts)

    def factory(self, cfg: Any) -> Callable[[], Station]:
        def make() -> Station:
            st = build_station(cfg, outputs=[self.out], with_northbound=not self.opts.no_northbound,
                               served_by_supervisor=self.served)
            st.slot_phase = self.phase
            mq = next((o for o in st.outputs if isinstance(o, MqttOutput)), None)
            if "site" in self.served and mq is not None:
                # the supervisor's console sees the site through this station's MQTT session
                mq.pump.add_site_feed(site_filters(mq.s.base_topic), self._site)
            return st
        return make

    def _site(self, topic: str, payload: bytes) -> None:
        """A retained state/status of the site (the pump thread) → the supervisor's console."""
        self.chan.send(FrameType.SITE, {"topic": topic[:1024],
                                        "payload": payload[:MAX_MESSAGE_BYTES + 1].decode("utf-8", "replace")})

    def _started(self, st: Station) -> None:
        if self.station is not None:
            self.earlier_results.extend(self.station.results)
        self.station = st

    # ------------------------------------------------------------ supervisor → worker
    def _reader(self) -> None:
        dec = FrameDecoder()
        try:
            while True:
                frames = read_frames(self.sock, dec)
                if frames is None:
                    break
                for ftype, body in frames:
                    if ftype == FrameType.COMMAND:
                        self._command(body)
                    elif ftype == FrameType.RELOAD and body.get("restart"):
                        self._restart_when_idle()
                    elif ftype == FrameType.RELOAD:
                        self._reload()
                    elif ftype == FrameType.GO:
                        self.go.set()
        except (OSError, ProtocolError) as e:
            log.error("supervisor link: %s", e)
        if not self.stop.is_set():
            log.warning("supervisor link closed; the station stops")
        self.stop.set()
        self.go.set()

    def _reply(self, fid: Any, ok: bool, reason: str, request_id: Any = None, code: int = 0) -> None:
        self.chan.send(FrameType.REPLY, {"id": fid, "ok": ok, "reason": reason, "code": code,
                                         "request_id": request_id})

    def _command(self, body: dict[str, Any]) -> None:
        fid = body.get("id")
        r = self.runner
        st = r.station if r is not None else None
        args = body.get("args") or {}
        if isinstance(args, dict) and body.get("request_id") is not None:
            args = {**args, "request_id": body.get("request_id")}
        # the one bounded intake of every door (gateway/core/command_intake.py)
        cmd = intake(body.get("kind"), args, safe(str(body.get("source") or "supervisor"), 80))
        if isinstance(cmd, Rejection):
            self._reply(fid, False, cmd.reason, None, int(cmd.code))
            return
        fut = submit_to(r.loop if r is not None else None, st.submit(cmd)) if st is not None else None
        if fut is None:
            self._reply(fid, False, "station is not running", cmd.request_id)
            return

        def done(f: Future[CommandReply]) -> None:
            try:
                rep = f.result()
                self._reply(fid, bool(rep.ok), rep.reason, rep.request_id, reply_code(rep))
            except Exception as e:  # the station's submit failed: an answer all the same
                self._reply(fid, False, f"{type(e).__name__}: {e}", cmd.request_id)
        fut.add_done_callback(done)

    def _reload(self) -> None:
        try:
            cfg = self.load()
        except (ConfigError, OSError) as e:
            log.error("reload refused, configuration kept: %s", str(e).replace("\n", "; "))
            return
        if self.runner is not None:
            self.runner.request_reload(self.factory(cfg))

    def _restart_when_idle(self) -> None:
        """The supervisor asks for a new worker process (new software installed): the station
        stops once idle — at once, or when its test ends — and the worker exits with
        :data:`RESTART_EXIT`, which the supervisor answers with a new worker at once."""
        def on_idle() -> None:
            self.exit_code = RESTART_EXIT
            self.stop.set()
        if self.runner is not None:
            self.runner.request_stop_when_idle(on_idle)

    def results(self) -> list[dict[str, Any]]:
        return self.earlier_results + (self.station.results if self.station is not None else [])

    # ------------------------------------------------------------ heartbeat (on the loop)
    def _heartbeat(self) -> None:
        r = self.runner
        st = r.station if r is not None else None
        self.chan.send(FrameType.HEARTBEAT, {
            "slots": st.stats.slots if st else 0, "filled": st.stats.filled if st else 0,
            "in_test": bool(st is not None and st.session is not None),
            # a test starting or running: a new configuration waits for its end (issue 37)
            "busy": bool(st is not None and st.busy),
            "results": len(self.results()),
            "dropped": self.chan.dropped, "crashes": r.crashes if r else 0})

    def _metrics(self) -> None:
        """The station's metrics snapshot to the supervisor (this thread, not the slot loop: the
        snapshot reads the drivers' counters and the outbox file, as a scrape does)."""
        r = self.runner
        st = r.station if r is not None else None
        m = next((o for o in (st.outputs if st is not None else ()) if isinstance(o, MetricsOutput)), None)
        if m is None:
            return
        try:
            snap = m.snapshot()
        except Exception:  # a failed snapshot must not stop the heartbeat
            log.exception("metrics snapshot failed")
            return
        self.chan.send(FrameType.METRICS, snap)

    def run(self) -> int:
        cfg = self.load()
        self.runner = r = StationRunner(cfg.station.id, self.factory(cfg), on_started=self._started,
                                           rt_priority=self.opts.realtime or 0)
        threading.Thread(target=self._reader, name="ipc-reader", daemon=True).start()
        self.chan.send(FrameType.HELLO, {"station": cfg.station.id, "pid": os.getpid(), "proto": PROTO,
                                         "software": __version__})
        self.go.wait()
        if self.stop.is_set():
            self.chan.flush()
            self.sock.close()
            return 0
        r.start()
        n = 0
        while not self.stop.is_set() and r.tl.running:
            self.stop.wait(HEARTBEAT_S)
            try:
                r.tl.call_soon(self._heartbeat)
            except RuntimeError:
                break
            n += 1
            if "metrics" in self.served and n % METRICS_EVERY == 0:
                self._metrics()
        clean = self.stop.is_set()
        r.request_stop()
        if r.tl.thread is not None:
            r.tl.thread.join(40)
        st = r.station
        final = {"stats": st.stats.summary() if st is not None else None,
                 "results": self.results()}
        self.chan.flush()
        self.chan.send_now(FrameType.FINAL, final)
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self.sock.close()
        if self.exit_code is not None:
            return self.exit_code
        return 0 if clean else 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hookwatch-worker", description=__doc__)
    ap.add_argument("station_file")
    ap.add_argument("--fd", type=int, required=True, help="the worker's end of the socketpair")
    ap.add_argument("--fleet-file", default="")
    ap.add_argument("--phase", type=float, default=0.0)
    ap.add_argument("--options", default="{}", help="hookwatch run's options as JSON")
    ap.add_argument("--summary-every", type=int, default=SUMMARY_EVERY)
    ap.add_argument("--served-by-supervisor", default="", metavar="LIST",
                    help="comma-separated: " + ", ".join(served_words()) + " — served by the supervisor "
                         "from this worker's IPC stream, not in this process")
    args = ap.parse_args(argv)
    opts = RunOptions(**json.loads(args.options))
    logging.basicConfig(level=getattr(logging, (opts.log_level or "info").upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    sys.setswitchinterval(0.0005)
    sock = socket.socket(fileno=args.fd)
    served = frozenset(x for x in args.served_by_supervisor.split(",") if x in served_words())
    w = Worker(sock, args.station_file, args.fleet_file or None, opts, args.phase, args.summary_every,
               served)
    signal.signal(signal.SIGTERM, lambda s, f: w.stop.set())
    signal.signal(signal.SIGINT, lambda s, f: w.stop.set())
    signal.signal(signal.SIGHUP, signal.SIG_IGN)      # reloads come from the supervisor
    try:
        return w.run()
    except ConfigError as e:
        log.error("%s: refused: %s", args.station_file, str(e).replace("\n", "; "))
        return 3


if __name__ == "__main__":
    sys.exit(main())
