"""Issue 20, the station side: the life prior of each test (METHOD.md §7a) and `hook_replaced`.

- The prior is resolved at each start: a fixed one in `method:` wins (published source `method`),
  else the `forecast.priors` entry of the grade and T_set (`config`), else the recorded history of
  every station under the same records root with ≥ 3 failures (`history:N`; the sidecar's
  `prior_source` is §7a's `config` / `history`), read and fitted off the slot loop; a
  damaged result is skipped with one log line. The prior goes into the sidecar's method section
  (so `hookwatch analyze` of the log gives the same forecast) and into the state.
- `hook_replaced` ends the running test (end_reason hook_replaced), appends one line to
  hooks.jsonl, derives `<old>-R<n>` when no sample id is given and, with restart_on_replace,
  starts the next test with the new hook. A hostile sample id is refused and changes nothing.
"""
import asyncio
import json
import logging
import os

import yaml

from gateway.core.control import ControlParams
from gateway.core.method.prior import PriorEntry
from gateway.core.records import Command, CommandKind, EventType
from gateway.core.records import TestState as TS
from gateway.station.command_desk import CODE
from gateway.station.hook_log import MAX_LINE, append_hook, next_sample_id, read_hooks
from gateway.station.priors import PriorBook
from gateway.station.station import Station, TestPlan
from kit.fakes import Capture, FakeMeter, QuietStm32

#: a start without a zero check that settles within 0.2 s on the fake meter (mean 0.5 N)
FAST = {"zero_check": False, "settle_time": 0.2, "w_ss": 1.0, "w_hold": 4.0, "tau": 1.0}


def _result(folder, name, grade, t_set, status, t_life):
    d = folder / name
    d.mkdir(parents=True)
    (d / "result.json").write_text(json.dumps({"grade": grade, "t_set": t_set,
                                               "method": {"status": status, "t_life": t_life}}))


def _station(tmp_path, sid="fc", method=None, plan=None):
    out = Capture()
    st = Station(station_id=sid, method={**FAST, **(method or {})}, control=ControlParams(),
                 meter=FakeMeter(0.4, 0.6), stm32=QuietStm32(), records_dir=str(tmp_path / "records"),
                 outputs=[out], default_plan=plan or TestPlan("S-1", "I", 0.5, 600.0))
    return st, out


def _run(st, during, limit_s=30.0):
    async def main():
        stop = asyncio.Event()
        task = asyncio.create_task(st.run(stop))
        try:
            while st.clock is None:
                await asyncio.sleep(0.005)
            return await asyncio.wait_for(during(st), limit_s)
        finally:
            stop.set()
            await task
    return asyncio.run(main())


async def _until(cond, limit_s=20.0):
    for _ in range(int(limit_s / 0.01)):
        if cond():
            return
        await asyncio.sleep(0.01)
    raise AssertionError("condition not reached")


def test_the_prior_comes_from_the_method_then_the_configuration_then_the_history(tmp_path, caplog):
    root = tmp_path / "records"
    # the box's history: 3 failures of grade I at 0.5 N on two stations, other grades and setpoints,
    # a test without failure, and a damaged result (skipped with one log line)
    _result(root / "a", "T1", "I", 0.5, "failure", 100.0)
    _result(root / "a", "T2", "I", 0.5, "failure", 120.0)
    _result(root / "b", "T3", "I", 0.5004, "failure", 110.0)
    _result(root / "b", "T4", "I", 0.5, "no_failure", None)
    _result(root / "b", "T5", "II", 0.5, "failure", 50.0)
    _result(root / "b", "T6", "I", 0.7, "failure", 60.0)
    (root / "b" / "T7").mkdir()
    (root / "b" / "T7" / "result.json").write_text("{not json")
    book = PriorBook("a", str(root), [PriorEntry("II", 0.5, 40.0, 4.0, 7)])

    async def read():
        book.refresh()                      # off the loop: the loop goes on meanwhile
        await _until(lambda: book.history is not None)
    with caplog.at_level(logging.WARNING):
        asyncio.run(read())
    assert sum("damaged result file" in r.getMessage() for r in caplog.records) == 1
    h = book.resolve("I", 0.5, {})
    assert h.source == "history" and h.label == "history:3" and h.n == 3 and h.mean == 110.0
    assert h.n_censored == 0
    assert abs(h.sd - 10.0) < 1e-9
    c = book.resolve("II", 0.5, {})
    assert (c.mean, c.sd, c.source, c.n) == (40.0, 4.0, "config", 7)
    f = book.resolve("I", 0.5, {"prior_mean": 90.0, "prior_sd": 9.0})
    assert (f.mean, f.sd, f.source, f.label) == (90.0, 9.0, "config", "method")
    assert book.resolve("I", 0.7, {}).source is None          # one failure only: no prior
    assert book.resolve(None, 0.5, {}).source is None


def test_a_test_starts_with_its_prior_in_the_sidecar_and_the_state(tmp_path):
    root = tmp_path / "records"
    for i, life in enumerate((100.0, 120.0, 110.0)):       # another station's failures on the box
        _result(root / "other", f"T{i}", "I", 0.5, "failure", life)
    st, out = _station(tmp_path, method={"lead": 20.0, "p_due": 0.2})

    async def during(st):
        await _until(lambda: st.tests.priors.history is not None)
        st.start_test(st.default_plan, "cli")
        await _until(lambda: st.session is not None)
        return dict(st.state.__dict__), st.session.recorder.meta

    state, meta = _run(st, during)
    assert state["prior_mean"] == 110.0 and state["prior_source"] == "history:3"
    # the planner's counts (§7a v3): 3 wear-out failures, no censored life, no early failure
    assert (state["prior_n"], state["prior_n_censored"], state["prior_n_early"]) == (3, 0, 0)
    assert state["lead_s"] == 20.0 and state["p_due"] == 0.2 and state["test_started_utc"]
    assert state["end_p50"] is None and state["due"] is False and state["warn_reasons"] == []
    assert meta["method"]["prior_mean"] == 110.0 and meta["method"]["lead"] == 20.0
    # the sidecar: §7a's source and counts; the state and the event: the published label
    assert meta["prior_source"] == "history" and meta["prior_n"] == 3 and meta["prior_n_censored"] == 0
    assert meta["prior_n_early"] == 0
    started = [e for e in out.events if e.type == EventType.TEST_STARTED][0]
    assert started.data["prior_source"] == "history:3" and started.data["prior_n"] == 3
    assert (started.data["prior_n_censored"], started.data["prior_n_early"]) == (0, 0)
    # the test ended (gateway shutdown): no forecast outside a test
    assert st.state.prior_mean is None and st.state.prior_source is None and st.state.lead_s is None
    assert st.state.prior_n is None and st.state.prior_n_early is None
    with open(meta_path(root / "fc")) as f:
        on_disk = yaml.safe_load(f)
    assert on_disk["method"]["prior_mean"] == 110.0 and on_disk["method"]["prior_sd"] == 10.0
    assert on_disk["prior_source"] == "history" and on_disk["prior_n_censored"] == 0


def meta_path(station_dir):
    (d,) = [os.path.join(station_dir, x) for x in os.listdir(station_dir)
            if os.path.isdir(os.path.join(station_dir, x))]
    return os.path.join(d, "log.meta.yaml")


def test_hook_replaced_ends_the_test_logs_it_and_restarts_with_the_new_hook(tmp_path):
    st, out = _station(tmp_path)
    st.tests.restart_on_replace = True

    async def during(st):
        await st.submit(Command(CommandKind.START, "mqtt", {"sample_id": "S-1", "grade": "I",
                                                             "t_set": 0.5}))
        await _until(lambda: st.session is not None)
        await _until(lambda: st.state.elapsed_s >= 0.2)
        first_test = st.test_id
        # hostile sample ids: refused, nothing changes
        for bad in ("S\x00-2", "x" * 200, "ünï", "", 42):
            r = await st.submit(Command(CommandKind.HOOK_REPLACED, "mqtt", {"sample_id": bad}))
            assert not r.ok and r.code == CODE["SAMPLE_ID"], (bad, r)
        r = await st.submit(Command(CommandKind.HOOK_REPLACED, "mqtt", {"grade": "nope"}))
        assert not r.ok and r.code == CODE["GRADE"]
        assert st.test_id == first_test and not os.path.exists(tmp_path / "records" / "fc" / "hooks.jsonl")
        # the replacement: the test ends, the new hook's test starts
        r = await st.submit(Command(CommandKind.HOOK_REPLACED, "sparkplug", {"sample_id": "S-2"}))
        assert r.ok, r
        await _until(lambda: st.session is not None and st.session.plan.sample_id == "S-2")
        # … and once more without a sample id: `<old>-R<n>`
        r = await st.submit(Command(CommandKind.HOOK_REPLACED, "cli"))
        assert r.ok, r
        await _until(lambda: st.session is not None and st.session.plan.sample_id == "S-2-R1")
        return first_test

    first_test = _run(st, during)
    ends = [r for r in st.results]
    assert ends[0]["end_reason"] == "hook_replaced" and ends[0]["test_id"] == first_test
    assert ends[0]["test_status"] == "aborted" and ends[1]["end_reason"] == "hook_replaced"
    hooks = read_hooks(str(tmp_path / "records" / "fc"))
    assert [(h["old_sample_id"], h["new_sample_id"], h["by"]) for h in hooks] == [
        ("S-1", "S-2", "sparkplug"), ("S-2", "S-2-R1", "cli")]
    assert hooks[0]["test_id"] == first_test and hooks[0]["grade"] == "I"
    assert hooks[0]["life_s"] > 0 and hooks[0]["station"] == "fc" and hooks[0]["utc"].endswith("Z")
    # the old hook's life in the §7a history: replaced before its end (censored) once its test had a
    # baseline, else none (§7a v3's kinds, gateway/station/hook_log.py)
    assert hooks[0]["life_kind"] == ("censored" if ends[0]["method"]["k_b"] is not None else None)
    ev = [e for e in out.events if e.type == EventType.HOOK_REPLACED]
    assert [e.data["new_sample_id"] for e in ev] == ["S-2", "S-2-R1"] and ev[0].data["logged"]
    refused = [e for e in out.events if e.type == EventType.COMMAND_REJECTED]
    assert st.desk.gate.refusals == 6 and 1 <= len(refused) <= 6    # counted; events per kind


def test_hook_replaced_without_restart_leaves_the_station_idle(tmp_path):
    st, _ = _station(tmp_path)

    async def during(st):
        st.start_test(st.default_plan, "cli")
        await _until(lambda: st.session is not None)
        r = await st.submit(Command(CommandKind.HOOK_REPLACED, "plc:127.0.0.1", {"sample_id": "S-1"}))
        assert r.ok
        await asyncio.sleep(0.2)
        return st.state.state

    assert _run(st, during) == TS.ABORTED
    (h,) = read_hooks(str(tmp_path / "records" / "fc"))
    # a PLC's staged sample id that is still the old hook's is no new one: `<old>-R1`
    assert h["old_sample_id"] == "S-1" and h["new_sample_id"] == "S-1-R1"
    assert st.state.sample_id == "S-1-R1" and st.session is None


def test_hooks_jsonl_is_bounded_and_a_damaged_line_is_skipped(tmp_path, caplog):
    d = str(tmp_path / "st")
    assert next_sample_id("S-9", 64) == "S-9-R1" and next_sample_id("S-9-R4", 64) == "S-9-R5"
    assert len(next_sample_id("x" * 64, 64)) == 64
    assert append_hook(d, {"station": "st", "old_sample_id": "A", "new_sample_id": "B",
                           "by": "x" * 100_000}) is None
    with open(os.path.join(d, "hooks.jsonl"), "ab") as f:
        f.write(b"{damaged\n" + b"y" * (3 * MAX_LINE) + b"\n")
    assert append_hook(d, {"station": "st", "old_sample_id": "B", "new_sample_id": "C"}) is None
    with open(os.path.join(d, "hooks.jsonl"), "rb") as f:
        first = f.readline()
    assert len(first) <= MAX_LINE
    with caplog.at_level(logging.WARNING):
        got = read_hooks(d)
    assert [h["new_sample_id"] for h in got] == ["B", "C"]
    assert sum("2 damaged line(s) skipped" in r.getMessage() for r in caplog.records) == 1
    assert read_hooks(d, max_lines=1) == [got[-1]]
    # a station folder that cannot be written (here: a file in its place) is a reason, not an
    # exception
    (tmp_path / "blocked").write_text("")
    err = append_hook(str(tmp_path / "blocked"), {"station": "st"})
    assert isinstance(err, str) and err


def _ended(folder, name, status, n_slots, reasons=None):
    d = folder / name
    d.mkdir(parents=True)
    (d / "result.json").write_text(json.dumps({
        "test_id": name, "grade": "I", "t_set": 0.5, "ts": 0.02,
        "method": {"status": status, "t_life": None, "k_b": 40000, "n_slots": n_slots,
                   "stop_reasons": reasons}}))


def test_censored_lives_enter_the_prior_fitted_off_the_loop(tmp_path, caplog, monkeypatch):
    import gateway.station.priors as P
    root = tmp_path / "records"
    for i, life in enumerate((2917.92, 3064.34, 3215.14, 3363.06)):
        _result(root / "a", f"F{i}", "I", 0.5, "failure", life)
    _ended(root / "a", "C1", "aborted", 130000, ["STOPPED"])   # hooks replaced early
    _ended(root / "b", "C2", "aborted", 145000, ["STOPPED"])
    _ended(root / "b", "C3", "no_failure", 150000)               # reached its planned end
    _ended(root / "b", "P1", "aborted", 100051, ["MISSING"])     # a protection stop: not a life
    book = PriorBook("a", str(root))

    async def read():
        book.refresh()
        await _until(lambda: book.history is not None)
    asyncio.run(read())
    # the worker fitted the group: the start only looks it up
    assert len(book.fitted.by_lives) == 1 and len(book.fitted.by_group) == 1
    h = book.resolve("I", 0.5, {})
    assert (h.source, h.label, h.n, h.n_censored) == ("history", "history:4", 4, 3)
    assert abs(h.mean - 3156.10905968845) <= 1e-10 * 3156 and abs(h.sd - 182.25402648037655) <= 1e-8
    assert h.sidecar()["prior_n_censored"] == 3
    # a test of this station just ended (not yet read again): a small group is fitted at the start
    book.add_result({"test_id": "C4", "grade": "I", "t_set": 0.5, "ts": 0.02,
                     "method": {"status": "no_failure", "k_b": 1, "n_slots": 160000}})
    h2 = book.resolve("I", 0.5, {})
    assert (h2.n, h2.n_censored) == (4, 4) and h2.mean > h.mean
    # a group too large to fit on the slot loop: the last read's fit, with one log line
    monkeypatch.setattr(P, "SYNC_FIT_MAX", 5)
    with caplog.at_level(logging.INFO, logger="hookwatch.station"):
        h3 = book.resolve("I", 0.5, {})
    assert (h3.mean, h3.n_censored) == (h.mean, 3)
    assert sum("fitted again off the loop" in r.getMessage() for r in caplog.records) == 1


def test_site_lives_that_change_are_refitted_off_the_loop_and_a_start_meanwhile_never_scans_a_large_history(
        tmp_path, caplog, monkeypatch):
    import gateway.station.priors as P
    from gateway.core.method.prior import PastTest
    root = tmp_path / "records"
    for i, life in enumerate((100.0, 120.0, 110.0)):
        _result(root / "a", f"T{i}", "I", 0.5, "failure", life)
    book = PriorBook("a", str(root))
    site = tuple(PastTest("I", 0.5, "failure", x, test_id=f"S{i}", station="s2", t_end=600.0)
                 for i, x in enumerate((90.0, 95.0)))

    async def go():
        book.refresh()
        await _until(lambda: book.history is not None)
        before = book.resolve("I", 0.5, {})
        book.set_site(site)               # received from the broker: fitted again off the loop
        during = book.resolve("I", 0.5, {})          # a small history: scanned at once
        await _until(lambda: book._fitted_site is site)
        return before, during, book.resolve("I", 0.5, {})
    before, during, after = asyncio.run(go())
    assert before.n == 3 and before.origin == "this station: 3 tests"
    assert during == after and after.n == 5
    assert after.origin == "the site: 5 tests from 2 stations (3 of this station; s2 2)"
    assert after.label == "history:5 (the site: 5 tests from 2 stations (3 of this station; s2 2))"
    assert after.station_ids == ("a", "s2") and after.sidecar()["prior_station_ids"] == ["a", "s2"]
    # a large history: a start before the refit uses the last fit (one log line), never a scan
    monkeypatch.setattr(P, "SCAN_MAX", 2)
    book.site = site + (PastTest("I", 0.5, "failure", 80.0, test_id="S9", station="s3", t_end=600.0),)
    with caplog.at_level(logging.INFO, logger="hookwatch.station"):
        stale = book.resolve("I", 0.5, {})
    assert stale == after
    assert sum("being fitted off the loop" in r.getMessage() for r in caplog.records) == 1


def test_an_early_failure_is_classed_in_the_pooled_history_of_the_box_and_the_site(tmp_path):
    """§7a v3 on the history as the start sees it: this box's records hold 3 failures near 100 s
    and one at 40 s (4 lives: no early failure, the short one widens the prior); the site shares
    2 censored lives — 6 lives, M = 100, and 40 s is an early failure, censored for the wear-out
    prior. The hook log's kind of a test is the same rule on the same history."""
    from gateway.core.method.prior import PastTest, history_prior, wear_out_prior
    from gateway.station.priors import life_kind
    root = tmp_path / "records"
    for i, life in enumerate((96.0, 100.0, 104.0, 40.0)):
        _result(root / "a", f"T{i}", "I", 0.5, "failure", life)
    book = PriorBook("a", str(root))
    site = tuple(PastTest("I", 0.5, "aborted", None, k_b=100, stop_reasons=("STOPPED",), n_slots=n,
                          ts=0.02, test_id=f"S{i}", station="s2", t_end=600.0)
                 for i, n in enumerate((5000, 5500)))           # 100 s and 110 s

    async def go():
        book.refresh()
        await _until(lambda: book.history is not None)
        alone = book.resolve("I", 0.5, {})
        book.set_site(site)
        await _until(lambda: book._fitted_site is site)
        return alone, book.resolve("I", 0.5, {})
    alone, pooled = asyncio.run(go())
    assert (alone.n, alone.n_censored, alone.n_early) == (4, 0, 0)
    assert (alone.mean, alone.sd) == wear_out_prior([96.0, 100.0, 104.0, 40.0])
    assert (pooled.n, pooled.n_censored, pooled.n_early) == (3, 2, 1)
    expected = history_prior([96.0, 100.0, 104.0, 40.0], [100.0, 110.0])
    assert abs(pooled.mean - expected[0]) <= 1e-12 * expected[0]
    assert abs(pooled.sd - expected[1]) <= 1e-12 * expected[1]
    assert pooled.sd < alone.sd / 3                     # the defect no longer widens the prior
    assert pooled.sidecar()["prior_n_early"] == 1 and pooled.lives_words() == (
        "3 wear-out failures, 2 censored, 1 early failure")
    # the kind of a test's life in that history, as the hook log names it
    short = {"test_id": "T3", "grade": "I", "t_set": 0.5, "method": {"status": "failure", "t_life": 40.0}}
    assert life_kind(short, book.known()) == "early"
    assert life_kind({**short, "test_id": "T1", "method": {"status": "failure", "t_life": 100.0}},
                     book.known()) == "wear_out"
    # … this box's alone: with the short one 4 lives (the records carry no test id: the short one
    # is left out of them, else it would count twice)
    box = [t for t in book.known() if t.station != "s2" and t.t_life != 40.0]
    assert life_kind(short, box) == "wear_out" and life_kind(short, box + list(site)) == "early"
    assert life_kind({**short, "method": {"status": "no_baseline"}}, book.known()) is None
