"""The four method vectors (copied from ../shared/vectors) through the CLI and through both forms."""
import glob
import json
import os
import subprocess

import pytest

from conftest import VECTORS, hookwatch_cmd
from gateway.analysis import params_for
from gateway.logio import read_log
from gateway.method import analyze_slots, run_streaming, to_slots

EXACT = ["status", "k_b", "stable_first", "stable_last", "k_life", "n_slots", "n_valid", "reasons",
         "stop_slot", "stop_reasons", "interrupted"]
CLOSE = ["mu_ss", "mu_th", "t_life"]
NAMES = sorted(os.path.basename(p)[:-len(".csv.gz")] for p in glob.glob(os.path.join(VECTORS, "*.csv.gz")))


def check(got, exp):
    for k in EXACT:
        assert got[k] == exp[k], k
    for k in CLOSE:
        if exp[k] is None:
            assert got[k] is None, k
        else:
            assert abs(got[k] - exp[k]) <= 1e-9, k


def expected(name):
    with open(os.path.join(VECTORS, name + ".expected.json")) as f:
        return json.load(f)


def test_there_are_four_vectors():
    assert NAMES == ["v1_failure", "v2_faults", "v3_no_failure", "v4_aborted"]


def test_cli_json_reproduces_every_vector():
    logs = [os.path.join(VECTORS, n + ".csv.gz") for n in NAMES]
    p = subprocess.run(hookwatch_cmd() + ["analyze", *logs, "--json"], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 0, p.stderr
    lines = [json.loads(ln) for ln in p.stdout.splitlines()]
    assert len(lines) == len(NAMES)
    from gateway.method import RESULT_KEYS
    for name, got in zip(NAMES, lines):
        assert set(got) == set(RESULT_KEYS) | {"log"}
        assert got["log"].endswith(name + ".csv.gz")
        check(got, expected(name))


@pytest.mark.parametrize("name", NAMES)
def test_batch_and_streaming_forms(name):
    log = read_log(os.path.join(VECTORS, name + ".csv.gz"))
    p = params_for(log.meta, {}, name)
    s = to_slots(log.t, log.t1, log.t2, p)
    batch = analyze_slots(s, p).as_dict()
    stream = run_streaming(p, s.present, s.t1, s.t2).as_dict()
    check(batch, expected(name))
    assert stream == batch


def test_cli_table_output_is_readable():
    p = subprocess.run(hookwatch_cmd() + ["analyze", os.path.join(VECTORS, "v4_aborted.csv.gz")],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 0
    assert "aborted" in p.stdout and "protection stop at slot 95050 (MISSING)" in p.stdout


def test_set_overrides_sidecar():
    log = os.path.join(VECTORS, "v1_failure.csv.gz")
    p = subprocess.run(hookwatch_cmd() + ["analyze", log, "--json", "--set", "delta=0.5"],
                       capture_output=True, text=True, timeout=60)
    got = json.loads(p.stdout)
    exp = expected("v1_failure")
    assert got["mu_ss"] == pytest.approx(exp["mu_ss"], abs=1e-12)
    assert got["mu_th"] == pytest.approx(1.5 * exp["mu_ss"], abs=1e-12)
