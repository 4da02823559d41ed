"""Issue 34 item 4: a command acts once for its whole window. The station's command desk on a
clock the test turns (pure: no loop thread, no broker):

- the request_id memory follows the rate budget: per source, every command the budget lets one
  source have taken within the 600 s TTL (burst 20 + 60 a minute × 10 minutes = 620);
- every command the desk takes costs its source one of the budget, refused ones included; a
  repeat answered from memory costs none;
- so no flood — of refused commands, of any length, at any pace, from the same source or
  others — pushes a request_id out before its 600 s: a stop's replay is answered from memory
  and ends nothing; after the 600 s it is a new command again;
- the memory itself never forgets an id early: a command it could not hold is refused (14).
"""
import asyncio

from gateway.core.records import Command, CommandKind, CommandReply, StationState
from gateway.core.records import TestState as TState
from gateway.station.command_desk import (
    CODE,
    COMMAND_BURST,
    COMMANDS_PER_MIN,
    REQUEST_ID_MAX_KEPT,
    REQUEST_ID_SOURCES,
    REQUEST_ID_TTL_S,
    CommandDesk,
    RequestLedger,
    StationLimits,
    budget_in,
    validate,
)


class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


class Desk:
    """A desk validating stops against a station that runs a test until a stop ends it."""

    def __init__(self) -> None:
        self.clock = Clock()
        self.state = StationState(station="s", state=TState.MONITORING, test_id="T1")
        self.acted: list[Command] = []
        self.refusals: list[dict] = []
        self.desk = CommandDesk(lambda c: validate(c, StationLimits(), self.state), self._act,
                                self.refusals.append, clock=self.clock)

    async def _act(self, cmd: Command) -> None:
        self.acted.append(cmd)
        if cmd.kind == CommandKind.STOP:
            self.state.state = TState.ABORTED
        elif cmd.kind == CommandKind.START:
            self.state.state, self.state.test_id = TState.MONITORING, f"T{len(self.acted)}"

    def submit(self, cmd: Command) -> CommandReply:
        async def go():
            return await self.desk.submit(cmd)
        return asyncio.run(go())

    def many(self, cmds) -> list[CommandReply]:
        async def go():
            return [await self.desk.submit(c) for c in cmds]
        return asyncio.run(go())


def stop(rid, source="mqtt", **args):
    return Command(CommandKind.STOP, source, dict(args), rid)


def ack(rid, source="mqtt"):
    return Command(CommandKind.ACK, source, {}, rid)


def start(rid, source="mqtt"):
    return Command(CommandKind.START, source, {"sample_id": "S-2", "t_set": 0.5}, rid)


def test_the_memory_per_source_is_what_the_budget_lets_through_in_the_ttl():
    assert budget_in(REQUEST_ID_TTL_S) == COMMAND_BURST + COMMANDS_PER_MIN * REQUEST_ID_TTL_S / 60 == 620
    assert REQUEST_ID_MAX_KEPT == budget_in(REQUEST_ID_TTL_S)
    assert budget_in(0) == COMMAND_BURST and budget_in(60, 60, 20) == 80 and budget_in(1.5, 60, 20) == 21
    led = RequestLedger()
    assert (led.ttl_s, led.per_source, led.max_sources) == (REQUEST_ID_TTL_S, 620, REQUEST_ID_SOURCES)


def test_refused_commands_cost_the_budget_and_repeats_do_not():
    d = Desk()
    assert d.submit(stop("X")).ok                       # ends test 1: one of the 20 spent
    out = d.many([stop(f"r{i}") for i in range(1100)])  # 1,100 refused stops at once
    codes = [r.code for r in out]
    assert codes[:COMMAND_BURST - 1] == [CODE["NOT_RUNNING"]] * (COMMAND_BURST - 1)
    assert set(codes[COMMAND_BURST - 1:]) == {CODE["RATE_LIMITED"]}
    c = d.desk.counters
    assert c["accepted"] == 1 and c["refused"] == 1100 and c["rate_limited"] == 1100 - (COMMAND_BURST - 1)
    # only what took budget is remembered: the stop and the refusals that were validated
    assert len(d.desk.ledger) == COMMAND_BURST
    # repeats of X cost nothing, as often as they come
    before = d.desk.rate.wait("mqtt")
    for _ in range(50):
        again = d.submit(stop("X"))
        assert again.ok and "duplicate of request_id 'X'" in again.reason
    assert d.desk.rate.wait("mqtt") == before and c["duplicates"] == 50
    assert len(d.acted) == 1


def test_a_replayed_stop_never_ends_a_new_test_within_its_600_s():
    d = Desk()
    assert d.submit(stop("X")).ok
    d.many([stop(f"burst{j}") for j in range(COMMAND_BURST)])       # the rest of the burst spent
    # then a flood at the fastest pace the budget allows, for nearly the whole TTL: every second
    # one refused command that takes the token of that second (an ack without an alarm), and 50
    # more (refused for the rate)
    for i in range(591):
        d.clock.t += 1.0
        out = d.many([ack(f"f{i}-{j}") for j in range(51)])
        assert out[0].code == CODE["NO_ALARM"] and {r.code for r in out[1:]} == {CODE["RATE_LIMITED"]}
        assert len(d.desk.ledger) <= REQUEST_ID_MAX_KEPT
        if i == 100:                      # a new test starts 100 s after the stop …
            d.clock.t += 1.0
            assert d.submit(start("S")).ok and d.state.test_id == "T2"
        if i in (101, 300, 590):          # … and X's replay never ends it, nor does a stop of test 1
            again = d.submit(stop("X"))
            assert again.ok and "duplicate" in again.reason, again
            assert d.state.state == TState.MONITORING
            d.clock.t += 1.0
            old = d.submit(stop(f"old{i}", test_id="T1"))
            assert old.code == CODE["WRONG_TEST"], old
            assert d.state.state == TState.MONITORING
    assert d.clock.t - 1000.0 < REQUEST_ID_TTL_S
    assert [c.kind for c in d.acted] == [CommandKind.STOP, CommandKind.START]
    # 600 s after it came, X is a new command: it is carried out (ends test 2)
    d.clock.t = 1000.0 + REQUEST_ID_TTL_S + 5.0
    r = d.submit(stop("X"))
    assert r.ok and "duplicate" not in r.reason and d.state.state == TState.ABORTED


def test_a_flood_from_other_sources_never_touches_a_sources_memory():
    d = Desk()
    assert d.submit(stop("X", source="mqtt")).ok
    for n in range(REQUEST_ID_SOURCES - 1):
        out = d.many([stop(f"p{n}-{j}", source=f"console:u{n}") for j in range(30)])
        assert sum(r.code == CODE["NOT_RUNNING"] for r in out) == COMMAND_BURST
    assert "duplicate" in d.submit(stop("X", source="mqtt")).reason
    # a source beyond the sources the memory holds is refused, never answered by forgetting one
    late = d.submit(stop("z", source="console:one-too-many"))
    assert late.code == CODE["RATE_LIMITED"] and "sources" in late.reason, late
    assert "duplicate" in d.submit(stop("X", source="mqtt")).reason
    d.clock.t += REQUEST_ID_TTL_S
    assert d.submit(stop("z", source="console:one-too-many")).code == CODE["NOT_RUNNING"]


def test_the_memory_refuses_rather_than_forgets():
    led = RequestLedger(ttl_s=10.0, per_source=3, max_sources=2)
    now = 0.0
    for i in range(3):
        cmd = stop(f"a{i}")
        assert led.room(cmd, now) is None
        led.note(cmd, CommandReply(True, "", cmd.request_id), now)
        now += 1.0
    why, wait = led.room(stop("a3"), now)
    assert "3 commands with a request_id" in why and wait == 7.0
    assert led.room(Command(CommandKind.STOP, "mqtt"), now) is None        # no id: no memory needed
    assert led.answer(stop("a0"), now).reason.startswith("duplicate of request_id 'a0'")
    assert led.room(stop("a3"), 10.0) is None and led.answer(stop("a0"), 10.0) is None   # a0 expired
    led.note(stop("b", source="plc:x"), CommandReply(True), 10.0)
    why, wait = led.room(stop("c", source="console:y"), 10.0)
    assert "2 sources" in why and wait == 2.0                               # when mqtt's a2 expires
    assert led.room(stop("c", source="console:y"), 11.0) is not None
    assert led.room(stop("c", source="console:y"), 12.0) is None
    assert len(led) == 1                                                    # b still held


def test_a_stop_naming_a_test_ends_that_test_only():
    lim = StationLimits()
    running = StationState(station="s", state=TState.MONITORING, test_id="T2")
    assert validate(stop(None, test_id="T2"), lim, running) is None
    r = validate(stop(None, test_id="T1"), lim, running)
    assert r.code == CODE["WRONG_TEST"] and "T1" in r.reason and "test 'T2' is running" in r.reason
    starting = StationState(station="s", state=TState.STARTING, test_id=None)
    assert validate(stop(None), lim, starting) is None                      # cancels the start
    r = validate(stop(None, test_id="T1"), lim, starting)
    assert r.code == CODE["WRONG_TEST"] and "starting" in r.reason
    idle = StationState(station="s", state=TState.ABORTED, test_id="T1")
    r = validate(stop(None, test_id="T1"), lim, idle)
    assert r.code == CODE["NOT_RUNNING"] and "test 'T1' ended" in r.reason
    assert validate(stop(None), lim, running) is None                       # naming none: the running one


def test_an_answer_is_remembered_by_its_arguments_digest():
    led = RequestLedger()
    first = Command(CommandKind.SETPOINT, "mqtt", {"t_set": 1}, "s1")
    led.note(first, CommandReply(True, "", "s1"), 0.0)
    same = Command(CommandKind.SETPOINT, "mqtt", {"t_set": 1.0}, "s1")         # 1 and 1.0: one number
    assert led.answer(same, 1.0).ok and "duplicate" in led.answer(same, 1.0).reason
    other = Command(CommandKind.SETPOINT, "mqtt", {"t_set": 0.6}, "s1")
    r = led.answer(other, 1.0)
    assert not r.ok and r.code == CODE["BAD_REQUEST"] and "names one command" in r.reason
    assert led.answer(Command(CommandKind.SETPOINT, "console:a", {"t_set": 0.6}, "s1"), 1.0) is None
