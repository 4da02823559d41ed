"""Data that flows one way through a station: slot records, events, station state, commands.

The station runtime produces one :class:`SlotRecord` per 20 ms slot and :class:`Event` objects
when something happens; outputs (recorder, MQTT, Modbus TCP) consume them. Commands from the CLI,
MQTT or a PLC come back as :class:`Command` and go through one validation path.
"""
from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, field
from typing import Any


class TestState(enum.IntEnum):
    """Test lifecycle (also the enum served in the PLC register map)."""
    IDLE = 0
    BASELINE_SEARCH = 1   # running, no baseline yet
    MONITORING = 2        # baseline established, watching for persistent exceedance
    END_OF_LIFE = 3       # t_life found; the test runs on to its planned t_end
    COMPLETED = 4
    ABORTED = 5
    STARTING = 6          # METHOD.md §3a: zero check and spin-up before slot 0 (nothing recorded)


@dataclass(slots=True)
class SlotRecord:
    """Everything known about one slot k (t = k · Ts from test start)."""
    k: int
    t: float
    present: bool
    t1: float            # N, NaN when MISSING
    t2: float
    q: int               # 1 valid, 0 invalid
    mask: int            # reason bits (gateway.core.method.rules)
    ratio: float | None
    mu: float | None     # only when q = 1
    mean_filt: float     # pre-filtered mean tension fed to the controller, N
    speed_cmd: float     # rpm commanded this slot
    speed_act: float     # rpm reported by the STM32 (NaN if unknown)
    saturated: bool      # control output clamped this slot
    lateness_s: float = 0.0   # how late the poll for this slot started vs. its deadline
    rtt_s: float = math.nan   # meter round-trip time


class AlarmState(str, enum.Enum):
    """The ISA-18.2 alarm states, the one definition (PLC enum register, MQTT, Sparkplug, the alarm
    store; the transitions are :mod:`gateway.core.alarms`). Enum order = PLC register value."""
    NORMAL = "normal"                          # nothing to do (also: closed, the hook was replaced)
    UNACKNOWLEDGED = "unacknowledged"          # new alarm, annunciated
    ACKNOWLEDGED = "acknowledged"              # known, still standing (the worn hook is still in)
    RTN_UNACKNOWLEDGED = "rtn_unacknowledged"  # returned to normal before anyone acknowledged
    SHELVED = "shelved"                        # silenced by an operator until its expiry
    OUT_OF_SERVICE = "out_of_service"          # taken out of service (a needle is being changed)


#: the alarm store's alarm kinds and their priority (1 = most urgent; ISA-18.2 style): end of life
#: outranks the wear warning
ALARM_END_OF_LIFE = "end_of_life"
ALARM_WARNING = "warning"
ALARM_PRIORITY = {ALARM_END_OF_LIFE: 1, ALARM_WARNING: 2}
#: the old alarm.json states (before ISA-18.2) → the model's
_OLD_ALARM_STATES = {"none": AlarmState.NORMAL, "active": AlarmState.UNACKNOWLEDGED,
                     "acknowledged": AlarmState.ACKNOWLEDGED}


@dataclass(frozen=True)
class AlarmRecord:
    """One alarm of a station's persisted alarm store (``gateway/station/alarm_store.py``) as it
    stands (also after it was cleared: what it was about); the MQTT output publishes it."""
    state: AlarmState = AlarmState.NORMAL
    raised: bool = False                 # False: there never was an alarm (nothing to publish)
    acknowledged: bool = False
    test_id: str | None = None
    sample_id: str | None = None
    t_life: float | None = None
    k_life: int | None = None
    mu_ss: float | None = None
    mu_th: float | None = None
    raised_at: str | None = None
    acknowledged_at: str | None = None
    acknowledged_by: str | None = None
    cleared_at: str | None = None
    kind: str = ALARM_END_OF_LIFE              # ALARM_END_OF_LIFE or ALARM_WARNING
    priority: int = ALARM_PRIORITY[ALARM_END_OF_LIFE]
    # the wear warning's figures (§5a); None for the end of life
    warn_slot: int | None = None
    t_warn: float | None = None
    headroom: float | None = None
    t_cross: float | None = None
    # … and its §5b forecast: the reasons of the due window, the end quantiles, P and the lead
    reasons: list[str] | None = None
    end_p10: float | None = None
    end_p50: float | None = None
    end_p90: float | None = None
    p_end: float | None = None
    lead_s: float | None = None
    condition: bool = False              # ISA-18.2: the process condition stands (the hook is worn)
    shelved_until: str | None = None     # UTC time a shelving expires

    @property
    def active(self) -> bool:
        """The alarm stands in some way (any state but normal)."""
        return self.state != AlarmState.NORMAL

    def as_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["alarm"] = d.pop("state").value          # the key alarm.json always had
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any], kind: str = ALARM_END_OF_LIFE) -> AlarmRecord:
        v = d.get("alarm", "normal")
        state = _OLD_ALARM_STATES[v] if v in _OLD_ALARM_STATES else AlarmState(v)
        names = {f for f in cls.__dataclass_fields__ if f not in ("state", "kind", "priority")}
        kw = {k: v for k, v in d.items() if k in names}
        kw.setdefault("raised", state != AlarmState.NORMAL)
        kw.setdefault("acknowledged", state in (AlarmState.ACKNOWLEDGED, AlarmState.NORMAL))
        kw.setdefault("condition", state in (AlarmState.UNACKNOWLEDGED, AlarmState.ACKNOWLEDGED))
        return cls(state=state, kind=kind, priority=ALARM_PRIORITY[kind], **kw)


class EventType(str, enum.Enum):
    TEST_STARTING = "test_starting"      # a start was accepted: zero check, then spin-up (§3a)
    START_FAILED = "start_failed"        # the start sequence refused or timed out (§3a): idle again
    TEST_STARTED = "test_started"        # slot 0: the tension has settled (§3a)
    BASELINE = "baseline_established"
    END_OF_LIFE = "end_of_life"
    WEAR_WARNING = "wear_warning"        # the §5a early warning (once per test, informative)
    PROTECTION_STOP = "protection_stop"
    DRIVE_STOPPED = "drive_stopped"      # the STM32 stopped the drive on its own (watchdog, trip)
    TEST_ENDED = "test_ended"
    PORT_LOST = "port_lost"
    PORT_BACK = "port_back"
    ALARM_ACK = "alarm_acknowledged"
    ALARM_CLEARED = "alarm_cleared"            # a new test started or the hook was replaced: closed
    ALARM_SHELVED = "alarm_shelved"
    ALARM_UNSHELVED = "alarm_unshelved"        # by command or at the shelving's expiry
    ALARM_OUT_OF_SERVICE = "alarm_out_of_service"
    ALARM_IN_SERVICE = "alarm_in_service"
    HOOK_REPLACED = "hook_replaced"      # a hook was replaced (its line in hooks.jsonl)
    COMMAND_REJECTED = "command_rejected"
    CONFIG_RELOADED = "config_reloaded"
    DISK_FULL = "disk_full"              # the records' or the outbox's disk cannot be written
    DISK_OK = "disk_ok"                  # … and can again (once per transition and store)
    RECORDS_PRUNED = "records_pruned"    # record retention removed completed tests (gateway/station/retention.py)


@dataclass
class Event:
    type: EventType
    station: str
    wall_time: float                   # UTC epoch seconds
    test_id: str | None = None
    k: int | None = None               # slot, when the event belongs to one
    data: dict[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {"type": self.type.value, "station": self.station, "time": self.wall_time,
                "test_id": self.test_id, "k": self.k, **self.data}


@dataclass
class StationState:
    """Slowly changing state of a station (retained MQTT `state`, PLC registers)."""
    station: str
    state: TestState = TestState.IDLE
    test_id: str | None = None
    sample_id: str | None = None
    grade: str | None = None
    t_set: float | None = None
    t_end: float | None = None
    mu_ss: float | None = None
    mu_th: float | None = None
    k_b: int | None = None
    t_life: float | None = None
    elapsed_s: float = 0.0
    status: str | None = None          # the method's status once the test has ended
    end_reason: str | None = None      # why a test ended (completed, protection stop, command, restart)
    alarm: str = AlarmState.NORMAL.value  # an AlarmState value (gateway.station.alarm_store keeps it)
    warning_alarm: str = AlarmState.NORMAL.value  # the §5a wear-warning alarm (lower priority)
    headroom: float | None = None      # §5a h of the last post-baseline window with a value
    t_cross: float | None = None       # §5a projected crossing of μ_th, s from test start (None: none)
    wear_warning: bool = False         # §5b early warning fired in this test (the first due window)
    # §5b/§7a remaining life (issue 20): all None/False/[] outside a test; no projection (end_p*,
    # p_end, t_cross, due) after the end of life was detected or after the test ended
    prior_mean: float | None = None    # the test's life prior, s (§7a)
    prior_sd: float | None = None
    prior_source: str | None = None    # "method", "config", "history:N" or None (no prior)
    prior_n: int | None = None         # its lives (§7a v3): wear-out failures, censored lives and
    prior_n_censored: int | None = None  # early failures (None: a prior without counts, or none)
    prior_n_early: int | None = None
    lead_s: float | None = None        # the planner's lead (§5b `lead`), s
    p_due: float | None = None         # the bound P is held against (§5b `p_due`)
    end_p10: float | None = None       # end quantiles of the last forecast time, s from slot 0
    end_p50: float | None = None
    end_p90: float | None = None
    p_end: float | None = None         # chance of the end within the lead (last forecast time)
    due: bool = False                  # the last forecast window is due (§5b)
    warn_reasons: list[str] = field(default_factory=list)   # the early warning's reasons, sorted
    test_started_utc: str | None = None   # ISO 8601 (UTC) of the test's slot 0
    stopped: bool = False              # the last test was ended on purpose (STOPPED, §3)
    protection_stop: bool = False
    meter_ok: bool = False
    stm32_ok: bool = False
    mqtt_ok: bool = False
    saturation: bool = False
    disk_ok: bool = True               # the records and the MQTT outbox can be written


class CommandKind(str, enum.Enum):
    START = "start"
    STOP = "stop"
    ACK = "ack"
    SETPOINT = "setpoint"
    HOOK_REPLACED = "hook_replaced"    # the worn hook was replaced: closes its end-of-life alarm
    SHELVE = "shelve"                  # shelve one alarm until an expiry (ISA-18.2)
    UNSHELVE = "unshelve"
    OUT_OF_SERVICE = "out_of_service"  # both alarms out of service while a needle is changed
    IN_SERVICE = "in_service"


#: a command argument's value, as the one intake lets it through (gateway/core/command_intake.py:
#: numbers finite and not booleans, text printable ASCII)
ArgValue = str | int | float
#: a command's arguments by name (gateway/core/command_rules.py COMMAND_KEYS: which each command takes)
CommandArgs = dict[str, ArgValue]
#: a refusal as the command_rejected event reports it: command, source, reason, code (and, once
#: counted, count and window_s)
RefusalData = dict[str, str | int | float]


@dataclass
class Command:
    kind: CommandKind
    source: str                          # "cli", "mqtt", "plc:<addr>"
    args: CommandArgs = field(default_factory=dict)
    request_id: str | None = None


@dataclass
class CommandReply:
    ok: bool
    reason: str = ""
    request_id: str | None = None
    #: 0 when accepted, else the refusal code (gateway/core/command_rules.py REJECT_CODES)
    code: int = 0
