"""What the pure edge node asks of its runtime: publish, end the session, hand a command over.

:class:`~.node.EdgeNode` and its parts return these as lists; the node's thread
(:class:`~.client.NodeRuntime`) carries them out in order: a :class:`Publish` on its paho session,
a :class:`Disconnect` once the network loop returns, a :class:`Submit` on the station's one
command path.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

QOS_DATA = 0          # NBIRTH, DBIRTH, NDATA, DDATA, DDEATH: QoS 0, not retained
QOS_DEATH = 1         # NDEATH (the Will): QoS 1, not retained


@dataclass(frozen=True)
class Publish:
    topic: str
    payload: bytes
    qos: int = QOS_DATA
    retain: bool = False


@dataclass(frozen=True)
class Disconnect:
    reason: str
    next_server: bool = False


@dataclass(frozen=True)
class Submit:
    device_id: str
    kind: str                       # gateway.core.records.CommandKind value
    args: dict[str, Any]


#: one output of the node
Action = Publish | Disconnect | Submit
