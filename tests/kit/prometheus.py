"""Debian's real Prometheus server for tests: started on a free loopback port with the shipped
recording rules, scraping one target; and its HTTP API (instant queries, series)."""
import json
import os
import subprocess
import time
import urllib.parse
import urllib.request

import pytest
import yaml

from conftest import ROOT
from kit.tools import free_port, require_tool

RULES = os.path.join(ROOT, "deploy", "prometheus", "hookwatch-rules.yml")


def query(api: str, promql: str) -> list[dict]:
    url = f"{api}/api/v1/query?" + urllib.parse.urlencode({"query": promql})
    with urllib.request.urlopen(url, timeout=5) as r:
        body = json.load(r)
    assert body["status"] == "success", body
    return body["data"]["result"]


def series(api: str, match: str) -> list[dict]:
    url = f"{api}/api/v1/series?" + urllib.parse.urlencode({"match[]": match})
    with urllib.request.urlopen(url, timeout=5) as r:
        body = json.load(r)
    assert body["status"] == "success", body
    return body["data"]


def wait_for(fn, timeout: float, what: str, log=lambda: ""):
    t_end = time.monotonic() + timeout
    last = None
    while time.monotonic() < t_end:
        try:
            last = fn()
            if last:
                return last
        except OSError as e:      # Prometheus not listening yet
            last = e
        time.sleep(0.5)
    raise AssertionError(f"{what}: last answer {last!r}\n{log()}")


@pytest.fixture
def prometheus(tmp_path):
    """Start Prometheus on a free loopback port; yields (start(target), api url)."""
    binary = require_tool("prometheus")
    procs = []

    def start(target: str) -> str:
        port = free_port()
        conf = tmp_path / "prometheus.yml"
        conf.write_text(yaml.safe_dump({
            "global": {"scrape_interval": "1s", "scrape_timeout": "900ms", "evaluation_interval": "1s"},
            "rule_files": [RULES],
            "scrape_configs": [{"job_name": "hookwatch", "static_configs": [{"targets": [target]}]}],
        }))
        log = open(tmp_path / "prometheus.log", "w")
        p = subprocess.Popen([binary, f"--config.file={conf}", f"--web.listen-address=127.0.0.1:{port}",
                              f"--storage.tsdb.path={tmp_path / 'tsdb'}", "--log.level=warn"],
                             stdout=log, stderr=subprocess.STDOUT)
        procs.append((p, log))
        return f"http://127.0.0.1:{port}"

    yield start
    for p, log in procs:
        p.terminate()
        try:
            p.wait(15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
        log.close()
