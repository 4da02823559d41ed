"""`hookwatch config acl PATH`: the broker's permissions of a box or a site, from the station files.

PATH is one box — its fleet folder (``fleet.yaml`` + ``stations/*.yaml``, as ``hookwatch run``
takes) or one station file — or a site description, a small YAML file naming the boxes of a site::

    boxes:                  # each box's identity on the broker → its fleet folder (or station file)
      edge-box01: box01     #   relative to this file
      edge-box02: box02
    commanders:             # identities that send commands → their door
      mes: default          #   the default door <base>/cmd/<command> (and Sparkplug NCMD/DCMD)
      panel: operator       #   <base>/cmd/operator/<command> of the stations with mqtt.command_doors: [operator]
    readers: [telegraf]     # identities that read the site and write nothing

A box's stations are read as ``hookwatch run`` reads them (the same validation: a broken station
file is an error here too); what the permissions need of each — its base topic, command doors,
reply prefix and Sparkplug device — is the pure input of :mod:`gateway.outputs.acl.broker_acl`, which writes
the Mosquitto ``acl_file`` or the RabbitMQ ``rabbitmqctl`` commands (docs/deploy.md, "Broker
permissions").
"""
from __future__ import annotations

import argparse
import os
import sys
from typing import Any

from ..cli import CliError
from ..config import ConfigError, load_fleet, load_station
from ..outputs.acl import broker_acl as A
from ..outputs.registry import mqtt_settings
from ..outputs.sparkplug.output import settings_from_config
from ..plumbing.safeout import write_atomic
from ..plumbing.safeyaml import YamlError, kind, load

HELP = "write the broker's permissions (Mosquitto ACL, RabbitMQ topic permissions) from the station files"
DESCRIPTION = (
    HELP + ". One identity per box: it may write only its own stations' topics (state, events, "
    "lives, results, replies, its Sparkplug node's), read their commands and the site's shared "
    "lives, state and status; commands are written only by the commanders, each on its own door "
    "(its own command budget); readers read. PATH is a box (its fleet folder or a station file; "
    "the identity is the stations' mqtt.username or --identity) or a site description (a YAML file "
    "with `boxes:`, `commanders:`, `readers:`; docs/deploy.md, \"Broker permissions\"). "
    "Exit 0: written; 1: the stations or the site cannot be given permissions (why, one line "
    "each); 2: usage.")

FORMATS = ("mosquitto", "rabbitmq")
SITE_KEYS = ("boxes", "commanders", "readers")
#: the commander's door that is the default one (``<base>/cmd/<command>``)
DEFAULT_DOOR = "default"
#: boxes in one site description at most (every input bounded)
MAX_BOXES = 1000


def add_arguments(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("path", metavar="PATH", help="a box's fleet folder or station file, or a site "
                    "description (YAML with `boxes:`)")
    ap.add_argument("--format", choices=FORMATS, default="mosquitto",
                    help="mosquitto: an acl_file; rabbitmq: a shell script of rabbitmqctl "
                         "set_permissions / set_topic_permissions (default: mosquitto)")
    ap.add_argument("-o", "--output", metavar="FILE", help="write here (atomically) instead of stdout")
    ap.add_argument("--identity", metavar="NAME", help="a box's identity on the broker (PATH a box; "
                    "default: its stations' mqtt.username)")
    ap.add_argument("--commander", metavar="NAME[=DOOR]", action="append", default=[],
                    help="an identity that sends commands, on DOOR (default: the default door "
                         "<base>/cmd/<command>); repeatable")
    ap.add_argument("--reader", metavar="NAME", action="append", default=[],
                    help="an identity that reads every station's topics and writes none; repeatable")
    ap.add_argument("--bridges", action="store_true",
                    help="the boxes bridge their edge brokers to this broker: each box may announce its "
                         "link on <prefix>/_bridge/<box>/state (Mosquitto's bridge notifications), "
                         "which commanders and readers read")
    ap.add_argument("--exchange", default="amq.topic",
                    help="rabbitmq: the MQTT plugin's topic exchange (mqtt.exchange; default amq.topic)")


# ----------------------------------------------------------------------------- the stations
def _configs(path: str) -> list[Any]:
    try:
        if os.path.isdir(path):
            cfgs = load_fleet(path)
            if not cfgs:
                raise CliError(f"{path}: no station files (expected {os.path.join(path, 'stations', '*.yaml')})", 1)
            return cfgs
        return [load_station(path)]
    except ConfigError as e:
        raise CliError(f"{path}: the stations cannot run, so they get no permissions:\n{e}", 1) from None
    except FileNotFoundError:
        raise CliError(f"{path}: no such file or folder", 1) from None


def station_topics(cfg: Any) -> A.StationTopics | None:
    """What the permissions need of one station (None: it uses no broker)."""
    m, sp = cfg.mqtt, cfg.sparkplug
    base = doors = reply = None
    if m.enabled:
        s = mqtt_settings(cfg)
        base, doors, reply = s.base_topic, s.command_doors, s.reply_prefix
    node = None
    if sp.enabled:
        n = settings_from_config(cfg)
        node = A.SparkplugNode(n.group_id, n.edge_node_id, n.device_id, n.primary_host_id)
    if base is None and node is None:
        return None
    return A.StationTopics(cfg.station.id, base, tuple(doors or ()), reply, node)


def box_of(path: str, identity: str | None = None) -> A.Box:
    """A box from its fleet folder or station file; its identity is ``identity`` or the one user
    name its stations log in with."""
    cfgs = _configs(path)
    stations = tuple(t for t in (station_topics(c) for c in cfgs) if t is not None)
    if identity is None:
        users = {sec.username for c in cfgs for sec in (c.mqtt, c.sparkplug) if sec.enabled}
        if len(users) != 1 or None in users:
            said = ", ".join(sorted(repr(u) for u in users)) or "none"
            raise CliError(f"{path}: which identity does this box have on the broker? Its stations' "
                           f"user names: {said}; give --identity NAME", 2)
        identity = users.pop()
    return A.Box(str(identity), stations)


# ----------------------------------------------------------------------------- a site description
def _site_error(doc: Any, keypath: tuple, message: str) -> CliError:
    pos = doc.pos.get(keypath)
    where = f"{doc.file}:{pos.line}" if pos is not None else doc.file
    return CliError(f"{where}: {message}", 1)


def _names(doc: Any, key: str) -> list[str]:
    v = doc.data.get(key, [])
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise _site_error(doc, (key,), f"`{key}` is {kind(v)}; allowed: a list of identities")
    return v


def _commanders(doc: Any) -> list[A.Commander]:
    v = doc.data.get("commanders", {})
    if not isinstance(v, dict):
        raise _site_error(doc, ("commanders",), f"`commanders` is {kind(v)}; allowed: a mapping "
                          f"identity → door (`{DEFAULT_DOOR}`: the default door)")
    out = []
    for name, door in v.items():
        if not isinstance(door, str):
            raise _site_error(doc, ("commanders", name), f"commander {name!r}: the door is {kind(door)}; "
                              f"allowed: a door's name, or `{DEFAULT_DOOR}`")
        out.append(A.Commander(str(name), None if door == DEFAULT_DOOR else door))
    return out


def site_of(path: str) -> A.SiteAcl:
    """A site from its description (see the module docstring)."""
    try:
        doc = load(path)
    except YamlError as e:
        raise CliError(str(e), 1) from None
    except OSError as e:
        raise CliError(f"{path}: cannot read: {e.strerror or e}", 1) from None
    for k in doc.data:
        if k not in SITE_KEYS:
            raise _site_error(doc, (k,), f"unknown key `{k}`; allowed: {', '.join(SITE_KEYS)}")
    boxes = doc.data.get("boxes")
    if not isinstance(boxes, dict) or not boxes:
        raise _site_error(doc, ("boxes",), "`boxes` must map each box's identity to its fleet folder "
                          "(or station file), relative to this file")
    if len(boxes) > MAX_BOXES:
        raise _site_error(doc, ("boxes",), f"{len(boxes)} boxes; at most {MAX_BOXES}")
    here = os.path.dirname(os.path.abspath(path))
    out = []
    for name, where in boxes.items():
        if not isinstance(where, str) or not where:
            raise _site_error(doc, ("boxes", name), f"box {name!r}: {kind(where)}; allowed: the path "
                              "of its fleet folder or station file")
        out.append(box_of(os.path.normpath(os.path.join(here, where)), str(name)))
    return A.SiteAcl(tuple(out), tuple(_commanders(doc)), tuple(_names(doc, "readers")))


def _is_site(path: str) -> bool:
    if not os.path.isfile(path):
        return False
    try:
        data = load(path).data
    except (YamlError, OSError):
        return False                    # read as a station file: its own error says why
    return "boxes" in data


# ----------------------------------------------------------------------------- the command
def _commander(arg: str) -> A.Commander:
    name, _, door = arg.partition("=")
    return A.Commander(name, None if door in ("", DEFAULT_DOOR) else door)


def _header(args: argparse.Namespace, site: A.SiteAcl) -> list[str]:
    cmd = ["hookwatch config acl", args.path]
    if args.identity:
        cmd += ["--identity", args.identity]
    cmd += [f"--commander {c}" for c in args.commander] + [f"--reader {r}" for r in args.reader]
    cmd += ["--bridges"] if args.bridges else []
    cmd += [f"--format {args.format}"]
    if args.exchange != "amq.topic":
        cmd += ["--exchange", args.exchange]
    head = [f"Generated by `{' '.join(cmd)}`:",
            "do not edit by hand; change the station files (or the site description) and generate it",
            "again (docs/deploy.md, \"Broker permissions\"). One identity per box: it writes only its own",
            "stations' topics (it can still lie about them, never about another box's), reads their",
            "commands and the site's lives, state and status; commands come only from the commanders,",
            "each on its own door; readers read."]
    if args.format == "rabbitmq":
        head += ["", "Usage: sh THIS-FILE [VHOST] (default /; RABBITMQCTL=… to name rabbitmqctl). The users",
                 "exist already (rabbitmqctl add_user NAME: their passwords are yours): "
                 + ", ".join(g for g in _identities(site)) + "."]
    return head


def _identities(site: A.SiteAcl) -> list[str]:
    return list(dict.fromkeys([b.identity for b in site.boxes] + [c.identity for c in site.commanders]
                              + list(site.readers)))


def render(args: argparse.Namespace) -> str:
    """The permissions the arguments ask for, as text (raises CliError)."""
    if _is_site(args.path):
        if args.identity:
            raise CliError("--identity names a box's identity; a site description names its boxes", 2)
        site = site_of(args.path)
        site = A.SiteAcl(site.boxes, site.commanders + tuple(_commander(c) for c in args.commander),
                         site.readers + tuple(args.reader), args.bridges)
    else:
        site = A.SiteAcl((box_of(args.path, args.identity),), tuple(_commander(c) for c in args.commander),
                         tuple(args.reader), args.bridges)
    try:
        gs = A.grants(site)
        if args.format == "rabbitmq":
            return A.rabbitmq(gs, _header(args, site), args.exchange)
        return A.mosquitto(gs, _header(args, site))
    except A.AclError as e:
        raise CliError(f"{args.path}: no permissions written:\n" + "\n".join(e.problems), 1) from None


def _write(path: str, text: str) -> None:
    write_atomic(os.path.abspath(path), text.encode("utf-8"), make_dir=False)


def run(args: argparse.Namespace) -> int:
    text = render(args)
    if args.output:
        try:
            _write(args.output, text)
        except OSError as e:
            raise CliError(f"{args.output}: cannot write: {e.strerror or e}", 1) from None
        print(f"{args.output}: {args.format} permissions written", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0
