"""The stations of one edge node as its devices: who is attached, and the DCMD path to them.

A station's Sparkplug output (:class:`~.output.SparkplugOutput`, or a fleet supervisor's
``SparkplugDevice``) attaches to its node with its device ID; the node's thread hands each command
a DCMD asks (:class:`~.actions.Submit`) to that station's loop: through the one bounded intake of
every door (:func:`gateway.core.command_intake.intake`: a DCMD metric's Sparkplug type is kept, so
a String "0.6" for Arg T Set or a 1 MB Arg Sample ID is refused as over MQTT), then the station's
``submit`` through the one thread→loop hand-over (:func:`gateway.plumbing.threadloop.submit_to`). The
outcome becomes the device's ``Device Control/Last Command`` and ``Last Result Code``: at once when
the command cannot go, or when the station replies (posted back to the node thread's mailbox).
"""
from __future__ import annotations

import asyncio
from collections.abc import Callable
from concurrent.futures import Future
from typing import Protocol

from ...core.command_intake import intake, rejected_event_data
from ...core.command_rules import Rejection, reply_code
from ...core.ports import StationView
from ...core.records import CommandKind, CommandReply
from ...plumbing.threadloop import call_soon_on, submit_to
from .actions import Submit


class NodeDevice(Protocol):
    """What the node needs of an attached station's output: the station and the loop it runs on
    (None until the output started)."""
    station: StationView | None
    loop: asyncio.AbstractEventLoop | None


#: the outcome of a command: (device ID, command kind, ok, result code, reason)
Result = tuple[str, str, bool, int, str]


class NodeStations:
    """The attached stations by device ID, and their commands (see the module docstring).

    ``reply`` takes an outcome known at once (on the node thread); ``post`` one a station's loop
    gives later (it hands it over to the node thread)."""

    def __init__(self, reply: Callable[[Result], None], post: Callable[[tuple], None]) -> None:
        self.outputs: dict[str, NodeDevice] = {}
        self._reply = reply
        self._post = post

    def submit(self, sub: Submit) -> None:
        out = self.outputs.get(sub.device_id)
        try:
            ck = CommandKind(sub.kind)
        except ValueError:
            self._reply((sub.device_id, sub.kind, False, 9, f"{sub.kind} is not available in this version"))
            return
        if out is None or out.station is None or out.loop is None or out.loop.is_closed():
            self._reply((sub.device_id, sub.kind, False, 10, "the station is not running"))
            return
        # the one bounded intake (gateway/core/command_intake.py): a DCMD metric's Sparkplug type
        # is kept, so a String "0.6" for Arg T Set or a 1 MB Arg Sample ID is refused like over MQTT
        cmd = intake(ck.value, sub.args, "sparkplug")
        if isinstance(cmd, Rejection):
            self._reply((sub.device_id, sub.kind, False, int(cmd.code), cmd.reason))
            call_soon_on(out.loop, out.station.refused, rejected_event_data(ck.value, cmd, "sparkplug"))
            return
        fut = submit_to(out.loop, out.station.submit(cmd))
        if fut is None:
            self._post(("result", sub.device_id, sub.kind, False, 10, "the station is not running"))
            return

        def done(f: Future[CommandReply], dev: str = sub.device_id, kind: str = sub.kind) -> None:
            try:
                r = f.result()
                self._post(("result", dev, kind, bool(r.ok), reply_code(r), r.reason))
            except Exception as e:  # noqa: BLE001 - the station failed to carry it out
                self._post(("result", dev, kind, False, 10, f"the station failed: {type(e).__name__}: {e}"))

        fut.add_done_callback(done)
