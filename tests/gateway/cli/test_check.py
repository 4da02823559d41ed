"""`hookwatch check` through the real CLI: the broken-configuration corpus (each case its specific
message and exit 1), the shipped fleet and the legal shared-port fleet (exit 0), usage errors (2)."""
import glob
import os
import subprocess

import pytest

from conftest import ROOT, hookwatch_cmd

CORPUS = os.path.join(ROOT, "tests", "configs")
BROKEN_FILES = sorted(glob.glob(os.path.join(CORPUS, "broken", "*.yaml")))
BROKEN_FLEETS = sorted(d for d in glob.glob(os.path.join(CORPUS, "fleets", "*")) if os.path.isdir(d))


def check(*args, cwd=ROOT, env=None):
    p = subprocess.run(hookwatch_cmd() + ["check", *args], capture_output=True, text=True,
                       cwd=cwd, timeout=120, env=env)
    return p.returncode, p.stdout, p.stderr


def _expectations_in_file(path):
    with open(path, encoding="utf-8") as f:
        return [ln[len("# expect: "):].rstrip("\n") for ln in f if ln.startswith("# expect: ")]


def test_corpus_is_large_enough():
    assert len(BROKEN_FILES) + len(BROKEN_FLEETS) >= 15
    for p in BROKEN_FILES:
        assert _expectations_in_file(p), f"{p}: no '# expect: ' line"


@pytest.mark.parametrize("path", BROKEN_FILES, ids=lambda p: os.path.basename(p)[:-5])
def test_broken_station_file(path):
    rel = os.path.relpath(path, ROOT)
    rc, out, err = check("--skip-local", rel)
    assert rc == 1, (rc, out, err)
    assert err == ""
    for exp in _expectations_in_file(path):
        assert exp in out, f"expected {exp!r} in:\n{out}"
    # every error line names the file
    for line in out.splitlines():
        if line.strip().startswith("error:"):
            assert rel in line, line


@pytest.mark.parametrize("folder", BROKEN_FLEETS, ids=os.path.basename)
def test_broken_fleet(folder):
    rel = os.path.relpath(folder, ROOT)
    rc, out, err = check("--skip-local", rel)
    assert rc == 1, (rc, out, err)
    with open(os.path.join(folder, "expect.txt"), encoding="utf-8") as f:
        expected = [ln.rstrip("\n") for ln in f if ln.strip()]
    assert expected
    for exp in expected:
        assert exp in out, f"expected {exp!r} in:\n{out}"


def test_shipped_fleet_passes():
    rc, out, err = check("--skip-local", "--strict", "config")
    assert rc == 0, out + err
    assert "4 stations: 4 OK, 0 with errors; 0 errors, 0 warnings" in out
    # the bus numbers are shown for every station
    assert out.count("poll ") == 4 and "38400 baud" in out


def test_shipped_fleet_passes_with_local_checks():
    # ports are absent on a build machine: warnings, never errors
    rc, out, err = check("config", "config/demo/station.yaml")
    assert rc == 0, out + err
    assert "5 stations: 5 OK" in out


def test_each_shipped_station_file_alone():
    for p in sorted(glob.glob(os.path.join(ROOT, "config", "stations", "*.yaml"))):
        rc, out, err = check("--skip-local", "--strict", os.path.relpath(p, ROOT))
        assert rc == 0, out + err


def test_shared_modbus_port_with_distinct_units_is_legal():
    rc, out, err = check("--skip-local", "--strict", "tests/configs/good/shared_port")
    assert rc == 0, out + err


def test_clash_across_paths_of_one_call(tmp_path):
    """Two station files named in one call are one box: the same port twice is an error."""
    a = tmp_path / "a.yaml"
    b = tmp_path / "b.yaml"
    a.write_text("station: {id: a}\nmeter: {port: /dev/x-meter}\nstm32: {port: /dev/x-stm32}\n")
    b.write_text("station: {id: b}\nmeter: {port: /dev/x-meter}\nstm32: {port: /dev/y-stm32}\n")
    rc, out, _ = check("--skip-local", str(a), str(b))
    assert rc == 1
    assert f"{b}:2: meter.port: '/dev/x-meter' is also the meter.port of station a ({a}:2)" in out
    rc, out, _ = check("--skip-local", str(a))
    assert rc == 0, out


def test_warnings_pass_unless_strict(tmp_path):
    p = tmp_path / "s.yaml"
    p.write_text("station: {id: s}\nmeter: {port: /dev/none-meter}\nstm32: {port: /dev/none-stm32}\n"
                 "method: {delta: 0.8}\n")
    rc, out, _ = check("--skip-local", str(p))
    assert rc == 0 and "warning:" in out and "method.delta: 0.8 is unusual" in out
    rc, _, _ = check("--skip-local", "--strict", str(p))
    assert rc == 1


def test_watchdog_margin_over_the_protection_stop(tmp_path):
    """Issue 27: the watchdog must outlast the protection stop (a stall the method tolerates
    must not stop the drive): below stop_after an error, within its margin a warning, null or
    ≥ stop_after + 0.5 s clean."""
    def run(stm32_extra, method=""):
        p = tmp_path / "s.yaml"
        p.write_text("station: {id: s}\nmeter: {port: /dev/none-meter}\n"
                     f"stm32: {{port: /dev/none-stm32{stm32_extra}}}\n{method}")
        return check("--skip-local", str(p))

    rc, out, _ = run(", watchdog_s: 1.2")
    assert rc == 0 and "stm32.watchdog_s: 1.2 s leaves less than 0.5 s" in out, out
    rc, out, _ = run(", watchdog_s: 1.5")
    assert rc == 0 and "watchdog_s" not in out, out
    rc, out, _ = run("")
    assert rc == 0 and "watchdog_s" not in out, out
    # a longer protection stop needs a longer watchdog
    rc, out, _ = run(", watchdog_s: 1.5", "method: {stop_after: 3}\n")
    assert rc == 1 and "shorter than the protection stop (method.stop_after = 3 s)" in out, out


def test_local_checks(tmp_path):
    p = tmp_path / "s.yaml"
    ro = tmp_path / "ro"
    ro.mkdir()
    p.write_text(f"station: {{id: s}}\nmeter: {{port: /dev/none-meter}}\nstm32: {{port: /dev/none-stm32}}\n"
                 f"recorder: {{dir: {ro}/records}}\n"
                 "mqtt: {enabled: true, username: u, password_env: HOOKWATCH_TEST_UNSET_VAR}\n")
    env = {k: v for k, v in os.environ.items() if k != "HOOKWATCH_TEST_UNSET_VAR"}
    rc, out, _ = check(str(p), env=env)
    assert rc == 0
    assert "meter.port: '/dev/none-meter' does not exist here" in out
    assert "mqtt.password_env: $HOOKWATCH_TEST_UNSET_VAR is not set" in out
    rc, out, _ = check(str(p), env={**env, "HOOKWATCH_TEST_UNSET_VAR": "x"})
    assert "HOOKWATCH_TEST_UNSET_VAR" not in out
    if os.geteuid() != 0:           # root may write anywhere
        ro.chmod(0o555)
        try:
            rc, out, _ = check(str(p), env=env)
            assert "recorder.dir" in out and "is not writable" in out
        finally:
            ro.chmod(0o755)


def test_station_file_named_differently(tmp_path):
    (tmp_path / "stations").mkdir()
    p = tmp_path / "stations" / "loom-09.yaml"
    p.write_text("station: {id: loom-9}\nmeter: {port: /dev/a}\nstm32: {port: /dev/b}\n")
    rc, out, _ = check("--skip-local", str(tmp_path))
    assert rc == 0
    assert "the unit hookwatch@loom-09 would run station loom-9" in out


def test_a_huge_station_id_is_echoed_clipped(tmp_path):
    """Issue 27.9: a 1 MB station id was printed whole, twice (the heading and the error). It is
    quoted by its start and its length; in a fleet folder the refusal the supervisor logs (at the
    start and on every reload) is as short (its name and message come from plan_fleet)."""
    from gateway.supervisor.fleetcfg import plan_fleet
    huge = "A" * 1_000_000
    (tmp_path / "stations").mkdir()
    (tmp_path / "stations" / "big.yaml").write_text(
        f"station: {{id: {huge}}}\nmeter: {{port: /dev/a}}\nstm32: {{port: /dev/b}}\n"
        f"mqtt: {{enabled: {huge[:40_000]}}}\n")
    (tmp_path / "stations" / "ok.yaml").write_text(
        "station: {id: ok}\nmeter: {port: /dev/c}\nstm32: {port: /dev/d}\n")
    rc, out, _ = check("--skip-local", str(tmp_path))
    assert rc == 1
    assert len(out) < 2000, len(out)
    assert "(1000000 chars)" in out and "is not a valid name" in out
    assert "(40000 chars) is not true or false" in out
    plan = plan_fleet(str(tmp_path))
    [r] = plan.refused
    assert len(r.name) < 100 and len(r.message()) < 1000, (len(r.name), len(r.message()))
    assert [c.station.id for _, c in plan.accepted] == ["ok"]


@pytest.mark.parametrize("args,fragment", [
    (["/no/such/file.yaml"], "/no/such/file.yaml: no such file or folder"),
    (["tests"], "tests: no station files (expected tests/stations/*.yaml)"),
])
def test_usage_errors_exit_2(args, fragment):
    rc, out, err = check(*args)
    assert rc == 2
    assert fragment in err


def test_no_arguments_is_usage_error():
    rc, _, err = check()
    assert rc == 2 and "PATH" in err
