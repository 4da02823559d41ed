"""A Sparkplug primary host for tests, whose decoder is NOT the gateway's code.

The payload classes come from compiling sparkplug_b.proto (the specification's definition) here,
with grpcio-tools, into a FileDescriptorSet loaded into a private descriptor pool: neither the
gateway's generated ``sparkplug_b_pb2`` nor its state machine or metric table is used.
"""
from __future__ import annotations

import json
import os
import threading
import time

import paho.mqtt.client as paho
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from grpc_tools import protoc
from paho.mqtt.enums import CallbackAPIVersion

from conftest import ROOT

PROTO = os.path.join(ROOT, "gateway", "outputs", "sparkplug", "sparkplug_b.proto")


def payload_class(tmp_dir):
    """The Sparkplug Payload message class, compiled from the .proto in ``tmp_dir``."""
    out = os.path.join(str(tmp_dir), "spb.desc")
    rc = protoc.main(["protoc", f"-I{os.path.dirname(PROTO)}", f"--descriptor_set_out={out}", PROTO])
    assert rc == 0, "protoc failed on sparkplug_b.proto"
    fds = descriptor_pb2.FileDescriptorSet()
    with open(out, "rb") as f:
        fds.ParseFromString(f.read())
    pool = descriptor_pool.DescriptorPool()
    for fd in fds.file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("org.eclipse.tahu.protobuf.Payload"))


class Msg:
    def __init__(self, topic: str, payload, t: float, retain: bool, qos: int):
        self.topic = topic
        self.kind = topic.split("/")[2] if topic.count("/") >= 3 else topic
        self.device = topic.split("/")[4] if topic.count("/") == 4 else None
        self.p = payload
        self.t = t
        self.retain = retain
        self.qos = qos

    def __repr__(self) -> str:
        seq = self.p.seq if self.p is not None and self.p.HasField("seq") else None
        return f"<{self.kind} {self.device or ''} seq={seq}>"


class PrimaryHost:
    """Subscribes to a group's messages, keeps them decoded, publishes STATE, NCMD and DCMD."""

    def __init__(self, port: int, host_id: str, group: str, tmp_dir, tls: dict | None = None):
        self.Payload = payload_class(tmp_dir)
        self.host_id = host_id
        self.group = group
        self.msgs: list[Msg] = []
        self._lock = threading.Lock()
        self.c = paho.Client(CallbackAPIVersion.VERSION2, client_id=f"host-{host_id}")
        self.c.will_set(f"spBv1.0/STATE/{host_id}", self._state(False), qos=1, retain=True)
        self.c.on_message = self._on_message
        self.c.reconnect_delay_set(0.05, 0.2)    # back before the edge node after a broker restart
        self.c.on_connect = lambda c, u, f, rc, p: c.subscribe(f"spBv1.0/{group}/#", qos=1)
        if tls:
            self.c.tls_set(ca_certs=tls["ca"], certfile=tls["cert"], keyfile=tls["key"])
        self.c.connect("127.0.0.1", port)
        self.c.loop_start()

    @staticmethod
    def _state(online: bool) -> bytes:
        return json.dumps({"online": online, "timestamp": int(time.time() * 1000)}).encode()

    def _on_message(self, client, userdata, m) -> None:
        p = self.Payload()
        p.ParseFromString(m.payload)
        with self._lock:
            self.msgs.append(Msg(m.topic, p, time.time(), bool(m.retain), m.qos))

    def state(self, online: bool) -> None:
        self.c.publish(f"spBv1.0/STATE/{self.host_id}", self._state(online), qos=1, retain=True).wait_for_publish(5)

    def command(self, topic: str, metrics: list[dict]) -> None:
        p = self.Payload()
        p.timestamp = int(time.time() * 1000)
        for d in metrics:
            m = p.metrics.add()
            for k, v in d.items():
                setattr(m, k, v)
        self.c.publish(topic, p.SerializeToString(), qos=0).wait_for_publish(5)

    def all(self, kind: str | None = None, since: int = 0) -> list[Msg]:
        with self._lock:
            ms = self.msgs[since:]
        return [m for m in ms if kind is None or m.kind == kind]

    def mark(self) -> int:
        with self._lock:
            return len(self.msgs)

    def wait(self, cond, timeout: float = 30.0, what: str = "messages"):
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            v = cond()
            if v:
                return v
            time.sleep(0.05)
        raise AssertionError(f"the primary host saw no {what} in {timeout} s; got {self.all()[-30:]}")

    def close(self) -> None:
        self.c.loop_stop()
        self.c.disconnect()


def metric_value(m):
    if m.is_null:
        return None
    which = m.WhichOneof("value")
    return getattr(m, which) if which else None
