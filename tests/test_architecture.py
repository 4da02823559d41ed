"""The import graph of gateway/ and drivers/, read from the source (AST): layers by folder, no
package cycles, no hidden imports.

- The folders are the layers (docs/architecture.md, "The tree at a glance"): ``gateway/core/`` the
  pure core (no I/O, no clock), ``gateway/plumbing/`` process plumbing, ``drivers/`` the devices,
  ``gateway/station/``, ``gateway/outputs/`` (a subpackage per door), ``gateway/offline/``,
  ``gateway/config/``, ``gateway/supervisor/``, ``gateway/commission/``, ``gateway/cli/``; the
  composition root ``gateway/compose.py``. What each layer may import of the others is the table
  ``LAYERS``; a module that sits in no layer folder fails (``LOOSE_ALLOWED``).
- Every import of the project's own modules is at module level (the one exception: gateway/cli/__init__.py
  loads the subcommand asked for with ``importlib``, which is not an ``import`` statement).
- No ``try: import … except ImportError`` around the project's own modules.
- The packages form no cycle. A node is a layer folder (``gateway.station``, ``drivers.sim``), an
  output's subpackage (``gateway.outputs.mqtt``) or a module directly in ``gateway/`` or
  ``gateway/outputs/`` (``gateway.compose``, ``gateway.outputs.registry``).
"""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from collections import defaultdict

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGES = ("gateway", "drivers")
#: the pure core: a folder (its modules import nothing of the project outside it, no I/O, no clock)
PURE_CORE = ("gateway.core",)
#: process plumbing: the bottom of the house (it imports nothing of the project)
PLUMBING = ("gateway.plumbing",)
#: what each layer folder may import of the project besides itself and the package face
#: (``gateway``: ``__version__``); a layer not named here may not be imported by the ones that are
LAYERS: dict[str, tuple[str, ...]] = {
    "gateway.plumbing": (),
    "gateway.core": (),
    "drivers": ("gateway.core", "gateway.plumbing"),
    "gateway.config": ("gateway.core", "gateway.plumbing", "drivers"),
    "gateway.offline": ("gateway.core", "gateway.plumbing"),
    "gateway.station": ("gateway.core", "gateway.plumbing", "gateway.offline"),
    "gateway.outputs": ("gateway.core", "gateway.plumbing", "gateway.offline", "gateway.station", "gateway.config"),
    "gateway.commission": ("gateway.core", "gateway.plumbing", "drivers", "gateway.config", "gateway.outputs"),
    "gateway.supervisor": ("gateway.core", "gateway.plumbing", "drivers", "gateway.config", "gateway.offline",
                           "gateway.station", "gateway.outputs", "gateway.compose"),
    "gateway.compose": ("gateway.core", "gateway.plumbing", "drivers", "gateway.config", "gateway.offline",
                        "gateway.station", "gateway.outputs"),
    "gateway.cli": ("gateway.core", "gateway.plumbing", "drivers", "gateway.config", "gateway.offline",
                    "gateway.station", "gateway.outputs", "gateway.compose", "gateway.supervisor",
                    "gateway.commission"),
}
#: the imports across layers that the table does not allow, each with why (a new one fails)
LAYER_EXCEPTIONS: dict[tuple[str, str], str] = {
    ("gateway.core.command_rules", "gateway.plumbing.ratelog"):
        "``clip``: the one bound on client text echoed back (pure text, beside the rate-limited log)",
    ("gateway.core.command_intake", "gateway.plumbing.ratelog"):
        "``clip``, ``safe``, ``ECHO_CHARS``: the one bound on client text echoed back (pure text)",
}
#: the modules that may sit outside a layer folder: the package faces, the composition root,
#: and the one module loose in gateway/outputs/ (with why)
LOOSE_ALLOWED = {
    "gateway": "the package face (``__version__``)",
    "gateway.compose": "the composition root",
    "gateway.outputs": "the outputs' package face",
    "gateway.outputs.registry": "the output registry: a row per output, read by the composition root, "
                                "the supervisor, the probe and the loader (issue 35 item 1)",
}
#: the standard library modules of I/O, time, threads and processes: none in the pure core
IMPURE = ("os", "io", "sys", "time", "socket", "select", "selectors", "threading", "multiprocessing",
          "asyncio", "subprocess", "sqlite3", "logging", "shutil", "pathlib", "tempfile", "signal",
          "random", "serial", "paho", "aiohttp", "yaml")


def _modules() -> dict[str, str]:
    out = {}
    for pkg in PACKAGES:
        for d, _, files in os.walk(os.path.join(ROOT, pkg)):
            for f in files:
                if f.endswith(".py"):
                    path = os.path.join(d, f)
                    rel = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
                    out[rel[:-len(".__init__")] if rel.endswith(".__init__") else rel] = path
    return out


MODULES = _modules()


def _is_pkg(mod: str) -> bool:
    return MODULES.get(mod, "").endswith("__init__.py")


def _resolve(mod: str, node: ast.ImportFrom | ast.Import) -> list[str]:
    """The project modules an import statement names (empty for third-party ones)."""
    names: list[str] = []
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        if node.level:
            base = mod.split(".") if _is_pkg(mod) else mod.split(".")[:-1]
            base = base[:len(base) - (node.level - 1)]
            prefix = ".".join(base + ([node.module] if node.module else []))
        else:
            prefix = node.module or ""
        names = [prefix]
        for a in node.names:          # `from . import schema` imports a module
            if f"{prefix}.{a.name}" in MODULES:
                names.append(f"{prefix}.{a.name}")
    return [n for n in names if n.split(".")[0] in PACKAGES]


def _node(mod: str) -> str:
    """The graph node of a module: its layer folder (an output's subpackage in gateway/outputs/),
    or itself when it sits directly in gateway/ or gateway/outputs/."""
    parts = mod.split(".")
    if parts[:2] == ["gateway", "outputs"] and len(parts) >= 3 and _is_pkg(".".join(parts[:3])):
        return ".".join(parts[:3])
    if len(parts) >= 2 and _is_pkg(".".join(parts[:2])):
        return ".".join(parts[:2])
    return mod


class _Scan(ast.NodeVisitor):
    def __init__(self, mod: str):
        self.mod = mod
        self.depth = 0
        self.edges: set[str] = set()
        self.hidden: list[str] = []
        self.guarded: list[str] = []

    def _imp(self, node: ast.Import | ast.ImportFrom) -> None:
        targets = _resolve(self.mod, node)
        self.edges.update(targets)
        if targets and self.depth:
            self.hidden.append(f"{self.mod}:{node.lineno} imports {', '.join(targets)} inside a function")

    visit_Import = visit_ImportFrom = _imp

    def _scope(self, node: ast.AST) -> None:
        self.depth += 1
        self.generic_visit(node)
        self.depth -= 1

    visit_FunctionDef = visit_AsyncFunctionDef = visit_Lambda = _scope

    def visit_Try(self, node: ast.Try) -> None:
        catches = set()
        for h in node.handlers:
            for n in ([h.type] if not isinstance(h.type, ast.Tuple) else h.type.elts) if h.type else []:
                if isinstance(n, ast.Name):
                    catches.add(n.id)
        if catches & {"ImportError", "ModuleNotFoundError"}:
            for stmt in node.body:
                for sub in ast.walk(stmt):
                    if isinstance(sub, (ast.Import, ast.ImportFrom)) and _resolve(self.mod, sub):
                        self.guarded.append(f"{self.mod}:{sub.lineno}")
        self.generic_visit(node)


def _scan() -> dict[str, _Scan]:
    out = {}
    for mod, path in sorted(MODULES.items()):
        with open(path, encoding="utf-8") as f:
            tree = ast.parse(f.read(), path)
        s = _Scan(mod)
        s.visit(tree)
        out[mod] = s
    return out


SCANS = _scan()


def _graph() -> dict[str, set[str]]:
    g: dict[str, set[str]] = defaultdict(set)
    for mod, s in SCANS.items():
        a = _node(mod)
        for t in s.edges:
            # a name imported from a package may be one of its modules: resolve to a known module
            while t not in MODULES and "." in t:
                t = t.rsplit(".", 1)[0]
            b = _node(t)
            if a != b and t in MODULES:
                g[a].add(b)
    return g


def _cycles(g: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(set(g) | {w for ws in g.values() for w in ws}):
        if v not in index:
            visit(v)
    return out


def _in(mod: str, prefixes: tuple[str, ...]) -> bool:
    return any(mod == p or mod.startswith(p + ".") for p in prefixes)


def test_the_scan_sees_the_project():
    g = _graph()
    assert "gateway.station" in g and "gateway.outputs.mqtt" in g and len(MODULES) > 50
    assert "gateway.core" in g["gateway.station"] and "gateway.outputs.broker" in g["gateway.outputs.mqtt"]


def test_no_package_cycles():
    assert _cycles(_graph()) == []


def test_no_function_level_imports_of_project_modules():
    hidden = [h for s in SCANS.values() for h in s.hidden]
    assert hidden == []


def test_no_import_error_guards_around_project_modules():
    assert [g for s in SCANS.values() for g in s.guarded] == []


def _layer(mod: str) -> str | None:
    """The layer folder of a module (the longest of ``LAYERS`` it sits in), None for a loose one."""
    return max((la for la in LAYERS if _in(mod, (la,))), key=len, default=None)


def _layer_breaches(scans: dict[str, _Scan]) -> list[str]:
    bad = []
    for m, s in scans.items():
        own = _layer(m)
        if own is None:
            continue
        for t in s.edges:
            while t not in MODULES and "." in t:
                t = t.rsplit(".", 1)[0]
            other = _layer(t)
            if t == "gateway" or other in (None, own) or other in LAYERS[own] or (m, t) in LAYER_EXCEPTIONS:
                continue
            bad.append(f"{m} ({own}) → {t} ({other})")
    return sorted(bad)


def test_each_layer_imports_only_the_layers_below_it():
    """The folders are the layers: a module imports of the project only its own layer folder and
    those ``LAYERS`` names for it (drivers sit on the pure core and the plumbing; the station on
    those and the offline readers; the outputs on the station; …)."""
    assert _layer_breaches(SCANS) == []
    used = {(m, t) for m, s in SCANS.items() for t in s.edges}
    assert set(LAYER_EXCEPTIONS) <= used, "an exception no longer needed: drop it from LAYER_EXCEPTIONS"


def test_no_module_sits_outside_a_layer_folder():
    """Issue 35: nothing loose at gateway/ beyond the composition root, the CLI (a package) and the
    package faces; nothing at gateway/outputs/ outside a subpackage but ``LOOSE_ALLOWED``; the old
    gateway/northbound/ is gone."""
    loose = sorted(m for m in MODULES if _layer(m) is None and m not in LOOSE_ALLOWED)
    assert loose == []
    assert set(LOOSE_ALLOWED) <= set(MODULES), "a listed loose module is gone: drop it from LOOSE_ALLOWED"
    assert not os.path.exists(os.path.join(ROOT, "gateway", "northbound"))
    assert [m for m in MODULES if m.startswith("gateway.outputs.") and m.count(".") == 2
            and not _is_pkg(m)] == ["gateway.outputs.registry"]


def test_the_pure_core_imports_nothing_else_of_the_project():
    bad = [f"{m} → {t}" for m, s in SCANS.items() if _in(m, PURE_CORE)
           for t in s.edges if not _in(t, PURE_CORE) and t != "gateway" and (m, t) not in LAYER_EXCEPTIONS]
    assert bad == []


def _std_imports(tree: ast.Module) -> set[str]:
    """The top-level names of the absolute imports of a module (``os``, ``numpy``, ``threading``)."""
    out = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.Import):
            out |= {a.name.split(".")[0] for a in n.names}
        elif isinstance(n, ast.ImportFrom) and not n.level and n.module:
            out.add(n.module.split(".")[0])
    return out


def test_the_pure_core_has_no_io_and_no_clock():
    """The pure core is a folder: none of its modules imports the standard library's I/O, time,
    threads or processes (nor a serial port, a broker client, a web stack, a YAML reader)."""
    bad = {m: sorted(_std_imports(t) & set(IMPURE)) for m, t in TREES.items() if _in(m, PURE_CORE)}
    assert {m: i for m, i in bad.items() if i} == {}
    assert len(bad) >= 15
    assert _std_imports(ast.parse("import os.path\nfrom time import monotonic\nfrom . import x\n")) == {"os", "time"}


def test_the_layer_check_flags_what_it_should():
    fake = {m: _Scan(m) for m in ("gateway.core.records", "drivers.meter.driver", "gateway.station.station")}
    fake["gateway.core.records"].edges = {"gateway.station.station", "gateway.core.ports"}
    fake["drivers.meter.driver"].edges = {"gateway.plumbing.ratelog", "gateway.outputs.mqtt.schema"}
    fake["gateway.station.station"].edges = {"drivers.meter.driver", "gateway", "gateway.offline.history"}
    assert _layer_breaches(fake) == [
        "drivers.meter.driver (drivers) → gateway.outputs.mqtt.schema (gateway.outputs)",
        "gateway.core.records (gateway.core) → gateway.station.station (gateway.station)",
        "gateway.station.station (gateway.station) → drivers.meter.driver (drivers)"]
    assert _layer("gateway.outputs.plc.modbus_tcp.framer") == "gateway.outputs" and _layer("gateway.compose") \
        == "gateway.compose" and _layer("gateway.outputs.registry") == "gateway.outputs"


def test_the_scanner_flags_what_it_should(tmp_path):
    """The rules themselves, on a small synthetic module."""
    src = ("import os\nfrom gateway.core import records\n"
           "try:\n    from gateway.outputs import registry\nexcept ImportError:\n    registry = None\n"
           "def f():\n    from .station import build\n    import json\n    return build, json\n")
    s = _Scan("gateway.fake")
    s.visit(ast.parse(src))
    assert "gateway.core.records" in s.edges and "gateway.outputs.registry" in s.edges
    assert s.hidden == ["gateway.fake:8 imports gateway.station, gateway.station.build inside a function"]
    assert s.guarded == ["gateway.fake:4"]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


# ------------------------------------------------------------------------------------------------
# structure rules (issues 23, 30): small classes everywhere, outputs typed against the StationView
# contract, one thread → loop hand-over


def _trees() -> dict[str, ast.Module]:
    out = {}
    for mod, path in MODULES.items():
        with open(path, encoding="utf-8") as f:
            out[mod] = ast.parse(f.read(), path)
    return out


TREES = _trees()
#: the longest class allowed in gateway/ and drivers/ (lines, docstrings included)
CLASS_MAX = 300
#: the classes over CLASS_MAX, each with its ceiling (its size when it was named here: it may
#: shrink, never grow) and why; each is named with its ceiling in docs/architecture.md ("Classes
#: over the bound, and why"). One that comes under the bound leaves the table.
CLASS_EXCEPTIONS: dict[str, tuple[int, str]] = {}


def _class_sizes(trees: dict[str, ast.Module]) -> dict[str, int]:
    """Every class (nested ones too) of the given modules: ``module.Class`` → its lines."""
    return {f"{m}.{n.name}": n.end_lineno - n.lineno + 1 for m, t in trees.items()
            for n in ast.walk(t) if isinstance(n, ast.ClassDef) and n.end_lineno is not None}


def _over_the_bound(sizes: dict[str, int], exceptions: dict[str, tuple[int, str]]) -> list[str]:
    """A class over CLASS_MAX that is not an exception, an exception over its ceiling, and an
    exception that is no longer needed (gone, or within the bound)."""
    bad = [f"{c}: {n} lines (at most {CLASS_MAX})" for c, n in sorted(sizes.items())
           if n > CLASS_MAX and c not in exceptions]
    for c, (ceiling, _why) in sorted(exceptions.items()):
        n = sizes.get(c)
        if n is None or n <= CLASS_MAX:
            bad.append(f"{c}: {'gone' if n is None else f'{n} lines'}, no longer an exception: "
                       "remove it from CLASS_EXCEPTIONS and docs/architecture.md")
        elif n > ceiling:
            bad.append(f"{c}: {n} lines, over its ceiling of {ceiling}")
    return bad


def test_no_class_in_gateway_or_drivers_is_over_300_lines():
    """The class bound of the whole house (issue 30 item 3): a class says one thing; the few over
    it are named with a ceiling they can only shrink from."""
    assert _over_the_bound(_class_sizes(TREES), CLASS_EXCEPTIONS) == []


def test_the_class_bound_flags_what_it_should():
    src = "class Small:\n    x = 1\n\n\nclass Big:\n" + "    x = 1\n" * CLASS_MAX
    sizes = _class_sizes({"m": ast.parse(src)})
    assert sizes == {"m.Small": 2, "m.Big": CLASS_MAX + 1}
    assert _over_the_bound(sizes, {}) == [f"m.Big: {CLASS_MAX + 1} lines (at most {CLASS_MAX})"]
    assert _over_the_bound(sizes, {"m.Big": (CLASS_MAX + 1, "")}) == []
    assert _over_the_bound(sizes, {"m.Big": (CLASS_MAX, "")}) == [
        f"m.Big: {CLASS_MAX + 1} lines, over its ceiling of {CLASS_MAX}"]
    assert [b.split(":")[0] for b in _over_the_bound(sizes, {"m.Big": (400, ""), "m.Small": (400, ""),
                                                              "m.Gone": (400, "")})] == ["m.Gone", "m.Small"]


def test_every_class_over_the_bound_is_named_in_the_architecture_doc():
    """docs/architecture.md names each exception with its ceiling, and no other class."""
    with open(os.path.join(ROOT, "docs", "architecture.md"), encoding="utf-8") as f:
        text = f.read()
    section = text.split("## Classes over the bound, and why", 1)[1].split("\n## ", 1)[0]
    rows = {r.split("|")[1].strip().strip("`"): r for r in section.splitlines() if r.startswith("| `")}
    assert set(rows) == set(CLASS_EXCEPTIONS), sorted(set(rows) ^ set(CLASS_EXCEPTIONS))
    for c, (ceiling, _why) in CLASS_EXCEPTIONS.items():
        assert f"| {ceiling} |" in rows[c], rows[c]


def test_no_class_in_the_console_is_over_300_lines():
    """Issue 30.3: the console in small rooms (``ConsoleServer`` was 717 lines, an exception):
    the app and its lifecycle, the shared context, a route module per subject, every class
    within the bound and none of the console named as an exception."""
    sizes = _class_sizes({m: t for m, t in TREES.items() if _in(m, ("gateway.outputs.console",))})
    assert "gateway.outputs.console.app.ConsoleServer" in sizes and len(sizes) > 10
    assert {c: n for c, n in sizes.items() if n > CLASS_MAX} == {}
    assert [c for c in CLASS_EXCEPTIONS if c.startswith("gateway.outputs.console.")] == []


def test_the_console_route_modules_never_import_the_app():
    """The route modules (and the context they share) see the console only through
    ``ConsoleContext``: none imports the app (``app.py``), so the rooms of the console form no
    cycle among themselves (the package graph cannot see this)."""
    rooms = [m for m in MODULES if m.startswith("gateway.outputs.console.routes_")]
    assert len(rooms) >= 3
    app = {"gateway.outputs.console.app"}
    back = [f"{m} → {t}" for m in (*rooms, "gateway.outputs.console.context") for t in SCANS[m].edges if t in app]
    assert back == []
    assert all("gateway.outputs.console.context" in SCANS[m].edges for m in rooms)


#: where outputs (and the station proxy they share) live
OUTPUT_PACKAGES = ("gateway.outputs", "gateway.outputs.console", "gateway.supervisor.remote", "gateway.compose")
#: what a ``station`` parameter may be typed as: the contract (or the station itself, in the
#: composition root), a station id, or a station's configuration mapping (docs renderers)
VIEW_TYPES = ("StationView", "StationLinks", "Station", "str", "dict")


def _station_params(tree: ast.Module) -> list[tuple[int, str, ast.expr | None]]:
    """Every parameter named ``station`` of a function or method: (line, function, annotation)."""
    out = []
    for n in ast.walk(tree):
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
            args = n.args
            for a in (*args.posonlyargs, *args.args, *args.kwonlyargs):
                if a.arg == "station":
                    out.append((n.lineno, n.name, a.annotation))
    return out


def _names(node: ast.expr | None) -> set[str]:
    return {x.id for x in ast.walk(node) if isinstance(x, ast.Name)} if node is not None else set()


def test_outputs_take_their_station_as_a_station_view():
    """A ``station`` parameter in an output module is typed with the contract (gateway/core/ports.py:
    ``StationView``, or ``StationLinks`` in the station's own process), so mypy checks what an
    output reads and calls; a station id is a ``str``. Never ``Any``, never untyped."""
    bad = []
    for m, t in TREES.items():
        if not _in(m, OUTPUT_PACKAGES):
            continue
        for line, fn, ann in _station_params(t):
            if ann is None or ast.unparse(ann) in ("Any", "Any | None", "Optional[Any]") \
                    or not _names(ann) & set(VIEW_TYPES):
                bad.append(f"{m}:{line} {fn}(station: {ast.unparse(ann) if ann else 'untyped'})")
    assert bad == []


def test_the_station_and_its_proxy_are_station_views():
    """Both implement the contract: mypy checks the uses; here, that the contract names every
    member both have (a member added to one and read by an output must be in StationView)."""
    def members(mod: str, cls: str) -> set[str]:
        node = next(n for n in TREES[mod].body if isinstance(n, ast.ClassDef) and n.name == cls)
        return {n.name for n in node.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
    view = members("gateway.core.ports", "StationView") | members("gateway.core.ports", "CommandSink")
    assert view >= {"id", "ts", "limits", "default_plan", "state", "alarms", "outputs", "submit",
                    "refused"}
    assert {"submit", "refused"} <= members("gateway.station.station", "Station")
    assert {"submit", "refused"} <= members("gateway.supervisor.remote", "RemoteStation")
    # the proxy feeds its outputs through the station's own fan-out: it constructs the Fanout
    # that gateway.station.fanout defines (read from the syntax tree, not a string search)
    tree = TREES["gateway.supervisor.remote"]
    imported = {a.asname or a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
                and (n.module or "").endswith("station.fanout") for a in n.names if a.name == "Fanout"}
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
             and n.func.id in imported]
    assert imported and calls, (imported, len(calls))


#: where asyncio.run_coroutine_threadsafe may be called (a module added here says why)
HANDOVER_ALLOWED = {
    "gateway.plumbing.threadloop": "the one hand-over",
}


def test_one_thread_to_loop_hand_over():
    """``asyncio.run_coroutine_threadsafe`` only in gateway/plumbing/threadloop.py (``submit_to``,
    ``ThreadLoop.submit``): every other module hands over through it."""
    stray = [f"{m}:{n.lineno}" for m, t in TREES.items() if m not in HANDOVER_ALLOWED
             for n in ast.walk(t)
             if isinstance(n, ast.Attribute) and n.attr == "run_coroutine_threadsafe"]
    assert stray == []


#: besides gateway/plumbing/threadloop.py (Mailbox, the one bounded hand-over of work between threads), the
#: modules that may build a queue or a condition of their own, each with why
WORK_HANDOVER_ALLOWED = {
    "drivers.sim.meter": "the simulated meter's ReplyWriter: a heap of replies due at set times (a "
                         "timer), not a first-in first-out hand-over",
}
#: the modules that hand work to another thread through a Mailbox (issue 30.2)
MAILBOX_USERS = ("gateway.offline.logcols",)
#: what a hand-over written by hand is built from: a thread-safe queue, or a condition to wait on
_QUEUE_MODULES = ("queue", "multiprocessing.queues")
_HANDOVER_CALLS = ("Queue", "SimpleQueue", "LifoQueue", "PriorityQueue", "JoinableQueue", "Condition")


def _work_handovers(tree: ast.Module) -> list[str]:
    """Where a module builds a hand-over between threads itself: imports a thread-safe queue
    module, or calls a queue or condition constructor (``queue.Queue(16)``, ``threading.Condition()``;
    ``asyncio``'s queue and condition live within one loop and are no hand-over between threads)."""
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Import):
            out += [f"{n.lineno} import {a.name}" for a in n.names if a.name in _QUEUE_MODULES]
        elif isinstance(n, ast.ImportFrom) and n.module in _QUEUE_MODULES and not n.level:
            out.append(f"{n.lineno} from {n.module} import")
        elif isinstance(n, ast.Call):
            f = n.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            if name in _HANDOVER_CALLS and not (isinstance(f, ast.Attribute) and ast.unparse(f.value) == "asyncio"):
                out.append(f"{n.lineno} {ast.unparse(f)}()")
    return out


def test_one_bounded_hand_over_of_work_between_threads():
    """Issue 30.2: a thread passes work to another through ``gateway.plumbing.threadloop.Mailbox`` (bounded,
    a drop policy, never blocking the producer); no other module builds a queue or a condition of
    its own (the log companion's writer had a ``queue.Queue`` and a ``Condition`` beside it)."""
    stray = {m: hs for m, t in TREES.items()
             if m != "gateway.plumbing.threadloop" and m not in WORK_HANDOVER_ALLOWED and (hs := _work_handovers(t))}
    assert stray == {}
    assert all(_work_handovers(TREES[m]) for m in WORK_HANDOVER_ALLOWED), "an allowed module no longer needs it"
    for m in MAILBOX_USERS:
        assert "gateway.plumbing.threadloop" in SCANS[m].edges, m


def test_the_hand_over_check_flags_what_it_should():
    by_hand = ("import queue\nimport threading\n_q = queue.Queue(maxsize=16)\n"
               "_idle = threading.Condition(threading.Lock())\n")
    assert _work_handovers(ast.parse(by_hand)) == ["1 import queue", "3 queue.Queue()",
                                                   "4 threading.Condition()"]
    assert _work_handovers(ast.parse("from queue import SimpleQueue\nq = SimpleQueue()\n")) == [
        "1 from queue import", "2 SimpleQueue()"]
    assert _work_handovers(ast.parse("import multiprocessing as mp\nq = mp.Queue()\n")) == ["2 mp.Queue()"]
    within_a_loop = ("import asyncio\nfrom .threadloop import Mailbox\nq = asyncio.Queue(8)\n"
                     "c = asyncio.Condition()\nbox = Mailbox(16)\n")
    assert _work_handovers(ast.parse(within_a_loop)) == []


def _state_writes(tree: ast.Module) -> list[str]:
    """Assignments to a field of a ``….state`` (directly, or through a local alias of it)."""
    out = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        aliases = {t.id for n in ast.walk(fn) if isinstance(n, ast.Assign)
                   and isinstance(n.value, ast.Attribute) and n.value.attr == "state"
                   for t in n.targets if isinstance(t, ast.Name)}
        for n in ast.walk(fn):
            targets = (n.targets if isinstance(n, ast.Assign)
                       else [n.target] if isinstance(n, (ast.AugAssign, ast.AnnAssign)) else [])
            for tg in targets:
                if isinstance(tg, ast.Attribute) and (
                        (isinstance(tg.value, ast.Attribute) and tg.value.attr == "state")
                        or (isinstance(tg.value, ast.Name) and tg.value.id in aliases)):
                    out.append(f"{n.lineno} {ast.unparse(tg)}")
    return out


def test_the_station_state_changes_in_one_place():
    """In gateway/station/ only the StatusBoard (status.py) writes StationState fields; the others
    call its ``update`` or one of its named transitions."""
    bad = [f"{m}:{w}" for m, t in TREES.items()
           if _in(m, ("gateway.station",)) and m != "gateway.station.status" for w in _state_writes(t)]
    assert bad == []
    old = "def f(self):\n    st = self.state\n    st.alarm = 1\n    self.state.test_id = None\n"
    assert _state_writes(ast.parse(old)) == ["3 st.alarm", "4 self.state.test_id"]


#: functions of the modules ``hookwatch run`` loads that may still import when first called (each
#: says why it is never called on a station's thread)
LATE_IMPORTS_ALLOWED = {
    ("gateway.offline.logio", "_decompress"): "reading a log (analyze, report), never `hookwatch run`",
    ("gateway.offline.logio", "_parse_forked"): "reading a log (analyze, report), never `hookwatch run`",
    ("gateway.offline.logio", "_parse_arrow"): "reading a log (analyze, report): pyarrow only there",
}


def _late_imports(tree: ast.Module) -> list[tuple[str, int]]:
    """(function, line) of every import statement inside a function."""
    return [(fn.name, n.lineno) for fn in ast.walk(tree)
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef))
            for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom))]


def test_what_the_runtime_loads_imports_at_start_up():
    """A module that `hookwatch run` loads imports everything at module level, so no import can
    happen on a station's slot thread: the first forecast imported scipy.special there (0.3 s
    quiet, up to 0.85 s loaded: slots MISSING, the STM32 watchdog tripped, a protection stop). The
    runtime set is read from a fresh interpreter that loads the run command and the composition
    root; scipy, pyarrow and matplotlib are not in it."""
    code = ("import sys, json, gateway.cli.run, gateway.compose; "
            "print(json.dumps(sorted(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout
    loaded = set(json.loads(out))
    assert not {"scipy", "pyarrow", "matplotlib"} & loaded
    runtime = sorted(m for m in loaded if m in TREES)
    assert "gateway.station.station" in runtime and "gateway.core.method.forecast" in runtime
    late = [f"{m}.{fn}:{line}" for m in runtime for fn, line in _late_imports(TREES[m])
            if (m, fn) not in LATE_IMPORTS_ALLOWED]
    assert late == []
    assert _late_imports(ast.parse("import a\ndef f():\n    import b\n")) == [("f", 3)]


def test_a_station_thread_imports_nothing_while_it_runs_a_life(tmp_path):
    """The dynamic half of the rule above, for what the static scan cannot see (numpy loads
    numpy.ma when np.median first runs): a fresh interpreter loads the runtime, then feeds the
    streaming method every vector's slots (with the v6 prior: the forecast) as a station does;
    no module may be imported from the first slot on."""
    import dataclasses

    from gateway.core.method import to_slots
    from gateway.offline.analysis import params_for
    from gateway.offline.logio import read_log

    vectors = os.path.join(ROOT, "tests", "vectors")
    lives = []
    for name in ("v1_failure", "v2_faults", "v6_prior"):
        log = read_log(os.path.join(vectors, f"{name}.csv.gz"))
        p = params_for(log.meta, {}, name)
        s = to_slots(log.t, log.t1, log.t2, p)
        lives.append({"p": dataclasses.asdict(p), "present": s.present.tolist(),
                      "t1": s.t1.tolist(), "t2": s.t2.tolist()})
    assert lives[-1]["p"]["prior_mean"] is not None
    path = tmp_path / "lives.json"
    path.write_text(json.dumps(lives))
    code = (
        "import sys, json, gateway.cli.run, gateway.compose\n"
        "from gateway.core.method import MethodParams, StreamingMonitor\n"
        f"lives = json.load(open({str(path)!r}))\n"
        "before, events = set(sys.modules), set()\n"
        "for life in lives:\n"
        "    mon = StreamingMonitor(MethodParams(**life['p']))\n"
        "    for k, (pr, a, b) in enumerate(zip(life['present'], life['t1'], life['t2'])):\n"
        "        if mon.finished: break\n"
        "        events.update(mon.push(pr, a, b).events)\n"
        "    mon.close(len(life['present']))\n"
        "print(json.dumps({'new': sorted(set(sys.modules) - before), 'events': sorted(events)}))\n")
    out = json.loads(subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                                    text=True, check=True).stdout)
    assert {"window", "forecast", "wear_warning"} <= set(out["events"])
    assert out["new"] == []


#: the command path behind every door: the pure command types, the station's desk, its handlers
COMMAND_PATH = ("gateway.core.command_rules", "gateway.station.command_desk", "gateway.station.dispatch")
#: the doors (and the pure tables they print) that reach the command path
COMMAND_DOORS = ("gateway.outputs.mqtt.output", "gateway.outputs.plc.server",
                 "gateway.outputs.sparkplug.runtime", "gateway.outputs.sparkplug.node",
                 "gateway.outputs.console.routes_station", "gateway.supervisor.worker", "gateway.supervisor.remote",
                 "gateway.core.command_intake", "gateway.outputs.plc.registers",
                 "gateway.outputs.mqtt.schema", "gateway.outputs.mqtt.schema_gen",
                 "gateway.outputs.mqtt.messages")


def test_the_command_path_is_typed_and_holds_no_module_state():
    """Issue 30.1: no ``Any``, no ``getattr``/``hasattr`` in the command path, no module-level
    mutable state (the refusal gate is a member of the station's desk); the doors and the pure
    register/schema tables take the command types from the pure gateway.core.command_rules, never from
    the runtime gateway.station.command_desk, and hand commands to their CommandSink."""
    bad = []
    for m in COMMAND_PATH:
        tree = TREES[m]
        for n in ast.walk(tree):
            if isinstance(n, ast.Name) and n.id == "Any":
                bad.append(f"{m}:{n.lineno} Any")
            if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in ("getattr", "hasattr"):
                bad.append(f"{m}:{n.lineno} {n.func.id}")
        for n in tree.body:
            if isinstance(n, (ast.Assign, ast.AnnAssign)) and isinstance(n.value, ast.Call):
                name = ast.unparse(n.value.func)
                if name.split(".")[-1] in ("WeakKeyDictionary", "WeakValueDictionary", "dict", "list", "set",
                                           "defaultdict", "OrderedDict"):
                    bad.append(f"{m}:{n.lineno} module state {ast.unparse(n)[:60]}")
    assert bad == []
    via_runtime = [m for m in COMMAND_DOORS if "gateway.station.command_desk" in SCANS[m].edges]
    assert via_runtime == []
    assert all("gateway.core.command_rules" in SCANS[m].edges for m in ("gateway.outputs.plc.registers",
                                                                  "gateway.outputs.mqtt.schema"))


def _class_members(mod: str, cls: str) -> set[str]:
    """The methods, properties and annotated fields a class of ``mod`` declares (its own body)."""
    node = next(n for n in TREES[mod].body if isinstance(n, ast.ClassDef) and n.name == cls)
    out = set()
    for n in node.body:
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
            out.add(n.name)
        elif isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name):
            out.add(n.target.id)
    return out


#: what outputs are given by contract: what they may read of a station, its state, its records
CONTRACTS = {"gateway.core.ports": ("StationView", "StationLinks", "AlarmExpiries", "AlarmStoreView", "PortLink",
                               "PlanView", "Output", "WorkerHooks"),
             "gateway.core.records": ("StationState", "SlotRecord", "Event")}
#: where the outputs live (and the console's feed)
CONTRACT_USERS = ("gateway.outputs", "gateway.outputs.console")


def _by_name_reads(tree: ast.Module, members: set[str]) -> list[str]:
    """``getattr``/``hasattr`` calls reading a contract member by name, or anything of a station."""
    out = []
    for n in ast.walk(tree):
        if not (isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
                and n.func.id in ("getattr", "hasattr") and len(n.args) >= 2):
            continue
        obj, attr = ast.unparse(n.args[0]), n.args[1]
        named = attr.value if isinstance(attr, ast.Constant) and isinstance(attr.value, str) else None
        if named in members or obj == "station" or obj.endswith(".station"):
            out.append(f"{n.lineno} {ast.unparse(n)}")
    return out


def test_outputs_use_their_contracts_by_their_types():
    """An output reads what StationView/StationLinks, the state and the records declare, as
    attributes mypy checks: no ``getattr``/``hasattr`` on a member they guarantee or on a station
    (a member an output needs is added to the Protocol, typed), no test of a class by its name."""
    members = {m for mod, classes in CONTRACTS.items() for c in classes for m in _class_members(mod, c)}
    assert {"state", "alarms", "meter", "stm32", "set_disk", "headroom", "disk_ok", "on_worker"} <= members
    bad = [f"{m}:{hit}" for m, t in TREES.items() if _in(m, CONTRACT_USERS)
           for hit in _by_name_reads(t, members)]
    bad += [f"{m}:{n.lineno} {ast.unparse(n)}" for m, t in TREES.items() if _in(m, CONTRACT_USERS)
            for n in ast.walk(t) if isinstance(n, ast.Compare)
            and any(isinstance(x, ast.Attribute) and x.attr == "__name__" for x in (n.left, *n.comparators))]
    assert bad == []


def test_the_by_name_check_flags_what_it_should():
    tree = ast.parse("getattr(self.station, 'meter', None)\nhasattr(st, 'disk_ok')\ngetattr(x, 'code', 0)\n"
                     "getattr(station, 'anything')\n")
    assert [h.split()[0] for h in _by_name_reads(tree, {"meter", "disk_ok"})] == ["1", "2", "4"]
    old = ast.parse('any(type(o).__name__ == "MqttOutput" and getattr(o, "connected", False) for o in outs)')
    assert [n for n in ast.walk(old) if isinstance(n, ast.Compare)
            and isinstance(n.left, ast.Attribute) and n.left.attr == "__name__"]
    assert _by_name_reads(old, {"connected"})


def test_the_station_contracts_hold_no_any():
    """The Protocols an output is given (StationView, StationLinks and what they return, the
    optional hooks) name their types: no ``Any`` anywhere in them."""
    tree = TREES["gateway.core.ports"]
    bad = []
    for n in tree.body:
        if isinstance(n, ast.ClassDef) and n.name in CONTRACTS["gateway.core.ports"]:
            bad += [f"{n.name}:{x.lineno}" for x in ast.walk(n) if isinstance(x, ast.Name) and x.id == "Any"]
    assert bad == []


#: the outputs that report slots by the window, each through the one accumulator
WINDOW_USERS = ("gateway.outputs.mqtt.output", "gateway.outputs.mqtt.messages", "gateway.outputs.sparkplug.output",
                "gateway.supervisor.worker", "gateway.outputs.plc.server",
                "gateway.outputs.prometheus.figures")


def test_one_slot_window_accumulator():
    """The per-window aggregation of slot records is written once (gateway/core/slotwindow.py): the
    outputs that aggregate slots import ``SlotWindow``, and no other module counts slots per
    reason (``enumerate(REASONS)`` outside the method core and the accumulator)."""
    for m in WINDOW_USERS:
        assert "gateway.core.slotwindow" in SCANS[m].edges, m
    counting = [m for m, t in TREES.items() if m != "gateway.core.slotwindow" and not _in(m, ("gateway.core.method",))
                for n in ast.walk(t) if isinstance(n, ast.Call) and ast.unparse(n) == "enumerate(REASONS)"]
    assert counting == []
    # the accumulator itself sits on the pure core (the catalog: the readings whose mean it keeps)
    assert set(SCANS["gateway.core.slotwindow"].edges) <= {"gateway.core.records", "gateway.core.method",
                                                           "gateway.core.method.rules", "gateway.core.catalog"}


#: the restarts and retries of stations and workers (their waits come from gateway/plumbing/backoff.py)
BACKOFF_USERS = ("gateway.station.fleet", "gateway.supervisor.supervisor", "gateway.outputs.broker.paho_session",
                 "gateway.outputs.sparkplug.runtime")


def test_one_restart_back_off():
    """The restart back-off is written once (gateway/plumbing/backoff.py): the station runner, the
    supervisor and the MQTT/Sparkplug session engines use it, and no module of the station or the
    supervisor computes a doubling wait of its own (``… * 2 ** n``)."""
    for m in BACKOFF_USERS:
        assert "gateway.plumbing.backoff" in SCANS[m].edges, m
    doubling = [f"{m}:{n.lineno}" for m, t in TREES.items() if _in(m, ("gateway.station", "gateway.supervisor"))
                for n in ast.walk(t) if isinstance(n, ast.BinOp) and isinstance(n.op, ast.Pow)
                and isinstance(n.left, ast.Constant) and n.left.value in (2, 2.0)]
    assert doubling == []
    # nor a wait doubled by hand anywhere (``self._backoff * 2``: the MQTT and Sparkplug sessions had one)
    by_hand = [f"{m}:{n.lineno}" for m, t in TREES.items() for n in ast.walk(t)
               if isinstance(n, ast.BinOp) and isinstance(n.op, ast.Mult)
               and any(isinstance(x, ast.Constant) and x.value in (2, 2.0) for x in (n.left, n.right))
               and any("backoff" in ast.unparse(x).lower() for x in (n.left, n.right))]
    assert by_hand == []


def test_the_composition_root_wires_through_constructors_and_methods():
    """gateway/compose.py builds parts and hands them their configuration (constructors, methods):
    it never assigns into a part's parts (``st.tests.priors.entries = …``)."""
    deep = [f"{n.lineno} {ast.unparse(tg)}" for n in ast.walk(TREES["gateway.compose"])
            if isinstance(n, (ast.Assign, ast.AugAssign, ast.AnnAssign))
            for tg in (n.targets if isinstance(n, ast.Assign) else [n.target])
            if isinstance(tg, ast.Attribute) and isinstance(tg.value, ast.Attribute)]
    assert deep == []


#: what only the composition root builds: a station, its runtime, the console
WIRED_IN_COMPOSE = ("Station", "StationRunner", "Fleet", "ConsoleServer", "ConsoleSettings")


def _calls(tree: ast.AST) -> set[str]:
    """What a module calls, as written (``asyncio.run``, ``loop.add_signal_handler``, ``drive``)."""
    return {ast.unparse(n.func) for n in ast.walk(tree) if isinstance(n, ast.Call)}


def test_the_demo_runs_its_station_through_drive():
    """Issue 30.4: ``hookwatch demo`` runs its station as ``hookwatch run`` does — built by the
    composition root, in run's one main loop (``drive``: signals, systemd, the end of the test) —
    with no event loop, signal handler or end watcher of its own; and no command builds a
    station, its runtime or the console itself (that is gateway/compose.py's)."""
    demo = "gateway.cli.demo"
    calls = _calls(TREES[demo])
    own = sorted(c for c in calls if c.startswith("asyncio.") or c.endswith("add_signal_handler")
                 or c in ("signal.signal", "signal.set_wakeup_fd"))
    assert own == []
    imported = {a.name for n in ast.walk(TREES[demo]) if isinstance(n, ast.Import) for a in n.names}
    assert "asyncio" not in imported
    assert {"drive", "build_station", "in_process_runtime", "build_console"} <= calls
    built = sorted(f"{m}: {c}" for m in TREES if m.startswith("gateway.cli.")
                   for c in _calls(TREES[m]) if c.split(".")[-1] in WIRED_IN_COMPOSE)
    assert built == []
    # the scan sees what it looks for
    assert _calls(ast.parse("asyncio.run(main(st.Station(x)))\nloop.add_signal_handler(2, g)\n")) == {
        "asyncio.run", "main", "st.Station", "loop.add_signal_handler"}


#: module file names still shared, each with why (a new shared name fails the test below)
SHARED_NAMES = {
    "docs.py": "each renders its own package's document (config, method, Sparkplug) from its one definition",
    "output.py": "each door's station output in its own package (outputs/mqtt/, outputs/sparkplug/)",
    "settings.py": "each output's settings in its own package (outputs/broker/, outputs/mqtt/, outputs/console/)",
    "driver.py": "each device's driver, the port the station uses, in its own package (drivers/meter/, drivers/stm32/)",
}


def test_module_names_say_what_they_hold():
    """No two modules of gateway/ and drivers/ share a file name a reader could confuse (the
    virtual twins are ``twin_*.py``, the Modbus transport's server ``tcp_server.py``, …), except
    the names listed with their reason."""
    by_name: dict[str, list[str]] = defaultdict(list)
    for mod, path in MODULES.items():
        if not path.endswith("__init__.py"):
            by_name[os.path.basename(path)].append(mod)
    shared = {n: sorted(ms) for n, ms in by_name.items() if len(ms) > 1}
    assert set(shared) <= set(SHARED_NAMES), {n: ms for n, ms in shared.items() if n not in SHARED_NAMES}
    assert set(SHARED_NAMES) <= set(shared), "a listed name is no longer shared: drop it from SHARED_NAMES"
