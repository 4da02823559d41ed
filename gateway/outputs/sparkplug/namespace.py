"""The edge node's names on the broker: its IDs and the Sparkplug topics built from them. Pure.

Topics are ``spBv1.0/<group>/<VERB>/<edge node>[/<device>]`` (tck-id-topic-structure); the primary
host's STATE is ``spBv1.0/STATE/<host id>``. IDs are refused when they are empty or hold an MQTT
separator or wildcard (tck-id-topic-structure-namespace-valid-*).
"""
from __future__ import annotations

from dataclasses import dataclass

NAMESPACE = "spBv1.0"
#: the verbs an edge node publishes: of the node itself, and of each of its devices (payloads.py;
#: the broker's ACL gives the node these and nothing else of the namespace, ``hookwatch config acl``)
NODE_OUT = ("NBIRTH", "NDEATH")
DEVICE_OUT = ("DBIRTH", "DDEATH", "DDATA")


def valid_id(s: str) -> bool:
    """Sparkplug IDs: UTF-8, non-empty, no MQTT separators or wildcards."""
    return bool(s) and not any(c in s for c in "/+#")


@dataclass(frozen=True)
class NodeTopics:
    """One edge node's IDs (checked when made: ValueError) and its topics."""
    group_id: str
    edge_node_id: str
    #: the primary host application whose STATE the node follows (None: none, births at once)
    host_id: str | None = None

    def __post_init__(self) -> None:
        for what, v in (("group_id", self.group_id), ("edge_node_id", self.edge_node_id)):
            if not valid_id(v):
                raise ValueError(f"sparkplug.{what} {v!r}: must be non-empty without '/', '+' or '#'")
        if self.host_id is not None and not valid_id(self.host_id):
            raise ValueError(f"sparkplug.primary_host_id {self.host_id!r}: must be non-empty without "
                             "'/', '+' or '#'")

    def topic(self, kind: str, device_id: str | None = None) -> str:
        t = f"{NAMESPACE}/{self.group_id}/{kind}/{self.edge_node_id}"
        return f"{t}/{device_id}" if device_id is not None else t

    def state_topic(self) -> str | None:
        return f"{NAMESPACE}/STATE/{self.host_id}" if self.host_id else None

    def publications(self, devices: tuple[str, ...]) -> list[str]:
        """Every topic the node publishes with ``devices`` attached (its births, deaths, data)."""
        return ([self.topic(v) for v in NODE_OUT]
                + [self.topic(v, d) for d in devices for v in DEVICE_OUT])

    def subscriptions(self) -> list[tuple[str, int]]:
        subs = [(self.topic("NCMD"), 1), (self.topic("DCMD", "+"), 1)]
        st = self.state_topic()
        if st:
            subs.append((st, 1))
        return subs

    def command_door(self, topic: str) -> tuple[str, str | None] | None:
        """``("ncmd", None)`` for this node's NCMD topic, ``("dcmd", device id)`` for one of its
        DCMD topics, None for any other topic."""
        parts = topic.split("/")
        if len(parts) == 4 and parts[2] == "NCMD" and topic == self.topic("NCMD"):
            return "ncmd", None
        if len(parts) == 5 and parts[2] == "DCMD" and topic.startswith(self.topic("DCMD") + "/"):
            return "dcmd", parts[4]
        return None
