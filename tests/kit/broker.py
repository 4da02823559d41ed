"""A real Mosquitto on a free loopback port, mosquitto_sub as a subscriber, mosquitto_pub.

Every JSON message a :class:`Sub` receives on a topic of hookwatch's tree is validated against the
shipped JSON Schema of its topic (docs/schemas/, generated from gateway/outputs/mqtt/schema.py) with
``jsonschema``: a violation fails the test (``messages()`` and ``stop()`` raise it, naming the
topic, the payload and the schema path). Commands (``cmd/…``, which the tests publish themselves,
some malformed on purpose), Sparkplug (protobuf, ``spBv1.0/…``) and a test's own messages on topics
outside the tree are not checked here; a message with the gateway's envelope (``schema``,
``station``) on a topic the tree does not name is a violation.
"""
from __future__ import annotations

import contextlib
import functools
import getpass
import json
import os
import re
import subprocess
import threading
import time

import jsonschema

from conftest import ROOT
from kit.proc import stop_process
from kit.tools import free_port, require_tool, wait_for, wait_port


class Broker:
    """Mosquitto on a free loopback port; ``persistent`` keeps sessions across restarts. With
    ``users`` (name → password) it takes only them (a ``password_file`` made by
    ``mosquitto_passwd``), and with ``acl`` (the text of an ``acl_file``) it gives each what the
    file says, as a site's broker does (docs/deploy.md, "Broker permissions")."""

    def __init__(self, tmp_path, persistent: bool = False, port: int | None = None,
                 users: dict[str, str] | None = None, acl: str | None = None):
        self.exe = require_tool("mosquitto")
        self.port = port or free_port()
        self.dir = tmp_path / f"broker-{self.port}"
        self.dir.mkdir(exist_ok=True)
        self.conf = self.dir / "mosquitto.conf"
        access = ["allow_anonymous true"]
        if users is not None:
            passwd = self.dir / "passwd"
            tool = require_tool("mosquitto_passwd")
            for i, (name, pw) in enumerate(users.items()):
                subprocess.run([tool, *(["-c"] if i == 0 else []), "-b", str(passwd), name, pw],
                               check=True, capture_output=True, timeout=20)
            os.chmod(passwd, 0o600)
            access = ["allow_anonymous false", f"password_file {passwd}"]
        if acl is not None:
            (self.dir / "acl").write_text(acl)
            access.append(f"acl_file {self.dir / 'acl'}")
        # as root, mosquitto would drop to user `mosquitto`, who may not write to the test folder
        lines = [f"user {getpass.getuser()}", f"listener {self.port} 127.0.0.1", *access,
                 f"persistence {'true' if persistent else 'false'}",
                 f"persistence_location {self.dir}/", "autosave_interval 1",
                 "max_queued_messages 100000", "log_type error", "log_type warning",
                 f"log_dest file {self.dir}/mosquitto.log"]
        self.conf.write_text("\n".join(lines) + "\n")
        self.p: subprocess.Popen | None = None

    def start(self) -> Broker:
        self.p = subprocess.Popen([self.exe, "-c", str(self.conf)], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        wait_port(self.port)
        return self

    def stop(self) -> None:
        stop_process(self.p, timeout=10)
        self.p = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


SCHEMA_DIR = os.path.join(ROOT, "docs", "schemas")


@functools.cache
def _schemas() -> tuple[tuple[re.Pattern, str | None], ...]:
    """(topic pattern, schema key or None for a command) for every topic of the tree."""
    from gateway.outputs.mqtt import schema as S
    out = []
    for t in S.TOPICS:
        path = re.escape(t.path).replace(re.escape("{type}"), "[^/]+")
        out.append((re.compile(f"(?:^|/){path}$"), t.key if t.direction == "publish" else None))
    # the longest paths first: `alarm/warning` before a topic whose last level is `warning`
    return tuple(sorted(out, key=lambda x: -len(x[0].pattern)))


@functools.cache
def _validator(key: str) -> jsonschema.Draft202012Validator:
    with open(os.path.join(SCHEMA_DIR, f"{key}.json"), encoding="utf-8") as f:
        return jsonschema.Draft202012Validator(json.load(f), format_checker=jsonschema.FormatChecker())


def schema_key(topic: str) -> str | None:
    """The schema of a message on ``topic``: its key (docs/schemas/<key>.json), "" for a topic
    that is not checked (a command, Sparkplug), None for a topic outside the tree."""
    if topic.startswith("spBv1.0/") or re.search(r"(?:^|/)cmd/[^/]*$", topic):
        return ""
    for pat, key in _schemas():
        if pat.search(topic):
            return key or ""
    return None


def check_message(topic: str, payload: str | bytes, schema: str | None = None) -> str | None:
    """None if the message on ``topic`` is valid for its topic's schema (or ``schema``, a key of
    docs/schemas, for a topic the tree does not name, e.g. an MQTT 5 response topic), else a
    description of the violation: topic, payload, schema path and the validator's message."""
    key = schema or schema_key(topic)
    if key == "" or payload in ("", b""):      # an empty payload clears a retained topic
        return None
    if isinstance(payload, bytes):
        payload = payload.decode("utf-8", "replace")
    try:
        doc = json.loads(payload)
    except json.JSONDecodeError as e:
        return None if key is None else f"{topic}: payload is not JSON ({e}): {payload[:500]}"
    if key is None:
        # a topic outside the tree: a test's own probe, unless it carries the gateway's envelope
        if isinstance(doc, dict) and {"schema", "station"} <= doc.keys():
            return f"{topic}: a gateway message on a topic without a JSON Schema (docs/schemas/): {payload[:500]}"
        return None
    err = jsonschema.exceptions.best_match(_validator(key).iter_errors(doc))
    if err is None:
        return None
    where = "/".join(str(x) for x in err.absolute_path) or "(top level)"
    return (f"{topic}: payload violates docs/schemas/{key}.json at {where} (schema path "
            f"{'/'.join(str(x) for x in err.absolute_schema_path)}): {err.message}\n  payload: {payload[:2000]}")


class SchemaViolation(AssertionError):
    """A message a station published does not match its topic's JSON Schema."""


class Sub:
    """mosquitto_sub printing `retain<TAB>topic<TAB>payload` lines, collected by a thread."""

    def __init__(self, port: int, topic: str, *, qos: int = 1, client_id: str | None = None,
                 clean: bool = True, extra: list[str] | None = None, schema: str | None = None,
                 checked: bool = True):
        """``schema``: the schema key for a topic outside hookwatch's tree (e.g. "reply" for an
        MQTT 5 response topic); messages on the tree's topics are checked by their topic, unless
        ``checked`` is False (a test's own probes on the tree's topics: the broker's ACL tests)."""
        exe = require_tool("mosquitto_sub")
        argv = [exe, "-h", "127.0.0.1", "-p", str(port), "-t", topic, "-q", str(qos),
                "-F", "%r\t%t\t%p", "-k", "5"]
        if client_id:
            argv += ["-i", client_id]
        if not clean:
            argv += ["-c"]
        argv += extra or []
        self.p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[tuple[bool, str, str, float]] = []
        self.schema = schema
        self.checked = checked
        self.violations: list[str] = []
        self._reported = 0
        self._lock = threading.Lock()
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self) -> None:
        for line in self.p.stdout:
            line = line.rstrip("\n")
            parts = line.split("\t", 2)
            if len(parts) == 3:
                bad = check_message(parts[1], parts[2], self.schema) if self.checked else None
                with self._lock:
                    self.lines.append((parts[0] == "1", parts[1], parts[2], time.time()))
                    if bad:
                        self.violations.append(bad)

    def check(self) -> None:
        """Raise :class:`SchemaViolation` for the violations not raised yet."""
        with self._lock:
            new = self.violations[self._reported:]
            self._reported = len(self.violations)
        if new:
            raise SchemaViolation(f"{len(new)} MQTT message(s) violate their JSON Schema:\n"
                                  + "\n".join(new[:5]))

    def messages(self, suffix: str | None = None) -> list[tuple[bool, str, dict, float]]:
        self.check()
        with self._lock:
            lines = list(self.lines)
        out = []
        for r, t, p, ts in lines:
            if suffix is not None and not (t == suffix or t.endswith("/" + suffix)):
                continue
            try:
                out.append((r, t, json.loads(p), ts))
            except json.JSONDecodeError:
                out.append((r, t, {"_raw": p}, ts))
        return out

    def wait(self, cond, timeout: float = 20.0, what: str = "messages"):
        return wait_for(lambda: cond(self), timeout, what=what)

    def stop(self) -> None:
        """Stop mosquitto_sub; then raise the schema violations no ``messages()`` raised yet."""
        if self.p.returncode is None or not self.p.stdout.closed:
            stop_process(self.p, timeout=5)
            self._t.join(5)
            self.p.stdout.close()
            self.p.stderr.close()
        self.check()


def pub_lines(port: int, topic: str, payloads: list[str]) -> None:
    """One mosquitto_pub sending each payload as a message, back to back (``-l``): a flood."""
    exe = require_tool("mosquitto_pub")
    p = subprocess.run([exe, "-h", "127.0.0.1", "-p", str(port), "-t", topic, "-q", "1", "-l"],
                       input="\n".join(payloads) + "\n", text=True, capture_output=True, timeout=120)
    assert p.returncode == 0, p.stderr


def pub(port: int, topic: str, payload: str, *, retain: bool = False, qos: int = 1,
        auth: tuple[str, str] | None = None) -> None:
    exe = require_tool("mosquitto_pub")
    argv = [exe, "-h", "127.0.0.1", "-p", str(port), "-t", topic, "-m", payload, "-q", str(qos)]
    if retain:
        argv.append("-r")
    if auth is not None:
        argv += ["-u", auth[0], "-P", auth[1]]
    subprocess.run(argv, check=True, timeout=20)


class Publisher:
    """One MQTT client (paho) logged in as ``user``: ``publish`` waits for the broker's answer
    and gives the PUBACK reason code (MQTT 5: 0 success, 0x87 not authorized; MQTT 3.1.1: always
    0 — a broker that denies it drops it silently, or closes the connection: RabbitMQ, then None).
    Messages of one client reach a subscriber in the order they were published."""

    def __init__(self, port: int, user: str | None, password: str | None = None, *, v5: bool = True,
                 host: str = "127.0.0.1"):
        import paho.mqtt.client as paho
        from paho.mqtt.enums import CallbackAPIVersion

        self._paho = paho
        self.c = paho.Client(CallbackAPIVersion.VERSION2, protocol=paho.MQTTv5 if v5 else paho.MQTTv311,
                             reconnect_on_failure=False)
        if user is not None:
            self.c.username_pw_set(user, password)
        self._codes: dict[int, int] = {}
        self._cv = threading.Condition()
        self.c.on_publish = self._on_publish
        self.c.connect(host, port, keepalive=10)
        self.c.loop_start()
        wait_for(self.c.is_connected, 20, what=f"{user} connected")

    def _on_publish(self, client, userdata, mid, reason_code, properties) -> None:
        with self._cv:
            self._codes[mid] = int(reason_code.value if hasattr(reason_code, "value") else reason_code)
            self._cv.notify_all()

    def publish(self, topic: str, payload: str | bytes, *, retain: bool = False, timeout: float = 20.0) -> int | None:
        info = self.c.publish(topic, payload, qos=1, retain=retain)
        t_end = time.monotonic() + timeout
        with self._cv:
            while info.mid not in self._codes:
                if not self.c.is_connected() or time.monotonic() > t_end:
                    return None
                self._cv.wait(0.1)
            return self._codes.pop(info.mid)

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.c.disconnect()
        self.c.loop_stop()


#: the MQTT 5 reason code of a publish the broker's ACL denies, and those of one it took
#: (success; success with no subscriber to hand it to)
NOT_AUTHORIZED = 0x87
ACCEPTED = frozenset({0x00, 0x10})


@contextlib.contextmanager
def station_on_broker(tmp_path, base: str, station_id: str, *, modbus_port: int | None = None,
                      stm32=None):
    """A station running on its own loop with its MQTT output on a fresh Mosquitto (the MES is a
    :class:`Sub` on ``base/#``) and, with ``modbus_port``, its Modbus TCP server (unit 1, writes
    from loopback: the PLC is mbpoll). Yields (broker, sub, station, loop thread) once both answer."""
    from gateway.outputs.mqtt.output import MqttOutput, MqttSettings
    from gateway.outputs.plc.server import ModbusOutput, ModbusSettings, shutdown_all
    from kit.northbound import LoopThread, RunningStation, make_station, mbpoll

    lt = LoopThread()
    with Broker(tmp_path) as b:
        sub = Sub(b.port, base + "/#")
        st = make_station(tmp_path, [], station_id=station_id, stm32=stm32)
        out = MqttOutput(MqttSettings(station_id=station_id, base_topic=base, port=b.port,
                                      outbox_path=str(tmp_path / "outbox.sqlite"),
                                      reconnect_min_s=0.2, reconnect_max_s=1.0), st)
        st.outputs.append(out)
        if modbus_port is not None:
            st.outputs.append(ModbusOutput(ModbusSettings(station_id, port=modbus_port, unit_id=1,
                                                          writes_enabled=True,
                                                          allowed_clients=("127.0.0.0/8",)), st))
        run = None
        try:
            run = RunningStation(lt, st)
            wait_for(lambda: out.connected, 20, what="connected")
            if modbus_port is not None:
                wait_for(lambda: mbpoll(modbus_port, "-t", "3", "-r", "1")[0] == 0, 20, what="modbus up")
            yield b, sub, st, lt
        finally:
            if run is not None:
                run.stop()
            lt.close()
            if modbus_port is not None:
                shutdown_all()
            sub.stop()
