"""The station configuration: ONE declarative definition of every key.

Each section is a frozen dataclass; each key is a field whose metadata (:func:`key`) holds its
kind, default, unit, allowed values and one line of documentation. The loader
(:mod:`gateway.config.loader`) validates and fills defaults from these definitions, and
``docs/configuration.md`` is generated from them (:mod:`gateway.config.docs`). Two sections come
from definitions that live elsewhere and are not repeated here:

- ``method:`` — the method's parameters, :data:`gateway.core.method.params.PARAMS` (names, defaults,
  units, ranges, checked by ``build_params``), except ``t_set``/``t_end`` which come from ``test:``;
- ``control:`` — the fields of :class:`gateway.core.control.ControlParams` (except ``ts``, which is the
  method's) and ``control.notch:`` those of :class:`gateway.core.control.NotchParams`; their types
  come from the dataclass defaults, their units, ranges and docs from :data:`CONTROL_KEYS`.

Rules that relate several keys are :data:`RULES` (each with the sentence the docs print).
"""
from __future__ import annotations

import dataclasses
import ipaddress
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from typing import Any

from drivers.stm32.protocol import watchdog_for

from ..core.command_rules import COMMAND_DOORS_MAX, door_problem
from ..core.control import ControlParams, NotchParams
from ..core.method.params import MAX_TENSION, TEN_YEARS
from ..core.method.params import PARAMS as METHOD_PARAMS
from ..core.method.prior import PriorEntry, same_t_set
from ..core.validation import show_yaml

# ---------------------------------------------------------------------------------------------
# key kinds


class _Required:
    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED: Any = _Required()

#: serial line rates a USB–RS-485 adapter and the ZN-S / STM32 accept
BAUDS: tuple[int, ...] = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600)
#: the ZN-S meter's rates (drivers/meter/meter_map.py accepts these)
METER_BAUDS: tuple[int, ...] = BAUDS[:9]

IDENT_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
ENV_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
TOPIC_RE = re.compile(r"^[^/+#\s]+(/[^/+#\s]+)*$")

KINDS = ("str", "ident", "topic", "envvar", "path", "port", "int", "float", "bool", "enum",
         "str_list", "ip_list", "prior_list")


@dataclass(frozen=True)
class Key:
    """One configuration key: how it is checked, its default and its documentation."""
    name: str
    kind: str
    default: Any = REQUIRED
    doc: str = ""
    unit: str = ""
    lo: float | None = None           # lower bound (inclusive unless lo_open)
    hi: float | None = None           # upper bound (inclusive unless hi_open)
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple | None = None
    nullable: bool = False
    null_means: str = ""              # what null (the default None) stands for
    example: Any = None

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    def allowed(self) -> str:
        """What the key accepts, as the docs and the error messages say it."""
        k = self.kind
        if self.choices is not None:
            s = "one of " + ", ".join(_show(c) for c in self.choices)
        elif k in ("int", "float"):
            s = ("an integer" if k == "int" else "a number") + _range_text(self)
        elif k == "bool":
            s = "true or false"
        elif k == "ident":
            s = "a name of letters, digits, '-', '_' and '.' (at most 64, not starting with '-', '_' or '.')"
        elif k == "topic":
            s = "an MQTT topic prefix without '+', '#', spaces or empty levels"
        elif k == "envvar":
            s = "the name of an environment variable"
        elif k == "path":
            s = "a file path (relative paths are relative to the folder of the file that sets it)"
        elif k == "port":
            s = "a serial device path, e.g. /dev/hookwatch/loom-01-meter or /dev/ttyUSB0"
        elif k == "str_list":
            s = "a list of strings"
        elif k == "ip_list":
            s = "a list of IP addresses or networks, e.g. [10.10.4.20, 10.10.5.0/24]"
        elif k == "prior_list":
            s = ("a list of {grade, t_set_n, mean_s, sd_s[, n, n_censored, n_early]}, e.g. "
                 "[{grade: I, t_set_n: 0.5, mean_s: 32306.9, sd_s: 951.7}] (0 < t_set_n ≤ "
                 f"{MAX_TENSION:g} N; 0 < mean_s, sd_s ≤ {TEN_YEARS:.0f} s, 10 years; "
                 f"1 ≤ n ≤ {MAX_PRIOR_N}; 0 ≤ n_censored, n_early ≤ {MAX_PRIOR_N})")
        else:
            s = "a string"
        if self.nullable:
            s += ", or null"
        return s


def _range_text(k: Key) -> str:
    if k.lo is not None and k.hi is not None:
        if not k.lo_open and not k.hi_open:
            return f" from {_num(k.lo)} to {_num(k.hi)}"
        return f" {'>' if k.lo_open else '≥'} {_num(k.lo)} and {'<' if k.hi_open else '≤'} {_num(k.hi)}"
    if k.lo is not None:
        return f" {'>' if k.lo_open else '≥'} {_num(k.lo)}"
    if k.hi is not None:
        return f" {'<' if k.hi_open else '≤'} {_num(k.hi)}"
    return ""


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


#: a value as written in YAML, and a bad value in a message: one definition (gateway.core.validation)
_show = show_yaml


def key(default: Any = REQUIRED, doc: str = "", *, kind: str, **kw: Any):
    """A dataclass field that is a configuration key (the name is the field's name)."""
    assert kind in KINDS, kind
    spec = dict(kind=kind, default=default, doc=doc, **kw)
    if default is REQUIRED:
        return field(metadata={"key": spec})
    return field(default=default, metadata={"key": spec})


def section(cls: type, doc: str, *, default: bool = True):
    """A dataclass field that is a nested section."""
    meta = {"section": cls, "doc": doc}
    if default:
        return field(default_factory=cls, metadata=meta)
    return field(metadata=meta)


# ---------------------------------------------------------------------------------------------
# the sections


@dataclass(frozen=True, kw_only=True)
class StationInfo:
    id: str = key(doc="the station's name: unique in the fleet; it names the records folder, "
                  "the MQTT topics and the systemd instance (`hookwatch@<id>`); by convention the "
                  "station file is `stations/<id>.yaml`", kind="ident", example="loom-01")
    site: str = key("", "plant or site, reported north with every result", kind="str", example="plant-a")
    area: str = key("", "hall or area within the site", kind="str", example="hall-2")
    line: str = key("", "production line or machine", kind="str", example="line-3")


@dataclass(frozen=True, kw_only=True)
class Rs485Config:
    enabled: bool = key(False, "put the meter's port into the kernel's RS-485 mode (TIOCSRS485): the "
                        "UART driver switches the transceiver's direction with RTS around each request. "
                        "Only for a board UART wired to an RS-485 transceiver (e.g. a Raspberry Pi or "
                        "i.MX UART); a USB–RS-485 adapter switches direction itself — leave this off",
                        kind="bool")
    rts_on_send: str = key("high", "RTS level while sending (the transceiver's DE is usually active "
                           "high)", kind="enum", choices=("high", "low"))
    rts_after_send: str = key("low", "RTS level after sending (receiving)", kind="enum",
                              choices=("high", "low"))
    delay_before_send_s: float = key(0.0, "RTS raised this long before the first bit", kind="float",
                                     unit="s", lo=0.0, hi=0.1)
    delay_after_send_s: float = key(0.0, "RTS kept this long after the last bit", kind="float",
                                    unit="s", lo=0.0, hi=0.1)


@dataclass(frozen=True, kw_only=True)
class MeterConfig:
    port: str = key(doc="serial port of the USB–RS-485 adapter on the ZN-S tension meter's bus",
                    kind="port", example="/dev/hookwatch/loom-01-meter")
    map: str | None = key(None, "register map of the meter (`config/meters/*.yaml`)", kind="path",
                          nullable=True, null_means="the packaged ZN-S map, config/meters/zn-s.yaml")
    baud: int | None = key(None, "line rate of the meter's bus; it sets the wire time of every poll "
                           "(`hookwatch check` says whether 50 Hz fits)", kind="int", unit="bit/s",
                           choices=METER_BAUDS, nullable=True, null_means="the map's baud")
    unit_id: int | None = key(None, "Modbus RTU address of the meter", kind="int", lo=1, hi=247,
                              nullable=True, null_means="the map's unit ID")
    parity: str | None = key(None, "parity of the meter's bus (N none, E even, O odd)", kind="enum",
                             choices=("N", "E", "O"), nullable=True, null_means="the map's parity")
    timeout_s: float = key(0.015, "a poll without a complete reply after this long counts as a "
                           "missing reading (the slot goes on without it)", kind="float", unit="s",
                           lo=0.0, hi=1.0, lo_open=True)
    swap_channels: bool = key(False, "true when the meter's channel 1 is the outgoing (T2) side, "
                              "i.e. the yarn runs through the meter the other way round", kind="bool")
    local_echo: bool = key(False, "the adapter hears its own transmission on the 2-wire bus (echo "
                           "on, or a transceiver whose receiver stays enabled): the echo of each "
                           "request is checked and discarded before the reply", kind="bool")
    rs485: Rs485Config = section(Rs485Config, "the kernel's RS-485 mode, for a board UART")


@dataclass(frozen=True, kw_only=True)
class Stm32Config:
    port: str = key(doc="serial port of the STM32 take-up motor controller", kind="port",
                    example="/dev/hookwatch/loom-01-stm32")
    baud: int = key(115200, "line rate of the STM32 link", kind="int", unit="bit/s", choices=BAUDS)
    timeout_s: float = key(0.01, "a request without a reply after this long is retried or given up "
                           "for this slot", kind="float", unit="s", lo=0.0, hi=1.0, lo_open=True)
    retries: int = key(1, "retries of a request that got no valid reply, within one slot",
                       kind="int", lo=0, hi=5)
    watchdog_s: float | None = key(None, "the STM32 stops the motor when it hears nothing for "
                                   "this long (sent to the controller with the enable command); "
                                   "shorter than `method.stop_after` is refused: a stall of the "
                                   "gateway that the protection stop tolerates would stop the "
                                   "drive (docs/protocols/stm32.md, safety argument)",
                                   kind="float", unit="s", lo=0.02, hi=60.0, nullable=True,
                                   null_means="`method.stop_after` + 0.5 s (1.5 s)")


@dataclass(frozen=True, kw_only=True)
class TestConfig:
    sample_id: str | None = key(None, "sample ID of a test started without one (by `--start`, "
                                "autostart, or a start command that names none)", kind="str",
                                nullable=True, null_means="`<station id>-sample`")
    grade: str | None = key(None, "needle grade of that sample; one of `grades`", kind="str",
                            nullable=True, null_means="not given")
    t_set_n: float = key(0.5, "tension setpoint T_set of a test (the method's `t_set`)", kind="float",
                         unit="N", lo=0.0, lo_open=True, hi=1000.0)
    t_end_s: float = key(36000.0, "planned test duration (the method's `t_end`); the test ends as "
                         "completed after this long", kind="float", unit="s", lo=0.0, lo_open=True,
                         hi=TEN_YEARS)
    autostart: bool = key(False, "start a test with these values as soon as the station runs",
                          kind="bool")
    restart_on_replace: bool = key(False, "a `hook_replaced` command starts the next test with the "
                                   "new hook at once (these values, the new sample ID and grade)",
                                   kind="bool")


#: the keys of one `forecast.priors` entry (METHOD.md §7a): required, then optional
PRIOR_ENTRY_KEYS = ("grade", "t_set_n", "mean_s", "sd_s")
PRIOR_ENTRY_OPTIONAL = ("n", "n_censored", "n_early")
#: entries a `forecast.priors` list may hold (grades × setpoints of one station)
MAX_PRIOR_ENTRIES = 256
#: the largest test count `n` of a prior entry
MAX_PRIOR_N = 1_000_000
#: the upper bound of each number of a prior entry (a tension; a life and its SD: 10 years)
_PRIOR_HI = {"t_set_n": MAX_TENSION, "mean_s": TEN_YEARS, "sd_s": TEN_YEARS}


def parse_prior_entries(v: Any) -> tuple[bool, Any]:
    """``forecast.priors``: (True, tuple of PriorEntry) or (False, message). Grades are checked
    against `grades` by a rule."""
    if not isinstance(v, list):
        return False, f"{show_yaml(v)} is not a list"
    if len(v) > MAX_PRIOR_ENTRIES:
        return False, f"{len(v)} entries; at most {MAX_PRIOR_ENTRIES}"
    out: list[PriorEntry] = []
    for i, item in enumerate(v, start=1):
        if not isinstance(item, dict):
            return False, f"entry {i} ({show_yaml(item)}) is not a mapping"
        unknown = [k for k in item if k not in PRIOR_ENTRY_KEYS + PRIOR_ENTRY_OPTIONAL]
        if unknown:
            return False, (f"entry {i}: unknown key {str(unknown[0])!r}; keys: "
                           f"{', '.join(PRIOR_ENTRY_KEYS + PRIOR_ENTRY_OPTIONAL)}")
        missing = [k for k in PRIOR_ENTRY_KEYS if k not in item]
        if missing:
            return False, f"entry {i}: {missing[0]} is missing"
        g = item["grade"]
        if isinstance(g, (int, float)) and not isinstance(g, bool):
            g = str(g)
        if not isinstance(g, str) or not g.strip():
            return False, f"entry {i}: grade {show_yaml(item['grade'])} is not a grade name"
        nums: dict[str, float] = {}
        for k in ("t_set_n", "mean_s", "sd_s"):
            x = item[k]
            if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(float(x)):
                return False, f"entry {i}: {k} {show_yaml(x)} is not a finite number"
            if not float(x) > 0:
                return False, f"entry {i} (grade {g}): {k} {show_yaml(x)} is impossible; allowed: > 0"
            if float(x) > _PRIOR_HI[k]:
                most = f"{MAX_TENSION:g} N" if k == "t_set_n" else f"{TEN_YEARS:.0f} s (10 years)"
                return False, f"entry {i} (grade {g}): {k} {show_yaml(x)} is out of range; allowed: ≤ {most}"
            nums[k] = float(x)
        n = item.get("n")
        if n is not None and (isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_PRIOR_N):
            return False, (f"entry {i}: n {show_yaml(n)} is not a count of tests (an integer from 1 "
                           f"to {MAX_PRIOR_N})")
        counts: dict[str, int | None] = {}
        for k in ("n_censored", "n_early"):
            c = item.get(k)
            if c is not None and (isinstance(c, bool) or not isinstance(c, int) or not 0 <= c <= MAX_PRIOR_N):
                return False, (f"entry {i}: {k} {show_yaml(c)} is not a count of tests (an "
                               f"integer from 0 to {MAX_PRIOR_N})")
            counts[k] = c
        out.append(PriorEntry(g.strip(), nums["t_set_n"], nums["mean_s"], nums["sd_s"], n,
                              counts["n_censored"], counts["n_early"]))
    return True, tuple(out)


@dataclass(frozen=True, kw_only=True)
class ForecastConfig:
    priors: tuple = key((), "the life of earlier hooks per grade and T_set: the prior of a new "
                        "test's forecast (METHOD.md §5b, §7a); without an entry for its grade and "
                        "T_set (±0.001 N) the prior comes from the completed tests of that grade "
                        "and T_set (at least 3 wear-out `failure`s; right-censored lives count "
                        "too, and early failures as censored ones: METHOD.md §7a), else there "
                        "is none. "
                        "`method.prior_mean`/`prior_sd` fix one prior that wins over both. "
                        "`hookwatch report … --priors FILE` writes this list", kind="prior_list")


@dataclass(frozen=True, kw_only=True)
class RetentionConfig:
    max_age_days: float | None = key(None, "completed tests older than this are pruned (whole test "
                                     "folders, oldest first)", kind="float", unit="d", lo=1.0, hi=36500.0,
                                     nullable=True, null_means="no age limit")
    max_total_mb: float | None = key(None, "the station's records may take at most this much disk; "
                                     "beyond it the oldest completed tests are pruned", kind="float",
                                     unit="MB", lo=1.0, hi=1e9, nullable=True, null_means="no size budget")
    min_free_percent: float = key(10.0, "while the records' file system has less free space than this, "
                                  "the oldest completed tests are pruned (0: off)", kind="float",
                                  unit="%", lo=0.0, hi=90.0)
    keep_last: int = key(20, "the newest this many completed tests of the station are never pruned",
                         kind="int", lo=1, hi=100000)
    interval_s: float = key(600.0, "how often the records are checked (also after every test end)",
                            kind="float", unit="s", lo=10.0, hi=86400.0)


@dataclass(frozen=True, kw_only=True)
class RecorderConfig:
    dir: str = key("/var/lib/hookwatch/records", "where tests are recorded: "
                   "`<dir>/<station>/<test_id>/` (log.csv.gz, log.meta.yaml, events.jsonl, result.json)",
                   kind="path")
    flush_interval_s: float = key(1.0, "the log is flushed to disk this often; a power cut loses at "
                                  "most this much", kind="float", unit="s", lo=0.05, hi=60.0)
    retention: RetentionConfig = section(RetentionConfig, "record retention: which completed tests are "
                                         "pruned so that the disk never fills (never the running test, "
                                         "never one whose result has not left the outbox)")


@dataclass(frozen=True, kw_only=True)
class MqttTlsConfig:
    enabled: bool = key(False, "connect with TLS", kind="bool")
    ca_file: str | None = key(None, "CA certificate(s) that sign the broker's certificate",
                              kind="path", nullable=True, null_means="the system's CA store")
    cert_file: str | None = key(None, "client certificate (with key_file: mutual TLS)", kind="path",
                                nullable=True, null_means="no client certificate")
    key_file: str | None = key(None, "private key of cert_file", kind="path", nullable=True,
                               null_means="no client certificate")


@dataclass(frozen=True, kw_only=True)
class MqttOutboxConfig:
    path: str | None = key(None, "the on-disk outbox (SQLite): messages wait here until the broker "
                           "confirms them, across link drops and restarts", kind="path",
                           nullable=True, null_means="`<recorder.dir>/<station id>/outbox.sqlite`")
    telemetry_budget_mb: float = key(50.0, "telemetry kept while the broker is unreachable; the "
                                     "oldest telemetry is dropped (counted) beyond it — events and "
                                     "results are never dropped", kind="float", unit="MB", lo=0.1, hi=1e6)


@dataclass(frozen=True, kw_only=True)
class BrokerConfig:
    """The broker connection keys both MQTT sections share (`mqtt:` and `sparkplug:`); one
    definition, read by gateway.outputs.broker.settings.broker_kwargs. A section redeclares a
    key only to say something of its own about it (the key keeps its place)."""
    enabled: bool = key(False, "connect to the broker", kind="bool")
    host: str = key("127.0.0.1", "broker host", kind="str")
    port: int = key(1883, "broker port", kind="int", lo=1, hi=65535)
    client_id: str | None = key(None, "MQTT client ID; must be unique on the broker", kind="str",
                                nullable=True, null_means="derived from the station / node")
    keepalive_s: int = key(30, "MQTT keep-alive interval", kind="int", unit="s", lo=5, hi=3600)
    username: str | None = key(None, "broker user", kind="str", nullable=True, null_means="anonymous")
    password_env: str | None = key(None, "name of the environment variable that holds the broker "
                                   "password (e.g. set by the unit's `EnvironmentFile=`)",
                                   kind="envvar", nullable=True, null_means="no password")
    tls: MqttTlsConfig = section(MqttTlsConfig, "TLS to the broker")


@dataclass(frozen=True, kw_only=True)
class MqttConfig(BrokerConfig):
    enabled: bool = key(False, "report telemetry, events and results over MQTT and accept commands",
                        kind="bool")
    host: str = key("127.0.0.1", "broker host (normally the edge broker on this box, which bridges "
                    "to the plant's central broker)", kind="str")
    prefix: str = key("hookwatch", "first level(s) of every topic", kind="topic")
    client_id: str | None = key(None, "MQTT client ID; must be unique on the broker", kind="str",
                                nullable=True, null_means="`hookwatch-<station id>`")
    protocol: str = key("auto", "MQTT protocol version: `auto` connects with MQTT 5 and falls back to "
                        "3.1.1 when the broker refuses it; with MQTT 5 a command is answered on its "
                        "Response Topic with its Correlation Data, with 3.1.1 on `reply`", kind="enum",
                        choices=("auto", "5", "3.1.1"))
    password_file: str | None = key(None, "file whose first line is the broker password (mode "
                                    "0600, owned by the hookwatch user)", kind="path",
                                    nullable=True, null_means="no password")
    reply_prefix: str | None = key(None, "MQTT 5: a command's Response Topic is obeyed only below "
                                   "this topic (`<reply_prefix>/…`); any other goes to `reply` and is "
                                   "counted, so a client allowed only `cmd/…` cannot make the gateway "
                                   "publish elsewhere", kind="topic", nullable=True,
                                   null_means="`<base>/reply` (the station's own reply topic)")
    servers: tuple[str, ...] | None = key(None, "the broker's servers, as `host:port` (`host` alone: "
                                          "`port`), e.g. the nodes of a clustered broker: the output "
                                          "connects to the first, moves to the next when one cannot be "
                                          "reached, and publishes its retained topics again after every "
                                          "(re)connect (docs/mqtt.md)", kind="str_list", nullable=True,
                                          null_means="`[<host>:<port>]`")
    telemetry_interval_s: float = key(1.0, "one telemetry message (slot aggregates) this often",
                                      kind="float", unit="s", lo=0.1, hi=3600.0)
    share_lives: bool = key(True, "share every completed test's life with the gateways of this "
                            "`station.site` on the broker, and pool theirs into the life prior's "
                            "history (METHOD.md §7a; a retained `<base>/lives` per station, "
                            "docs/mqtt.md); false: neither share nor receive", kind="bool")
    command_doors: tuple[str, ...] = key((), "named command doors besides the default "
                                         "`<base>/cmd/<command>` (the MES's): each "
                                         "`<base>/cmd/<door>/<command>` for another writer (an "
                                         "operator's panel, a second MES), with its own command "
                                         "budget (source `mqtt:<door>`, docs/limits.md); the "
                                         "broker's ACL confines each writer to its door "
                                         "(`hookwatch config acl`)", kind="str_list",
                                         example=["operator"])
    outbox: MqttOutboxConfig = section(MqttOutboxConfig, "durable delivery")


@dataclass(frozen=True, kw_only=True)
class SparkplugConfig(BrokerConfig):
    enabled: bool = key(False, "publish the station as a Sparkplug B 3.0 device of its edge node "
                        "(docs/sparkplug.md); alongside or instead of the JSON tree of `mqtt:`",
                        kind="bool")
    group_id: str | None = key(None, "Sparkplug group ID", kind="ident", nullable=True,
                               null_means="`station.site`")
    edge_node_id: str | None = key(None, "Sparkplug edge node ID; stations of one gateway (a fleet's "
                                   "supervisor, or one process) with the same broker, group and edge "
                                   "node share one node (one MQTT session, a device per station)",
                                   kind="ident", nullable=True,
                                   null_means="`<station.area>-<station.line>`")
    device_id: str | None = key(None, "Sparkplug device ID of this station", kind="ident",
                                nullable=True, null_means="`station.id`")
    primary_host_id: str | None = key(None, "the primary host application whose "
                                      "`spBv1.0/STATE/<id>` gates publishing (data is stored while "
                                      "it is offline and replayed as historical)", kind="ident",
                                      nullable=True, null_means="no primary host: publish whenever "
                                      "connected")
    client_id: str | None = key(None, "MQTT client ID of the edge node", kind="str", nullable=True,
                                null_means="`hookwatch-spb-<group>-<edge node>`")
    data_interval_s: float = key(1.0, "one DDATA of the measured values (slot aggregates) this "
                                 "often; state changes are sent as they happen", kind="float",
                                 unit="s", lo=0.1, hi=3600.0)
    store_path: str | None = key(None, "SQLite store of the node: bdSeq and the data held while no "
                                 "primary host is online", kind="path", nullable=True,
                                 null_means="`<recorder.dir>/sparkplug-<group>-<edge node>.sqlite`")
    history_budget_mb: float = key(50.0, "measured values kept while the host is offline; the "
                                   "oldest are dropped (counted) beyond it — state and alarm "
                                   "changes are never dropped", kind="float", unit="MB", lo=0.1, hi=1e6)
    servers: tuple[str, ...] | None = key(None, "the Sparkplug server set (3.0 §8.2), as `host:port` "
                                          "(`host` alone: `port`); the node connects to the first, and "
                                          "moves to the next on `Node Control/Next Server`, when the "
                                          "primary host's STATE goes offline, or when a server cannot "
                                          "be reached", kind="str_list", nullable=True,
                                          null_means="`[<host>:<port>]`")
    rebirth_min_interval_s: float = key(2.0, "at most one birth (NBIRTH and the DBIRTHs) per this "
                                        "interval: `Node Control/Rebirth` requests inside it are "
                                        "coalesced into one rebirth when it has passed; likewise "
                                        "at most one session end (`Reboot`, `Next Server`: NDEATH "
                                        "and a new connection) per interval after the birth and "
                                        "the last one, requests inside it coalesced", kind="float",
                                        unit="s", lo=0.0, hi=3600.0)
    max_command_bytes: int = key(16384, "largest NCMD / DCMD payload decoded; a larger one is "
                                 "ignored (counted, logged)", kind="int", unit="bytes", lo=256,
                                 hi=1048576)
    max_command_metrics: int = key(64, "most metrics in one NCMD / DCMD; more: the payload is "
                                   "ignored (counted, logged)", kind="int", lo=1, hi=4096)
    max_string_chars: int = key(256, "longest metric name or string value in an NCMD / DCMD; "
                                "longer: the payload is ignored (counted, logged)", kind="int",
                                lo=16, hi=65536)
    state_max_bytes: int = key(1024, "largest STATE payload of the primary host parsed; a larger "
                               "one is ignored (counted, logged)", kind="int", unit="bytes", lo=64,
                               hi=65536)
    state_future_skew_s: float = key(300.0, "a STATE timestamp further than this ahead of the "
                                     "node's clock is accepted but taken as the node's \"now\" "
                                     "(docs/sparkplug.md, STATE timestamps)", kind="float", unit="s",
                                     lo=0.0, hi=31536000.0)


def _door_keys(cap: int, request_s: float, idle_s: float, what: str, accepts: float = 100.0,
               per_address: int = 16) -> dict[str, Any]:
    """The keys of a listening door (gateway/plumbing/doors.py: one mechanism for every TCP port)."""
    return {
        "max_connections": key(cap, f"connections open at once on {what}; one more is closed at "
                               "once (counted). Granted within the process's descriptor budget "
                               "(`process.fd_reserve`)", kind="int", lo=2, hi=100000),
        "request_timeout_s": key(request_s, "a request must be complete (all its bytes) within "
                                 "this long of its first byte, however they trickle in; else the "
                                 "connection is closed", kind="float", unit="s", lo=0.1, hi=600.0),
        "idle_timeout_s": key(idle_s, "a connection that begins no request this long after its "
                              "last reply (or does not read a reply for as long) is closed; "
                              "Modbus: also this long after it was opened (HTTP: the first "
                              "request is due within request_timeout_s of the connect)",
                              kind="float", unit="s", lo=0.5, hi=86400.0),
        "accept_pause_s": key(0.5, "after an accept error (EMFILE, ENFILE …: counted, one log line "
                              "a minute) the port stops accepting this long", kind="float",
                              unit="s", lo=0.01, hi=60.0),
        "accepts_per_s": key(accepts, "new connections accepted per second at most (a burst of as "
                             "many at once); beyond, the port waits and further connects queue in "
                             "the kernel's backlog: a connect flood costs the process a bounded "
                             "amount of work, whatever its rate", kind="float", unit="1/s",
                             lo=1.0, hi=100000.0),
        "max_per_address": key(per_address, f"connections of one client address open at once on "
                               f"{what}; one more closes that address's connection idle longest "
                               "(≥ 1 s) or is closed at once (counted). At max_connections a "
                               "newcomer closes the oldest connection of the address holding the "
                               "most: one client cannot starve the others", kind="int", lo=1,
                               hi=100000),
    }


def _door_section(name: str, cap: int, request_s: float, idle_s: float, what: str,
                  per_address: int) -> type:
    keys = _door_keys(cap, request_s, idle_s, what, per_address=per_address)
    cls = dataclasses.make_dataclass(name, [(k, float if k.endswith(("_s", "per_s")) else int, f)
                                            for k, f in keys.items()], frozen=True, kw_only=True)
    cls.__doc__ = f"connection limits of {what}"
    cls.__module__ = __name__
    return cls


ModbusDoorConfig = _door_section("ModbusDoorConfig", 64, 10.0, 60.0, "the Modbus TCP port", 16)
MetricsDoorConfig = _door_section("MetricsDoorConfig", 8, 5.0, 30.0, "the metrics endpoint", 4)
ConsoleDoorConfig = _door_section("ConsoleDoorConfig", 256, 10.0, 60.0, "the console (every "
                                  "listen address together)", 32)


@dataclass(frozen=True, kw_only=True)
class ModbusWritesConfig:
    enabled: bool = key(False, "accept writes (commands) from a PLC; reads are always allowed",
                        kind="bool")
    allowed_clients: tuple[str, ...] = key((), "client addresses that may write; required when "
                                           "writes are enabled", kind="ip_list")


@dataclass(frozen=True, kw_only=True)
class ModbusTcpConfig:
    enabled: bool = key(False, "serve the station's register map to a PLC over Modbus TCP",
                        kind="bool")
    host: str = key("127.0.0.1", "address to listen on (0.0.0.0: every interface)", kind="str")
    port: int = key(5020, "TCP port; stations of one fleet may share a port with distinct "
                    "unit_id (one server, one unit per station)", kind="int", lo=1, hi=65535)
    unit_id: int = key(1, "the station's Modbus unit ID on that port", kind="int", lo=1, hi=247)
    word_order: str = key("big", "order of the two registers of a 32-bit value (big: high word "
                          "first)", kind="enum", choices=("big", "little"))
    writes: ModbusWritesConfig = section(ModbusWritesConfig, "commands from the PLC")
    connections: ModbusDoorConfig = section(ModbusDoorConfig, "connection limits of the port "  # type: ignore[valid-type]
                                            "(the first station on a port sets them); clients in "
                                            "writes.allowed_clients always find room")


@dataclass(frozen=True, kw_only=True)
class MetricsConfig:
    enabled: bool = key(False, "serve the gateway's own health (slots, lateness, meter RTT, link "
                        "errors, outbox, PLC) to Prometheus at http://host:port/metrics "
                        "(docs/metrics.md)", kind="bool")
    host: str = key("127.0.0.1", "address to listen on (0.0.0.0: every interface; the endpoint has "
                    "no authentication)", kind="str")
    port: int = key(9620, "TCP port; every station of a fleet (`hookwatch run DIR`) shares the "
                    "endpoint on the same host and port (one series set per station)", kind="int",
                    lo=1, hi=65535)
    connections: MetricsDoorConfig = section(MetricsDoorConfig, "connection limits of the "  # type: ignore[valid-type]
                                             "endpoint (the first station's)")


@dataclass(frozen=True, kw_only=True)
class ConsoleTlsConfig:
    cert_file: str | None = key(None, "server certificate (PEM) for HTTPS on the plant network",
                                kind="path", nullable=True, null_means="plain HTTP")
    key_file: str | None = key(None, "private key of cert_file", kind="path", nullable=True,
                               null_means="plain HTTP")


@dataclass(frozen=True, kw_only=True)
class ConsoleConfig:
    enabled: bool = key(False, "serve the operator console (web pages: fleet, station, history); "
                        "one console per process shows every station of the fleet, configured by "
                        "the first station file", kind="bool")
    listen: tuple[str, ...] = key(("127.0.0.1:8080",), "addresses to listen on, as host:port",
                                  kind="str_list")
    tls: ConsoleTlsConfig = section(ConsoleTlsConfig, "HTTPS (certificate and key)")
    users_file: str | None = key(None, "users who may give commands (`hookwatch console-user "
                                 "add`); salted scrypt hashes", kind="path", nullable=True,
                                 null_means="`console-users.json` in recorder.dir")
    read_without_login: str = key("local", "who may read without logging in: local (clients on "
                                  "the loopback address), all, none", kind="enum",
                                  choices=("local", "all", "none"))
    session_ttl_s: float = key(28800.0, "a login lasts this long without activity", kind="float",
                               unit="s", lo=60.0, hi=7 * 86400.0)
    lockout_attempts: int = key(5, "failed logins of one user from one client address (within "
                                "lockout_s) before that pair is locked out; another address is "
                                "not affected", kind="int", lo=1, hi=100)
    lockout_s: float = key(300.0, "how long a lockout lasts (and the window failures are "
                           "counted in)", kind="float", unit="s", lo=1.0, hi=86400.0)
    login_failures_per_address: int = key(20, "failed logins from one client address, any user "
                                           "(within lockout_s), before the address is locked out",
                                           kind="int", lo=1, hi=10000)
    login_hashes_per_s: float = key(4.0, "password hashes (scrypt, one per login) per second "
                                    "over all logins, in one worker thread at nice 19; a login "
                                    "beyond gets HTTP 429 with Retry-After without hashing "
                                    "(counted, one log line a minute)", kind="float", unit="1/s",
                                    lo=0.1, hi=1000.0)
    login_hash_burst: int = key(10, "password hashes allowed at once beyond login_hashes_per_s "
                                "(the token bucket's size)", kind="int", lo=1, hi=10000)
    login_hashes_per_user_per_s: float = key(1.0, "password hashes per second for one user name "
                                             "(a flood on one name leaves the budget of the "
                                             "others); beyond, HTTP 429 with Retry-After",
                                             kind="float", unit="1/s", lo=0.01, hi=1000.0)
    login_hash_burst_per_user: int = key(5, "password hashes allowed at once for one user name "
                                         "beyond login_hashes_per_user_per_s", kind="int", lo=1,
                                         hi=10000)
    allowed_hosts: tuple[str, ...] = key((), "host names the console answers in the HTTP Host "
                                         "header besides the addresses it listens on (and "
                                         "`localhost` on a loopback address); other names get "
                                         "HTTP 421 (DNS rebinding)", kind="str_list")
    report_jobs: int = key(1, "report processes (Fig. 7 of a test, campaign reports) running at "
                           "once", kind="int", lo=1, hi=16)
    report_queue: int = key(8, "report requests waiting for a process; beyond, HTTP 503 with "
                            "Retry-After (requests for the same figure share one process)",
                            kind="int", lo=0, hi=256)
    stream_connects_per_address: int = key(30, "live-stream (SSE) connects per minute from one "
                                           "client address; beyond, HTTP 429 with Retry-After",
                                           kind="int", lo=1, hi=10000, unit="1/min")
    stream_connects_total: int = key(120, "live-stream (SSE) connects per minute from all "
                                     "clients together; beyond, HTTP 429 with Retry-After",
                                     kind="int", lo=1, hi=100000, unit="1/min")
    site_view: bool = key(True, "the due list and the fleet cards can show every station of this "
                          "station.site (a `whole site` switch): the other boxes' stations, read-only, "
                          "learned from their retained MQTT state and status on the session of the "
                          "first MQTT-enabled station of this process (docs/console.md)", kind="bool")
    connections: ConsoleDoorConfig = section(ConsoleDoorConfig, "connection limits of the "  # type: ignore[valid-type]
                                             "console")


@dataclass(frozen=True, kw_only=True)
class ProcessConfig:
    fd_reserve: int = key(128, "file descriptors kept for the stations' own work (slot loops, "
                          "recorder files, serial ports, MQTT outbox, the supervisor's worker "
                          "restarts): the listening ports never take them. The soft "
                          "RLIMIT_NOFILE is raised to the hard limit at start; the ports' "
                          "connection caps are granted out of the rest (the first station "
                          "file's value for the process)", kind="int", lo=32, hi=100000)


@dataclass(frozen=True, kw_only=True)
class LoggingConfig:
    level: str = key("info", "log level of the station (journal / stderr)", kind="enum",
                     choices=("debug", "info", "warning", "error"))


# ---------------------------------------------------------------------------------------------
# control: names and types from gateway.core.control; units, ranges and docs here

#: per ControlParams / NotchParams field: the Key arguments other than name, kind and default
CONTROL_KEYS: dict[str, dict[str, Any]] = {
    "mode": dict(doc="closed: PID on the tension; open: a fixed speed command (open_loop_rpm)",
                 choices=("closed", "open")),
    "open_loop_rpm": dict(unit="rpm", doc="speed command in open-loop mode", lo=0.0, hi=20000.0),
    "kp": dict(unit="rpm/N", doc="proportional gain", lo=0.0, hi=1e6),
    "ki": dict(unit="rpm/(N·s)", doc="integral gain", lo=0.0, hi=1e6),
    "kd": dict(unit="rpm·s/N", doc="derivative gain (on the low-passed derivative)", lo=0.0,
               hi=1e6),
    "plant_sign": dict(doc="+1: more take-up speed gives more tension; -1: the other way round",
                       choices=(1, -1)),
    "n_max_rpm": dict(unit="rpm", doc="upper clamp of the speed command (the lower one is 0); the "
                      "clamp is the anti-windup", lo=0.0, lo_open=True, hi=20000.0),
    "slew_rpm_per_slot": dict(unit="rpm per slot", doc="largest change of the command from one slot "
                              "to the next", lo=0.0, lo_open=True, hi=20000.0),
    "dead_band_n": dict(unit="N", doc="tension errors smaller than this count as zero", lo=0.0,
                        hi=MAX_TENSION),
    "prefilter_fc_hz": dict(unit="Hz", doc="cut-off of the first-order pre-filter on the feedback; "
                            "below the Nyquist frequency 1/(2·ts)", lo=0.0, lo_open=True, hi=1000.0),
    "deriv_fc_hz": dict(unit="Hz", doc="cut-off of the derivative's low-pass; below 1/(2·ts)",
                        lo=0.0, lo_open=True, hi=1000.0),
    "hold_missing_s": dict(unit="s", doc="a missing reading is replaced by the last one for at most "
                           "this long; then the command is held", lo=0.0, hi=60.0),
    # notch
    "enabled": dict(doc="speed-adaptive notch on the feedback (removes the ripple at the shaft "
                    "frequency)"),
    "bw_hz": dict(unit="Hz", doc="notch bandwidth B_w: Q = f0 / B_w, clamped to [q_min, q_max]",
                  lo=0.0, lo_open=True, hi=1000.0),
    "q_min": dict(doc="lower clamp of the notch quality factor", lo=0.0, lo_open=True, hi=1000.0),
    "q_max": dict(doc="upper clamp of the notch quality factor (≥ q_min)", lo=0.0, lo_open=True,
                  hi=1000.0),
    "alpha_f": dict(doc="smoothing factor of the notch frequency update", lo=0.0, hi=1.0, lo_open=True),
    "alpha_q": dict(doc="smoothing factor of the Q update", lo=0.0, hi=1.0, lo_open=True),
    "n_min_rpm": dict(unit="rpm", doc="the notch is bypassed below this speed", lo=0.0, hi=20000.0),
    "f_update_hz": dict(unit="Hz", doc="coefficients are recomputed when f0 moved more than this",
                        lo=0.0, hi=1000.0),
    "q_update": dict(doc="… or when Q moved more than this", lo=0.0, hi=1000.0),
    "ratio_i": dict(doc="transmission ratio i: disturbance frequency f0 = speed/60 · i · h",
                    lo=0.0, lo_open=True, hi=1000.0),
    "harmonic_h": dict(doc="harmonic order h of the disturbance", lo=1, hi=20),
}

#: ControlParams fields that are not keys of `control:` (ts is the method's sampling period)
CONTROL_EXCLUDED = ("ts",)


def _kind_of(value: Any) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "float"
    return "enum" if isinstance(value, str) else "str"


def _control_field(f: dataclasses.Field) -> tuple[str, Any, Any]:
    extra = dict(CONTROL_KEYS.get(f.name, {"doc": "(undocumented)"}))
    kind = _kind_of(f.default)
    if kind == "enum" and "choices" not in extra:
        kind = "str"
    return f.name, f.type, key(f.default, kind=kind, **extra)


NotchConfig = dataclasses.make_dataclass(
    "NotchConfig", [_control_field(f) for f in fields(NotchParams)],
    frozen=True, kw_only=True)
NotchConfig.__doc__ = "control.notch: the fields of gateway.core.control.NotchParams"
NotchConfig.__module__ = __name__

ControlConfig = dataclasses.make_dataclass(
    "ControlConfig",
    [_control_field(f) for f in fields(ControlParams) if f.name not in CONTROL_EXCLUDED + ("notch",)]
    + [("notch", NotchConfig, section(NotchConfig, "speed-adaptive notch filter (METHOD.md §8.1)"))],
    frozen=True, kw_only=True)
ControlConfig.__doc__ = "control: the fields of gateway.core.control.ControlParams except ts"
ControlConfig.__module__ = __name__

#: method parameters a station file may set in `method:` (t_set/t_end come from `test:`)
METHOD_EXCLUDED = {"t_set": "test.t_set_n", "t_end": "test.t_end_s",
                   "end_slot": "the sidecar (written by the gateway when a test is ended on purpose)"}
METHOD_KEYS = tuple(p.name for p in METHOD_PARAMS if p.name not in METHOD_EXCLUDED)


def method_defaults() -> dict[str, float | None]:
    return {p.name: p.default for p in METHOD_PARAMS if p.name in METHOD_KEYS}


@dataclass(frozen=True, kw_only=True)
class StationConfig:
    station: StationInfo = section(StationInfo, "who the station is", default=False)
    meter: MeterConfig = section(MeterConfig, "the ZN-S tension meter (Modbus RTU over RS-485)",
                                 default=False)
    stm32: Stm32Config = section(Stm32Config, "the STM32 take-up motor controller (serial link)",
                                 default=False)
    method: dict = field(default_factory=method_defaults, metadata={
        "method": True, "doc": "the method's parameters (METHOD.md §10, docs/method.md)"})
    # ControlConfig is made by make_dataclass: a value to mypy, not a type
    control: ControlConfig = section(ControlConfig, "tension control (METHOD.md §8)")  # type: ignore[valid-type]
    test: TestConfig = section(TestConfig, "the test a station starts without further instructions")
    forecast: ForecastConfig = section(ForecastConfig, "the life priors of the remaining-life "
                                       "forecast (METHOD.md §5b, §7a)")
    grades: tuple[str, ...] = key(("I", "II"), "needle grades a test may name", kind="str_list")
    recorder: RecorderConfig = section(RecorderConfig, "recording of every test")
    mqtt: MqttConfig = section(MqttConfig, "northbound MQTT (to the MES)")
    modbus_tcp: ModbusTcpConfig = section(ModbusTcpConfig, "northbound Modbus TCP server (to the PLC)")
    sparkplug: SparkplugConfig = section(SparkplugConfig, "northbound Sparkplug B 3.0 (to SCADA / MES)")
    metrics: MetricsConfig = section(MetricsConfig, "metrics for Prometheus (the gateway's own health)")
    console: ConsoleConfig = section(ConsoleConfig, "operator console (web pages)")
    logging: LoggingConfig = section(LoggingConfig, "logging")
    process: ProcessConfig = section(ProcessConfig, "the gateway process (descriptor budget)")
    #: not a key: the station file this configuration was read from, and its fleet file
    source: str = field(default="", metadata={"internal": True})
    fleet_file: str | None = field(default=None, metadata={"internal": True})
    #: not a key of its own: the sections of plug-in outputs by name (gateway/config/plugins.py)
    plugins: dict[str, object] = field(default_factory=dict, metadata={"internal": True})

    def stm32_watchdog_s(self) -> float:
        """The STM32 watchdog period the gateway sets at enable: ``stm32.watchdog_s``, or when
        null `method.stop_after` + WATCHDOG_MARGIN_S (docs/protocols/stm32.md, safety argument)."""
        if self.stm32.watchdog_s is not None:
            return float(self.stm32.watchdog_s)
        return watchdog_for(float(self.method.get("stop_after", 1.0) or 0.0))


# ---------------------------------------------------------------------------------------------
# the tree of specs the loader and the docs walk


@dataclass(frozen=True)
class Section:
    name: str
    cls: type
    doc: str
    entries: tuple  # Key | Section | MethodSection


@dataclass(frozen=True)
class MethodSection:
    name: str
    doc: str


def _section(name: str, cls: type, doc: str) -> Section:
    entries: list[Key | Section | MethodSection] = []
    for f in fields(cls):
        m = f.metadata
        if "key" in m:
            entries.append(Key(name=f.name, **m["key"]))
        elif "section" in m:
            entries.append(_section(f.name, m["section"], m["doc"]))
        elif m.get("method"):
            entries.append(MethodSection(f.name, m["doc"]))
    return Section(name, cls, doc, tuple(entries))


ROOT = _section("", StationConfig, "a station")
#: the spec of a section class (a plug-in output's section: gateway/config/plugins.py)
section_spec = _section


def walk(sec: Section = ROOT, prefix: tuple = ()):
    """Every (path, Key|Section|MethodSection) in definition order."""
    for e in sec.entries:
        p = prefix + (e.name,)
        yield p, e
        if isinstance(e, Section):
            yield from walk(e, p)


def lookup(path: tuple):
    node: Any = ROOT
    for name in path:
        if not isinstance(node, Section):
            return None
        node = next((e for e in node.entries if e.name == name), None)
        if node is None:
            return None
    return node


# ---------------------------------------------------------------------------------------------
# rules across keys: each with the sentence the docs print; fn(cfg, report)


@dataclass(frozen=True)
class Rule:
    doc: str
    fn: Callable


def _writes(cfg, r):
    w = cfg.modbus_tcp.writes
    if w.enabled and not w.allowed_clients:
        r.error(("modbus_tcp", "writes", "allowed_clients"),
                "writes are enabled but no client may write; list the PLC's address(es) in "
                "modbus_tcp.writes.allowed_clients (writes open to anyone are not allowed)",
                anchor=("modbus_tcp", "writes", "enabled"))


def _password(cfg, r):
    m = cfg.mqtt
    if m.password_env and m.password_file:
        r.error(("mqtt", "password_file"), "password_env and password_file are both set; give one")
    if (m.password_env or m.password_file) and not m.username:
        r.warning(("mqtt", "username"), "a password is configured but no username")


def _tls(cfg, r):
    t = cfg.mqtt.tls
    if bool(t.cert_file) != bool(t.key_file):
        r.error(("mqtt", "tls", "cert_file" if not t.cert_file else "key_file"),
                "cert_file and key_file go together (mutual TLS needs both)")


def _grade(cfg, r):
    g = cfg.test.grade
    if g is not None and g not in cfg.grades:
        r.error(("test", "grade"), f"{g!r} is not one of the grades; allowed: "
                f"{', '.join(cfg.grades) or '(grades is empty)'}")
    if len(set(cfg.grades)) != len(cfg.grades):
        r.error(("grades",), "a grade is listed twice")


def _forecast(cfg, r):
    seen: list[PriorEntry] = []
    for i, e in enumerate(cfg.forecast.priors, start=1):
        if e.grade not in cfg.grades:
            r.error(("forecast", "priors"), f"entry {i}: grade {e.grade!r} is not one of the grades; "
                    f"allowed: {', '.join(cfg.grades) or '(grades is empty)'}")
        if any(o.grade == e.grade and same_t_set(o.t_set, e.t_set) for o in seen):
            r.error(("forecast", "priors"), f"entry {i}: grade {e.grade} at {e.t_set:g} N is given twice")
        seen.append(e)


def _ports(cfg, r):
    if cfg.meter.port == cfg.stm32.port:
        r.error(("stm32", "port"), f"{cfg.stm32.port!r} is also meter.port; the meter and the "
                "STM32 need one serial port each")


def parse_server(item: str, default_port: int) -> tuple[str, int] | None:
    """``host:port``, ``host``, ``[v6]:port`` or ``[v6]`` → (host, port); None if malformed."""
    item = item.strip()
    host, port = item, default_port
    if item.startswith("["):
        end = item.find("]")
        if end < 0:
            return None
        host, rest = item[1:end], item[end + 1:]
        if rest:
            if not rest.startswith(":"):
                return None
            port_s = rest[1:]
            if not port_s.isdigit():
                return None
            port = int(port_s)
    elif item.count(":") == 1:
        host, port_s = item.split(":")
        if not port_s.isdigit():
            return None
        port = int(port_s)
    elif ":" in item:
        return None             # a bare IPv6 address needs brackets: [::1]:1883
    if not host or any(c.isspace() for c in host) or not 1 <= port <= 65535:
        return None
    return host, port


def _servers(cfg, r):
    for name in ("mqtt", "sparkplug"):
        sec = getattr(cfg, name)
        if sec.servers is None:
            continue
        if not sec.servers:
            r.error((name, "servers"), "an empty server set; list at least one `host:port`, or "
                    f"leave the key out to use {name}.host and port")
            continue
        seen = set()
        for i, item in enumerate(sec.servers):
            hp = parse_server(item, int(sec.port))
            if hp is None:
                r.error((name, "servers"), f"item {i + 1} ({item!r}) is not `host:port` (port 1 … "
                        "65535; an IPv6 address in brackets: `[::1]:1883`)")
            elif hp in seen:
                r.error((name, "servers"), f"item {i + 1} ({item!r}) is listed twice")
            else:
                seen.add(hp)


def _control(cfg, r):
    c = cfg.control
    if c.open_loop_rpm > c.n_max_rpm:
        r.error(("control", "open_loop_rpm"), f"{c.open_loop_rpm:g} rpm is above control.n_max_rpm "
                f"({c.n_max_rpm:g} rpm); allowed: 0 … n_max_rpm")
    if c.notch.q_min > c.notch.q_max:
        r.error(("control", "notch", "q_min"), f"{c.notch.q_min:g} is above q_max ({c.notch.q_max:g})")
    ts = cfg.method.get("ts")
    if ts:
        nyq = 0.5 / ts
        for name in ("prefilter_fc_hz", "deriv_fc_hz"):
            v = getattr(c, name)
            if v >= nyq:
                r.error(("control", name), f"{v:g} Hz is not below the Nyquist frequency "
                        f"{nyq:g} Hz of ts = {ts:g} s; allowed: < {nyq:g}")


def _doors(cfg, r):
    doors = cfg.mqtt.command_doors
    if len(doors) > COMMAND_DOORS_MAX:
        r.error(("mqtt", "command_doors"), f"{len(doors)} doors; allowed: at most {COMMAND_DOORS_MAX}")
    for i, d in enumerate(doors):
        why = door_problem(d)
        if why is not None:
            r.error(("mqtt", "command_doors"), f"item {i + 1} ({d!r}): {why}")
        elif d in doors[:i]:
            r.error(("mqtt", "command_doors"), f"item {i + 1} ({d!r}) is listed twice")


RULES: tuple[Rule, ...] = (
    Rule("`modbus_tcp.writes.enabled: true` needs a non-empty `allowed_clients`.", _writes),
    Rule("`mqtt.password` is never accepted inline: use `password_env` or `password_file` (one of them).",
         _password),
    Rule("`mqtt.tls.cert_file` and `key_file` go together.", _tls),
    Rule("`test.grade` is one of `grades`; `grades` has no duplicates.", _grade),
    Rule("`forecast.priors` names only grades of `grades`, each grade and T_set (±0.001 N) once.",
         _forecast),
    Rule("`meter.port` and `stm32.port` differ.", _ports),
    Rule("`mqtt.servers` and `sparkplug.servers`: each `host:port` (or `host`, on the section's "
         "`port`), none twice.", _servers),
    Rule("`control.open_loop_rpm` ≤ `n_max_rpm`; `control.notch.q_min` ≤ `q_max`; "
         "`prefilter_fc_hz` and `deriv_fc_hz` below the Nyquist frequency 1/(2·`method.ts`).",
         _control),
    Rule(f"`mqtt.command_doors`: at most {COMMAND_DOORS_MAX}, each 1–32 letters, digits, '-' and '_' "
         "(no command's name), none twice.", _doors),
)


def check_ident(v: str) -> bool:
    return bool(IDENT_RE.match(v))


def check_ip(v: str) -> bool:
    try:
        ipaddress.ip_network(v, strict=False)
        return True
    except ValueError:
        return False


def finite(x: float) -> bool:
    return math.isfinite(x)
