"""The console's door bounds on their own (virtual clocks): Host names, connect rates, the
once-a-minute log line with its count, the report pool, and the lockout's check-and-count."""
from __future__ import annotations

import asyncio
import logging

import pytest

from gateway.outputs.console import auth
from gateway.outputs.console.guard import Busy, HostAllow, LogLimit, RateBound, ReportPool, host_name


def test_host_names():
    assert host_name("[::1]:8080") == "::1" and host_name("Console.Plant.:8443") == "console.plant"
    h = HostAllow(["console.plant.example"], ["127.0.0.1", "0.0.0.0", "10.10.4.2"])
    assert h.allowed("console.plant.example:8443", "10.10.4.2")
    assert h.allowed("10.10.4.2:8443", "127.0.0.1")                   # a listen address
    assert h.allowed("192.168.7.3", "192.168.7.3")                     # where the client connected
    assert h.allowed("localhost:8080", "127.0.0.1") and h.allowed("app.localhost", "::1")
    assert h.allowed("localhost", "::ffff:127.0.0.1")
    assert not h.allowed("localhost", "10.10.4.2")                    # not on loopback
    assert not h.allowed("0.0.0.0", "10.10.4.2")                      # an unspecified address is no name
    for bad in ("evil.example", "console.plant.example.evil.example", "10.10.4.3", "", None,
                "127.0.0.1.nip.io"):
        assert not h.allowed(bad, "127.0.0.1"), bad


def test_rate_bound_burst_then_refill():
    now = [0.0]
    r = RateBound(6, clock=lambda: now[0], max_keys=3)
    assert [r.take("a") for _ in range(6)] == [0.0] * 6
    assert r.take("a") == pytest.approx(10.0)          # 6 a minute: the next in 10 s
    assert r.take("b") == 0.0                           # another key has its own bucket
    now[0] += 10.0
    assert r.take("a") == 0.0 and r.take("a") > 0
    for k in ("c", "d", "e"):
        r.take(k)
    assert len(r._b) <= 3                               # bounded table


def test_log_limit_one_line_per_kind_a_minute_with_count(caplog):
    caplog.set_level(logging.INFO)
    now = [0.0]
    lim = LogLimit(logging.getLogger("hookwatch.console"), clock=lambda: now[0])
    for _ in range(5):
        lim.warn("bad JSON", "POST %s refused", "/api/login")
    lim.warn("deep JSON", "deep")
    now[0] += 61
    lim.warn("bad JSON", "POST %s refused", "/api/login")
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs == ["console: POST /api/login refused (×1)", "console: deep (×1)",
                    "console: POST /api/login refused (×4 in the last 60 s)",
                    "console: POST /api/login refused (×1)"]
    lim.close()
    assert all(r.levelno == logging.WARNING and not r.exc_info for r in caplog.records)
    assert lim.counts == {"bad JSON": 6, "deep JSON": 1}


def test_report_pool_bounds_queues_and_coalesces():
    async def main():
        pool = ReportPool(jobs=2, queue=1)
        gate = asyncio.Event()
        started = []

        def job(name):
            async def run():
                started.append(name)
                await gate.wait()
                return name
            return run

        a1 = asyncio.ensure_future(pool.run("a", job("a")))
        a2 = asyncio.ensure_future(pool.run("a", job("a-again")))      # joins a
        b = asyncio.ensure_future(pool.run("b", job("b")))
        c = asyncio.ensure_future(pool.run("c", job("c")))              # waits (queue 1)
        await asyncio.sleep(0.01)
        with pytest.raises(Busy) as e:
            await pool.run("d", job("d"))
        assert e.value.retry_after >= 1
        assert pool.running == 2 and sorted(started) == ["a", "b"]
        a1.cancel()                                  # a client going away does not end the job
        gate.set()
        assert await a2 == "a" and await b == "b" and await c == "c"
        assert pool.peak == 2 and pool.pending == 0 and pool.refused == 1
        assert started.count("a") == 1 and "a-again" not in started
    asyncio.run(main())


def test_lockout_attempt_counts_before_the_check_and_forgives_success():
    now = [0.0]
    lk = auth.Lockout(3, 60, clock=lambda: now[0])
    limits = {"ua:1 alice": 3, "a:1": 5}
    assert [lk.attempt(limits) for _ in range(3)] == [0.0, 0.0, 0.0]   # three checks, no awaits
    assert lk.attempt(limits) == 60                                      # the fourth is refused
    assert lk.attempt({"ua:2 alice": 3, "a:2": 5}) == 0                  # another address
    lk.forgive(clear=("ua:1 alice",), one=("a:1",))                     # the third was right
    assert lk.attempt(limits) == 0
    now[0] += 61
    assert lk.locked("ua:1 alice", "a:1") == 0


def test_limits_doc_names_each_console_key_with_its_default():
    """docs/limits.md lists each console bound with its key and the schema's default."""
    import dataclasses
    import os

    from conftest import ROOT
    from gateway.config.sections import ConsoleConfig

    with open(os.path.join(ROOT, "docs", "limits.md"), encoding="utf-8") as f:
        text = f.read()
    section = text.split("### Operator console", 1)[1].split("\n### ", 1)[0]
    defaults = {f.name: f.default for f in dataclasses.fields(ConsoleConfig)}
    for k in ("lockout_attempts", "login_failures_per_address", "report_jobs", "report_queue",
              "stream_connects_per_address", "stream_connects_total"):
        assert f"`console.{k}` ({defaults[k]}" in section, k
    assert f"`console.lockout_s` ({defaults['lockout_s']:g} s)" in section
    assert "`console.allowed_hosts` (default none)" in section and defaults["allowed_hosts"] == ()
