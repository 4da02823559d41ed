"""Sparkplug B 3.0 edge node as a pure state machine: no sockets, no clock, no threads.

Inputs (method calls, each with the time in ms where it matters):
  ``connecting()`` before each MQTT CONNECT (→ the Will: NDEATH with the next bdSeq, persisted
  by the caller before it connects), ``connected_ok()``, ``disconnected()``, ``host_state()`` (the
  primary host's ``spBv1.0/STATE/<host_id>``), ``device_up()`` / ``device_update()`` /
  ``device_down()`` (a station), ``command()`` (NCMD/DCMD payloads), ``command_result()``.
Outputs (:mod:`.actions`): :class:`Publish` (topic, payload bytes, qos, retain), :class:`Disconnect`,
:class:`Submit` (a device command for the station's one command path) — returned as lists.

:class:`EdgeNode` is the session's state (connected, host online, born) and composes the parts
that each keep one thing:

- :class:`~.namespace.NodeTopics`: its IDs and topics;
- :class:`~.bdseq.BdSeq`: the birth/death sequence number per CONNECT;
- :class:`~.payloads.Outgoing`: the messages as payloads, each with the next ``seq``;
- :class:`~.devices.DeviceTable`: the devices (stations), their metric values and alias blocks;
- :class:`~.primary_host.PrimaryHost`: the host's STATE and the timestamp rule;
- :class:`~.pacing.Pacing`: the rate limits of Rebirth, Reboot and Next Server;
- :class:`~.node_commands.CommandReader`: NCMD/DCMD read into node controls and station commands;
- :class:`~.replay.StoreAndForward`: device data held while no host listens, and its replay.

The parts count in the node's one :attr:`EdgeNode.counters` (the metrics endpoint's figures).

Everything received is parsed within bounds (:mod:`.inbound`); a bad payload is counted
(``counters["bad_<kind>"]``) and noted for the caller's rate-limited log (:meth:`EdgeNode.take_bad`),
never raised. STATE timestamps follow the rule of :meth:`.primary_host.PrimaryHost.state`;
rebirths, Reboots and Next Servers are rate-limited (:meth:`EdgeNode.rebirth`,
:meth:`EdgeNode.reboot`, :meth:`EdgeNode.tick`).

Store and forward: while no primary host is online (or no connection), device data goes to a
:class:`~.replay.Buffer` as historical DDATA; when the host is online again, after NBIRTH and the
DBIRTHs, :meth:`EdgeNode.drain` replays it in order, and only then is data published live.

See docs/sparkplug.md for the rules implemented (with the specification's statement IDs).
"""
from __future__ import annotations

from typing import Any

from . import metrics as M
from .actions import Action, Disconnect, Publish
from .bdseq import BdSeq
from .devices import DeviceTable
from .inbound import BadInputs, InboundLimits
from .namespace import NodeTopics
from .node_commands import CommandReader
from .pacing import Pacing
from .payloads import Outgoing
from .primary_host import PrimaryHost
from .replay import Buffer, MemoryBuffer, StoreAndForward


class EdgeNode:
    """One Sparkplug edge node hosting stations as devices (see the module docstring)."""

    def __init__(self, group_id: str, edge_node_id: str, *, primary_host_id: str | None = None,
                 last_bdseq: int | None = None, software: str = "hookwatch", replay_batch: int = 50,
                 limits: InboundLimits | None = None, rebirth_min_interval_ms: int = 2000,
                 state_future_skew_ms: int = 300_000, buffer: Buffer | None = None):
        self.topics = NodeTopics(group_id, edge_node_id, primary_host_id)
        #: bdSeq of the current session; the caller persists it after connecting() and before it
        #: connects
        self.bdseq = BdSeq(last_bdseq)
        self.connected = False
        self.node_born = False
        self.limits = limits or InboundLimits()
        self.counters: dict[str, int] = {"stored": 0, "replayed": 0, "births": 0, "rebirths": 0,
                                         "ignored_commands": 0, "rebirths_coalesced": 0,
                                         "reboots": 0, "reboots_coalesced": 0,
                                         "bad_state": 0, "bad_ncmd": 0, "bad_dcmd": 0, "bad_topic": 0,
                                         "stale_state": 0, "future_state": 0}
        #: bad inputs not yet taken by the caller
        self.bad = BadInputs(self.counters)
        self.host = PrimaryHost(primary_host_id, self.limits, self.bad, state_future_skew_ms)
        self.pacing = Pacing(rebirth_min_interval_ms, self.counters)
        self.devices = DeviceTable()
        self.outgoing = Outgoing(self.topics, software)
        self.commands = CommandReader(self.topics, self.limits, self.devices, self.outgoing.node_aliases,
                                      self.bad)
        self.replay = StoreAndForward(buffer if buffer is not None else MemoryBuffer(), self.devices,
                                   self.outgoing, self.counters, replay_batch)

    @property
    def buffer(self) -> Buffer:
        return self.replay.buffer

    @property
    def publishing(self) -> bool:
        """Live data may go out now: connected, host online, births done."""
        return self.connected and self.host.online and self.node_born

    @property
    def replaying(self) -> bool:
        return self.replay.replaying

    def take_bad(self) -> list[tuple[str, str]]:
        """The bad inputs noted since the last call (for the caller's rate-limited log)."""
        return self.bad.take()

    # ------------------------------------------------------------------ session
    def connecting(self) -> Publish:
        """Before each CONNECT: the next bdSeq and the Will (NDEATH, QoS 1, not retained). The caller
        persists :attr:`bdseq` before connecting, so a restart after kill -9 continues from it."""
        self.bdseq.next_connect()
        return self.ndeath()

    def connect_failed(self) -> None:
        """No CONNECT packet went out (the TCP connection failed): the bdSeq is not used up."""
        self.bdseq.not_sent()

    def ndeath(self) -> Publish:
        return self.outgoing.ndeath(self.bdseq.value)

    def connected_ok(self, now_ms: int) -> list[Publish]:
        self.connected = True
        self.node_born = False
        # STATE timestamps are compared within one MQTT session only (see PrimaryHost.state);
        # with a primary host: wait for its retained STATE before any birth
        self.host.session_start()
        if not self.host.online:
            return []
        return self._births(now_ms)

    def disconnected(self) -> None:
        self.connected = False
        self.node_born = False
        self.pacing.session_gone()     # the session it asked to end has ended
        self.replay.replaying = False
        self.devices.all_unborn()

    def host_state(self, payload: bytes, now_ms: int) -> list[Publish | Disconnect]:
        """``spBv1.0/STATE/<host_id>``: births when the host came online, the session's end
        (NDEATH first, then the next server of the set) when it went offline; the timestamp
        rule is :meth:`.primary_host.PrimaryHost.state`'s."""
        change = self.host.state(payload, now_ms)
        if change is True and self.connected:
            return [*self._births(now_ms)]
        if change is False and self.connected and self.node_born:
            # the host is gone: end this session (NDEATH first) and connect to the next server
            # of the set (tck-id-operational-behavior-edge-node-termination-host-offline-reconnect)
            out: list[Publish | Disconnect] = [self.ndeath()]
            self.node_born = False
            self.devices.all_unborn()
            out.append(Disconnect("primary host offline", next_server=True))
            return out
        return []

    # ------------------------------------------------------------------ births and deaths
    def _births(self, now_ms: int) -> list[Publish]:
        out = [self.outgoing.nbirth(now_ms, self.bdseq.value, self.devices.running())]
        self.node_born = True
        self.counters["births"] += 1
        self.pacing.born(now_ms)
        held = self.replay.held()
        out.extend(self.outgoing.dbirth(dev, now_ms) for dev in self.devices if not dev.stopped or held)
        out.extend(self.replay.start(now_ms))
        return out

    def rebirth(self, now_ms: int) -> list[Publish]:
        """Node Control/Rebirth: NBIRTH (same bdSeq, seq 0) and every DBIRTH again — at most one
        birth per ``rebirth_min_interval_ms``: a request inside that interval is coalesced into
        one pending rebirth, carried out by :meth:`tick` when the interval has passed."""
        if not (self.connected and self.host.online):
            return []
        if not self.pacing.ask_rebirth(now_ms):
            return []
        self.counters["rebirths"] += 1
        return self._births(now_ms)

    def reboot(self, name: str, now_ms: int) -> list[Publish | Disconnect]:
        """Node Control/Reboot or Next Server: NDEATH, then the session ends (the runtime
        reconnects: to the next server for Next Server) — at most one per
        ``rebirth_min_interval_ms``, as births: a request inside that interval is coalesced into
        one pending one (Next Server over Reboot), carried out by :meth:`tick` when it is due."""
        d = Disconnect(name, next_server=name == M.NEXT_SERVER)
        if not self.pacing.ask_end(d, now_ms):
            return []
        return self._end_session(d, now_ms)

    def _end_session(self, d: Disconnect, now_ms: int) -> list[Publish | Disconnect]:
        out: list[Publish | Disconnect] = []
        self.pacing.ended(now_ms)
        if self.connected:
            out.append(self.ndeath())
        self.node_born = False
        out.append(d)
        return out

    def tick(self, now_ms: int) -> list[Publish | Disconnect]:
        """Called often by the runtime: the pending (coalesced) Reboot / Next Server, then the
        pending (coalesced) rebirth, once due."""
        end = self.pacing.due_end(now_ms, self.connected)
        if end is not None:
            return self._end_session(end, now_ms)
        if not self.pacing.due_rebirth(now_ms, self.connected and self.host.online and self.node_born):
            return []
        self.counters["rebirths"] += 1
        return list(self._births(now_ms))

    # ------------------------------------------------------------------ devices
    def device_up(self, device_id: str, values: dict[str, Any], now_ms: int) -> list[Publish]:
        dev = self.devices.up(device_id, values, now_ms)
        if self.publishing:
            return [self.outgoing.dbirth(dev, now_ms)]
        return []

    def device_down(self, device_id: str, now_ms: int) -> list[Publish]:
        dev = self.devices.get(device_id)
        if dev is None:
            return []
        if self.publishing and not self.replay.replaying:
            out = [self.outgoing.ddeath(dev, now_ms)] if dev.born else []
            self.devices.remove(device_id)
            return out
        dev.stopped = True         # buried after its stored data went out
        return []

    def device_update(self, device_id: str, values: dict[str, Any], now_ms: int) -> list[Publish]:
        """New values of a station's metrics: DDATA by alias now, or into the buffer."""
        dev = self.devices.get(device_id)
        if dev is None:
            return []
        changed = self.devices.update(dev, values, now_ms)
        if not changed:
            return []
        if self.publishing and dev.born and not self.replay.replaying:
            return [self.outgoing.ddata(dev, changed, now_ms)]
        if self.replay.replaying and self.publishing:
            self.replay.changed_during_replay(device_id, changed)
        self.replay.hold(dev, changed, now_ms)
        return []

    def drain(self, now_ms: int) -> tuple[list[Publish], list[int]]:
        """The next batch of stored DDATA (oldest first, seq assigned now) and the buffer keys to
        remove once they are handed to the client (:meth:`.replay.StoreAndForward.drain`)."""
        if not (self.publishing and self.replay.replaying):
            return [], []
        return self.replay.drain(now_ms)

    # ------------------------------------------------------------------ commands
    def command(self, topic: str, payload: bytes, now_ms: int) -> list[Action]:
        """An NCMD or DCMD; metrics by name or by alias. Bad payloads (beyond the limits of
        :class:`InboundLimits`, undecodable) are counted and noted, unknown metrics counted."""
        controls, submits = self.commands.read(topic, payload)
        out: list[Action] = []
        for name in controls:
            if name == M.REBIRTH:
                out.extend(self.rebirth(now_ms))
            else:
                out.extend(self.reboot(name, now_ms))
        out.extend(submits)
        return out

    def command_result(self, device_id: str, kind: str, ok: bool, code: int, reason: str,
                       now_ms: int) -> list[Publish]:
        text = (f"{kind}: accepted" + (f" ({reason})" if reason else "")) if ok else f"{kind}: rejected: {reason}"
        return self.device_update(device_id, {"Device Control/Last Command": text,
                                              "Device Control/Last Result Code": 0 if ok else int(code)},
                                  now_ms)
