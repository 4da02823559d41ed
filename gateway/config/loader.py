"""Read, merge and validate station files against the schema (:mod:`gateway.config.sections`).

The merge rule
--------------
A fleet folder holds ``fleet.yaml`` and ``stations/<id>.yaml``. ``fleet.yaml`` has one section,
``defaults:``, written like a station file; each station file is deep-merged over it (mappings
merge key by key, anything else — numbers, strings, lists — is replaced as a whole; a section left
empty in the station file keeps the defaults). A station file given on its own takes its defaults
from ``../fleet.yaml`` when it lies in a folder named ``stations``, and stands alone otherwise.

Every value remembers the file and line it came from: errors point there, and relative paths are
resolved against the folder of that file.
"""
from __future__ import annotations

import dataclasses
import glob
import os
from dataclasses import dataclass, field
from typing import Any

from drivers.meter.meter_map import DEFAULT_MAP_PATH, load_map

from ..core.method.params import PRIOR_NAMES, ParamError, build_params
from ..core.validation import MISSING, Problem, did_you_mean, show_value, show_yaml, suggestion_text
from ..plumbing.ratelog import clip
from . import plugins as P
from . import sections as S
from .yamlpos import Pos, YamlError
from .yamlpos import load as load_yaml

#: longest piece of a bad value quoted in a message (a 1 MB station id is shown by its start and
#: length: gateway/plumbing/ratelog.py clip)
ECHO = 64


def _shown(v: Any) -> str:
    """A bad value in a message: a string quoted and clipped (ratelog.clip), anything else as
    validation.show_value shows it."""
    return clip(v, ECHO) if isinstance(v, str) else show_value(v)

AUTO: Any = object()  # fleet_file: find it by the rule above

#: the keys of fleet.yaml
FLEET_KEYS = ("defaults",)


@dataclass(frozen=True)
class Issue:
    """A problem of a station as `hookwatch check` reports it: where, which key, the sentence;
    and the same as data (``path``, ``value``, ``allowed``, ``suggestion``), never to be parsed
    back from the sentence."""
    severity: str              # "error" | "warning"
    key: str                   # dotted key path, "" for the file as a whole
    message: str
    file: str | None = None
    line: int | None = None
    path: tuple = field(default=(), compare=False)
    value: Any = field(default=MISSING, compare=False)
    allowed: str | None = field(default=None, compare=False)
    suggestion: str | None = field(default=None, compare=False)

    @property
    def where(self) -> str:
        if self.file and self.line:
            return f"{self.file}:{self.line}"
        return self.file or ""

    def __str__(self) -> str:
        parts = [p for p in (self.where, self.key) if p]
        return ": ".join(parts + [self.message])


class ConfigError(ValueError):
    """A configuration that cannot run. ``issues`` lists every error; ``str()`` is one line each."""

    def __init__(self, issues: list[Issue]):
        self.issues = list(issues)
        super().__init__("\n".join(str(i) for i in self.issues))


@dataclass
class Loaded:
    """One station file after validation: the config (None when it has errors) and its issues."""
    path: str
    cfg: Any
    issues: list[Issue] = field(default_factory=list)
    fleet_file: str | None = None
    pos: dict = field(default_factory=dict)
    name: str | None = None       # station.id as written (also when the file has errors)

    @property
    def errors(self) -> list[Issue]:
        return [i for i in self.issues if i.severity == "error"]

    @property
    def warnings(self) -> list[Issue]:
        return [i for i in self.issues if i.severity == "warning"]

    def locate(self, path: tuple) -> Pos | None:
        return _locate(self.pos, path)

    def issue(self, severity: str, path: tuple, message: str, anchor: tuple | None = None,
              data: Problem | None = None) -> Issue:
        """An Issue at ``path`` (located at the key, else at ``anchor``, else at the nearest
        parent); ``data`` adds the value, what is allowed and a suggestion."""
        p = self.pos.get(tuple(path)) or (self.locate(anchor) if anchor else None) or self.locate(path)
        extra: dict[str, Any] = {"path": tuple(path)}
        if data is not None:
            extra.update(value=data.value, allowed=data.allowed, suggestion=data.suggestion)
        if p is None:
            return Issue(severity, _dotted(path), message, self.path, None, **extra)
        return Issue(severity, _dotted(path), message, p.file, p.line, **extra)


def _dotted(path: tuple) -> str:
    return ".".join(str(p) for p in path)


def _locate(pos: dict, path: tuple) -> Pos | None:
    path = tuple(path)
    while path:
        if path in pos:
            return pos[path]
        path = path[:-1]
    return None


class _Report:
    def __init__(self, loaded: Loaded):
        self.loaded = loaded

    def error(self, path: tuple, message: str, anchor: tuple | None = None,
              data: Problem | None = None) -> None:
        self.loaded.issues.append(self.loaded.issue("error", path, message, anchor, data))

    def problem(self, path: tuple, pr: Problem, anchor: tuple | None = None) -> None:
        """A Problem of the engine, reported at ``path`` (the key as the file names it)."""
        self.loaded.issues.append(self.loaded.issue(pr.severity, path, pr.message, anchor, pr))

    def warning(self, path: tuple, message: str, anchor: tuple | None = None) -> None:
        self.loaded.issues.append(self.loaded.issue("warning", path, message, anchor))

    def file_of(self, path: tuple) -> str:
        p = _locate(self.loaded.pos, path)
        return p.file if p else self.loaded.path


# ---------------------------------------------------------------------------------------------
# public API


def fleet_file_for(path: str) -> str | None:
    """The fleet.yaml a lone station file takes its defaults from, or None."""
    folder = os.path.dirname(os.path.abspath(path))
    if os.path.basename(folder) != "stations":
        return None
    candidate = os.path.normpath(os.path.join(os.path.dirname(path) or ".", "..", "fleet.yaml"))
    return candidate if os.path.isfile(candidate) else None


def station_files(folder: str) -> list[str]:
    sdir = os.path.join(folder, "stations")
    return sorted(p for p in glob.glob(os.path.join(sdir, "*.yaml")) + glob.glob(os.path.join(sdir, "*.yml"))
                  if os.path.isfile(p))


def validate_station(path: str, fleet_file: Any = AUTO) -> Loaded:
    """Read and validate one station file; never raises for bad content (see ``Loaded.issues``).
    A missing station file raises FileNotFoundError."""
    if not os.path.isfile(path):
        raise FileNotFoundError(path)
    P.load_plugins()            # the sections of plug-in outputs ($HOOKWATCH_OUTPUTS)
    if fleet_file is AUTO:
        fleet_file = fleet_file_for(path)
    loaded = Loaded(path=path, cfg=None, fleet_file=fleet_file)
    tree: dict = {}
    pos: dict = {}
    if fleet_file:
        ftree, fpos, fissues = _read_fleet(fleet_file)
        loaded.issues.extend(fissues)
        if ftree is None:
            try:                      # still name the station in reports
                st = load_yaml(path).data.get("station")
                loaded.name = st.get("id") if isinstance(st, dict) and isinstance(st.get("id"), str) else None
            except (YamlError, OSError, UnicodeDecodeError):
                pass
            return loaded
        tree, pos = ftree, fpos
    try:
        doc = load_yaml(path)
    except YamlError as e:
        loaded.issues.append(Issue("error", "", e.msg, e.file, e.line))
        return loaded
    except (OSError, UnicodeDecodeError) as e:
        loaded.issues.append(Issue("error", "", f"cannot read: {getattr(e, 'strerror', None) or e}", path))
        return loaded
    tree = _merge(tree, doc.data)
    pos = {**pos, **doc.pos}
    loaded.pos = pos
    st = tree.get("station")
    if isinstance(st, dict) and isinstance(st.get("id"), str):
        loaded.name = st["id"]
    loaded.cfg = _build(tree, loaded)
    if loaded.errors:
        loaded.cfg = None
    return loaded


def validate_fleet(folder: str) -> list[Loaded]:
    """Validate every station of a fleet folder (``fleet.yaml`` + ``stations/*.yaml``)."""
    if not os.path.isdir(folder):
        raise FileNotFoundError(folder)
    candidate = os.path.join(folder, "fleet.yaml")
    ff = candidate if os.path.isfile(candidate) else None
    return [validate_station(p, fleet_file=ff) for p in station_files(folder)]


def load_station(path: str, fleet_file: Any = AUTO):
    """The StationConfig of one station file; ConfigError lists every problem."""
    loaded = validate_station(path, fleet_file)
    if loaded.errors:
        raise ConfigError(_dedupe(loaded.errors))
    return loaded.cfg


def load_fleet(folder: str) -> list:
    """The StationConfigs of a fleet folder, in file-name order. ConfigError lists every problem,
    including clashes between stations (ids, serial ports, Modbus TCP units, MQTT client ids)."""
    loaded = validate_fleet(folder)
    errors = [i for ld in loaded for i in ld.errors]
    if not errors:
        errors = [i for _, i in cross_issues(loaded) if i.severity == "error"]
    if errors:
        raise ConfigError(_dedupe(errors))
    return [ld.cfg for ld in loaded]


def _dedupe(issues: list[Issue]) -> list[Issue]:
    seen, out = set(), []
    for i in issues:
        if i not in seen:
            seen.add(i)
            out.append(i)
    return out


# ---------------------------------------------------------------------------------------------
# fleet.yaml and the merge


def _read_fleet(file: str) -> tuple[dict | None, dict, list[Issue]]:
    try:
        doc = load_yaml(file)
    except YamlError as e:
        return None, {}, [Issue("error", "", e.msg, e.file, e.line)]
    except (OSError, UnicodeDecodeError) as e:
        return None, {}, [Issue("error", "", f"cannot read: {getattr(e, 'strerror', None) or e}", file)]
    issues = []
    for k in doc.data:
        if k in FLEET_KEYS:
            continue
        p = doc.pos[(k,)]
        if S.lookup((k,)) is not None or any(k == p.spec.name for p in P.sections()):
            msg = f"station settings in fleet.yaml go under `defaults:` (defaults:\\n  {k}: …)"
        else:
            msg = ("unknown key" + suggestion_text(did_you_mean(k, FLEET_KEYS))
                   + f"; fleet.yaml has: {', '.join(FLEET_KEYS)}")
        issues.append(Issue("error", k, msg, file, p.line))
    defaults = doc.data.get("defaults")
    if defaults is None:
        defaults = {}
    if not isinstance(defaults, dict):
        issues.append(Issue("error", "defaults", f"{_shown(defaults)} is not a mapping; allowed: "
                            "a station file's sections (meter:, method:, mqtt:, …)", file,
                            doc.pos[("defaults",)].line))
        return None, {}, issues
    st = defaults.get("station")
    if isinstance(st, dict) and "id" in st:
        issues.append(Issue("error", "station.id", "cannot be a fleet default: each station file "
                            "names its own station", file, doc.pos[("defaults", "station", "id")].line))
    if issues:
        return None, {}, issues
    pos = {p[1:]: v for p, v in doc.pos.items() if p[:1] == ("defaults",) and len(p) > 1}
    return defaults, pos, []


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        if isinstance(out.get(k), dict) and (isinstance(v, dict) or v is None):
            out[k] = _merge(out[k], v or {})
        else:
            out[k] = v
    return out


# ---------------------------------------------------------------------------------------------
# validation against the schema

_SPECIAL_UNKNOWN = {
    ("mqtt", "password"): "a password is never written into a configuration file: name an "
                          "environment variable in mqtt.password_env (e.g. set by the unit's "
                          "EnvironmentFile=) or a file (mode 0600) in mqtt.password_file",
    ("method", "t_set"): "not set in method: — the tension setpoint of a test is test.t_set_n "
                         "(or `hookwatch run --t-set`)",
    ("method", "t_end"): "not set in method: — the planned duration of a test is test.t_end_s "
                         "(or `hookwatch run --t-end`)",
    ("control", "ts"): "the sampling period is a method parameter: method.ts",
}


def _unknown(path: tuple, options, rep: _Report) -> None:
    special = _SPECIAL_UNKNOWN.get(path)
    if special:
        rep.error(path, special)
        return
    name = path[-1]
    sugg = did_you_mean(name, options)
    hint = suggestion_text(sugg)
    if not hint:
        elsewhere = [_dotted(p) for p, e in S.walk() if p[-1] == name and p[:-1] != path[:-1]]
        if elsewhere:
            hint = f"; it is a key of {' / '.join(e.rsplit('.', 1)[0] + ':' for e in elsewhere)}"
    where = f"keys of {_dotted(path[:-1])}:" if len(path) > 1 else "sections:"
    msg = f"unknown key{hint} ({where} {', '.join(options)})"
    rep.problem(path, Problem(path, msg, allowed=", ".join(options), suggestion=sugg))


_WRONG_TYPE = {"int": "an integer", "float": "a number", "bool": "true or false",
               "str_list": "a list", "ip_list": "a list"}


def convert(k: S.Key, v: Any) -> tuple[bool, Any]:
    """(True, value) or (False, Problem) for one key's value (the Problem's path is empty: the
    caller knows where the value is)."""
    allowed = k.allowed()

    def _bad(v: Any, message: str, allowed: str) -> Problem:
        return Problem((), message, value=v, allowed=allowed)

    if v is None:
        if k.nullable:
            return True, None
        d = "" if k.required else f"; leave the key out for the default ({show_yaml(k.default)})"
        return False, _bad(v, f"null is not allowed; allowed: {allowed}{d}", allowed)
    if isinstance(v, dict):
        return False, _bad(v, f"a mapping is not allowed here; allowed: {allowed}", allowed)
    kind = k.kind
    if kind == "prior_list":
        good, out = S.parse_prior_entries(v)
        return (True, out) if good else (False, _bad(v, f"{out}; allowed: {allowed}", allowed))
    if kind in ("int", "float"):
        bad = isinstance(v, bool) or not isinstance(v, (int, float)) or (kind == "int" and isinstance(v, float))
        if bad:
            return False, _bad(v, f"{_shown(v)} is not {_WRONG_TYPE[kind]}; allowed: {allowed}", allowed)
        if kind == "float":
            v = float(v)
            if not S.finite(v):
                return False, _bad(v, f"{_shown(v)} is not a finite number; allowed: {allowed}", allowed)
        if k.choices is not None:
            if v not in k.choices:
                return False, _bad(v, f"{_shown(v)} is not allowed; allowed: {allowed}", allowed)
            return True, v
        if ((k.lo is not None and (v <= k.lo if k.lo_open else v < k.lo))
                or (k.hi is not None and (v >= k.hi if k.hi_open else v > k.hi))):
            return False, _bad(v, f"{_shown(v)} is out of range; allowed: {allowed}", allowed)
        return True, v
    if kind == "bool":
        if not isinstance(v, bool):
            return False, _bad(v, f"{_shown(v)} is not true or false; allowed: {allowed}", allowed)
        return True, v
    if kind in ("str_list", "ip_list"):
        if not isinstance(v, list):
            return False, _bad(v, f"{_shown(v)} is not a list; allowed: {allowed}", allowed)
        out = []
        for i, item in enumerate(v):
            if not isinstance(item, str) or not item.strip():
                return False, _bad(v, f"item {i + 1} ({_shown(item)}) is not a string; "
                                   f"allowed: {allowed}", allowed)
            if kind == "ip_list" and not S.check_ip(item.strip()):
                return False, _bad(v, f"item {i + 1} ({clip(item, ECHO)}) is not an IP address or network; "
                                   f"allowed: {allowed}", allowed)
            out.append(item.strip())
        return True, tuple(out)
    # string kinds
    if not isinstance(v, str):
        hint = ""
        if isinstance(v, bool):
            hint = " (YAML reads yes/no/on/off/true/false as a boolean: put the value in quotes)"
        elif isinstance(v, (int, float)):
            hint = f" (put it in quotes: '{v}')"
        elif isinstance(v, list):
            hint = ""
        return False, _bad(v, f"{_shown(v)} is not a string{hint}; allowed: {allowed}", allowed)
    if kind == "enum":
        for c in k.choices or ():
            if v.strip().lower() == str(c).lower():
                return True, c
        return False, _bad(v, f"{clip(v, ECHO)} is not allowed; allowed: {allowed}", allowed)
    if kind == "str":
        return True, v
    s = v.strip()
    if not s:
        return False, _bad(v, f"{clip(v, ECHO)} is empty; allowed: {allowed}", allowed)
    if kind == "ident" and not S.check_ident(s):
        return False, _bad(v, f"{clip(v, ECHO)} is not a valid name; allowed: {allowed}", allowed)
    if kind == "topic" and not S.TOPIC_RE.match(s):
        return False, _bad(v, f"{clip(v, ECHO)} is not a valid topic prefix; allowed: {allowed}", allowed)
    if kind == "envvar" and not S.ENV_RE.match(s):
        return False, _bad(v, f"{clip(v, ECHO)} is not a valid variable name; allowed: {allowed}", allowed)
    return True, s


def _resolve(value: str, origin: str) -> str:
    if "://" in value:
        return value                      # pyserial URL (socket://, rfc2217://)
    value = os.path.expanduser(value) if value.startswith("~/") else value
    if os.path.isabs(value):
        return os.path.normpath(value)
    return os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(origin)), value))


def _section(sec: S.Section, tree: Any, path: tuple, rep: _Report, ctx: dict):
    if tree is None:
        tree = {}
    if not isinstance(tree, dict):
        rep.error(path, f"{_shown(tree)} is not a mapping; allowed: a section with the keys "
                  f"{', '.join(e.name for e in sec.entries)}")
        return None
    names = [e.name for e in sec.entries]
    for k in tree:
        if k not in names:
            _unknown(path + (k,), names, rep)
    kw: dict[str, Any] = {}
    ok = True
    for e in sec.entries:
        p = path + (e.name,)
        if isinstance(e, S.Key):
            if e.name in tree:
                good, val = convert(e, tree[e.name])
                if not good:
                    rep.problem(p, val)
                    ok = False
                    continue
                if e.kind in ("path", "port") and val is not None:
                    val = _resolve(val, rep.file_of(p))
            elif e.required:
                ex = f" (e.g. {e.example})" if e.example is not None else ""
                where = "" if (not path or path in rep.loaded.pos) else f" (there is no {_dotted(path)}: section)"
                rep.error(p, f"missing{where}; required: {e.doc}{ex}", anchor=path)
                ok = False
                continue
            else:
                val = e.default
            kw[e.name] = val
        elif isinstance(e, S.Section):
            val = _section(e, tree.get(e.name), p, rep, ctx)
            if val is None:
                ok = False
                continue
            kw[e.name] = val
        elif isinstance(e, S.MethodSection):
            ctx["method_tree"] = (tree.get(e.name), p)
    if sec is S.ROOT:
        mt, mp = ctx["method_tree"]
        m = _method(mt, mp, rep, kw.get("test") or S.TestConfig())
        if m is None:
            return None
        kw["method"] = m
    if not ok:
        return None
    try:
        return sec.cls(**kw)
    except TypeError as e:  # pragma: no cover - a schema bug
        rep.error(path, f"internal: {e}")
        return None


def _method(tree: Any, path: tuple, rep: _Report, test) -> dict | None:
    if tree is None:
        tree = {}
    if not isinstance(tree, dict):
        rep.error(path, f"{_shown(tree)} is not a mapping; allowed: method parameters "
                  f"({', '.join(S.METHOD_KEYS)})")
        return None
    values: dict[str, Any] = {}
    ok = True
    for k, v in tree.items():
        if k in S.METHOD_KEYS:
            values[k] = v
        else:
            _unknown(path + (k,), S.METHOD_KEYS, rep)
            ok = False
    base = {"t_set": test.t_set_n, "t_end": test.t_end_s}
    from_test = {"t_set": ("test", "t_set_n"), "t_end": ("test", "t_end_s")}
    bad: set[str] = set()
    params = None
    for _ in range(len(values) + 2):
        try:
            params = build_params({**{k: v for k, v in values.items() if k not in bad}, **base})
            break
        except ParamError as e:
            pr = e.problem
            ok = False
            # the fields the problem involves that this file sets; a rule between two of them
            # (r_min < r_max) is reported once, on the last one the message names
            mine = [f[0] for f in pr.fields if f and f[0] in values and f[0] not in bad]
            if not mine:
                name = pr.path[0] if pr.path else ""
                rep.problem(from_test.get(name, path), pr)
                break
            bad.update(mine)
            rep.problem(path + (mine[-1],), pr)
            if bad & set(PRIOR_NAMES):      # the prior is one value: its other half is not
                bad.update(PRIOR_NAMES)     # reported as "without" the refused one
    if not ok or params is None:
        return None
    return {k: getattr(params, k) for k in S.METHOD_KEYS}


def default_meter_map() -> str:
    """The packaged ZN-S register map."""
    return os.fspath(DEFAULT_MAP_PATH)


def load_meter_map(cfg):
    """The MeterMap of a station with its overrides applied; MapError/ValueError on a bad map."""
    m = load_map(cfg.meter.map)
    return m.with_overrides(baud=cfg.meter.baud, unit_id=cfg.meter.unit_id, parity=cfg.meter.parity)


def _build(tree: dict, loaded: Loaded):
    rep = _Report(loaded)
    plugged = {p.spec.name: p.spec for p in P.sections()}
    cfg = _section(S.ROOT, {k: v for k, v in tree.items() if k not in plugged}, (), rep, {})
    # the sections of plug-in outputs: checked like the others, handed over on cfg.plugins
    extra = {name: _section(spec, tree.get(name), (name,), rep, {}) for name, spec in plugged.items()}
    if cfg is None or any(v is None for v in extra.values()):
        return None
    # defaults that depend on other keys
    meter = cfg.meter
    if meter.map is None:
        meter = dataclasses.replace(meter, map=default_meter_map())
    outbox = cfg.mqtt.outbox
    if outbox.path is None:
        outbox = dataclasses.replace(outbox, path=os.path.join(cfg.recorder.dir, cfg.station.id,
                                                               "outbox.sqlite"))
    cfg = dataclasses.replace(cfg, meter=meter, mqtt=dataclasses.replace(cfg.mqtt, outbox=outbox),
                              plugins=extra, source=os.path.abspath(loaded.path), fleet_file=(
                                  os.path.abspath(loaded.fleet_file) if loaded.fleet_file else None))
    for rule in S.RULES:
        rule.fn(cfg, rep)
    _check_map(cfg, rep)
    return cfg


def _check_map(cfg, rep: _Report) -> None:
    path = cfg.meter.map
    where = ("meter", "map")
    if not os.path.isfile(path):
        given = _locate(rep.loaded.pos, where) is not None and where in rep.loaded.pos
        rep.error(where, f"{path!r}: no such file" + ("" if given else
                  " (the packaged default map; set meter.map to a register map file)"),
                  anchor=("meter",))
        return
    try:
        load_meter_map(cfg)
    except Exception as e:                # MapError (a ValueError) or a bad override
        text = str(e)
        rep.error(where, text if text.startswith(path + ":") else f"{path}: {text}", anchor=("meter",))


# ---------------------------------------------------------------------------------------------
# clashes between stations


def cross_issues(loaded: list[Loaded]) -> list[tuple[int, Issue]]:
    """Clashes between the stations that run on one box: (index of the station, issue)."""
    out: list[tuple[int, Issue]] = []

    def clash(kind: str, items):
        first: dict = {}
        for idx, path, value, text in items:
            ld = loaded[idx]
            if value in first:
                j, jp = first[value]
                other = loaded[j]
                loc = other.locate(jp)
                ref = f" ({loc})" if loc else ""
                out.append((idx, ld.issue("error", path, f"{text} is also the {_dotted(jp)} of station "
                                          f"{other.cfg.station.id}{ref}; {kind}",
                                          anchor=("station", "id"))))
            else:
                first[value] = (idx, path)

    ok = [(i, ld.cfg) for i, ld in enumerate(loaded) if ld.cfg is not None]
    clash("every station needs its own name",
          [(i, ("station", "id"), c.station.id, repr(c.station.id)) for i, c in ok])
    ports = []
    for i, c in ok:
        for sec in ("meter", "stm32"):
            p = getattr(c, sec).port
            ports.append((i, (sec, "port"), os.path.realpath(p) if os.path.exists(p) else p, repr(p)))
    clash("a serial port can be opened by one station only", ports)
    units = []
    for i, c in ok:
        m = c.modbus_tcp
        if m.enabled:
            host = "*" if m.host in ("0.0.0.0", "::", "") else m.host
            units.append((i, ("modbus_tcp", "unit_id"), (m.port, m.unit_id, host),
                          f"unit {m.unit_id} on {m.host}:{m.port}"))
    # a wildcard listener clashes with every host on that port
    expanded = []
    hosts_by_port: dict[int, set] = {}
    for _, _, (port, _, host), _ in units:
        hosts_by_port.setdefault(port, set()).add(host)
    for i, path, (port, unit, host), text in units:
        hs = hosts_by_port[port]
        if host == "*" or "*" in hs:
            expanded.append((i, path, (port, unit, "*"), text))
        else:
            expanded.append((i, path, (port, unit, host), text))
    clash("one unit ID per station on a shared port", expanded)
    for port, hs in hosts_by_port.items():
        if "*" in hs and len(hs) > 1:
            i = next(i for i, _, (p, _, h), _ in units if p == port and h != "*")
            out.append((i, loaded[i].issue("error", ("modbus_tcp", "host"),
                                           f"port {port} is also served on every interface (0.0.0.0) "
                                           f"by another station; stations sharing a port need the same host")))
    # the gateway's default client ID is hookwatch-<station id> (gateway/outputs/mqtt/output.py)
    clash("MQTT client IDs must be unique on the broker",
          [(i, ("mqtt", "client_id"), (c.mqtt.host, c.mqtt.port, c.mqtt.client_id or f"hookwatch-{c.station.id}"),
            repr(c.mqtt.client_id or f"hookwatch-{c.station.id}"))
           for i, c in ok if c.mqtt.enabled])
    clash("each station needs its own outbox file",
          [(i, ("mqtt", "outbox", "path"), os.path.normpath(c.mqtt.outbox.path), repr(c.mqtt.outbox.path))
           for i, c in ok if c.mqtt.enabled])
    # the doors of plug-in outputs that listen per station (the output registry's rows)
    for p in P.sections():
        if not p.shared:
            clash(f"{p.spec.name} listens on a port of its own per station",
                  [(i, tuple(key.split(".")), (host, port), f"{host}:{port}")
                   for i, c in ok for key, host, port in p.doors(c)])
    return out
