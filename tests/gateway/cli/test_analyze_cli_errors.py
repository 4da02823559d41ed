"""`hookwatch analyze` on bad input: exit 2, one clear line naming the file and the problem."""
import gzip
import os
import subprocess

import pytest

from conftest import VECTORS, hookwatch_cmd


def analyze(*args):
    return subprocess.run(hookwatch_cmd() + ["analyze", *args], capture_output=True, text=True, timeout=60)


def write(path, text, meta="method:\n  t_set: 0.5\n"):
    path.write_text(text)
    if meta is not None:
        (path.parent / (path.name[:-4] + ".meta.yaml")).write_text(meta)
    return str(path)


def one_line_error(p, *needles):
    assert p.returncode == 2, (p.returncode, p.stdout, p.stderr)
    err = p.stderr.strip()
    assert "Traceback" not in err
    assert len(err.splitlines()) == 1, err
    for n in needles:
        assert n in err, (n, err)
    return err


def test_missing_file(tmp_path):
    one_line_error(analyze(str(tmp_path / "nope.csv")), "nope.csv", "no such file")


def test_missing_column(tmp_path):
    f = write(tmp_path / "a.csv", "t,T1,X\n0,0.3,0.6\n")
    one_line_error(analyze(f), "a.csv", "missing column 'T2'")


def test_unparsable_row_names_the_line(tmp_path):
    f = write(tmp_path / "b.csv", "t,T1,T2\n0,0.3,0.6\n0.02,0.3,0.6\n0.04,abc,0.6\n")
    one_line_error(analyze(f), "b.csv", "line 4", "'abc'")


def test_short_row_names_the_line(tmp_path):
    f = write(tmp_path / "c.csv", "t,T1,T2\n0,0.3,0.6\n0.02,0.3\n0.04,0.3,0.6\n")
    one_line_error(analyze(f), "c.csv", "line 3")


def test_unknown_parameter_lists_valid_names(tmp_path):
    f = write(tmp_path / "d.csv", "t,T1,T2\n0,0.3,0.6\n")
    err = one_line_error(analyze(f, "--set", "dleta=0.3"), "dleta", "valid names")
    assert "delta" in err and "tau_g" in err


def test_unknown_parameter_in_sidecar(tmp_path):
    f = write(tmp_path / "e.csv", "t,T1,T2\n0,0.3,0.6\n", meta="method:\n  t_set: 0.5\n  thetta: 100\n")
    one_line_error(analyze(f), "e.csv", "thetta", "valid names")


@pytest.mark.parametrize("setting,needle", [
    ("ts=0", "ts"), ("ts=-1", "ts"), ("delta=0", "delta"), ("delta=-0.1", "delta"),
    ("r_min=5", "r_min"), ("tau=abc", "not a number"), ("t_set=nan", "t_set"),
])
def test_impossible_values(tmp_path, setting, needle):
    f = write(tmp_path / "f.csv", "t,T1,T2\n0,0.3,0.6\n")
    one_line_error(analyze(f, "--set", setting), needle)


def test_t_set_missing(tmp_path):
    f = write(tmp_path / "g.csv", "t,T1,T2\n0,0.3,0.6\n", meta=None)
    one_line_error(analyze(f), "g.csv", "t_set", "missing")


def test_malformed_sidecar(tmp_path):
    f = write(tmp_path / "h.csv", "t,T1,T2\n0,0.3,0.6\n", meta="method: [t_set: 0.5\n")
    one_line_error(analyze(f), "h.meta.yaml", "not valid YAML")


def test_bad_set_syntax(tmp_path):
    f = write(tmp_path / "i.csv", "t,T1,T2\n0,0.3,0.6\n")
    one_line_error(analyze(f, "--set", "delta"), "NAME=VALUE")


def test_good_logs_still_reported_beside_a_bad_one(tmp_path):
    good = os.path.join(VECTORS, "v4_aborted.csv.gz")
    p = analyze(str(tmp_path / "missing.csv"), good, "--json")
    assert p.returncode == 2
    assert '"status": "aborted"' in p.stdout
    assert "missing.csv" in p.stderr


def test_truncated_gzip_keeps_complete_rows(tmp_path):
    """A log cut off by kill -9 still reads: every complete row counts."""
    rows = "t,T1,T2\n" + "".join(f"{k * 0.02:.2f},0.300,0.600\n" for k in range(5000))
    data = gzip.compress(rows.encode())
    f = tmp_path / "cut.csv.gz"
    f.write_bytes(data[: len(data) - 40])
    (tmp_path / "cut.meta.yaml").write_text("method:\n  t_set: 0.5\n")
    p = analyze(str(f), "--json")
    assert p.returncode == 0, p.stderr
    import json
    got = json.loads(p.stdout)
    assert 4000 < got["n_slots"] <= 5000
    assert got["reasons"]["MISSING"] == 0
