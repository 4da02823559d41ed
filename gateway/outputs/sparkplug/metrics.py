"""The ONE definition of the Sparkplug metrics of an edge node and of a station (device).

Names, Sparkplug datatypes, engineering units and descriptions; the aliases are derived from it
(stable across restarts, so that data stored before a restart still means the same after it).
Values come from the station's records, events and state (see :mod:`.output`).
"""
from __future__ import annotations

import enum
import zlib
from dataclasses import dataclass

from ...core import catalog


class DataType(enum.IntEnum):
    """Sparkplug B datatypes (the index table of sparkplug_b.proto)."""
    Int8 = 1
    Int16 = 2
    Int32 = 3
    Int64 = 4
    UInt8 = 5
    UInt16 = 6
    UInt32 = 7
    UInt64 = 8
    Float = 9
    Double = 10
    Boolean = 11
    String = 12
    DateTime = 13
    Text = 14


@dataclass(frozen=True)
class MetricDef:
    name: str
    datatype: DataType
    units: str = ""
    description: str = ""
    writable: bool = False        # a command the host may write (DCMD / NCMD)
    telemetry: bool = False       # a periodic measurement (its history may be trimmed over budget)


# ------------------------------------------------------------------------------ node (NBIRTH)
BDSEQ = "bdSeq"
REBIRTH = "Node Control/Rebirth"
NEXT_SERVER = "Node Control/Next Server"
REBOOT = "Node Control/Reboot"

NODE_METRICS: tuple[MetricDef, ...] = (
    MetricDef(BDSEQ, DataType.Int64, description="birth/death sequence of this MQTT session"),
    MetricDef(REBIRTH, DataType.Boolean, description="write true: publish NBIRTH and every DBIRTH again",
              writable=True),
    MetricDef(NEXT_SERVER, DataType.Boolean, description="write true: NDEATH, disconnect, connect to the "
              "next configured server (the same one when only one is configured)", writable=True),
    MetricDef(REBOOT, DataType.Boolean, description="write true: restart the Sparkplug session (NDEATH, "
              "new connection, new bdSeq, births); the box, the stations and their tests are NOT "
              "restarted", writable=True),
    MetricDef("Properties/Software", DataType.String, description="gateway software and version"),
    MetricDef("Properties/Devices", DataType.Int32, description="stations (devices) hosted by this node"),
)

# ------------------------------------------------------------------------------ device (DBIRTH)
START = "Device Control/Start Test"
STOP = "Device Control/Stop Test"
ACK = "Device Control/Acknowledge Alarm"
HOOK_REPLACED = "Device Control/Hook Replaced"
OUT_OF_SERVICE = "Device Control/Alarms Out Of Service"
IN_SERVICE = "Device Control/Alarms In Service"
SHELVE = "Device Control/Shelve Alarm"
UNSHELVE = "Device Control/Unshelve Alarm"
ARG_SAMPLE_ID = "Device Control/Sample ID"
ARG_GRADE = "Device Control/Grade"
ARG_T_SET = "Device Control/Setpoint"
ARG_T_END = "Device Control/Planned End"
ARG_ALARM = "Device Control/Alarm"
ARG_DURATION = "Device Control/Shelve Duration"
ARG_REQUEST_ID = "Device Control/Request ID"
ARG_TEST_ID = "Device Control/Test ID"

def _metric_of(value: str) -> str:
    """The Sparkplug name of the catalog's row ``value`` (gateway/core/catalog.py)."""
    sp = catalog.BY_NAME[value].sparkplug
    assert sp is not None
    return sp.name


#: the forecast's metrics (METHOD.md §5a, §5b, §7a): the catalog's rows, by their Sparkplug names
FC_STARTED = _metric_of("test_started_utc")
FC_P10 = _metric_of("end_p10")
FC_P50 = _metric_of("end_p50")
FC_P90 = _metric_of("end_p90")
FC_P_END = _metric_of("p_end")
FC_DUE = _metric_of("due")
FC_HEADROOM = _metric_of("headroom")
FC_T_CROSS = _metric_of("t_cross")
FC_WARNING = _metric_of("wear_warning")
FC_REASONS = _metric_of("warn_reasons")
FC_PRIOR_MEAN = _metric_of("prior_mean")
FC_PRIOR_SD = _metric_of("prior_sd")
FC_PRIOR_SOURCE = _metric_of("prior_source")
FC_LEAD = _metric_of("lead_s")

#: the station's alarms as Sparkplug metric folders: ISA-18.2 name (gateway.core.alarms.ALARMS) → folder
ALARM_FOLDERS = {"end_of_life": "Alarm/End Of Life", "wear_warning": "Alarm/Wear Warning"}

#: DCMD metric → command kind (gateway.core.records.CommandKind value)
COMMANDS = {START: "start", STOP: "stop", ACK: "ack", HOOK_REPLACED: "hook_replaced",
            OUT_OF_SERVICE: "out_of_service", IN_SERVICE: "in_service", SHELVE: "shelve",
            UNSHELVE: "unshelve"}
#: DCMD argument metric → key of the command's arguments (gateway.station.command_desk.COMMAND_KEYS)
COMMAND_ARGS = {ARG_SAMPLE_ID: "sample_id", ARG_GRADE: "grade", ARG_T_SET: "t_set", ARG_T_END: "t_end",
                ARG_ALARM: "alarm", ARG_DURATION: "duration_s", ARG_REQUEST_ID: "request_id",
                ARG_TEST_ID: "test_id"}


def _alarm_metrics(name: str, what: str) -> tuple[MetricDef, ...]:
    """State, Active, Priority of one alarm (the same for each; Shelved Until is appended later)."""
    folder = ALARM_FOLDERS[name]
    return (
        MetricDef(f"{folder}/State", DataType.String, description=f"{what} alarm, ISA-18.2: normal | "
                  "unacknowledged | acknowledged | rtn_unacknowledged | shelved | out_of_service "
                  "(gateway/core/alarms.py)"),
        MetricDef(f"{folder}/Active", DataType.Boolean, description="the alarm is standing (annunciated)"),
        MetricDef(f"{folder}/Priority", DataType.Int32, description="ISA-18.2 priority, 1 critical … 4 low"),
    )


def _shelved_metric(name: str) -> MetricDef:
    return MetricDef(f"{ALARM_FOLDERS[name]}/Shelved Until", DataType.DateTime, "ms",
                     "UTC time (ms since the epoch) the shelving expires; null unless shelved")

def _at(index: int, defs: tuple[MetricDef, ...]) -> dict[int, MetricDef]:
    return {index + i: d for i, d in enumerate(defs)}


#: the device's own metrics, each at its fixed alias index: the alarms' folders (from the station's
#: alarm store) and the controls; the metrics that follow the station's state and the data
#: interval's figures (from the slot records) are the catalog's rows (gateway/core/catalog.py
#: CATALOG and SLOT_CATALOG), each at the alias index its row names. Aliases are base + index: an
#: index is never reused or changed (data stored before a restart keeps its meaning), a new metric
#: takes the next free one.
DEVICE_OWN: dict[int, MetricDef] = {
    **_at(12, _alarm_metrics("end_of_life", "end-of-life")),
    **_at(26, (
        MetricDef("Device Control/Last Command", DataType.String,
                  description="the last command received over DCMD and its outcome"),
        MetricDef("Device Control/Last Result Code", DataType.Int32,
                  description="0 accepted, else the rejection code (docs/mqtt.md)"),
        MetricDef(START, DataType.Boolean, description="write true (with the argument metrics) to "
                  "start a test", writable=True),
        MetricDef(STOP, DataType.Boolean, description="write true to stop the running test (with "
                  "`Device Control/Test ID`: that test only)", writable=True),
        MetricDef(ACK, DataType.Boolean, description="write true to acknowledge the unacknowledged "
                  "alarms (end of life and wear warning)", writable=True),
        MetricDef(HOOK_REPLACED, DataType.Boolean, description="write true once the worn hook is "
                  "replaced (optional `Device Control/Sample ID` / `Grade`: the new hook's; the "
                  "running test ends, the replacement is logged)", writable=True),
        MetricDef(ARG_SAMPLE_ID, DataType.String, description="start and hook-replaced argument: "
                  "sample ID", writable=True),
        MetricDef(ARG_GRADE, DataType.String, description="start and hook-replaced argument: needle "
                  "grade", writable=True),
        MetricDef(ARG_T_SET, DataType.Float, "N", "start argument: setpoint", writable=True),
        MetricDef(ARG_T_END, DataType.Double, "s", "start argument: planned duration", writable=True),
        MetricDef(OUT_OF_SERVICE, DataType.Boolean, description="write true to take the alarms out of "
                  "service (ISA-18.2) while a needle is being changed", writable=True),
        MetricDef(IN_SERVICE, DataType.Boolean, description="write true to return the alarms to "
                  "service", writable=True),
    )),
    **_at(38, (
        *_alarm_metrics("wear_warning", "wear-warning (§5a early warning)"),
        _shelved_metric("end_of_life"),
        _shelved_metric("wear_warning"),
        MetricDef(SHELVE, DataType.Boolean, description="write true (with `Device Control/Alarm` and "
                  "`Device Control/Shelve Duration`) to shelve one annunciated alarm (ISA-18.2)",
                  writable=True),
        MetricDef(UNSHELVE, DataType.Boolean, description="write true (with `Device Control/Alarm`) "
                  "to end the shelving of one alarm", writable=True),
        MetricDef(ARG_ALARM, DataType.String, description="shelve / unshelve argument: `end_of_life` "
                  "or `wear_warning`", writable=True),
        MetricDef(ARG_DURATION, DataType.Double, "s", "shelve argument: how long, (0, 43200] s",
                  writable=True),
    )),
    **_at(61, (
        MetricDef(ARG_REQUEST_ID, DataType.String, description="any command's argument: the host's "
                  "id of the request (1–64 printable ASCII); a DCMD repeated with the same id within "
                  "600 s is answered again and not carried out again (docs/limits.md)", writable=True),
        MetricDef(ARG_TEST_ID, DataType.String, description="stop argument: the test to stop (its "
                  "`Test/ID`); a stop naming a test that is not the running one is refused (15 "
                  "WRONG_TEST) and stops nothing", writable=True),
    )),
}


def state_metric(v: catalog.Value) -> MetricDef:
    """The device metric of a catalog row (its Sparkplug name, datatype, units, description)."""
    sp = v.sparkplug
    assert sp is not None
    return MetricDef(sp.name, DataType[sp.datatype], sp.units, sp.description)


def slot_metric(v: catalog.SlotValue) -> MetricDef:
    """The device metric of a slot records' row: a periodic measurement (``telemetry``)."""
    sp = v.sparkplug
    assert sp is not None
    return MetricDef(sp.name, DataType[sp.datatype], sp.units, sp.description, telemetry=True)


def device_metrics(values: tuple[catalog.Value, ...] = catalog.CATALOG,
                   slots: tuple[catalog.SlotValue, ...] = catalog.SLOT_CATALOG) -> tuple[MetricDef, ...]:
    """A device's metrics in alias order: :data:`DEVICE_OWN` and the catalog's rows (the state's
    and the slot records'), each at its index. A row on an index already taken, or a gap, fails
    here (at import)."""
    by_index = dict(DEVICE_OWN)
    rows = [(v.name, v.sparkplug, state_metric(v)) for v in values if v.sparkplug is not None]
    rows += [(s.name, s.sparkplug, slot_metric(s)) for s in slots if s.sparkplug is not None]
    for name, sp, metric in rows:
        if sp.alias in by_index:
            raise ValueError(f"Sparkplug alias index {sp.alias} of {name} is taken by "
                             f"{by_index[sp.alias].name}: a new metric takes the next free one "
                             f"({max(by_index) + 1})")
        by_index[sp.alias] = metric
    if sorted(by_index) != list(range(len(by_index))):
        missing = sorted(set(range(max(by_index) + 1)) - set(by_index))
        raise ValueError(f"Sparkplug device metrics: no metric at alias index {missing}")
    return tuple(by_index[i] for i in range(len(by_index)))


#: the catalog's rows a device publishes (its state's metrics), and their metrics by the rows' names
STATE_VALUES = tuple(v for v in catalog.CATALOG if v.sparkplug is not None)
STATE_METRIC = {v.name: _metric_of(v.name) for v in STATE_VALUES}
DEVICE_METRICS: tuple[MetricDef, ...] = device_metrics()
NODE_BY_NAME = {m.name: m for m in NODE_METRICS}
DEVICE_BY_NAME = {m.name: m for m in DEVICE_METRICS}


def node_aliases() -> dict[str, int]:
    """Node metrics: aliases 1 … n, except bdSeq (the Will carries it by name) and
    Node Control/Rebirth (tck-id-operational-behavior-data-commands-rebirth-name-aliases)."""
    return {m.name: i for i, m in enumerate(NODE_METRICS) if m.name not in (BDSEQ, REBIRTH)}


def device_alias_base(device_id: str) -> int:
    """Aliases of a device's metrics are base + index: base from the device ID (stable across
    restarts and start orders), above every node alias; unique in the node (checked there)."""
    return (zlib.crc32(device_id.encode("utf-8")) + 1) << 12
