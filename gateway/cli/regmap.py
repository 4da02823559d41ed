"""`hookwatch regmap [STATION.yaml] [--format md|csv]`: the PLC register map of a station."""
from __future__ import annotations

import os
import sys

from ..cli import CliError
from ..config import ConfigError, load_station
from ..outputs.plc import registers

HELP = "print the PLC register map (Modbus TCP) of a station, as Markdown or CSV"
DESCRIPTION = (HELP + ". With a station file the header names its server, unit ID, word order, "
               "write permissions and grade codes; without one, the generic map (docs/registers.md).")


def add_arguments(ap):
    ap.add_argument("station", nargs="?", metavar="STATION.yaml", help="a station file")
    ap.add_argument("--format", choices=("md", "csv"), default="md", help="output format (default md)")
    ap.add_argument("-o", "--output", metavar="PATH", help="write here instead of stdout")


def station_info(path: str) -> dict:

    if os.path.isdir(path):
        raise CliError(f"{path}: a folder; give one station file (stations/<id>.yaml)", 2)
    try:
        cfg = load_station(path)
    except ConfigError as e:
        raise CliError(str(e), 1) from None
    except FileNotFoundError:
        raise CliError(f"{path}: no such file", 2) from None
    mb = cfg.modbus_tcp
    return {"id": cfg.station.id, "host": mb.host, "port": mb.port, "unit_id": mb.unit_id,
            "word_order": mb.word_order, "writes": bool(mb.writes.enabled),
            "allowed_clients": list(mb.writes.allowed_clients or ()), "enabled": bool(mb.enabled),
            "grades": list(cfg.grades)}


def run(args) -> int:

    info = station_info(args.station) if args.station else None
    text = registers.render_csv(info) if args.format == "csv" else registers.render(info)
    if info is not None and not info["enabled"] and args.format == "md":
        text = text.replace("## Conventions", "Note: `modbus_tcp.enabled` is false in this file: the "
                            "station does not serve this map until it is enabled.\n\n## Conventions", 1)
    if args.output:
        try:
            with open(args.output, "w", encoding="utf-8") as f:
                f.write(text)
        except OSError as e:
            raise CliError(f"{args.output}: cannot write: {e.strerror}", 1) from None
    else:
        sys.stdout.write(text)
    return 0
