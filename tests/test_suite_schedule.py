"""The suite's schedule (tests/conftest.py) is declared once and names only tests that exist: a
renamed or deleted test in the slow tier silently moved its successor into the quick loop (a
stale entry named tests/gateway/test_logio_cache.py, gone), and a module that marked itself slow
besides the table was a second place to look."""
import ast
import os
import re
import subprocess
import sys

import conftest as C

ROOT = C.ROOT


def _tests_of(path: str) -> set[str]:
    with open(os.path.join(ROOT, path), encoding="utf-8") as f:
        tree = ast.parse(f.read())
    return {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
            and n.name.startswith("test")}


def schedule_problems() -> list[str]:
    bad = []
    tables = {"SLOW": C.SLOW, "CPU": C.CPU, **{f"SHARED_GROUPS[{g!r}]": t for g, t in C.SHARED_GROUPS.items()}}
    for table, entries in tables.items():
        for path, names in entries.items():
            if not os.path.isfile(os.path.join(ROOT, path)):
                bad.append(f"{table}: {path}: no such module")
                continue
            have = _tests_of(path)
            bad += [f"{table}: {path}::{n}: no such test" for n in names if n != "*" and n not in have]
    for path in (*C.MODULE_GROUPS, *C.FLEETS):
        if not os.path.isfile(os.path.join(ROOT, path)):
            bad.append(f"{path}: no such module")
    # the order of the units: each a group, or a module of no group (a grouped module's tests
    # are ordered by their group's entry: an entry of its own would do nothing)
    groups = {C.CPU_GROUP, C.FLEET_GROUP, *C.SHARED_GROUPS, *C.MODULE_GROUPS}
    grouped = {*C.CPU, *C.FLEETS, *(p for t in C.SHARED_GROUPS.values() for p in t)}
    for unit in C.LONGEST_FIRST:
        if unit in groups:
            continue
        if not os.path.isfile(os.path.join(ROOT, unit)):
            bad.append(f"LONGEST_FIRST: {unit}: no such group or module")
        elif unit in grouped and all(n == "*" for t in (C.CPU, *C.SHARED_GROUPS.values())
                                     for n in t.get(unit, ("*",))):
            bad.append(f"LONGEST_FIRST: {unit}: in a group, ordered by the group's entry")
    return bad


def users_of(fixture: str) -> set[str]:
    """``path::test`` of every test function that takes ``fixture`` (from the syntax trees)."""
    found = set()
    for d, _, files in os.walk(os.path.join(ROOT, "tests")):
        for f in files:
            if f.startswith("test_") and f.endswith(".py"):
                path = os.path.join(d, f)
                with open(path, encoding="utf-8") as fh:
                    tree = ast.parse(fh.read())
                rel = os.path.relpath(path, ROOT)
                found |= {f"{rel}::{n.name}" for n in ast.walk(tree)
                          if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)) and n.name.startswith("test")
                          and fixture in [a.arg for a in n.args.args]}
    return found


def slow_marks(src: str) -> list[int]:
    """Lines of ``pytest.mark.slow`` in a module's source (its syntax tree: a mention in a
    docstring is no mark)."""
    return [n.lineno for n in ast.walk(ast.parse(src)) if isinstance(n, ast.Attribute) and n.attr == "slow"
            and isinstance(n.value, ast.Attribute) and n.value.attr == "mark"]


def test_every_entry_of_the_schedule_names_an_existing_test():
    assert schedule_problems() == []


def test_the_slow_tier_is_declared_in_conftest_only():
    """No `pytestmark = pytest.mark.slow` nor `@pytest.mark.slow` in a test module."""
    bad = []
    for d, _, files in os.walk(os.path.join(ROOT, "tests")):
        for f in files:
            if f.startswith("test_") and f.endswith(".py"):
                path = os.path.join(d, f)
                with open(path, encoding="utf-8") as fh:
                    bad += [f"{os.path.relpath(path, ROOT)}:{ln}" for ln in slow_marks(fh.read())]
    assert bad == []


def test_the_checks_see_a_stale_entry_and_a_mark(tmp_path, monkeypatch):
    """The two checks above have teeth: a table naming a missing test, and a module marking
    itself, are both found."""
    monkeypatch.setattr(C, "SLOW", {"tests/test_suite_schedule.py": ("test_gone",),
                                    "tests/nowhere.py": ("*",)})
    found = schedule_problems()
    assert "SLOW: tests/test_suite_schedule.py::test_gone: no such test" in found
    assert "SLOW: tests/nowhere.py: no such module" in found
    assert slow_marks("import pytest\npytestmark = pytest.mark.slow\n") == [2]
    assert slow_marks('"""pytest.mark.slow in words"""\n@pytest.mark.slow\ndef test_x():\n    pass\n') == [2]


def test_the_tests_on_the_shared_rabbitmq_cluster_are_its_group():
    """Every test that takes the worker's RabbitMQ cluster is in its xdist group (else it starts a
    second cluster on another worker), and every test of the group takes it."""
    table = C.SHARED_GROUPS["rabbitmq"]
    grouped = {f"{path}::{n}" for path, names in table.items() for n in names if n != "*"}
    grouped |= {f"{path}::{n}" for path, names in table.items() if "*" in names for n in _tests_of(path)}
    users = users_of("rabbitmq_cluster")
    assert len(users) >= 3
    assert users == grouped


def test_loadgroup_runs_a_group_on_one_worker(tmp_path):
    """`./run-tests` schedules by `xdist_group` (`--dist loadgroup`), marked as tests/conftest.py
    marks them. Every table above was ignored, silently: a module of the CPU group ran on two
    workers, its module-scoped fixture made on each. Two causes: the marks came after
    pytest-xdist's worker had read them (its pytest_collection_modifyitems names the group in the
    node ID and ran first: ours must be tryfirst), and pytest 9.2 keeps node IDs structured, so
    that naming has no effect (pytest-dev/pytest-xdist#1386: pytest < 9.2 in pyproject.toml). A
    group of two modules' tests must run on one worker, under its group's name."""
    assert C.pytest_collection_modifyitems.pytest_impl.get("tryfirst") is True
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    (tmp_path / "conftest.py").write_text(
        "import pytest\n\n\n"
        "@pytest.hookimpl(tryfirst=True)\n"
        "def pytest_collection_modifyitems(config, items):\n"
        "    for item in items:\n"
        "        if item.name.startswith('test_grouped'):\n"
        "            item.add_marker(pytest.mark.xdist_group('g'))\n")
    for m in ("a", "b"):
        (tmp_path / f"test_{m}.py").write_text("".join(
            f"def test_{kind}_{i}():\n    pass\n\n\n" for kind in ("free", "grouped") for i in range(4)))
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_")}
    argv = [sys.executable, "-m", "pytest", "-n", "2", "--dist", "loadgroup", "-v", "-p", "no:cacheprovider",
            str(tmp_path)]
    r = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    ran = re.findall(r"\[(gw\d+)\] \[\s*\d+%\] PASSED (\S+)", r.stdout)
    assert len(ran) == 16, r.stdout
    grouped = {(gw, nodeid) for gw, nodeid in ran if "test_grouped" in nodeid}
    assert len(grouped) == 8 and all(nodeid.endswith("@g") for _gw, nodeid in grouped), r.stdout
    assert len({gw for gw, _ in grouped}) == 1, r.stdout
