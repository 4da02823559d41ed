"""NCMD and DCMD read into what they ask: node controls, and commands for a station. Pure.

An NCMD's metrics (by name or alias) set to true name node controls (``Node Control/Rebirth``,
``Reboot``, ``Next Server``; the node rate-limits them, :mod:`.pacing`). A DCMD's writable metrics
become at most one :class:`~.actions.Submit` per command metric set to true, each with the
``Arg …`` metrics its command takes, for the station's one command path (the runtime's intake
checks them, :mod:`gateway.core.command_intake`). Payloads are parsed within bounds
(:mod:`.inbound`): a bad one is counted and noted, never raised; an unknown or read-only metric,
and a command for a device that does not run here, are counted (``ignored_commands``).
"""
from __future__ import annotations

from typing import Any

from ...core.command_rules import COMMAND_KEYS
from ...core.records import CommandKind
from . import metrics as M
from .actions import Submit
from .devices import DeviceTable
from .inbound import BadInput, BadInputs, InboundLimits, parse_payload
from .namespace import NodeTopics
from .payloads import get_value
from .sparkplug_b_pb2 import Payload


class CommandReader:
    """The node's command doors: its NCMD topic and its devices' DCMD topics."""

    def __init__(self, topics: NodeTopics, limits: InboundLimits, devices: DeviceTable,
                 node_aliases: dict[str, int], bad: BadInputs) -> None:
        self.topics = topics
        self.limits = limits
        self.devices = devices
        self._by_alias = {a: n for n, a in node_aliases.items()}
        self.bad = bad
        self.counters = bad.counters

    def read(self, topic: str, payload: bytes) -> tuple[list[str], list[Submit]]:
        """The node controls asked by an NCMD (in order), and the commands of a DCMD."""
        door = self.topics.command_door(topic)
        if door is None:
            self.bad.refused(BadInput("topic", f"a message on {topic[:80]!r}, which is not a command "
                                      "topic of this node"))
            return [], []
        kind, device_id = door
        try:
            p = parse_payload(kind, payload, self.limits)
        except BadInput as e:
            self.bad.refused(e)
            return [], []
        if device_id is None:
            return self._node_controls(p), []
        return [], self._device_commands(device_id, p)

    def _node_controls(self, p: Payload) -> list[str]:
        out = []
        for m in p.metrics:
            name = m.name or self._by_alias.get(m.alias, "")
            if get_value(m) is not True:
                continue
            if name in (M.REBIRTH, M.NEXT_SERVER, M.REBOOT):
                out.append(name)
            else:
                self.counters["ignored_commands"] += 1
        return out

    def _device_commands(self, device_id: str, p: Payload) -> list[Submit]:
        dev = self.devices.get(device_id)
        if dev is None or dev.stopped:
            self.counters["ignored_commands"] += 1
            return []
        names = dev.names_by_alias()
        vals: dict[str, Any] = {}
        for m in p.metrics:
            name = m.name or names.get(m.alias, "")
            if name in M.DEVICE_BY_NAME and M.DEVICE_BY_NAME[name].writable:
                vals[name] = get_value(m)
            else:
                self.counters["ignored_commands"] += 1
        args = {M.COMMAND_ARGS[k]: v for k, v in vals.items() if k in M.COMMAND_ARGS and v is not None}
        subs: list[Submit] = []
        for name, ck in M.COMMANDS.items():
            if vals.get(name) is True:      # each command takes the arguments it knows
                keys = COMMAND_KEYS[CommandKind(ck)] + ("request_id",)
                subs.append(Submit(dev.device_id, ck, {k: v for k, v in args.items() if k in keys}))
        return subs
