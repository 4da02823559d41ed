"""A report reads a log as `hookwatch analyze` and the live station do: the sidecar's
``lost_spans`` (slots the recorder could not write during a disk outage) are LOST slots."""
import os
import shutil

import yaml

from conftest import ROOT
from gateway.offline.analysis import analyze_file, params_for
from gateway.offline.logio import read_meta
from gateway.offline.report.per_log import analyze_test

VECTORS = os.path.join(ROOT, "tests", "vectors")


def test_the_report_reads_the_recorded_lost_spans(tmp_path):
    log = str(tmp_path / "v1.csv.gz")
    shutil.copy(os.path.join(VECTORS, "v1_failure.csv.gz"), log)
    meta = read_meta(os.path.join(VECTORS, "v1_failure.csv.gz"))
    plain = analyze_test({"log": log, "params": params_for(meta, {}, "v1"), "factors": [1.0]})
    assert "error" not in plain, plain
    meta["lost_spans"] = [[2000, 2499], [9000, 9099]]
    with open(str(tmp_path / "v1.meta.yaml"), "w") as f:
        yaml.safe_dump(meta, f)
    p = params_for(meta, {}, "v1")
    got = analyze_test({"log": log, "params": p, "factors": [1.0]})
    assert "error" not in got, got
    want = analyze_file(log).as_dict()
    assert got["results"][1.0] == want
    assert want["n_valid"] < plain["results"][1.0]["n_valid"] - 500     # the spans were read
    # a malformed span is the log's error, not the campaign's end
    meta["lost_spans"] = "everything"
    with open(str(tmp_path / "v1.meta.yaml"), "w") as f:
        yaml.safe_dump(meta, f)
    bad = analyze_test({"log": log, "params": p, "factors": [1.0]})
    assert "lost_spans" in bad["error"]
