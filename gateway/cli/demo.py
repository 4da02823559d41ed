"""`hookwatch demo`: the main job on its built-in default — a simulated loom station, no hardware.

It starts the virtual station (`hookwatch sim` on the demo scenario: a compressed needle life of a
few minutes) as its own process, runs the gateway's station runtime against its two
pseudo-terminals exactly as it would run against a real ZN-S meter and STM32 — the station built
by the composition root, run by `hookwatch run`'s one main loop (`drive`: signals, systemd, the
end of the test) — with the whole product around it: the operator console (web pages, a demo
login), the PLC register map on a local Modbus TCP port and MQTT to a Mosquitto it starts itself
when one is installed. It prints the URL
and ready-to-paste `mbpoll` and `mosquitto_sub` lines, and when the test has ended says in plain
words what happened, re-analyses the recorded log offline to show that both results are identical
and writes the paper's Fig. 7 of the test.
"""
from __future__ import annotations

import dataclasses
import getpass
import json
import logging
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from typing import Any

from ..cli import CliError
from ..compose import build_console, build_station, in_process_runtime
from ..config import ConfigError, load_station
from ..core.records import Event, EventType, SlotRecord, StationState
from ..offline.analysis import analyze_file
from ..offline.report.pipeline import build_report
from ..outputs.console import auth
from ..outputs.mqtt import schema as mqtt_schema
from ..plumbing.osprio import deployed_nice, die_with_parent
from ..station.build import method_values
from ..station.station import Station
from ..station.terminal import TerminalOutput
from .run import AfterDone, DriveOptions, Hangup, drive

HELP = "run hookwatch on its built-in default: a simulated loom station through a compressed needle life"
DESCRIPTION = HELP + (". Starts `hookwatch sim` on the demo scenario, runs the station against its "
                      "serial ports, prints progress and events, and compares the online result "
                      "with `hookwatch analyze` of the recorded log.")

_ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", ".."))
DEMO_SCENARIO = os.path.join(_ROOT, "config", "scenarios", "demo.yaml")
DEMO_STATION = os.path.join(_ROOT, "config", "demo", "station.yaml")


def add_arguments(ap):
    ap.add_argument("--scenario", default=DEMO_SCENARIO, help="virtual-station scenario (default: the demo life)")
    ap.add_argument("--station", default=DEMO_STATION, help="station configuration (default: config/demo/station.yaml)")
    ap.add_argument("--dir", help="where to keep the links and records (default: a new temporary folder)")
    ap.add_argument("--seed", type=int, default=1, help="simulator seed")
    ap.add_argument("--every", type=float, default=5.0, metavar="S", help="progress line interval, s")
    ap.add_argument("--timeout", type=float, default=1800.0, metavar="S", help="give up after this long")
    ap.add_argument("--t-end", type=float, default=120.0, metavar="S",
                    help="planned test duration (default 120 s: the alarm comes at ≈ 107 s)")
    ap.add_argument("--console-port", type=int, default=8080, metavar="PORT",
                    help="console port on 127.0.0.1 (default 8080; a free one if taken)")
    ap.add_argument("--plc-port", type=int, default=5020, metavar="PORT",
                    help="Modbus TCP port of the PLC map on 127.0.0.1 (default 5020; a free one if taken)")
    ap.add_argument("--mqtt-port", type=int, default=1883, metavar="PORT",
                    help="port of the demo's own Mosquitto (default 1883; a free one if taken)")
    ap.add_argument("--no-console", action="store_true", help="without the web console")
    ap.add_argument("--no-northbound", action="store_true", help="without the PLC map and MQTT")


class _LifeWatcher:
    """The demo's own output: what its closing words tell of the life — the slot the end of life
    was detected in, and the test's result as the station announced it (``test_ended``)."""

    def __init__(self) -> None:
        self.k_detect: int | None = None
        self.result: dict[str, Any] | None = None

    async def start(self) -> None:
        pass

    async def stop(self) -> None:
        pass

    def on_record(self, rec: SlotRecord) -> None:
        pass

    def on_state(self, st: StationState) -> None:
        pass

    def on_event(self, ev: Event) -> None:
        if ev.type == EventType.END_OF_LIFE and ev.k is not None:
            self.k_detect = ev.k
        elif ev.type == EventType.TEST_ENDED and ev.k is not None:   # (not a cut-off test closed at start)
            self.result = {"test_id": ev.test_id, "test_status": ev.data.get("test_status"),
                           "end_reason": ev.data.get("reason"), "method": ev.data.get("result") or {}}


def _start_sim(args, work: str) -> tuple[subprocess.Popen, dict[str, str]]:
    links = os.path.join(work, "links")
    os.makedirs(links, exist_ok=True)
    truth = os.path.join(work, "truth.json")
    cmd = [sys.executable, "-m", "gateway.cli", "sim", args.scenario, "--link-dir", links,
           "--seed", str(args.seed), "--truth", truth,
           # the twin stands for hardware: its loop under SCHED_FIFO 10 where permitted (below
           # the station's 20), so a browser starting beside the demo does not starve it
           "--realtime", "10"]
    log = open(os.path.join(work, "sim.log"), "w")
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=log, text=True, preexec_fn=die_with_parent)
    assert p.stdout is not None
    log.close()
    paths: dict[str, str] = {}
    t_end = time.monotonic() + 30
    while len(paths) < 2 and time.monotonic() < t_end:
        line = p.stdout.readline()
        if not line:
            break
        for key in ("meter", "stm32"):
            if line.startswith(key + ":"):
                paths[key] = line.split(":", 1)[1].strip()
    if len(paths) < 2:
        p.kill()
        p.wait()
        with open(os.path.join(work, "sim.log")) as f:
            raise CliError("the virtual station did not start:\n" + f.read()[-2000:], 1)
    return p, {"meter": os.path.join(links, "meter"), "stm32": os.path.join(links, "stm32"),
               "truth": truth}


def _port(wanted: int) -> int:
    """``wanted`` if it is free on 127.0.0.1, else a free port."""
    for port in (wanted, 0):
        with socket.socket() as sk:
            try:
                sk.bind(("127.0.0.1", port))
            except OSError:
                continue
            return sk.getsockname()[1]
    raise CliError("no free TCP port on 127.0.0.1", 1)


def _start_mosquitto(work: str, port: int) -> subprocess.Popen | None:
    """The demo's own broker on 127.0.0.1, when Mosquitto is installed; None otherwise."""
    exe = shutil.which("mosquitto") or ("/usr/sbin/mosquitto" if os.path.exists("/usr/sbin/mosquitto") else None)
    if exe is None:
        return None
    d = os.path.join(work, "mosquitto")
    os.makedirs(d, exist_ok=True)
    conf = os.path.join(d, "mosquitto.conf")
    with open(conf, "w") as f:
        # as root, mosquitto would drop to user `mosquitto`, who may not write here
        f.write(f"user {getpass.getuser()}\nlistener {port} 127.0.0.1\nallow_anonymous true\n"
                f"persistence false\nlog_dest file {d}/mosquitto.log\n")
    p = subprocess.Popen([exe, "-c", conf], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                         preexec_fn=die_with_parent)
    t_end = time.monotonic() + 5
    while time.monotonic() < t_end:
        with socket.socket() as sk:
            if sk.connect_ex(("127.0.0.1", port)) == 0:
                return p
        if p.poll() is not None:
            break
        time.sleep(0.05)
    p.kill()
    p.wait()
    return None


def _stop_proc(p: subprocess.Popen | None) -> None:
    if p is None:
        return
    if p.poll() is None:
        p.send_signal(signal.SIGTERM)
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    if p.stdout:
        p.stdout.close()


def _demo_console(cfg, work: str, port: int):
    """The station's console (``console:`` enabled on 127.0.0.1:``port``) with one demo user (a
    fresh random password, printed); the configuration it is in, and the console (None: it did
    not start)."""
    users = os.path.join(work, "console-users.json")
    password = secrets.token_urlsafe(9)
    auth.add_user(users, "demo", password)
    cfg = dataclasses.replace(cfg, console=dataclasses.replace(
        cfg.console, enabled=True, listen=(f"127.0.0.1:{port}",), users_file=users))
    console = build_console([cfg])
    urls = console.start() if console is not None else []
    if console is None or not urls:
        return cfg, None
    url = f"{urls[0].rstrip('/')}/#/station/{cfg.station.id}"
    print(f"console : {url}  (μ(t) live; reading is open; to acknowledge log in as demo / {password})", flush=True)
    return cfg, console


def run(args) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    # as in `hookwatch run`: the slot loop must not wait 5 ms for the GIL behind the console,
    # the PLC server or paho
    sys.setswitchinterval(0.0005)
    try:
        cfg = load_station(args.station)
    except ConfigError as e:
        raise CliError(str(e), 1) from None
    # as deployed (the units' Nice=-5): the demo's threads and its simulator (started below,
    # it inherits this) ahead of a browser or a compile on the same box; elsewhere as is
    deployed_nice()
    work = args.dir or tempfile.mkdtemp(prefix="hookwatch-demo-")
    os.makedirs(work, exist_ok=True)
    print(f"hookwatch demo: a virtual loom station (scenario {os.path.relpath(args.scenario)}), "
          f"files under {work}", flush=True)
    sim, links = _start_sim(args, work)
    broker = None
    console = None
    watcher = _LifeWatcher()
    verdict: list[int] = []
    try:
        cfg = dataclasses.replace(
            cfg,
            meter=dataclasses.replace(cfg.meter, port=links["meter"]),
            stm32=dataclasses.replace(cfg.stm32, port=links["stm32"]),
            recorder=dataclasses.replace(cfg.recorder, dir=os.path.join(work, "records")),
            test=dataclasses.replace(cfg.test, autostart=True, t_end_s=float(args.t_end)),
        )
        if not args.no_northbound:
            plc_port = _port(args.plc_port)
            cfg = dataclasses.replace(cfg, modbus_tcp=dataclasses.replace(
                cfg.modbus_tcp, enabled=True, host="127.0.0.1", port=plc_port))
            mqtt_port = _port(args.mqtt_port)
            broker = _start_mosquitto(work, mqtt_port)
            if broker is not None:
                cfg = dataclasses.replace(cfg, mqtt=dataclasses.replace(
                    cfg.mqtt, enabled=True, host="127.0.0.1", port=mqtt_port))
        print(f"meter on {os.path.realpath(links['meter'])}, STM32 on {os.path.realpath(links['stm32'])}; "
              f"test {cfg.test.sample_id} grade {cfg.test.grade}, T_set {cfg.test.t_set_n} N, "
              f"planned {cfg.test.t_end_s:g} s", flush=True)
        if not args.no_console:
            cfg, console = _demo_console(cfg, work, _port(args.console_port))
        if cfg.modbus_tcp.enabled:
            p = cfg.modbus_tcp.port
            print(f"PLC map : Modbus TCP on 127.0.0.1:{p} (docs/registers.md); test state, status, alarm:\n"
                  f"          mbpoll -m tcp -p {p} -a 1 -0 -t 3 -r 0 -c 8 -1 127.0.0.1\n"
                  f"          T1, T2, tension, μ, μ_ss, μ_th:\n"
                  f"          mbpoll -m tcp -p {p} -a 1 -0 -t 3:float -B -r 8 -c 6 -1 127.0.0.1", flush=True)
        if cfg.mqtt.enabled:
            st_ = cfg.station
            base = mqtt_schema.base_topic(cfg.mqtt.prefix, st_.site, st_.area, st_.line, st_.id)
            print(f"MES     : MQTT on the demo's own Mosquitto, 127.0.0.1:{cfg.mqtt.port} (docs/mqtt.md):\n"
                  f"          mosquitto_sub -h 127.0.0.1 -p {cfg.mqtt.port} -t '{base}/#' -v", flush=True)
        elif not args.no_northbound:
            print("MES     : no MQTT (Mosquitto is not installed: apt-get install mosquitto)", flush=True)

        # the station runs as `hookwatch run` runs it: on its thread (SCHED_FIFO 20 where
        # permitted, as deployed), in the one main loop (signals, systemd, the end of the test);
        # the demo's own outputs: the terminal's lines and what its closing words tell
        hold = console is not None or broker is not None

        def station() -> Station:
            return build_station(cfg, outputs=[TerminalOutput(every_s=args.every), watcher],
                                 with_northbound=not args.no_northbound, console=console)

        def when_done() -> AfterDone:
            # the closing words beside the idle station (it, the console and the PLC map answer on)
            verdict.append(_closing(watcher, cfg, links, work))
            if not hold:
                return AfterDone.END
            print(AFTER_LIFE, flush=True)
            return AfterDone.HOLD

        runtime = in_process_runtime({cfg.station.id: station}, rt_priority=20, rt_optional=True)
        t0 = time.monotonic()
        drive(runtime, DriveOptions(duration_s=args.timeout, exit_when_done=True, print_report=False,
                                    when_done=when_done, hangup=Hangup.STOP))
        if not verdict and time.monotonic() - t0 >= args.timeout:
            print("hookwatch demo: timed out", file=sys.stderr)
    finally:
        _stop_proc(sim)
        if console is not None:
            console.stop()
        _stop_proc(broker)
    if verdict:
        return verdict[0]
    # ended early (Ctrl-C, SIGTERM, a closed terminal, the timeout): the words on what there was
    return _closing(watcher, cfg, links, work)


#: said once the life is over and the console and broker stay up (a CI script waits for this
#: exact line, then sends SIGINT: keep it)
AFTER_LIFE = "hookwatch demo: the life is over; the console and the broker stay up until Ctrl-C"


def _closing(watcher: _LifeWatcher, cfg, links: dict[str, str], work: str) -> int:
    """The closing words (what happened, online against offline, the files) and the demo's
    verdict: 0 when the life ended in a detected end of life and online == offline."""
    res = watcher.result
    if res is None:
        print(f"hookwatch demo: no test was completed (files under {work})", file=sys.stderr)
        return 1
    m = res["method"]
    mv = method_values(cfg)
    ended = {} if watcher.k_detect is None else {"k_detect": watcher.k_detect}
    test_dir = os.path.join(cfg.recorder.dir, cfg.station.id, res["test_id"])
    log_path = os.path.join(test_dir, "log.csv.gz")
    off = analyze_file(log_path).as_dict()
    same = off == m
    onset = None
    try:
        with open(links["truth"]) as f:
            onset = json.load(f).get("onset_run_s")
    except (OSError, ValueError):
        pass
    completed = res["test_status"] == "completed"
    print()
    print(f"test {res['test_id']}: " + _plain_words(m, ended, onset, float(mv.get("tau", 60.0)),
                                                     float(mv.get("ts", 0.02)), same, completed,
                                                     res.get("end_reason")))
    why = _lead_words(m)
    if why:
        print(f"  warning: {why}")
    print(f"  online : {m['status']}, μ_ss {_num(m['mu_ss'], 4)}, μ_th {_num(m['mu_th'], 4)}, "
          f"t_life {_num(m['t_life'], 1)} s, valid {m['n_valid']} of {m['n_slots']} slots")
    print(f"  offline: hookwatch analyze {log_path}"
          f"\n           {'gives the identical result' if same else 'GIVES A DIFFERENT RESULT: ' + json.dumps(off)}")
    print(f"  records: {test_dir}/ (log.csv.gz, log.meta.yaml, events.jsonl, result.json)")
    fig = _fig7(test_dir, os.path.join(work, "report"))
    print(f"  Fig. 7 : {fig}" if fig else "  Fig. 7 : not written (see hookwatch report)")
    print(f"  files  : everything the demo wrote is under {work} (remove it with: rm -r {work})",
          flush=True)
    detected = m.get("t_life") is not None and ended.get("k_detect") is not None
    if not completed:
        print(f"hookwatch demo: the test did not complete ({res.get('end_reason')})", file=sys.stderr)
    if not detected:
        print("hookwatch demo: no end of life was detected", file=sys.stderr)
    return 0 if detected and same else 1


#: where an early warning's lead comes from (METHOD.md §5b: the result's warn_reasons)
LEAD_SOURCES = {
    "prior": "the life prior (what earlier hooks of this grade at this T_set lasted)",
    "trend": "the trend of μ (its rise extrapolated to μ_th)",
    "headroom": "the wear headroom (μ close to μ_th for n_warn windows)",
}


def _lead_words(m: dict) -> str:
    reasons = m.get("warn_reasons") or []
    if m.get("warn_slot") is None or not reasons:
        return ""
    return "its lead came from " + " and ".join(LEAD_SOURCES.get(r, r) for r in reasons)


def _num(v: float | None, digits: int) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def _plain_words(m: dict, ended: dict, onset: float | None, tau: float, ts: float, same: bool,
                 completed: bool, end_reason: str | None) -> str:
    """What happened, in one sentence, from the real numbers (rounded as a person reads them)."""
    agrees = "offline analysis of the recorded log agrees" if same else "OFFLINE ANALYSIS DISAGREES"
    t_life = m.get("t_life")
    # a test that ended early still says what it had found before the stop
    early = [] if completed else [f"the test ended early ({end_reason}); before the stop"]
    if t_life is None:
        return "; ".join(early + [f"no end of life {'was found' if early else 'within the test'} "
                                  f"(status {m.get('status')})"]
                         + _warned_early(m, ts)
                         + ([f"simulated wear onset {onset:.1f} s"] if onset is not None else [])
                         + [agrees])
    parts = early + [f"the hook reached its end of life {t_life:.1f} s after the start"]
    k = ended.get("k_detect")
    if k is not None:
        t_det = (k + 1) * ts
        parts.append(f"detected {t_det - t_life:.1f} s later (the {tau:g} s persistence)")
    parts.append(_warned(m, t_life, ts))
    if onset is not None:
        parts.append(f"the simulated wear began to accelerate at {onset:.1f} s")
    parts.append(agrees)
    return "; ".join(parts)


def _warned(m: dict, t_life: float, ts: float) -> str:
    """How far ahead the early warning (METHOD.md §5b) came, and why."""
    warn_slot = m.get("warn_slot")
    if warn_slot is None:
        return "no early warning came before the end of life was detected"
    t_warn = (int(warn_slot) + 1) * ts
    why = ", ".join(m.get("warn_reasons") or [])
    if t_warn <= t_life:
        return f"warned {t_life - t_warn:.1f} s before the end of life (reasons: {why})"
    return f"warned only {t_warn - t_life:.1f} s after the end of life began (reasons: {why})"


def _warned_early(m: dict, ts: float) -> list[str]:
    """An early warning that came although no end of life was found (yet)."""
    warn_slot = m.get("warn_slot")
    if warn_slot is None:
        return []
    why = ", ".join(m.get("warn_reasons") or [])
    return [f"warned at {(int(warn_slot) + 1) * ts:.1f} s (reasons: {why})"]


def _fig7(test_dir: str, out: str) -> str | None:
    try:
        build_report(test_dir, out, progress=False)
    except Exception as e:  # the demo's result stands without its picture
        print(f"  (Fig. 7 not written: {type(e).__name__}: {e})")
        return None
    d = os.path.join(out, "figures")
    names = sorted(n for n in os.listdir(d) if n.startswith("fig7")) if os.path.isdir(d) else []
    return os.path.join(d, names[0]) if names else None
