"""What a station does with a command it accepted: a table from command kind to handler.

``Station.submit`` validates a command once (``gateway.station.command_desk.validate``, the same for
CLI, MQTT, PLC, console and Sparkplug), then calls ``HANDLERS[cmd.kind]``. A new command is a
new row here (and its rules in ``command_desk.py``); nothing else branches on the kind.
"""
from __future__ import annotations

import time
from collections.abc import Awaitable, Callable
from dataclasses import replace
from typing import Protocol

from ..core.command_rules import ALARM_COMMAND_EVENTS, text_arg
from ..core.ports import StationLimits
from ..core.records import Command, CommandArgs, CommandKind, EventType
from .lifecycle import TestLifecycle
from .session import TestPlan
from .status import StatusBoard

__all__ = ["HANDLERS", "CommandTarget", "plan_of"]


class CommandTarget(Protocol):
    """What the handlers act on (a :class:`~gateway.station.station.Station`)."""
    board: StatusBoard
    default_plan: TestPlan | None
    limits: StationLimits

    tests: TestLifecycle

    def start_test(self, plan: TestPlan, source: str = "station") -> None: ...
    async def stop_test(self, source: str, test_id: str | None = None) -> None: ...


Handler = Callable[[CommandTarget, Command], Awaitable[None]]


def plan_of(st: CommandTarget, args: CommandArgs) -> TestPlan:
    """The test plan a (validated) start asks for; a start without t_end runs the default's."""
    t_end = args.get("t_end") or (st.default_plan.t_end if st.default_plan
                                  else st.limits.t_end_default_s)
    return TestPlan(sample_id=str(args["sample_id"]), grade=text_arg(args, "grade"),
                    t_set=float(args["t_set"]), t_end=float(t_end))


async def _start(st: CommandTarget, cmd: Command) -> None:
    st.start_test(plan_of(st, cmd.args), source=cmd.source)


async def _stop(st: CommandTarget, cmd: Command) -> None:
    await st.stop_test(cmd.source, text_arg(cmd.args, "test_id"))


async def _ack(st: CommandTarget, cmd: Command) -> None:
    st.board.emit(EventType.ALARM_ACK, source=cmd.source)
    st.board.push()


async def _hook_replaced(st: CommandTarget, cmd: Command) -> None:
    a = cmd.args
    await st.tests.hook_replaced(cmd.source, text_arg(a, "sample_id"), text_arg(a, "grade"), st.default_plan,
                                 st.limits.sample_id_max)


async def _alarm(st: CommandTarget, cmd: Command) -> None:
    """ISA-18.2 shelve / unshelve / out of service / in service: an event the alarm store applies."""
    data: dict[str, str | float] = {"source": cmd.source}
    if cmd.args.get("alarm") is not None:
        data["alarm"] = str(cmd.args["alarm"])
    if cmd.kind == CommandKind.SHELVE:
        data["until"] = time.time() + float(cmd.args["duration_s"])
    st.board.emit_data(ALARM_COMMAND_EVENTS[cmd.kind], data)
    st.board.push()


async def _setpoint(st: CommandTarget, cmd: Command) -> None:
    if st.default_plan is not None:
        st.default_plan = replace(st.default_plan, t_set=float(cmd.args["t_set"]))


HANDLERS: dict[CommandKind, Handler] = {
    CommandKind.START: _start,
    CommandKind.STOP: _stop,
    CommandKind.ACK: _ack,
    CommandKind.HOOK_REPLACED: _hook_replaced,
    CommandKind.SETPOINT: _setpoint,
    **{kind: _alarm for kind in ALARM_COMMAND_EVENTS},
}
