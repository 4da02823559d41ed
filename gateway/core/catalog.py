"""The one catalog of a station's published values: a row per value, every door's name for it.

A row says what the value is (name, type, unit, meaning), where it comes from (``source``: a pure
function of the station's :class:`~gateway.core.records.StationState`) and how each door publishes
it: its key in the retained MQTT ``state``, its Sparkplug device metric (name, alias index,
datatype), its PLC input register (block, name, type) or status bit, its Prometheus gauge (name,
help) and its label in the web console. Every door derives its set from these rows (issue 35 item 2):

- MQTT: the ``state`` payload, its fields in docs/mqtt.md and the JSON schemas, and what makes a
  new retained ``state`` worth sending (``gateway/outputs/mqtt/schema.py``, ``messages.py``);
- Sparkplug: the device metrics that follow the state, in DBIRTH and DDATA, each at the alias
  ``device base + alias`` (``gateway/outputs/sparkplug/metrics.py``, ``output.py``);
- PLC: the input registers the state fills, each in its block (``gateway/outputs/plc/registers.py``:
  a row whose register the block's layout does not place is appended at the end of its block, in
  the block's reserved space: no existing address moves), and the flags' bits of ``status``;
- Prometheus: a gauge per row (an enumeration: one gauge per choice, labelled), from the station's
  snapshot (``gateway/outputs/prometheus/``);
- the console: the page asks ``/api/values`` for the rows with a label and shows every one of
  them for a station (``gateway/outputs/console/``), and the site view reads a remote station's
  ``state`` by the rows' types (``gateway/outputs/console/site.py``).

**A new published value** is its source (a field of ``StationState`` the station fills, or a
function of the existing ones) and one row appended here: a new Sparkplug alias (the next free
index), a register in a block with reserved space (then ``MAP_MINOR`` bumped and the golden map
frozen: ``python -m gateway.outputs.plc.registers --freeze tests/golden/plc_register_map.txt``),
and the generated docs regenerated (docs/mqtt.md and the JSON schemas, docs/sparkplug.md,
docs/registers.md, docs/metrics.md's table: each with the command its "docs current" test
names). ``tests/gateway/outputs/test_catalog.py`` proves both: every door publishes exactly these
rows, and a row added in-process shows at every door.

**The values of the slot records** (per 20 ms slot, per telemetry interval) are the rows of
:data:`SLOT_CATALOG` (:class:`SlotValue`): a figure of a window of slot records
(``gateway/core/slotwindow.py``: its MQTT telemetry key and source), its Sparkplug data-interval
metric (name, alias index, datatype: a periodic measurement) and its PLC live register (read from
the latest slot record or from the running test's window). MQTT telemetry
(``mqtt/schema.py: telemetry_fields``, ``mqtt/messages.py: telemetry_summary``), the Sparkplug data
interval (``sparkplug/output.py: window_values``, ``sparkplug/metrics.py: device_metrics``) and
the PLC's live registers (``plc/registers.py: input_layout``, ``plc/server.py``), and a row's
Prometheus gauge and console label of the latest slot's reading (none today:
``prometheus/figures.py: SLOT_GAUGES``, ``console/feed.py: SLOT_VALUES``) derive their sets from
them. A value read from each slot record (a third meter channel: a new ``SlotRecord`` field) is
one :func:`channel` row: the window keeps its mean (``SlotWindow.means``), the PLC, Prometheus and
the console the latest slot's. ``tests/gateway/outputs/test_catalog_slots.py`` proves both, as
above. Not rows: the console's live series (the chart) and the Prometheus slot counters.

Pure: data and functions of the state and the slot records; no I/O, no clock, nothing of the doors.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from .method.rules import REASON_NAMES
from .records import AlarmState, SlotRecord, StationState, TestState

if TYPE_CHECKING:
    from .slotwindow import SlotWindow

#: a published value as its source reads it
Reading = str | int | float | bool | list[str] | None
Source = Callable[[StationState], Reading]

#: the Sparkplug B datatypes a row may name (gateway/outputs/sparkplug/metrics.py DataType)
SPARKPLUG_TYPES = ("Int32", "Int64", "UInt32", "Float", "Double", "Boolean", "String", "DateTime")
#: the PLC register types a row may name (gateway/outputs/plc/registers.py SIZES)
PLC_TYPES = ("uint16", "enum", "bits", "uint32", "float32", "string", "string80")
#: the value types (the MQTT schema's, without ``|null``)
TYPES = ("str", "int", "float", "bool", "list")


@dataclass(frozen=True)
class SparkplugMetric:
    """The value as a Sparkplug device metric: its name, its alias index (the metric's alias is
    the device's alias base + this; never reused, never changed) and datatype."""
    name: str
    alias: int
    datatype: str
    units: str = ""
    description: str = ""
    #: the metric's value when the source reads None (None: a null metric)
    empty: str | None = None


@dataclass(frozen=True)
class PlcRegister:
    """The value as a PLC input register in ``block`` (gateway/outputs/plc/registers.py)."""
    name: str
    block: str
    type: str
    unit: str
    doc: str
    #: the register's own reading of the state (None: the row's source)
    source: Source | None = None


@dataclass(frozen=True)
class PlcBit:
    """A flag as a bit of the PLC's input register ``status`` (a free bit: never reused, never
    moved; gateway/outputs/plc/registers.py STATUS_BITS)."""
    bit: int
    name: str
    doc: str


@dataclass(frozen=True)
class PromGauge:
    """The value as a Prometheus gauge ``hookwatch_<name>`` labelled by station; an enumeration
    is one gauge per choice with ``label`` (1 for the current one)."""
    name: str
    help: str
    label: str = ""
    #: its meaning in docs/metrics.md ("": the help)
    doc: str = ""


@dataclass(frozen=True)
class Value:
    """One published value of a station (see the module doc)."""
    name: str                  # its name: the key in the MQTT `state` (and the snapshots)
    type: str                  # the MQTT schema's type: str, str|null, int|null, float|null, bool, list
    unit: str                  # engineering unit ("": none)
    doc: str                   # what it means (docs/mqtt.md's state table)
    source: Source             # how it is read from the station's state
    mqtt: bool = True          # a key of the retained MQTT `state`
    ticks: bool = False        # changes with time alone: no reason for a new retained `state`
    choices: tuple[str, ...] = ()  # an enumeration's (or a list's) values, in their number's order
    sparkplug: SparkplugMetric | None = None
    plc: PlcRegister | None = None
    plc_bit: PlcBit | None = None  # a flag's bit in the PLC's status register
    prometheus: PromGauge | None = None
    label: str = ""            # the console's label ("": not shown)

    @property
    def base_type(self) -> str:
        """``type`` without ``|null``."""
        return self.type.split("|")[0]


#: test states a test runs in (baseline search, monitoring, end of life)
RUNNING = (TestState.BASELINE_SEARCH, TestState.MONITORING, TestState.END_OF_LIFE)
ALARM_STATES = tuple(a.value for a in AlarmState)
TEST_STATES = tuple(s.name.lower() for s in sorted(TestState, key=int))
#: the early warning's reasons (§5b), in their PLC bit order
WARN_REASONS = ("headroom", "prior", "trend")
_ALARM_ENUM = ", ".join(f"{i} {n}" for i, n in enumerate(ALARM_STATES))


def _left(e: float | None, st: StationState) -> float | None:
    """The remaining time to an end quantile ``e`` (s from slot 0): at least 0; None without one."""
    return max(0.0, e - float(st.elapsed_s)) if e is not None else None


def _end_left(q: int, read: Callable[[StationState], float | None]) -> Value:
    return Value(
        f"end_p{q}_left", "float|null", "s", f"remaining time to the {q} % end quantile at the last "
        "forecast time (§5b), s", lambda st: _left(read(st), st), mqtt=False,
        plc=PlcRegister(f"end_p{q}_left", "forecast", "float32", "s", f"remaining time to the {q} % "
                        "end quantile of the forecast at the last forecast time (METHOD.md §5b): e_p "
                        "− elapsed, at least 0; NaN without a prior, outside a test and once the end "
                        "of life was detected"),
        prometheus=PromGauge(f"end_p{q}_seconds", f"remaining time to the {q} % end quantile of the "
                             "hook's life forecast at its last forecast time (METHOD.md §5b); absent "
                             "without a prior, outside a test and once the end of life was detected",
                             doc=f"remaining time to the {q} % end quantile of the hook's life forecast "
                             f"at its last forecast time (METHOD.md §5b: e{q} − elapsed, at least 0); no "
                             "series without a life prior, outside a test and once the end of life was "
                             "detected"),
        label=f"end P{q} in")


def _sp(name: str, alias: int, datatype: str, units: str = "", description: str = "",
        empty: str | None = None) -> SparkplugMetric:
    return SparkplugMetric(name, alias, datatype, units, description, empty)


#: every published value of a station, in the order of the MQTT `state` (append new rows at the end)
CATALOG: tuple[Value, ...] = (
    Value("test_state", "str", "", "idle, starting (zero check and spin-up before slot 0, METHOD.md "
          "§3a), baseline_search, monitoring, end_of_life, completed, aborted",
          lambda st: st.state.name.lower(), choices=TEST_STATES,
          sparkplug=_sp("Test/State", 0, "String", description="idle | starting | baseline_search | "
                        "monitoring | end_of_life | completed | aborted"),
          plc=PlcRegister("test_state", "status", "enum", "", "test state: "
                          + ", ".join(f"{s.value} {s.name.lower()}" for s in TestState)),
          prometheus=PromGauge("station_state", "the station's test state (1 for the current one)",
                               "state", "the test state, one series per state (" + ", ".join(
                                   f"`{c}`" for c in TEST_STATES) + "), 1 for the current one"),
          label="test state"),
    Value("test_id", "str|null", "", "id of the current (or last) test", lambda st: st.test_id,
          sparkplug=_sp("Test/ID", 1, "String"),
          plc=PlcRegister("run_test_id", "run", "string80", "", "test ID of the current / last test "
                          "(its records folder, the `test_id` of its MQTT messages), up to 80 ASCII "
                          "characters as `run_sample_id`"),
          label="test"),
    Value("sample_id", "str|null", "", "sample under test", lambda st: st.sample_id,
          sparkplug=_sp("Test/Sample ID", 2, "String"),
          plc=PlcRegister("run_sample_id", "run", "string", "", "sample ID of the current / last test, "
                          "up to 32 ASCII characters, two per register (first character in the high "
                          "byte), padded with 0; empty before the first test"),
          label="sample"),
    Value("grade", "str|null", "", "needle grade of the sample", lambda st: st.grade,
          sparkplug=_sp("Test/Grade", 3, "String"), label="grade"),
    Value("t_set", "float|null", "N", "tension setpoint of the test, N", lambda st: st.t_set,
          sparkplug=_sp("Test/Setpoint", 4, "Float", "N", "mean tension setpoint t_set"),
          plc=PlcRegister("t_set", "live", "float32", "N", "setpoint of the current / last test (NaN "
                          "before the first test)"),
          label="T_set"),
    Value("t_end", "float|null", "s", "planned test duration, s", lambda st: st.t_end,
          sparkplug=_sp("Test/Planned End", 5, "Double", "s", "planned test duration t_end"),
          label="planned duration"),
    Value("mu_ss", "float|null", "", "baseline friction coefficient μ_ss (null before the baseline)",
          lambda st: st.mu_ss,
          sparkplug=_sp("Method/mu_ss", 9, "Double", "", "steady-state friction coefficient μ_ss"),
          plc=PlcRegister("mu_ss", "live", "float32", "", "baseline μ_ss of the current / last test "
                          "(NaN before the baseline)"),
          prometheus=PromGauge("mu_ss", "steady baseline μ_ss of the running test",
                               doc="the test's steady baseline μ_ss, once found"),
          label="μ_ss"),
    Value("mu_th", "float|null", "", "end-of-life threshold μ_th = (1+δ)·μ_ss", lambda st: st.mu_th,
          sparkplug=_sp("Method/mu_th", 10, "Double", "", "end-of-life threshold (1+δ)·μ_ss"),
          plc=PlcRegister("mu_th", "live", "float32", "", "end-of-life threshold μ_th (NaN before the "
                          "baseline)"),
          prometheus=PromGauge("mu_threshold", "end-of-life threshold (1+δ)·μ_ss",
                               doc="its end-of-life threshold (1+δ)·μ_ss"),
          label="μ_th"),
    Value("k_b", "int|null", "slots", "slot at which the baseline was established", lambda st: st.k_b,
          label="baseline slot"),
    Value("t_life", "float|null", "s", "wear life found, s from test start (null until end of life)",
          lambda st: st.t_life,
          sparkplug=_sp("Method/t_life", 11, "Double", "s", "wear life: start of the persistent exceedance"),
          plc=PlcRegister("t_life", "live", "uint32", "s", "wear life found, s from test start, rounded "
                          "(0 until end of life)"),
          label="t_life"),
    Value("elapsed_s", "float", "s", "time since test start, s", lambda st: round(float(st.elapsed_s), 3),
          ticks=True, sparkplug=_sp("Test/Elapsed", 6, "Double", "s", "time since the test started"),
          label="elapsed"),
    Value("status", "str|null", "", "the method's status once the test has ended", lambda st: st.status,
          sparkplug=_sp("Test/Status", 7, "String", description="the method's status once the test "
                        "ended: failure | no_failure | no_baseline | aborted"),
          label="method status"),
    Value("end_reason", "str|null", "", "why the test ended (completed, protection stop, stopped by "
          "command, gateway shutdown, …) or the start failed (§3a)", lambda st: st.end_reason,
          sparkplug=_sp("Test/End Reason", 8, "String"), label="end reason"),
    Value("alarm", "str", "", "end-of-life alarm, ISA-18.2 state: " + ", ".join(ALARM_STATES),
          lambda st: st.alarm, choices=ALARM_STATES,
          plc=PlcRegister("alarm", "status", "enum", "", "end-of-life alarm: " + _ALARM_ENUM),
          prometheus=PromGauge("alarm", "end-of-life alarm state (1 for the current one)", "alarm",
                               "end-of-life alarm, ISA-18.2 state, one series per state (" + ", ".join(
                                   f"`{c}`" for c in ALARM_STATES) + "), 1 for the current one"),
          label="end-of-life alarm"),
    Value("protection_stop", "bool", "", "the test was stopped by the protection rule (§3)",
          lambda st: bool(st.protection_stop), sparkplug=_sp("Status/Protection Stop", 15, "Boolean"),
          plc_bit=PlcBit(4, "protection_stop", "the last test was stopped by the protection rule"),
          label="protection stop"),
    Value("stopped", "bool", "", "the test was ended on purpose (STOPPED, §3: a command or a clean "
          "shutdown), not by a dead meter", lambda st: bool(st.stopped),
          plc_bit=PlcBit(11, "stopped", "the last test was ended on purpose (operator, PLC, MES stop or "
                         "a clean shutdown): STOPPED, not a dead meter"),
          label="stopped on purpose"),
    Value("headroom", "float|null", "", "wear headroom h of the last complete window with a value "
          "(§5a): 1 at the baseline, 0 at the threshold, negative above; informative",
          lambda st: st.headroom,
          sparkplug=_sp("Forecast/Headroom", 53, "Double", "", "wear headroom h of the last window "
                        "with a value (§5a)"),
          plc=PlcRegister("headroom", "wear", "float32", "", "wear headroom h of the last complete "
                          "window with a value (METHOD.md §5a): 1 at the baseline, 0 at the threshold "
                          "μ_th, negative above; NaN before the first window after the baseline. "
                          "Informative: never changes the result"),
          prometheus=PromGauge("wear_headroom", "wear headroom h of the last window (METHOD.md §5a): "
                               "1 at the baseline, 0 at the threshold",
                               doc="wear headroom h of the last window (METHOD.md §5a: 1 at the baseline, "
                               "0 at the threshold, negative above), when the station state carries it"),
          label="headroom"),
    Value("t_cross", "float|null", "s", "projected time (s from test start) at which the recent trend "
          "of μ reaches μ_th (§5a), from the last window with a value; null: no projection",
          lambda st: st.t_cross,
          sparkplug=_sp("Forecast/t_cross", 54, "Double", "s", "projected crossing of μ_th, s from "
                        "slot 0 (§5a)"),
          plc=PlcRegister("t_cross", "wear", "uint32", "s", "projected time from test start at which "
                          "the recent trend of μ reaches μ_th (§5a), rounded; 0 = no projection. It "
                          "assumes the trend goes on; the accelerated stage usually comes sooner"),
          prometheus=PromGauge("wear_projected_end_seconds", "test time at which the recent μ trend "
                               "reaches the threshold (METHOD.md §5a projection)",
                               doc="test time at which the recent μ trend reaches the threshold (§5a "
                               "projection), when known"),
          label="projected crossing"),
    Value("wear_warning", "bool", "", "the §5b early warning (the first due window) fired in this test",
          lambda st: bool(st.wear_warning),
          sparkplug=_sp("Forecast/Warning", 55, "Boolean", description="the early warning (the first "
                        "due window) fired in this test"),
          plc_bit=PlcBit(10, "wear_warning", "the §5a early warning fired in the current / last test "
                         "(informative; until a new test starts)"),
          prometheus=PromGauge("wear_warning", "1 once the test's early wear warning fired "
                               "(METHOD.md §5a)", doc="1 once the test's early warning fired (METHOD.md "
                               "§5b: the first due window; once per test)"),
          label="wear warning"),
    Value("end_p10", "float|null", "s", "end of life, 10 % quantile of the forecast from the prior at "
          "the last forecast time (§5b), s from the test's slot 0 (`test_started_utc` + this = wall "
          "time); null without a prior, outside a test or once the end of life was detected",
          lambda st: st.end_p10,
          sparkplug=_sp("Forecast/End P10", 48, "Double", "s", "end of life, 10 % quantile of the "
                        "forecast from the life prior at the last forecast time (§5b), s from slot 0"),
          label="end P10"),
    Value("end_p50", "float|null", "s", "end of life, median of that forecast, s from slot 0",
          lambda st: st.end_p50,
          sparkplug=_sp("Forecast/End P50", 49, "Double", "s", "end of life, median of that forecast, "
                        "s from slot 0"),
          label="end P50"),
    Value("end_p90", "float|null", "s", "end of life, 90 % quantile of that forecast, s from slot 0",
          lambda st: st.end_p90,
          sparkplug=_sp("Forecast/End P90", 50, "Double", "s", "end of life, 90 % quantile, s from slot 0"),
          label="end P90"),
    Value("p_end", "float|null", "", "chance that the end comes within the lead `lead_s` (§5b P)",
          lambda st: st.p_end,
          sparkplug=_sp("Forecast/P End", 51, "Double", "", "chance that the end comes within the "
                        "lead (§5b P)"),
          plc=PlcRegister("p_end", "forecast", "float32", "", "chance that the end comes within the "
                          "lead (§5b P) at the last forecast time; NaN without a prior, outside a "
                          "test, after the end-of-life detection"),
          prometheus=PromGauge("end_within_lead_probability", "chance that the hook's end comes "
                               "within the lead (METHOD.md §5b P)", doc="the chance that the end comes "
                               "within the lead (§5b P), at the last forecast time"),
          label="P end within the lead"),
    Value("due", "bool", "", "the last forecast window is due (§5b: P ≥ p_due, a headroom run or a "
          "projected crossing within the lead)", lambda st: bool(st.due),
          sparkplug=_sp("Forecast/Due", 52, "Boolean", description="the last forecast window is due (§5b)"),
          plc_bit=PlcBit(14, "hook_due", "the hook is due (METHOD.md §5b): the last forecast window of the "
                         "running test is due (P ≥ p_due, a headroom run or a projected crossing "
                         "within the lead); 0 outside a test and once the end of life was detected "
                         "(the end-of-life alarm speaks then)"),
          prometheus=PromGauge("hook_due", "1 while the last forecast window of the running test is "
                               "due (METHOD.md §5b: P ≥ p_due, a headroom run or a projected crossing "
                               "within the lead)", doc="1 while the last forecast window of the running "
                               "test is due (§5b: P ≥ `p_due`, a headroom run or a projected crossing "
                               "within the lead); the alert `HookwatchHookDue` in "
                               "deploy/prometheus/hookwatch-rules.yml fires on it"),
          label="due"),
    Value("warn_reasons", "list", "", "the early warning's reasons once it fired (sorted: headroom, "
          "prior, trend), else []", lambda st: list(st.warn_reasons or []), choices=WARN_REASONS,
          sparkplug=_sp("Forecast/Warning Reasons", 56, "String", description="its reasons, sorted, "
                        "comma-separated (headroom, prior, trend); empty before"),
          plc=PlcRegister("warn_reasons", "forecast", "bits", "", "the early warning's reasons once "
                          "it fired in the running test (status bit 10), see the table below; 0 "
                          "before and outside a test"),
          label="warning reasons"),
    Value("prior_mean", "float|null", "s", "the test's life prior, mean, s (§7a)", lambda st: st.prior_mean,
          sparkplug=_sp("Forecast/Prior Mean", 57, "Double", "s", "the test's life prior, mean (§7a)"),
          label="life prior, mean"),
    Value("prior_sd", "float|null", "s", "the test's life prior, SD, s", lambda st: st.prior_sd,
          sparkplug=_sp("Forecast/Prior SD", 58, "Double", "s", "the test's life prior, SD"),
          label="life prior, SD"),
    Value("prior_source", "str|null", "", "where the prior came from: `method` (fixed in the station's "
          "method section), `config` (forecast.priors), `history:N` (N recorded wear-out failures; from "
          "other stations too: `history:N (the site: T tests from K stations (M of this station; a 30, "
          "b 12))`, the other stations named with their tests, at most 3 and `and J more`), "
          "METHOD.md §7a), null: none", lambda st: st.prior_source,
          sparkplug=_sp("Forecast/Prior Source", 59, "String", description="method | config | "
                        "history:N (empty: no prior)", empty=""),
          label="life prior from"),
    Value("prior_n", "int|null", "", "the count of wear-out failures the prior came from (§7a; a "
          "configured prior: the count its entry gives, or null)", lambda st: st.prior_n,
          label="prior: wear-out failures"),
    Value("prior_n_censored", "int|null", "", "… of right-censored lives (hooks replaced or tests "
          "ended before their end of life)", lambda st: st.prior_n_censored,
          label="prior: censored lives"),
    Value("prior_n_early", "int|null", "", "… of early failures (§7a v3: a failure below 0.75 × the "
          "median of all lives, counted as a censored life, not as wear)", lambda st: st.prior_n_early,
          label="prior: early failures"),
    Value("lead_s", "float|null", "s", "the planner's lead (§5b `lead`), s", lambda st: st.lead_s,
          sparkplug=_sp("Forecast/Lead", 60, "Double", "s", "the planner's lead the hook is judged "
                        "against (§5b)"),
          plc=PlcRegister("lead", "forecast", "uint32", "s", "the lead the hook is judged against "
                          "(§5b `lead`), s; 0 outside a test",
                          lambda st: st.lead_s if st.lead_s is not None and st.state in RUNNING else 0),
          prometheus=PromGauge("lead_seconds", "the planner's lead the hook is judged against "
                               "(METHOD.md §5b)", doc="the planner's lead the running test's hook is "
                               "judged against (§5b `lead`)"),
          label="lead"),
    Value("p_due", "float|null", "", "the bound P is held against (§5b `p_due`)", lambda st: st.p_due,
          label="p_due"),
    Value("test_started_utc", "str|null", "", "UTC time of the test's slot 0, ISO 8601",
          lambda st: st.test_started_utc,
          sparkplug=_sp("Test/Started", 47, "DateTime", "ms", "UTC time of the test's slot 0 (ms since "
                        "the epoch): the forecast's times are seconds from it"),
          label="test started (UTC)"),
    Value("warning_alarm", "str", "", "wear-warning alarm (priority 2), ISA-18.2 state: "
          + ", ".join(ALARM_STATES), lambda st: st.warning_alarm, choices=ALARM_STATES,
          plc=PlcRegister("warning_alarm", "wear", "enum", "", "wear-warning alarm (priority 2, below "
                          "the end of life): " + _ALARM_ENUM),
          label="wear-warning alarm"),
    Value("meter_ok", "bool", "", "the tension meter answers", lambda st: bool(st.meter_ok),
          sparkplug=_sp("Status/Meter OK", 16, "Boolean", description="Modbus RTU link to the tension meter"),
          plc_bit=PlcBit(5, "meter_ok", "the tension meter answers"),
          label="meter answers"),
    Value("stm32_ok", "bool", "", "the motor controller answers", lambda st: bool(st.stm32_ok),
          sparkplug=_sp("Status/STM32 OK", 17, "Boolean", description="serial link to the motor controller"),
          plc_bit=PlcBit(6, "stm32_ok", "the motor controller answers"),
          label="STM32 answers"),
    Value("disk_ok", "bool", "", "the test records and the MQTT outbox can be written (false: a full "
          "or read-only disk; see the disk_full event)", lambda st: bool(st.disk_ok),
          plc_bit=PlcBit(13, "disk_ok", "the test records and the MQTT outbox can be written (0: a full "
                         "or read-only disk; the station runs on, see docs/limits.md)"),
          prometheus=PromGauge("disk_ok", "1 when the test records and the MQTT outbox can be written "
                               "(0: a full or read-only disk)", doc="1 when the test records and the MQTT "
                               "outbox can be written; 0 on a full or read-only disk (the station runs "
                               "on; `disk_full`/`disk_ok` events, PLC status bit `disk_ok`; "
                               "docs/limits.md)"),
          label="disk writable"),
    # values of the state that are not keys of the MQTT `state` (derived for the other doors)
    Value("test_running", "bool", "", "a test is running (baseline search, monitoring or end of life)",
          lambda st: st.state in RUNNING, mqtt=False,
          prometheus=PromGauge("test_running", "1 while a test runs", doc="1 while a test runs "
                               "(baseline search, monitoring, end of life); 0 during `starting` (METHOD.md "
                               "§3a: zero check and spin-up before slot 0, no test id yet, nothing "
                               "recorded, may still end in `start_failed`)")),
    _end_left(10, lambda st: st.end_p10),
    _end_left(50, lambda st: st.end_p50),
    _end_left(90, lambda st: st.end_p90),
)


# ------------------------------------------------------------------ the values of the slot records
#: a window's figure: a reading, or an object of readings (MQTT telemetry's `tension`, `counts`)
Figure = Reading | dict[str, Reading]
#: a figure of a window of slot records (gateway/core/slotwindow.py)
WindowSource = Callable[["SlotWindow"], Figure]
#: a figure of one slot record (the latest)
SlotSource = Callable[[SlotRecord], Reading]


@dataclass(frozen=True)
class SlotValue:
    """One published value of the slot records (a row of :data:`SLOT_CATALOG`): a figure of a
    window of slots (an MQTT telemetry interval, a Sparkplug data interval) and, for the PLC, of
    the latest slot or of the running test's window.

    ``window`` is the figure MQTT telemetry carries under ``name`` (None: not in telemetry);
    ``sparkplug_window`` Sparkplug's own reading of the interval (None: ``window``'s). The PLC
    register reads ``latest`` of the latest slot record, or ``plc_test`` of the test's window
    (neither: the PLC output fills it itself, e.g. μ of the latest valid slot within a second)."""
    name: str                  # its key in MQTT telemetry (and its name in the catalog)
    type: str                  # the MQTT schema's type (TYPES or "object")
    unit: str
    doc: str                   # docs/mqtt.md's telemetry table
    window: WindowSource | None
    in_test: bool = False      # telemetry: null outside a test
    sparkplug: SparkplugMetric | None = None
    sparkplug_window: WindowSource | None = None
    plc: PlcRegister | None = None
    latest: SlotSource | None = None
    plc_test: WindowSource | None = None
    #: the window keeps the mean of this reading over its slots (gateway/core/slotwindow.py
    #: ``SlotWindow.means``): a channel's row (:func:`channel`)
    mean: SlotSource | None = None
    #: a Prometheus gauge of the latest slot's reading (``latest``)
    prometheus: PromGauge | None = None
    #: the console's label of the latest slot's reading (``latest``; "": not shown)
    label: str = ""

    @property
    def base_type(self) -> str:
        return self.type.split("|")[0]


def _r(x: float | None) -> float | None:
    """Telemetry's rounding (6 decimals)."""
    return None if x is None else round(x, 6)


def _tension(w: SlotWindow) -> Figure:
    nr = w.n_read
    return {"mean": _r(w.sm / nr) if nr else None, "min": _r(w.mn) if nr else None,
            "max": _r(w.mx) if nr else None}


def _latest(read: Callable[[SlotRecord], float]) -> SlotSource:
    """A reading of the latest slot record: NaN when the slot has no meter reading."""
    return lambda rec: read(rec) if rec.present else math.nan


def _slot_sp(name: str, alias: int, datatype: str, units: str = "", description: str = "",
             window: WindowSource | None = None) -> tuple[SparkplugMetric, WindowSource | None]:
    return SparkplugMetric(name, alias, datatype, units, description), window


def _row(name: str, type_: str, unit: str, doc: str, window: WindowSource | None, *,
         in_test: bool = False, sp: tuple[SparkplugMetric, WindowSource | None] | None = None,
         plc: PlcRegister | None = None, latest: SlotSource | None = None,
         test: WindowSource | None = None) -> SlotValue:
    return SlotValue(name, type_, unit, doc, window, in_test, sp[0] if sp else None,
                     sp[1] if sp else None, plc, latest, test)


#: every published value of the slot records, in the order of MQTT telemetry (append new rows at
#: the end: a new Sparkplug alias takes the next free index, a new PLC register goes to a block
#: with reserved space, e.g. "more")
SLOT_CATALOG: tuple[SlotValue, ...] = (
    _row("slots", "int", "slots", "slots in the interval", lambda w: w.n,
         plc=PlcRegister("slots", "live", "uint32", "slots", "slots of the current / last test"),
         test=lambda w: w.n),
    _row("t1", "float|null", "N", "mean T1 (inlet tension), N, over slots with a reading",
         lambda w: _r(w.t1_mean),
         sp=_slot_sp("Tension/T1", 18, "Float", "N", "inlet tension, interval mean", lambda w: w.t1_mean),
         plc=PlcRegister("t1", "live", "float32", "N", "inlet tension T1 of the latest slot (NaN "
                         "without a reading)"), latest=_latest(lambda rec: rec.t1)),
    _row("t2", "float|null", "N", "mean T2 (outlet tension), N", lambda w: _r(w.t2_mean),
         sp=_slot_sp("Tension/T2", 19, "Float", "N", "outlet tension, interval mean", lambda w: w.t2_mean),
         plc=PlcRegister("t2", "live", "float32", "N", "outlet tension T2 of the latest slot"),
         latest=_latest(lambda rec: rec.t2)),
    _row("tension", "object", "N", "mean tension (T1+T2)/2 per slot: {mean, min, max}, N (null "
         "without readings)", _tension,
         sp=_slot_sp("Tension/Mean", 20, "Float", "N", "(T1+T2)/2, interval mean",
                     lambda w: (w.s1 + w.s2) / (2 * w.n_read) if w.n_read else None),
         plc=PlcRegister("tension", "live", "float32", "N", "mean tension (T1+T2)/2 of the latest slot"),
         latest=_latest(lambda rec: (rec.t1 + rec.t2) * 0.5)),
    _row("mu", "float|null", "", "mean μ of the valid slots of the interval (null if none)",
         lambda w: _r(w.mu_mean),
         sp=_slot_sp("Friction/mu", 21, "Double", "", "capstan μ = ln(T2/T1)/θ over valid slots, "
                     "interval mean", lambda w: w.mu_mean),
         plc=PlcRegister("mu", "live", "float32", "", "μ of the latest valid slot within the last "
                         "second (NaN if none)")),
    _row("valid_ratio", "float|null", "", "valid slots / slots in the interval (null outside a test)",
         lambda w: w.valid_ratio, in_test=True,
         sp=_slot_sp("Quality/Valid Ratio", 22, "Double", "", "valid slots / slots in the interval",
                     lambda w: w.valid_ratio),
         plc=PlcRegister("valid_ratio", "live", "float32", "", "valid slots / slots of the current / "
                         "last test (NaN outside)"),
         test=lambda w: w.n_valid / w.n if w.n else math.nan),
    _row("counts", "object", "slots", "slots per reason in the interval: {"
         + ", ".join(REASON_NAMES) + "}", lambda w: dict(w.reason_counts())),
    _row("speed_cmd", "float", "rpm", "speed command at the end of the interval, rpm",
         lambda w: w.speed_cmd, sp=_slot_sp("Control/Speed Command", 23, "Float", "rpm"),
         plc=PlcRegister("speed_cmd", "live", "float32", "rpm", "speed command of the latest slot"),
         latest=lambda rec: rec.speed_cmd),
    _row("speed_act", "float|null", "rpm", "actual speed reported by the STM32, rpm",
         lambda w: w.speed_act, sp=_slot_sp("Control/Speed Actual", 24, "Float", "rpm"),
         plc=PlcRegister("speed_act", "live", "float32", "rpm", "actual speed reported by the STM32 "
                         "(NaN if unknown)"), latest=lambda rec: rec.speed_act),
    _row("saturated_slots", "int", "slots", "slots in which the control output was clamped",
         lambda w: w.n_sat),
    _row("saturation", "bool", "", "the control output was clamped at least once in the interval",
         lambda w: w.n_sat > 0,
         sp=_slot_sp("Control/Saturation", 25, "Boolean", description="control output clamped in "
                     "the interval")),
    _row("valid_slots", "int", "slots", "valid slots of the current / last test", None,
         plc=PlcRegister("valid_slots", "live", "uint32", "slots", "valid slots of the current / last "
                         "test"), test=lambda w: w.n_valid),
)


def channel(name: str, unit: str, doc: str, read: SlotSource, sparkplug: SparkplugMetric | None = None,
            plc: PlcRegister | None = None, prometheus: PromGauge | None = None,
            label: str = "") -> SlotValue:
    """The row of a value read from each slot record (a meter channel, a figure of the slot):
    MQTT telemetry and Sparkplug carry its interval mean over the slots where it is a number (the
    window keeps it: ``mean``); the PLC register, the Prometheus gauge and the console its latest
    slot's reading. A third meter channel is its record field and one such row, appended to
    :data:`SLOT_CATALOG`."""
    return SlotValue(name, "float|null", unit, doc, lambda w: _r(w.mean(read)), sparkplug=sparkplug,
                     sparkplug_window=lambda w: w.mean(read), plc=plc, latest=read, mean=read,
                     prometheus=prometheus, label=label)


def means(slots: tuple[SlotValue, ...]) -> tuple[SlotSource, ...]:
    """The readings whose mean a window of slots keeps for ``slots`` (their rows with a ``mean``)."""
    return tuple(s.mean for s in slots if s.mean is not None)


#: the readings every window keeps the mean of (none of the rows above: their windows' own sums)
MEANS = means(SLOT_CATALOG)


def problems(values: tuple[Value, ...], slots: tuple[SlotValue, ...] = ()) -> list[str]:
    """What breaks the catalog's rules (empty: none): a name, an MQTT key, a Sparkplug name or
    alias, a PLC register or a Prometheus name used twice (among the state's rows and the slot
    records' rows together); an unknown type; an enumeration without its choices."""
    out: list[str] = []

    def once(what: str, keys: Sequence[object]) -> None:
        seen: set[object] = set()
        for k in keys:
            if k in seen:
                out.append(f"{what} {k!r} twice")
            seen.add(k)

    once("name", [v.name for v in values] + [v.name for v in slots])
    sps: list[SparkplugMetric] = [v.sparkplug for v in values if v.sparkplug]
    sps += [s.sparkplug for s in slots if s.sparkplug]
    once("Sparkplug metric", [sp.name for sp in sps])
    once("Sparkplug alias", [sp.alias for sp in sps])
    once("PLC register", [v.plc.name for v in values if v.plc] + [v.plc.name for v in slots if v.plc])
    once("Prometheus gauge", [v.prometheus.name for v in values if v.prometheus]
         + [v.prometheus.name for v in slots if v.prometheus])
    once("PLC status bit", [v.plc_bit.bit for v in values if v.plc_bit])
    for v in values:
        if v.base_type not in TYPES:
            out.append(f"{v.name}: type {v.type!r} is not one of {TYPES}")
        if v.sparkplug and v.sparkplug.datatype not in SPARKPLUG_TYPES:
            out.append(f"{v.name}: Sparkplug datatype {v.sparkplug.datatype!r}")
        if v.plc and v.plc.type not in PLC_TYPES:
            out.append(f"{v.name}: PLC type {v.plc.type!r}")
        if v.plc and v.plc.type in ("enum", "bits") and not v.choices:
            out.append(f"{v.name}: a PLC {v.plc.type} register needs the value's choices")
        if v.plc_bit and (v.base_type != "bool" or not 0 <= v.plc_bit.bit <= 15):
            out.append(f"{v.name}: a PLC status bit is a flag's, bit 0 … 15")
        if v.prometheus and v.prometheus.label and not v.choices:
            out.append(f"{v.name}: a labelled Prometheus gauge needs the value's choices")
    for s in slots:
        if s.base_type not in TYPES + ("object",):
            out.append(f"{s.name}: type {s.type!r} is not one of {TYPES + ('object',)}")
        if s.sparkplug and s.sparkplug.datatype not in SPARKPLUG_TYPES:
            out.append(f"{s.name}: Sparkplug datatype {s.sparkplug.datatype!r}")
        if s.sparkplug and s.window is None and s.sparkplug_window is None:
            out.append(f"{s.name}: a Sparkplug metric needs a window source")
        if s.plc and s.plc.type not in ("uint16", "uint32", "float32"):
            out.append(f"{s.name}: PLC type {s.plc.type!r} (a slot value is a number)")
        if s.latest and s.plc_test:
            out.append(f"{s.name}: a PLC register reads the latest slot or the test's window, not both")
        if (s.prometheus or s.label) and s.latest is None:
            out.append(f"{s.name}: a Prometheus gauge or a console label reads the latest slot (``latest``)")
        if s.prometheus and s.prometheus.label:
            out.append(f"{s.name}: a slot value's Prometheus gauge is a number, not labelled")
    return out


def check(values: tuple[Value, ...], slots: tuple[SlotValue, ...] = ()) -> tuple[Value, ...]:
    """``values`` when they (with the slot records' rows ``slots``) keep the catalog's rules, else
    ValueError (at import: a broken row never reaches a door)."""
    bad = problems(values, slots)
    if bad:
        raise ValueError("catalog of published values: " + "; ".join(bad))
    return values


check(CATALOG, SLOT_CATALOG)
BY_NAME = {v.name: v for v in CATALOG}
SLOT_BY_NAME = {v.name: v for v in SLOT_CATALOG}


def read_window(slots: tuple[SlotValue, ...], w: SlotWindow, in_test: bool = True) -> dict[str, Figure]:
    """MQTT telemetry's figures of the window ``w``: every row with a window source (a row that is
    null outside a test: None when not ``in_test``)."""
    return {s.name: (s.window(w) if in_test or not s.in_test else None)
            for s in slots if s.window is not None}


def read_latest(slots: tuple[SlotValue, ...], rec: SlotRecord | None) -> dict[str, Reading]:
    """The latest slot's reading of every row of ``slots`` with one (None before a slot)."""
    return {s.name: (s.latest(rec) if rec is not None else None) for s in slots if s.latest is not None}


def read_sparkplug(slots: tuple[SlotValue, ...], w: SlotWindow) -> dict[str, Figure]:
    """A Sparkplug data interval's metrics of the window ``w``, by metric name."""
    out: dict[str, Figure] = {}
    for s in slots:
        if s.sparkplug is not None:
            f = s.sparkplug_window or s.window
            assert f is not None
            out[s.sparkplug.name] = f(w)
    return out


def read(values: tuple[Value, ...], st: StationState) -> dict[str, Reading]:
    """Every value of ``values`` as its source reads ``st``."""
    return {v.name: v.source(st) for v in values}


def plc_number(v: Value, st: StationState) -> Reading:
    """The value as its PLC register holds it: an enumeration's number (its index in the
    choices, 0 when unknown), a list's bits (bit i: the i-th choice), else the reading."""
    assert v.plc is not None
    x = (v.plc.source or v.source)(st)
    if v.plc.type == "enum":
        return v.choices.index(x) if isinstance(x, str) and x in v.choices else 0
    if v.plc.type == "bits":
        items = x if isinstance(x, list) else []
        return sum(1 << v.choices.index(r) for r in items if r in v.choices)
    return x
