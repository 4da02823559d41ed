"""`hookwatch hooks STATION.yaml [--replaced [--sample-id ID] [--grade G]]`: a station's hooks.

Without ``--replaced``: the station's life log of replaced hooks (``<recorder.dir>/<station>/
hooks.jsonl``, the newest 10,000 lines; a damaged line is skipped with one log line), one line
per replacement with the old hook's life and what it was in the METHOD.md §7a history when it was
replaced (a wear-out failure, an early failure — §7a v3 —, or censored). With ``--replaced``:
tells the running station that its hook was replaced — the command ``hook_replaced`` over the
station's MQTT broker (``cmd/hook_replaced`` with a request id; the station's answer on ``reply``
is printed), through the same intake and validation as every other door. The running test ends,
the replacement is logged, and with ``test.restart_on_replace`` the next test starts with the new
hook.
"""
from __future__ import annotations

import json
import os
import secrets
import threading

from ..cli import CliError
from ..config import ConfigError, load_station
from ..outputs.broker.settings import BrokerSettings, SecretError, broker_kwargs
from ..outputs.mqtt.schema import base_topic
from ..plumbing import safeout
from ..station.hook_log import HOOKS_NAME, LIFE_KINDS, MAX_LINES, read_hooks

HELP = "list a station's replaced hooks (hooks.jsonl), or tell the running station its hook was replaced"
DESCRIPTION = HELP + (". --replaced sends `hook_replaced` over the station's MQTT broker "
                      "(cmd/hook_replaced) and prints the station's reply.")

#: how long --replaced waits for the station's reply, s
REPLY_TIMEOUT_S = 15.0


def add_arguments(ap):
    ap.add_argument("station", metavar="STATION.yaml", help="the station's file")
    ap.add_argument("--replaced", action="store_true", help="the hook was replaced: tell the station")
    ap.add_argument("--sample-id", metavar="ID", help="the new hook's sample id (default: <old>-R<n>)")
    ap.add_argument("--grade", metavar="G", help="the new hook's grade (default: the old hook's)")
    ap.add_argument("--json", action="store_true", help="the life log as JSON lines")


def _load(path: str):
    if os.path.isdir(path):
        raise CliError(f"{path}: a folder; give one station file (stations/<id>.yaml)", 2)
    try:
        return load_station(path)
    except ConfigError as e:
        raise CliError(str(e), 1) from None
    except FileNotFoundError:
        raise CliError(f"{path}: no such file", 2) from None


def _fmt(v) -> str:
    return "–" if v is None else (f"{v:.1f} s" if isinstance(v, float) else str(v))


def run(args) -> int:
    cfg = _load(args.station)
    if args.replaced:
        return _send(cfg, args.sample_id, args.grade)
    d = os.path.join(cfg.recorder.dir, cfg.station.id)
    hooks = read_hooks(d, MAX_LINES)
    if args.json:
        for h in hooks:
            print(safeout.dumps(h, compact=False, ensure_ascii=False))
        return 0
    if not hooks:
        print(f"{cfg.station.id}: no hook replaced yet ({os.path.join(d, HOOKS_NAME)})")
        return 0
    for h in hooks:
        lk = h.get("life_kind")
        kind = LIFE_KINDS.get(lk) if isinstance(lk, str) else None
        print(f"{h.get('utc', '?')}  {h.get('old_sample_id')} → {h.get('new_sample_id')}  "
              f"grade {_fmt(h.get('grade'))}  life {_fmt(h.get('life_s'))}"
              f"{'' if kind is None else f' ({kind})'}  "
              f"test {_fmt(h.get('test_id'))}  by {_fmt(h.get('by'))}")
    return 0


def _send(cfg, sample_id: str | None, grade: str | None) -> int:
    """``hook_replaced`` to the running station over its MQTT broker; its reply decides the exit
    code (0 accepted, 1 refused or no answer)."""
    import paho.mqtt.client as paho
    from paho.mqtt.enums import CallbackAPIVersion

    m = cfg.mqtt
    if not m.enabled:
        raise CliError(f"{cfg.station.id}: the station has no MQTT (mqtt.enabled: false); tell it "
                       "through the PLC (command code 5) or the console", 1)
    st = cfg.station
    base = base_topic(m.prefix, st.site, st.area, st.line, st.id)
    rid = "cli-" + secrets.token_hex(6)
    body: dict[str, str] = {"request_id": rid}
    if sample_id is not None:
        body["sample_id"] = sample_id
    if grade is not None:
        body["grade"] = grade
    bs = BrokerSettings(**{**broker_kwargs(m), "client_id": None})
    got: dict = {}
    done = threading.Event()

    def on_message(_c, _u, msg):
        try:
            p = json.loads(msg.payload)
        except ValueError:
            return
        if isinstance(p, dict) and p.get("request_id") == rid:
            got.update(p)
            done.set()

    def on_connect(c, _u, _f, rc, _p=None):
        if not rc.is_failure:
            c.subscribe(f"{base}/reply", qos=1)
            c.publish(f"{base}/cmd/hook_replaced", json.dumps(body), qos=1)

    c = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"hookwatch-cli-{rid}")
    try:
        bs.apply(c)
    except (SecretError, OSError, ValueError) as e:
        raise CliError(f"{cfg.station.id}: MQTT credentials: {e}", 1) from None
    c.on_message, c.on_connect = on_message, on_connect
    try:
        c.connect(bs.host, bs.port, keepalive=30)
    except OSError as e:
        raise CliError(f"{cfg.station.id}: MQTT broker {bs.host}:{bs.port}: {e.strerror or e}", 1) from None
    c.loop_start()
    try:
        if not done.wait(REPLY_TIMEOUT_S):
            raise CliError(f"{cfg.station.id}: no reply within {REPLY_TIMEOUT_S:g} s (is the station "
                           "running and connected to the broker?)", 1)
    finally:
        c.loop_stop()
        c.disconnect()
    if got.get("ok"):
        print(f"{cfg.station.id}: hook replaced" + (f" (new sample {sample_id})" if sample_id else ""))
        return 0
    raise CliError(f"{cfg.station.id}: refused ({got.get('code')}): {got.get('reason')}", 1)
