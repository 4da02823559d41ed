"""Generate docs/configuration.md from the schema: `python -m gateway.config.docs > docs/configuration.md`."""
from __future__ import annotations

from ..core.method.params import PARAMS
from ..plumbing import safeyaml
from . import sections as S
from .checks import CHECKS
from .loader import FLEET_KEYS

CROSS = (
    "No two stations share a `station.id`.",
    "No serial port (`meter.port`, `stm32.port`) is used twice.",
    "Stations with `modbus_tcp.enabled` may share a port (one server, one unit per station) but not "
    "a `unit_id` on it; stations on one port listen on the same `host`.",
    "No two stations with `mqtt.enabled` share an explicit `mqtt.client_id` or an outbox file.",
    "A plug-in output (`HOOKWATCH_OUTPUTS`: its own section, checked like these; docs/architecture.md, "
    "\"Adding an output\") that listens per station does not share its port with another station.",
)


def _default(k: S.Key) -> str:
    if k.required:
        return "**required**"
    if k.default is None:
        return f"null ({k.null_means})" if k.null_means else "null"
    if isinstance(k.default, tuple) and not k.default:
        return "`[]`"
    if k.default == "":
        return '`""`'
    return f"`{S._show(k.default)}`"


def _esc(s: str) -> str:
    return s.replace("|", "\\|")


def render() -> str:
    out = [
        "# Station configuration",
        "",
        "Generated from `gateway/config/sections.py` (`python -m gateway.config.docs > "
        "docs/configuration.md`); do not edit by hand.",
        "",
        "## Files",
        "",
        "A **fleet folder** (on a box: `/etc/hookwatch`) holds `fleet.yaml` and one file per station, "
        "`stations/<id>.yaml`. `hookwatch run DIR` runs every station of the folder, each in its own "
        "worker process under one supervisor that serves the Modbus TCP ports, the Sparkplug edge nodes, "
        "the console and the metrics endpoint (docs/runtime.md; `--in-process`: all in one process); "
        "`hookwatch run DIR/stations/<id>.yaml` (the `hookwatch@<id>` unit) runs one.",
        "",
        f"- `fleet.yaml` has one section, `defaults:` (its keys: {', '.join(FLEET_KEYS)}), written like "
        "a station file. Every station file is **deep-merged** over it: mappings merge key by key; "
        "numbers, strings and lists are replaced as a whole; a section left empty in the station file "
        "keeps the defaults. `station.id` cannot be a default.",
        "- A station file given on its own takes its defaults from `../fleet.yaml` when it lies in a "
        "folder named `stations`, and stands alone otherwise.",
        "- Relative paths are relative to the folder of the file that sets them (a `meter.map` set in "
        "`fleet.yaml` is relative to the fleet folder).",
        "- Units are in the key names (`_s` seconds, `_n` newton, `_hz`, `_rpm`, `_mb`) or in the "
        "tables below.",
        "- Secrets are never written inline: `mqtt.password` is refused; name an environment variable "
        "(`mqtt.password_env`) or a file (`mqtt.password_file`).",
        "",
        "Errors name the file, the line, the key path, the bad value and what is allowed; an unknown "
        "key is an error with a did-you-mean:",
        "",
        "```",
        "config/stations/loom-02.yaml:14: meter.baud: 'fast' is not an integer; allowed: one of "
        + ", ".join(str(b) for b in S.METER_BAUDS) + ", or null",
        "config/stations/loom-02.yaml:9: meter.buad: unknown key; did you mean 'baud'? (keys of "
        "meter: port, map, baud, unit_id, parity, timeout_s, swap_channels, local_echo, rs485)",
        "```",
        "",
        "A minimal station file (everything else from `fleet.yaml` or the defaults below):",
        "",
        "```yaml",
        "station: {id: loom-01}",
        "meter: {port: /dev/hookwatch/loom-01-meter}",
        "stm32: {port: /dev/hookwatch/loom-01-stm32}",
        "```",
        "",
        "## Keys",
        "",
    ]
    for sec in S.ROOT.entries:
        if isinstance(sec, S.Key):
            out += [f"### `{sec.name}`", "", f"{sec.doc}.", "",
                    "| key | allowed | default | unit |", "|---|---|---|---|",
                    f"| `{sec.name}` | {_esc(sec.allowed())} | {_default(sec)} | {sec.unit} |", ""]
            continue
        if isinstance(sec, S.MethodSection):
            out += ["### `method:`", "",
                    "The method's parameters (METHOD.md §10; the one definition is "
                    "`gateway/core/method/params.py`, which also checks their ranges — see "
                    "docs/method.md). `t_set` and `t_end` are not set here: they are "
                    "`test.t_set_n` and `test.t_end_s`.", "",
                    "| key | default | unit | meaning |", "|---|---|---|---|"]
            for p in PARAMS:
                if p.name in S.METHOD_KEYS:
                    d = ("null" if p.default is None else str(p.default).lower()
                         if isinstance(p.default, bool) else f"{p.default:g}")
                    out.append(f"| `method.{p.name}` | `{d}` | {p.unit} | {_esc(p.doc)} |")
            out.append("")
            continue
        out += _section_doc(sec, (sec.name,))
    out += ["## Rules across keys", "", "Checked whenever a file is loaded (`hookwatch run`, "
            "`hookwatch check`):", ""]
    out += [f"- {r.doc}" for r in S.RULES]
    out += ["", "Between the stations of one fleet folder (and everything named in one "
            "`hookwatch check` call):", ""]
    out += [f"- {c}" for c in CROSS]
    out += ["", "## Limits of a YAML file", "",
            "Every YAML file the gateway reads (station, fleet, meter map, scenario, log sidecar) is "
            "read by one bounded reader (`gateway/plumbing/safeyaml.py`), safe schema only (no `!!python` "
            "tags). A file beyond a limit is refused with one line that names the file, the line "
            "where known, the limit and what is allowed — by `hookwatch check` (exit 1), at start, "
            "and on a reload (the running configuration stays).", "",
            "| limit | configuration files | log sidecars |", "|---|---|---|"]
    for name, what in (("max_bytes", "file size"), ("max_depth", "nesting of lists/mappings"),
                       ("max_aliases", "aliases (`*name`)"),
                       ("max_nodes", "values once aliases and merge keys are expanded"),
                       ("max_int_digits", "characters of an integer")):
        c, sc = getattr(safeyaml.CONFIG, name), getattr(safeyaml.SIDECAR, name)
        fmt = safeyaml._size if name == "max_bytes" else str
        out.append(f"| {what} | {fmt(c)} | {fmt(sc)} |")
    out += ["", "Also refused: text that is not UTF-8, a NUL byte or another control character "
            "(tab and line breaks are fine), a recursive alias, a key given twice. Errors never "
            "quote the content of a file that is not what it should be (`meter.map: /etc/shadow` "
            "says it is not a register map, not what its first line holds).", ""]
    out += ["## `hookwatch check PATH...`", "",
            "Validates, then checks that each valid station can work before anything runs. Exit 0: "
            "no errors (warnings allowed; `--strict` fails on warnings too); 1: errors; 2: usage "
            "(no such path, a folder without `stations/*.yaml`). `--skip-local` leaves out the "
            "checks marked *(this machine)*, for checking a configuration elsewhere than where it runs.",
            ""]
    for c in CHECKS:
        out.append(f"- {c.doc}" + (" *(this machine)*" if c.local else ""))
    out += ["", "Example:", "", "```",
            "config/stations/loom-03.yaml:10: meter.baud: 9600 baud: one poll takes 23.8 ms on the "
            "wire (8 B request + 2.0 ms turnaround + 11 B reply, 11 bits/char), the STM32 exchange "
            "3.5 ms at 115200 baud; the slot is 20.0 ms — 50 Hz is impossible; use ≥ 38400 baud",
            "```", ""]
    return "\n".join(out)


def _section_doc(sec: S.Section, path: tuple) -> list[str]:
    name = ".".join(path)
    out = [f"### `{name}:`", "", f"{sec.doc[0].upper()}{sec.doc[1:]}.", "",
           "| key | allowed | default | unit | meaning |", "|---|---|---|---|---|"]
    subs = []
    for e in sec.entries:
        if isinstance(e, S.Key):
            out.append(f"| `{name}.{e.name}` | {_esc(e.allowed())} | {_esc(_default(e))} | {e.unit} | "
                       f"{_esc(e.doc)} |")
        elif isinstance(e, S.Section):
            out.append(f"| `{name}.{e.name}:` | section, below | | | {_esc(e.doc)} |")
            subs.append(e)
    out.append("")
    for e in subs:
        out += _section_doc(e, path + (e.name,))
    return out


if __name__ == "__main__":
    print(render(), end="")
