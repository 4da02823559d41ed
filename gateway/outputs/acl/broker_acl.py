"""The broker's permissions of a site, generated from its stations (``hookwatch config acl``).

Pure: data in, text out (no I/O). The only input is the site as :class:`SiteAcl` — its boxes, each
an identity (the MQTT user name it logs in with on the broker: the CN of its bridge's certificate
on a central Mosquitto, its user on RabbitMQ) with its stations' topics (:class:`StationTopics`,
read from the station files by ``gateway/cli/config_acl.py``), the *commanders* (identities
that send commands, each on one door) and the *readers* (the MES adapter, Telegraf). Every topic
comes from its one definition — the topic tree of ``gateway/outputs/mqtt/schema.py``, the site's
lives (``sitelives.site_filter``, ``mqtt_schema.lives_request_topic``), the console's site view
(``gateway.outputs.console.site.filters``), the Sparkplug node's topics (``sparkplug/namespace.py``) —
never a hand-written string. The rule, for Mosquitto (:func:`mosquitto`) and RabbitMQ
(:func:`rabbitmq`) alike:

- a box writes only its own stations' topics (state, status, telemetry, events, alarms, result,
  lives, replies and its MQTT 5 reply prefix; its Sparkplug edge node's births, deaths and data)
  and the site's shared ``lives_request``; it reads its own stations' commands, the site's lives
  and the site view (state and status of every station of its site);
- a station's commands are written only by the commanders: a commander on the default door writes
  ``<base>/cmd/<command>`` of every station (and the Sparkplug NCMD/DCMD of every node and the
  STATE of the primary hosts the stations follow); one on a named door writes only
  ``<base>/cmd/<door>/<command>`` of the stations that listen on that door (``mqtt.command_doors``);
- commanders and readers read everything below their sites (and the Sparkplug groups).

What it cannot prevent: a box may still publish false values on its *own* stations' topics (a
compromised box lies about its own stations, docs/mqtt.md). :func:`problems` refuses a site in
which one box could write another's topics (a station or an edge node in two boxes, a reply
prefix on someone else's topics or on a command door).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

from ...core.command_rules import door_problem
from ..console.site import filters as site_view_filters
from ..mqtt import schema as mqtt_schema
from ..mqtt.sitelives import site_filter
from ..sparkplug.namespace import NAMESPACE, NodeTopics

__all__ = ["AclError", "Box", "Commander", "Grant", "SiteAcl", "SparkplugNode", "StationTopics",
           "bridge_topic", "grants", "mosquitto", "overlap", "problems", "rabbitmq", "routing_key",
           "write_regex", "read_regex", "IDENTITY_RE", "BRIDGE_LEVEL"]

#: an identity: an MQTT user name (one word: a Mosquitto ACL line, a rabbitmqctl argument)
IDENTITY_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.@-]{0,63}$")
#: a box that bridges its edge broker to the site's announces the link on
#: ``<prefix>/_bridge/<box>/state`` (Mosquitto's bridge notifications, deploy/mosquitto/edge/)
BRIDGE_LEVEL = "_bridge"
#: the MQTT plugin's queues of a user's sessions (RabbitMQ 3.10: ``mqtt-subscription-<id>qos<n>``)
RABBITMQ_QUEUES = "mqtt-subscription-"


class AclError(ValueError):
    """The site cannot be given permissions as it is: every problem, one per line."""

    def __init__(self, problems: list[str]):
        self.problems = problems
        super().__init__("\n".join(problems))


@dataclass(frozen=True)
class SparkplugNode:
    """A station as a device of a Sparkplug edge node (``sparkplug:`` enabled)."""
    group: str
    node: str
    device: str
    host: str | None = None


@dataclass(frozen=True)
class StationTopics:
    """What the permissions need of one station: its id, its base topic (None: no ``mqtt:``, a
    Sparkplug device only), the named command doors it listens on, its MQTT 5 reply prefix (None:
    ``<base>/reply``) and its Sparkplug device (None: no ``sparkplug:``)."""
    station: str
    base: str | None
    doors: tuple[str, ...] = ()
    reply_prefix: str | None = None
    sparkplug: SparkplugNode | None = None


@dataclass(frozen=True)
class Box:
    identity: str
    stations: tuple[StationTopics, ...]


@dataclass(frozen=True)
class Commander:
    """An identity that sends commands, on one door (None: the default door, the MES's)."""
    identity: str
    door: str | None = None


@dataclass(frozen=True)
class SiteAcl:
    boxes: tuple[Box, ...]
    commanders: tuple[Commander, ...] = ()
    readers: tuple[str, ...] = ()
    #: the boxes bridge their edge brokers to this broker (each writes its bridge's state topic)
    bridges: bool = False


@dataclass(frozen=True)
class Grant:
    """What one identity may do: the topic filters it may read (subscribe to) and write."""
    identity: str
    comment: str
    reads: tuple[str, ...] = ()
    writes: tuple[str, ...] = ()
    #: read anything below these roots (commanders, readers): RabbitMQ checks a subscription's own
    #: filter against the read permission, so theirs is a prefix
    read_roots: tuple[str, ...] = field(default=())


# ----------------------------------------------------------------------------- the topics
def _uniq(xs: list[str]) -> tuple[str, ...]:
    return tuple(dict.fromkeys(xs))


def _filter(path: str) -> str:
    """A topic path of the tree (``event/{type}``) as a filter (``event/+``)."""
    return re.sub(r"\{[^}]*\}", "+", path)


def site_root(base: str) -> str:
    """``<prefix>/<site>`` of a station's base topic."""
    return base.rsplit("/", 3)[0]


def bridge_topic(prefix: str, box: str) -> str:
    """Where the bridge of box ``box`` says whether its plant link is up (1) or down (0)."""
    return f"{prefix}/{BRIDGE_LEVEL}/{box}/state"


def _reply_prefix(base: str, st: StationTopics) -> str:
    return st.reply_prefix or mqtt_schema.topic_for(base, "reply")


def _node(sp: SparkplugNode) -> NodeTopics:
    return NodeTopics(sp.group, sp.node, sp.host)


def station_writes(st: StationTopics) -> list[str]:
    """What one station publishes (its shared site topics apart)."""
    out = []
    if st.base is not None:
        out += [f"{st.base}/{_filter(t.path)}" for t in mqtt_schema.TOPICS if t.direction == "publish"]
        out.append(_reply_prefix(st.base, st) + "/#")
    if st.sparkplug is not None:
        out += _node(st.sparkplug).publications((st.sparkplug.device,))
    return out


def station_reads(st: StationTopics) -> list[str]:
    """What one station subscribes to: its command doors, the site's lives and site view, and its
    Sparkplug node's commands and its primary host's STATE."""
    out = []
    if st.base is not None:
        out += [mqtt_schema.command_door_filter(st.base)]
        out += [mqtt_schema.command_door_filter(st.base, d) for d in st.doors]
        out += [site_filter(st.base), mqtt_schema.lives_request_topic(st.base), *site_view_filters(st.base)]
    if st.sparkplug is not None:
        out += [t for t, _ in _node(st.sparkplug).subscriptions()]
    return out


def _command_writes(st: StationTopics, door: str | None) -> list[str]:
    if door is not None:
        return [mqtt_schema.command_door_filter(st.base, door)] if st.base and door in st.doors else []
    out = [mqtt_schema.command_door_filter(st.base)] if st.base is not None else []
    if st.sparkplug is not None:
        n = _node(st.sparkplug)
        out += [n.topic("NCMD"), n.topic("DCMD", st.sparkplug.device)]
        host = n.state_topic()
        if host:
            out.append(host)
    return out


def _owned(box: Box) -> list[str]:
    """Every topic of a box's stations and edge nodes (no other box may write one)."""
    out = [f"{st.base}/#" for st in box.stations if st.base is not None]
    for st in box.stations:
        if st.sparkplug is not None:
            n = st.sparkplug
            out += [f"{NAMESPACE}/{n.group}/+/{n.node}", f"{NAMESPACE}/{n.group}/+/{n.node}/+"]
    return out


def _shared(box: Box) -> set[str]:
    """The site-level topics every box of a site writes (the lives requests)."""
    return {mqtt_schema.lives_request_topic(st.base) for st in box.stations if st.base is not None}


def overlap(a: str, b: str) -> bool:
    """Whether two topic filters match a common topic."""
    pa, pb = a.split("/"), b.split("/")
    for i in range(max(len(pa), len(pb))):
        x = pa[i] if i < len(pa) else None
        y = pb[i] if i < len(pb) else None
        if x == "#" or y == "#":
            return True
        if x is None or y is None:
            return False
        if x != y and "+" not in (x, y):
            return False
    return True


# ----------------------------------------------------------------------------- the checks
def _level_problems(topic: str, what: str) -> list[str]:
    bad = [lv for lv in topic.split("/") if not lv or any(c.isspace() or ord(c) < 32 for c in lv)]
    return [f"{what}: topic {topic!r} has an empty level or one with a space or a control "
            "character; rename it"] if bad else []


def _identities(site: SiteAcl) -> list[str]:
    out: list[str] = []
    seen: dict[str, str] = {}
    roles = ([(b.identity, "box") for b in site.boxes] + [(c.identity, "commander") for c in site.commanders]
             + [(r, "reader") for r in site.readers])
    for ident, role in roles:
        if not IDENTITY_RE.match(ident):
            out.append(f"{role} identity {ident!r}: a user name of 1–64 letters, digits, '.', '_', '-' "
                       "and '@', starting with a letter or digit")
        elif ident in seen and not (role == seen[ident] == "commander"):
            out.append(f"identity {ident!r} is named twice (as {seen[ident]} and as {role}); "
                       "one identity, one role")
        seen.setdefault(ident, role)
    return out


def _commanders(site: SiteAcl) -> list[str]:
    out: list[str] = []
    doors = {d for b in site.boxes for st in b.stations for d in st.doors}
    pairs: set[tuple[str, str | None]] = set()
    for c in site.commanders:
        if (c.identity, c.door) in pairs:
            continue
        if any(i == c.identity for i, _ in pairs):
            out.append(f"commander {c.identity!r} is given two doors; an identity commands through one")
        pairs.add((c.identity, c.door))
        if c.door is None:
            continue
        why = door_problem(c.door)
        if why is not None:
            out.append(f"commander {c.identity!r}, door {c.door!r}: {why}")
        elif c.door not in doors:
            out.append(f"commander {c.identity!r}, door {c.door!r}: no station of the site listens on it "
                       "(mqtt.command_doors of the stations it commands)")
    return out


def _clashes(site: SiteAcl) -> list[str]:
    out: list[str] = []
    bases: dict[str, str] = {}
    nodes: dict[tuple[str, str], str] = {}
    for b in site.boxes:
        if not b.stations:
            out.append(f"box {b.identity!r} has no station")
        for st in b.stations:
            where = f"box {b.identity!r}, station {st.station!r}"
            for t in (st.base, st.reply_prefix):
                out += _level_problems(t, where) if t else []
            owner = bases.setdefault(st.base, b.identity) if st.base is not None else b.identity
            if owner != b.identity:
                out.append(f"station {st.station!r} ({st.base}) is in box {owner!r} and in box "
                           f"{b.identity!r}; a station belongs to one box")
            if st.sparkplug is not None:
                key = (st.sparkplug.group, st.sparkplug.node)
                if key in nodes and nodes[key] != b.identity:
                    out.append(f"Sparkplug edge node {key[1]!r} of group {key[0]!r} is in box "
                               f"{nodes[key]!r} and in box {b.identity!r}; an edge node belongs to one box")
                nodes.setdefault(key, b.identity)
    return out


def _trespass(site: SiteAcl) -> list[str]:
    """A box's write that reaches another box's topics or a command door (a reply prefix there)."""
    out: list[str] = []
    doors = [w for b in site.boxes for st in b.stations for d in (None, *st.doors)
             for w in _command_writes(st, d)]
    for b in site.boxes:
        shared = _shared(b)
        writes = [w for st in b.stations for w in station_writes(st) if w not in shared]
        others = [(o.identity, f) for o in site.boxes if o.identity != b.identity for f in _owned(o)]
        for w in _uniq(writes):
            hit = next((f"box {who!r}'s {f}" for who, f in others if overlap(w, f)), None)
            hit = hit or next((f"the command door {d}" for d in doors if overlap(w, d)), None)
            if hit:
                out.append(f"box {b.identity!r} would write {w}, which reaches {hit}: a reply prefix "
                           "(mqtt.reply_prefix) belongs below the station's own base topic, outside cmd/")
    return out


def problems(site: SiteAcl) -> list[str]:
    """Everything that keeps the site from its permissions (empty: none)."""
    if not site.boxes:
        return ["no box: a site needs at least one box with its stations"]
    return _identities(site) + _commanders(site) + _clashes(site) + _trespass(site)


# ----------------------------------------------------------------------------- the grants
def _box_grant(site: SiteAcl, b: Box) -> Grant:
    writes = [w for st in b.stations for w in station_writes(st)]
    writes += sorted(_shared(b))
    # its own configuration report (issue 37: `hookwatch config`), the box named by its identity
    writes += sorted({f"{site_root(st.base)}/{mqtt_schema.BOX_LEVEL}/{mqtt_schema.topic_level(b.identity)}/"
                      f"{mqtt_schema.BOX_CONFIG}" for st in b.stations if st.base is not None})
    if site.bridges:
        writes += [bridge_topic(_prefix(st.base), b.identity) for st in b.stations if st.base is not None]
    reads = [r for st in b.stations for r in station_reads(st)]
    names = ", ".join(st.station for st in b.stations)
    return Grant(b.identity, f"box {b.identity}: its stations {names}", _uniq(reads), _uniq(writes))


def _prefix(base: str) -> str:
    return site_root(base).rsplit("/", 1)[0]


def _roots(site: SiteAcl) -> list[str]:
    sts = [st for b in site.boxes for st in b.stations]
    roots = [site_root(st.base) for st in sts if st.base is not None]
    if site.bridges:
        roots += [f"{_prefix(st.base)}/{BRIDGE_LEVEL}" for st in sts if st.base is not None]
    roots += [st.reply_prefix for st in sts if st.reply_prefix and not any(
        overlap(st.reply_prefix + "/#", r + "/#") for r in roots)]
    roots += [f"{NAMESPACE}/{st.sparkplug.group}" for st in sts if st.sparkplug is not None]
    if any(st.sparkplug is not None and st.sparkplug.host for st in sts):
        roots.append(f"{NAMESPACE}/STATE")
    return roots


def grants(site: SiteAcl) -> list[Grant]:
    """Every identity's permissions (raises :class:`AclError` with :func:`problems`)."""
    found = problems(site)
    if found:
        raise AclError(found)
    out = [_box_grant(site, b) for b in site.boxes]
    roots = _uniq([f"{r}/#" for r in _roots(site)])
    sts = [st for b in site.boxes for st in b.stations]
    done: set[str] = set()
    for c in site.commanders:
        if c.identity in done:
            continue
        done.add(c.identity)
        writes = [w for st in sts for w in _command_writes(st, c.door)]
        door = "the default door" if c.door is None else f"door {c.door}"
        out.append(Grant(c.identity, f"commander {c.identity}: commands on {door}; reads the site",
                         roots, _uniq(writes), roots))
    for r in dict.fromkeys(site.readers):
        out.append(Grant(r, f"reader {r}: reads the site, writes nothing", roots, (), roots))
    return out


# ----------------------------------------------------------------------------- Mosquitto
def mosquitto(gs: list[Grant], header: list[str]) -> str:
    """A Mosquitto ``acl_file``: a ``user`` block per identity (``topic write|read|readwrite``)."""
    out = [f"# {h}" if h else "#" for h in header]
    for g in gs:
        out += ["", f"# {g.comment}", f"user {g.identity}"]
        for w in g.writes:
            out.append(f"topic {'readwrite' if w in g.reads else 'write'} {w}")
        out += [f"topic read {r}" for r in g.reads if r not in g.writes]
    return "\n".join(out) + "\n"


# ----------------------------------------------------------------------------- RabbitMQ
_META = re.compile(r"([\\.^$|?*+()\[\]{}])")


def routing_key(topic: str) -> str:
    """An MQTT topic or filter as RabbitMQ's MQTT plugin routes or binds it ('/' → '.', '+' → '*')."""
    return topic.replace("/", ".").replace("+", "*")


def _level(lv: str, first: bool) -> str:
    if first and lv == NAMESPACE:       # the plugin's sparkplug_b option makes it spBv1_0
        return _META.sub(r"\\\1", NAMESPACE).replace(r"\.", "[._]")
    return _META.sub(r"\\\1", lv)


def write_regex(filters: tuple[str, ...]) -> str:
    """The routing keys of the topics ``filters`` match ('+' one level, a last '#' any below)."""
    alts = []
    for f in filters:
        levels = f.split("/")
        tail = ""
        if levels[-1] == "#":
            levels, tail = levels[:-1], r"(?:\..*)?"
        alts.append(r"\.".join("[^.]+" if lv == "+" else _level(lv, i == 0) for i, lv in enumerate(levels))
                    + tail)
    return "^(?:" + "|".join(alts) + ")$" if alts else "^$"


def read_regex(filters: tuple[str, ...], roots: tuple[str, ...]) -> str:
    """The subscriptions (binding keys, their wildcards as written) ``filters`` name, and anything
    below ``roots`` (each ``<root>/#``)."""
    alts = [r"\.".join(r"\*" if lv == "+" else _level(lv, i == 0) for i, lv in enumerate(f.split("/")))
            for f in filters if f not in roots]
    alts += [r"\.".join(_level(lv, i == 0) for i, lv in enumerate(r[:-2].split("/"))) + r"(?:\..*)?"
             for r in roots]
    return "^(?:" + "|".join(alts) + ")$" if alts else "^$"


def rabbitmq_problems(gs: list[Grant]) -> list[str]:
    """Topic levels RabbitMQ cannot tell apart: its MQTT plugin turns '/' into '.' (and '+' into
    '*'), so a '.' or '*' inside a level would be read as another level or a wildcard."""
    out = []
    for g in gs:
        for t in (*g.writes, *g.reads):
            levels = t.split("/")
            bad = [lv for i, lv in enumerate(levels) if ("." in lv or "*" in lv)
                   and not (i == 0 and lv == NAMESPACE)]
            if bad:
                out.append(f"{g.identity}: topic {t} has a level with '.' or '*' ({bad[0]!r}), which "
                           "RabbitMQ's MQTT plugin reads as a level separator or a wildcard; rename it")
    return list(dict.fromkeys(out))


def _q(s: str) -> str:
    return "'" + s.replace("'", "'\"'\"'") + "'"


def rabbitmq(gs: list[Grant], header: list[str], exchange: str = "amq.topic") -> str:
    """A shell script of ``rabbitmqctl`` commands: per identity its vhost permissions (its MQTT
    sessions' queues, the topic exchange) and its topic permissions on ``exchange`` (write: the
    routing keys it may publish to; read: the subscriptions it may make). Raises
    :class:`AclError` for a topic RabbitMQ cannot tell apart (:func:`rabbitmq_problems`)."""
    found = rabbitmq_problems(gs)
    if found:
        raise AclError(found)
    x = _META.sub(r"\\\1", exchange)
    res = f"^(?:{x}|{RABBITMQ_QUEUES}.*)$"
    out = ["#!/bin/sh", *[f"# {h}" if h else "#" for h in header],
           "set -eu", 'VHOST="${1:-/}"', 'CTL="${RABBITMQCTL:-rabbitmqctl}"']
    for g in gs:
        out += ["", f"# {g.comment}",
                f'$CTL set_permissions -p "$VHOST" {_q(g.identity)} {_q("^" + RABBITMQ_QUEUES)} '
                f"{_q(res)} {_q(res)}",
                f'$CTL set_topic_permissions -p "$VHOST" {_q(g.identity)} {_q(exchange)} '
                f"{_q(write_regex(g.writes))} {_q(read_regex(g.reads, g.read_roots))}"]
    return "\n".join(out) + "\n"
