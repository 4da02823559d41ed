"""A real RabbitMQ cluster on loopback ports: three nodes with the MQTT plugin, one epmd.

Debian's ``rabbitmq-server`` (3.10: MQTT 3.1.1 only, a v5 CONNECT is dropped; retained messages
are kept per node). Each node has its own node name (``rabbitN@localhost``), AMQP, distribution and
MQTT ports (free loopback ports), Mnesia and log folders under the test's tmp_path; the nodes share
one Erlang cookie (one HOME) and one epmd on its own port (``ERL_EPMD_PORT``), started here, so
that parallel tests and a system RabbitMQ never meet. Every process is ended by its PID (a node's
process group: the start script, ``beam.smp`` and its ``erl_child_setup``), never by name.

A node takes ~130 MB and ~20 s to start; :meth:`Cluster.kill` is ``kill -9`` of a node,
:meth:`Cluster.restart` starts it again (it rejoins the cluster it knows from its Mnesia folder).
The tests share one cluster per worker (the ``rabbitmq_cluster`` fixture of
tests/kit/rabbitmq_pool.py): :meth:`Cluster.whole` restarts what a test left down,
:meth:`Cluster.fresh_vhost` gives each test an empty virtual host.
"""
from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import socket
import subprocess
import threading
import time

from kit.tools import free_port, require_tool, wait_port

RABBIT_BIN = "/usr/lib/rabbitmq/bin"
#: a node's start, a join: bounds against a hang on a loaded box, not speed goals
START_TIMEOUT_S = 120.0
CTL_TIMEOUT_S = 120.0


def require_rabbitmq() -> str:
    """The folder of RabbitMQ's scripts (skipped locally, failed under CI when it is missing)."""
    if not os.path.exists(os.path.join(RABBIT_BIN, "rabbitmq-server")):
        require_tool("rabbitmq-server")          # skips (or fails in CI) with the apt hint
    return RABBIT_BIN


#: the nodes' ports come from below the kernel's ephemeral range (32768 and up): a port from
#: kit.tools.free_port is one an outgoing connection (a gateway's, the CLI's) may take as its
#: local port while a killed node is away, and the node then cannot listen there again (seen:
#: `dist_port_already_used … not_erlang`)
QUIET_PORTS = (20000, 32000)
_taken: set[int] = set()
_rng = random.Random()


def quiet_port() -> int:
    """A free loopback port below the ephemeral range, none handed out twice in this process."""
    while True:
        port = _rng.randrange(*QUIET_PORTS)
        if port in _taken:
            continue
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _taken.add(port)
        return port


def _group_members(pgid: int) -> list[int]:
    """The PIDs of the processes in process group ``pgid`` (from /proc)."""
    out = []
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat", encoding="ascii", errors="replace") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(int(d))
    return out


def _kill_group(p: subprocess.Popen, timeout: float = 30.0) -> None:
    """SIGKILL to the process group ``p`` leads (started with ``start_new_session``), then wait
    until none of it runs any more (``beam.smp`` takes a moment to go, holding its ports)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(p.pid, signal.SIGKILL)
    with contextlib.suppress(subprocess.TimeoutExpired):
        p.wait(10)
    t_end = time.monotonic() + timeout
    while _group_members(p.pid) and time.monotonic() < t_end:
        time.sleep(0.05)


class Node:
    """One RabbitMQ node (see the module docstring)."""

    def __init__(self, base, index: int, epmd_port: int, home: str):
        self.index = index
        self.name = f"rabbit{index}@localhost"
        self.mqtt_port = quiet_port()
        self.amqp_port = quiet_port()
        self.dist_port = quiet_port()
        self.dir = base / f"rabbit{index}"
        (self.dir / "mnesia").mkdir(parents=True, exist_ok=True)
        (self.dir / "log").mkdir(exist_ok=True)
        conf = self.dir / "rabbitmq.conf"
        conf.write_text(f"mqtt.listeners.tcp.default = 127.0.0.1:{self.mqtt_port}\n"
                        "mqtt.allow_anonymous = true\n"
                        # a persistent MQTT session's queue replicated on the nodes: it outlives
                        # the node its subscriber was connected to (docs/deploy.md)
                        "mqtt.durable_queue_type = quorum\n"
                        f"listeners.tcp.default = 127.0.0.1:{self.amqp_port}\n"
                        "log.file.level = warning\n"
                        "log.console = false\n")
        plugins = self.dir / "enabled_plugins"
        plugins.write_text("[rabbitmq_mqtt].\n")
        self.env = {
            **os.environ,
            "HOME": home,
            "ERL_EPMD_PORT": str(epmd_port),
            "RABBITMQ_NODENAME": self.name,
            "RABBITMQ_NODE_IP_ADDRESS": "127.0.0.1",
            "RABBITMQ_NODE_PORT": str(self.amqp_port),
            "RABBITMQ_DIST_PORT": str(self.dist_port),
            "RABBITMQ_MNESIA_BASE": str(self.dir / "mnesia"),
            "RABBITMQ_LOG_BASE": str(self.dir / "log"),
            "RABBITMQ_CONFIG_FILE": str(conf),
            "RABBITMQ_ENABLED_PLUGINS_FILE": str(plugins),
            "RABBITMQ_CONF_ENV_FILE": str(self.dir / "rabbitmq-env.conf"),     # none: no site file
            "RABBITMQ_ADVANCED_CONFIG_FILE": str(self.dir / "advanced.config"),
            "RABBITMQ_PID_FILE": str(self.dir / "rabbit.pid"),
            "ERL_CRASH_DUMP": str(self.dir / "erl_crash.dump"),     # not in the working directory
            # the distribution listens on loopback only
            # one scheduler without busy-waiting: three nodes share a small box with real-time
            # stations (the default spins its schedulers, a core's worth of CPU per node)
            "RABBITMQ_SERVER_ADDITIONAL_ERL_ARGS": "-kernel inet_dist_use_interface {127,0,0,1} "
                                                   "+S 1:1 +sbwt none +sbwtdcpu none +sbwtdio none",
        }
        self.p: subprocess.Popen | None = None
        self.log_file = self.dir / "stdout.log"

    def start(self) -> Node:
        with open(self.log_file, "ab") as out:
            self.p = subprocess.Popen([os.path.join(RABBIT_BIN, "rabbitmq-server")], env=self.env, cwd=self.dir,
                                      stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                      start_new_session=True)
        return self

    def wait_ready(self) -> None:
        wait_port(self.mqtt_port, timeout=START_TIMEOUT_S, proc=self.p)

    def ctl(self, *args: str) -> str:
        """``rabbitmqctl -n NODE ARGS`` (fails with its output)."""
        p = subprocess.run([os.path.join(RABBIT_BIN, "rabbitmqctl"), "-n", self.name, *args], env=self.env,
                           capture_output=True, text=True, timeout=CTL_TIMEOUT_S)
        assert p.returncode == 0, f"rabbitmqctl -n {self.name} {' '.join(args)}: {p.stdout}{p.stderr}"
        return p.stdout

    @property
    def running(self) -> bool:
        return self.p is not None and self.p.poll() is None

    def kill(self) -> None:
        """``kill -9`` of the node (its process group, by the PID of the process this started)."""
        if self.p is None:
            return
        _kill_group(self.p)
        self.p = None

    def stop(self) -> None:
        """A clean stop (SIGTERM: ``rabbitmqctl stop`` by the start script), then kill -9."""
        if self.p is None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.p.pid, signal.SIGTERM)
        try:
            self.p.wait(30)
        except subprocess.TimeoutExpired:
            pass
        self.kill()


class Cluster:
    """Three clustered RabbitMQ nodes with the MQTT plugin (see the module docstring)."""

    def __init__(self, tmp_path, n: int = 3):
        require_rabbitmq()
        self.base = tmp_path / "rabbitmq"
        home = self.base / "home"
        home.mkdir(parents=True, exist_ok=True)
        cookie = home / ".erlang.cookie"
        cookie.write_text(f"HOOKWATCHTEST{os.getpid()}{free_port()}")
        os.chmod(cookie, 0o400)
        self.epmd_port = quiet_port()
        self.epmd: subprocess.Popen | None = None
        self.nodes = [Node(self.base, i + 1, self.epmd_port, str(home)) for i in range(n)]
        self.vhost: str | None = None

    def start(self) -> Cluster:
        epmd = require_tool("epmd")
        self.epmd = subprocess.Popen([epmd, "-port", str(self.epmd_port), "-address", "127.0.0.1"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     start_new_session=True)
        wait_port(self.epmd_port, proc=self.epmd)
        for n in self.nodes:
            n.start()
        for n in self.nodes:
            n.wait_ready()
        first = self.nodes[0]
        for n in self.nodes[1:]:
            n.ctl("stop_app")
            n.ctl("join_cluster", first.name)
            n.ctl("start_app")
            n.wait_ready()
        return self

    def running_nodes(self) -> str:
        return self.nodes[0].ctl("cluster_status")

    @property
    def servers(self) -> list[str]:
        """Every node's MQTT listener as ``host:port``."""
        return [f"127.0.0.1:{n.mqtt_port}" for n in self.nodes]

    def kill(self, i: int) -> None:
        self.nodes[i].kill()

    def restart(self, i: int) -> None:
        self.nodes[i].start()
        self.nodes[i].wait_ready()

    def whole(self) -> None:
        """Every node running again (a test that killed one and left it down): each is started
        and rejoins the cluster it knows from its Mnesia folder."""
        for i, n in enumerate(self.nodes):
            if not n.running:
                self.restart(i)

    def fresh_vhost(self, name: str) -> None:
        """Route every node's MQTT listener to a new, empty virtual host ``name``
        (``mqtt_port_to_vhost_mapping``): its retained messages, persistent sessions and their
        queues are its own, so nothing a test left in the cluster reaches the next one. The
        vhost before it is deleted (with its queues)."""
        first = self.nodes[0]
        first.ctl("add_vhost", name)
        first.ctl("set_permissions", "-p", name, "guest", ".*", ".*", ".*")
        mapping = {str(n.mqtt_port): name for n in self.nodes}
        first.ctl("set_global_parameter", "mqtt_port_to_vhost_mapping", json.dumps(mapping))
        if self.vhost is not None:
            first.ctl("delete_vhost", self.vhost)
        self.vhost = name

    def stop(self) -> None:
        for n in self.nodes:
            n.kill()
        if self.epmd is not None:
            _kill_group(self.epmd)
            self.epmd = None

    def __enter__(self) -> Cluster:
        try:
            return self.start()
        except BaseException:
            self.stop()
            raise

    def __exit__(self, *exc) -> None:
        self.stop()


class Mes:
    """An MES on the cluster: a paho MQTT 3.1.1 client with a persistent session (clean session
    off, QoS 1: its queue is a quorum queue, replicated) and a server list, reconnecting to the
    next node whenever its node goes. Every message is kept (topic, payload, retained); a
    payload is checked against its topic's JSON Schema (kit.broker.check_message)."""

    def __init__(self, servers: list[tuple[str, int]], topic: str, client_id: str = "mes"):
        import paho.mqtt.client as paho
        from paho.mqtt.enums import CallbackAPIVersion

        self._paho = paho
        self.servers = servers
        self.topic = topic
        self.messages: list[tuple[str, bytes, bool]] = []
        self.violations: list[str] = []
        self.connects = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._i = 0
        self.c = paho.Client(CallbackAPIVersion.VERSION2, client_id=client_id, clean_session=False,
                             protocol=paho.MQTTv311)
        self.c.on_connect = self._on_connect
        self.c.on_message = self._on_message
        self._t = threading.Thread(target=self._run, daemon=True)

    def start(self) -> Mes:
        self._t.start()
        return self

    def _on_connect(self, client, userdata, flags, rc, props) -> None:
        if not rc.is_failure:
            self.connects += 1
            client.subscribe(self.topic, qos=1)

    def _on_message(self, client, userdata, msg) -> None:
        from kit.broker import check_message
        bad = check_message(msg.topic, msg.payload)
        with self._lock:
            self.messages.append((msg.topic, bytes(msg.payload), bool(msg.retain)))
            if bad:
                self.violations.append(bad)

    def _run(self) -> None:
        paho = self._paho
        connected = False
        while not self._stop.is_set():
            if not connected:
                host, port = self.servers[self._i % len(self.servers)]
                try:
                    self.c.connect(host, port, keepalive=10)
                    connected = True
                except OSError:
                    self._i += 1
                    self._stop.wait(0.2)
                    continue
            if self.c.loop(timeout=0.1) != paho.MQTT_ERR_SUCCESS:
                connected = False
                self._i += 1
        with contextlib.suppress(Exception):
            self.c.disconnect()

    def snapshot(self) -> list[tuple[str, bytes, bool]]:
        with self._lock:
            return list(self.messages)

    def stop(self) -> None:
        self._stop.set()
        self._t.join(10)


__all__ = ["Cluster", "Mes", "Node", "require_rabbitmq"]
