"""Hostile YAML (issue 12 item 5, item 10's `meter.map: /etc/shadow`) through the real CLI:
`hookwatch check` refuses each file with ONE clear line (file:line, the limit, what is allowed)
and exit 1, never a traceback, within a small address space (RLIMIT_AS in the child) and
quickly (the subprocess timeout). The same reader serves meter maps, scenarios and sidecars."""
import os
import resource
import subprocess

import pytest

from conftest import ROOT, hookwatch_cmd

AS_LIMIT = 400 << 20   # the billion-laughs file took 1.6 GB before the reader was bounded

HEAD = ("station: {id: hostile}\nmeter: {port: /dev/hookwatch/t-meter}\n"
        "stm32: {port: /dev/hookwatch/t-stm32}\n")

LAUGHS = "".join(
    [f'{chr(97)}: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n']
    + [f"{chr(97 + i)}: &{chr(97 + i)} [" + ",".join([f"*{chr(96 + i)}"] * 9) + "]\n"
       for i in range(1, 9)])


def _limited():
    resource.setrlimit(resource.RLIMIT_AS, (AS_LIMIT, AS_LIMIT))


def check(path, timeout=30):
    p = subprocess.run(hookwatch_cmd() + ["check", "--skip-local", str(path)], capture_output=True,
                       text=True, cwd=ROOT, timeout=timeout, preexec_fn=_limited)
    return p.returncode, p.stdout, p.stderr


def one_error(path, *fragments, line=None):
    rc, out, err = check(path)
    assert rc == 1, (rc, out, err)
    assert err == "" and "Traceback" not in out, (out, err)
    errors = [ln.strip() for ln in out.splitlines() if ln.strip().startswith("error:")]
    assert len(errors) == 1, out
    where = f"{path}:{line}: " if line else f"{path}:"
    assert where in errors[0], errors[0]
    for f in fragments:
        assert f in errors[0], (f, errors[0])
    return errors[0]


def test_billion_laughs_is_refused_fast_in_little_memory(tmp_path):
    p = tmp_path / "laughs.yaml"
    p.write_text(LAUGHS)
    assert os.path.getsize(p) < 700
    one_error(p, "more than 100000 values once the aliases are expanded", "allowed: at most 100000")


def test_merge_key_bomb_is_refused(tmp_path):
    lines = ["a0: &a0 {x: 1, y: 2}"]
    for i in range(1, 30):
        lines.append(f"a{i}: &a{i} {{<<: [*a{i - 1}], z{i}: [*a{i - 1}, *a{i - 1}]}}")
    p = tmp_path / "merge.yaml"
    p.write_text("\n".join(lines) + "\n")
    one_error(p, "once the aliases are expanded")


def test_recursive_alias_is_refused(tmp_path):
    p = tmp_path / "rec.yaml"
    p.write_text(HEAD + "grades: &g [I, *g]\n")
    one_error(p, "recursive alias", line=4)


def test_too_many_aliases(tmp_path):
    p = tmp_path / "aliases.yaml"
    p.write_text(HEAD + "x: &x 1\ngrades: [" + ", ".join(["*x"] * 1001) + "]\n")
    one_error(p, "more than 1000 aliases", "allowed: at most 1000", line=5)


@pytest.mark.parametrize("opener", ["[", "{a: ", "- "])
def test_deep_nesting(tmp_path, opener):
    p = tmp_path / "deep.yaml"
    p.write_text(HEAD + "grades: " + (opener * 50_000 if opener != "- " else "\n" + "- " * 50_000 + "x") + "\n")
    one_error(p, "nested deeper than 64 levels", "allowed: at most 64 levels")


def test_nul_byte(tmp_path):
    p = tmp_path / "nul.yaml"
    p.write_bytes(HEAD.encode() + b"test:\n  sample_id: ab\x00cd\n")
    one_error(p, "a NUL byte", "column 16", "allowed: text without control characters", line=5)


def test_long_integer(tmp_path):
    p = tmp_path / "digits.yaml"
    p.write_text(HEAD + "mqtt:\n  port: " + "9" * 5000 + "\n")
    one_error(p, "an integer of 5000 characters", "allowed: at most 32", line=5)


def test_not_utf8(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes(HEAD.encode() + "test:\n  sample_id: Müller\n".encode("latin-1"))
    one_error(p, "not UTF-8 text: byte 0xfc", "allowed: UTF-8 text", line=5)


def test_large_file_is_refused_before_reading(tmp_path):
    p = tmp_path / "huge.yaml"
    with open(p, "wb") as f:
        f.write(HEAD.encode())
        f.truncate(50 << 20)              # 50 MB (sparse): refused by size, not parsed for 100 s
    one_error(p, "the file is 52428800 bytes", "allowed: at most 1 MiB")


def test_fleet_defaults_file_is_bounded_too(tmp_path):
    (tmp_path / "stations").mkdir()
    (tmp_path / "fleet.yaml").write_text(LAUGHS)
    (tmp_path / "stations" / "s1.yaml").write_text(HEAD.replace("hostile", "s1"))
    rc, out, err = check(tmp_path)
    assert rc == 1 and err == "", (out, err)
    assert f"{tmp_path / 'fleet.yaml'}:" in out and "aliases are expanded" in out, out


def test_meter_map_bomb_and_secret_file(tmp_path):
    bomb = tmp_path / "bomb-map.yaml"
    bomb.write_text(LAUGHS)
    p = tmp_path / "map-bomb.yaml"
    p.write_text(HEAD.replace("t-meter}", f"t-meter, map: {bomb}}}"))
    one_error(p, "meter.map", "aliases are expanded", line=2)
    # a file that is not a register map (meter.map: /etc/shadow): its content is never printed
    secret = tmp_path / "shadow"
    secret.write_text("root:$6$s3cr3tH4sh:19000:0:99999:7:::\ndaemon:*:19000:0:99999:7:::\n")
    p = tmp_path / "map-secret.yaml"
    p.write_text(HEAD.replace("t-meter}", f"t-meter, map: {secret}}}"))
    line = one_error(p, "meter.map", "not a register map", "allowed keys: model", line=2)
    assert "s3cr3t" not in line and "root:" not in line and "daemon" not in line
    if os.access("/etc/shadow", os.R_OK):
        p.write_text(HEAD.replace("t-meter}", "t-meter, map: /etc/shadow}"))
        with open("/etc/shadow", encoding="utf-8", errors="replace") as f:
            first = f.readline().strip()
        rc, out, err = check(p)
        assert rc == 1 and first not in out and first.split(":")[0] + ":" not in out, out


def test_scenario_and_sidecar_readers_are_bounded(tmp_path):
    from drivers.sim.scenario import ScenarioError, load_scenario
    from gateway.offline.logio import LogError, read_meta

    p = tmp_path / "scen.yaml"
    p.write_text(LAUGHS)
    with pytest.raises(ScenarioError, match="aliases are expanded"):
        load_scenario(str(p))
    log = tmp_path / "x.csv"
    log.write_text("t,T1,T2\n0,0.3,0.6\n")
    (tmp_path / "x.meta.yaml").write_bytes(b"sample_id: a\x00b\n")
    with pytest.raises(LogError, match=r"x.meta.yaml: \(line 1\): a NUL byte"):
        read_meta(str(log))
