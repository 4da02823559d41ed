"""Issue 22 item 6: record retention wired in. A real station (``hookwatch run``) against
``hookwatch sim``, many short tests on a real small tmpfs whose free space is always below
``min_free_percent`` (so every completed test that may go, goes): the disk never fills, the
newest test and every result that has not left the MQTT outbox (a real Mosquitto, stopped for a
while) stay, and the ``records_pruned`` events (the MES's ``mosquitto_sub``) and the Prometheus
counters show the prunings."""
import asyncio
import json
import os
import sqlite3
import time
import urllib.request

import yaml

from gateway.core.records import Event, EventType
from gateway.station.recorder import RESULT_NAME
from gateway.station.retention import Policy, RetentionOutput
from kit.broker import Broker, Sub, pub
from kit.e2e import run_gateway, scenario_file, station_yaml, test_dirs, virtual_station
from kit.smallfs import small_tmpfs
from kit.tools import free_port, wait_for

TUNED = {"dead_band_n": 0.01}
FS_SIZE = 4 << 20
T_END = 3
#: retention is the subject, not the §3a start (tests/gateway/station/test_station_start_e2e.py):
#: each of the ten tests starts without the zero check and after 0.5 s of settled tension instead
#: of 2 s, so the ten lives are mostly their tests, not their starts
QUICK_START = {"zero_check": False, "settle_time": 0.5}


def _ballast(fs: str, leave: int) -> None:
    """Take the file system's free space down to ``leave`` bytes."""
    st = os.statvfs(fs)
    free = st.f_bavail * st.f_frsize
    with open(os.path.join(fs, "ballast.bin"), "wb") as f:
        f.write(b"\0" * max(0, free - leave))


def _station(tmp_path, links, mqtt_port, metrics_port=None):
    path = station_yaml(tmp_path, links, name="ret", control=TUNED, method=QUICK_START,
                        test={"t_end_s": T_END},
                        mqtt={"enabled": True, "port": mqtt_port})
    with open(path) as f:
        cfg = yaml.safe_load(f)
    # min_free_percent 50 on a 4 MB file system left with 1 MB free: always below the floor
    cfg["recorder"]["retention"] = {"min_free_percent": 50, "keep_last": 1, "interval_s": 10}
    if metrics_port is not None:
        cfg["metrics"] = {"enabled": True, "host": "127.0.0.1", "port": metrics_port}
    with open(path, "w") as f:
        yaml.safe_dump(cfg, f)
    return path


def _one_test(tmp_path, st, i):
    gw = run_gateway(tmp_path, st, "--start", "--exit-when-done", "--duration", "60", name=f"gw{i}")
    try:
        assert gw.p.wait(90) == 0, gw.log()
    finally:
        gw.stop()
    glog = gw.log_all()
    assert "Traceback" not in glog and "station failed" not in glog, glog
    assert "cannot write" not in glog and "disk_full" not in glog, glog   # the disk never fills
    return glog


def _in_outbox(outbox):
    db = sqlite3.connect(f"file:{outbox}?mode=ro", uri=True)
    try:
        rows = db.execute("SELECT payload FROM messages WHERE kind='result'").fetchall()
    finally:
        db.close()
    return {json.loads(p)["test_id"] for (p,) in rows}


def _done(tmp_path):
    return [d for d in test_dirs(tmp_path, "ret") if os.path.exists(os.path.join(d, RESULT_NAME))]


def test_retention_over_many_short_tests_on_a_small_disk(tmp_path):
    sc = scenario_file(tmp_path, "ret")
    rec = tmp_path / "records"
    broker = Broker(tmp_path, port=free_port()).start()
    sub = Sub(broker.port, "hookwatch/#")
    try:
        with small_tmpfs(rec, "4m") as fs, virtual_station(tmp_path, sc) as (_sim, links):
            _ballast(fs, 1 << 20)
            st = _station(tmp_path, links, broker.port)
            outbox = os.path.join(fs, "ret", "outbox.sqlite")
            seen: list[str] = []
            # phase 1: the broker takes the results; every older test goes
            for i in range(6):
                _one_test(tmp_path, st, i)
                done = _done(tmp_path)
                seen += [os.path.basename(d) for d in done if os.path.basename(d) not in seen]
                # the newest stays; at most one more: its result may not have left the outbox yet
                assert seen[-1] in {os.path.basename(d) for d in done}
                assert len(done) <= 2, done
            # phase 2: the broker is down, results wait in the outbox: none of those tests goes
            broker.stop()
            held = []
            for i in range(6, 9):
                _one_test(tmp_path, st, i)
                held.append(os.path.basename(_done(tmp_path)[-1]))
                names = {os.path.basename(d) for d in _done(tmp_path)}
                assert set(held) <= names and set(held) <= _in_outbox(outbox), (held, names)
            assert not set(seen) & {os.path.basename(d) for d in _done(tmp_path)}   # phase 1 all gone
            # phase 3: the broker is back; the held results leave, their tests go; the metrics count
            broker = Broker(tmp_path, port=broker.port).start()
            # the MES is subscribed again before the held results leave (mosquitto_sub reconnects
            # on its own; the pruning events are not retained: one published before would be missed)
            n_probe = len(sub.messages("probe"))

            def probe(s):
                pub(broker.port, "hookwatch/probe", "{}", qos=1)
                return len(s.messages("probe")) > n_probe
            sub.wait(probe, 30, what="the MES subscribed again")
            mport = free_port()
            st = _station(tmp_path, links, broker.port, metrics_port=mport)
            gw = run_gateway(tmp_path, st, "--start", "--duration", str(T_END + 40), name="gw-last")
            try:
                def pruned():
                    try:
                        with urllib.request.urlopen(f"http://127.0.0.1:{mport}/metrics", timeout=5) as r:
                            text = r.read().decode()
                    except OSError:
                        return None
                    vals = {}
                    for ln in text.splitlines():
                        if ln.startswith("hookwatch_records_pruned_") and 'station="ret"' in ln:
                            vals[ln.split("{")[0]] = float(ln.rsplit(" ", 1)[1])
                    if vals.get("hookwatch_records_pruned_tests_total", 0) >= len(held):
                        return vals
                    return None
                vals = wait_for(pruned, 60, interval=0.5, what="pruned counters")
                assert vals["hookwatch_records_pruned_bytes_total"] > 0, vals
            finally:
                gw.stop()
            assert "Traceback" not in gw.log_all() and "cannot write" not in gw.log_all()
            names = {os.path.basename(d) for d in _done(tmp_path)}
            assert not set(held) & names, names
            assert len(names) == 1
        # the MES saw each pruning as a records_pruned event (schema-checked by Sub)
        sub.wait(lambda s: sum(len(m[2]["data"]["tests"]) for m in s.messages("records_pruned"))
                 >= len(seen) + len(held) - 1, 20, what="records_pruned events")
        evs = [m[2]["data"] for m in sub.messages("records_pruned")]
        gone = [t for e in evs for t in e["tests"]]
        assert len(gone) == len(set(gone))                      # each test pruned once
        assert set(held) <= set(gone) and set(seen[:-1]) <= set(gone)
        assert all(e["bytes"] > 0 and set(e["rules"]) == {"min_free_percent"} for e in evs), evs
        assert all(len(e["rules"]) == len(e["tests"]) for e in evs)
    finally:
        sub.stop()
        broker.stop()


def test_one_pass_at_a_time_and_a_request_during_a_pass_runs_once_more(tmp_path):
    """The output on a real event loop: passes run in a worker thread, never two at once; a test
    end during a pass gives exactly one more pass; the running test is never pruned."""
    sd = tmp_path / "st"
    for i in range(5):
        d = sd / f"2026010{i}T000000.000Z-S"
        d.mkdir(parents=True)
        (d / "log.csv.gz").write_bytes(b"x" * 1000)
        if i < 4:
            (d / RESULT_NAME).write_text("{}")
            os.utime(d / RESULT_NAME, (1_700_000_000 + i, 1_700_000_000 + i))
    pruned = []
    running = "20260104T000000.000Z-S"

    async def main():
        out = RetentionOutput("st", str(sd), Policy(max_total_mb=None, min_free_percent=0.0,
                                                     keep_last=1, max_age_days=1.0),
                              3600.0, lambda: running, None, pruned.append)
        await out.start()
        ev = Event(EventType.TEST_ENDED, "st", time.time())
        for _ in range(5):
            out.on_event(ev)
        for _ in range(200):
            await asyncio.sleep(0.02)
            if out._pass is not None and out._pass.done():
                break
        await out.stop()
        return out

    out = asyncio.run(main())
    assert out.failures == 0 and 1 <= out.passes <= 3
    assert sum(len(p.tests) for p in pruned) == 3 == out.pruned_tests
    left = sorted(os.listdir(sd))
    assert left == ["20260103T000000.000Z-S", running]        # the newest completed + the running


def test_metrics_count_the_records_pruned_events():
    """The two counters follow the events (a snapshot of an older worker without them reads 0)."""
    from gateway.outputs.prometheus import MetricsOutput, families

    class Port:             # a southbound port's health (gateway.core.ports.PortLink)
        connected = True
        counters: dict = {}

    class View:             # what the metrics read of their station (gateway.core.ports.StationLinks)
        id = "mx-ret"
        ts = 0.02
        meter = stm32 = Port()

    m = MetricsOutput(View(), serve=False)
    for tests, n in ((["a", "b"], 1000), (["c"], 234)):
        m.on_event(Event(EventType.RECORDS_PRUNED, "mx-ret", time.time(),
                         data={"tests": tests, "bytes": n, "rules": ["min_free_percent"] * len(tests)}))
    snap = m.snapshot()
    old = {**snap, "station": "old"}
    old.pop("records_pruned")

    def value(name, station):
        fam = next(f for f in families([snap, old]) if f.name == name)
        return next(s.value for s in fam.samples if s.labels["station"] == station)

    assert value("hookwatch_records_pruned_tests", "mx-ret") == 3
    assert value("hookwatch_records_pruned_bytes", "mx-ret") == 1234
    assert value("hookwatch_records_pruned_tests", "old") == 0
    assert snap["events"]["records_pruned"] == 2
