"""Issue 29 item 2, the pure part: a station's lives as its retained snapshot, the bounded intake
of another station's (every implausible record refused with one counted log line, never reaching
a prior), the bounds per station and in all, the local copy (a gateway that restarts while the
broker is down still has the site's lives), and the topic design."""
import json
import logging
import math

import pytest

from gateway.core.command_intake import Refused
from gateway.core.method.prior import PastTest, resolve_prior
from gateway.outputs.mqtt import sitelives as SL

BASE_A = "hookwatch/plant/hall/l1/a"
TOPIC_A = SL.lives_topic(BASE_A)


def life(i, status="failure", t_life=3000.0, n_slots=None, stop=None, station="a", grade="I"):
    return PastTest(grade, 0.5, status, t_life if status == "failure" else None, k_b=40000,
                    stop_reasons=stop, n_slots=n_slots or (int(t_life / 0.02) + 3000), ts=0.02,
                    test_id=f"T-{station}-{i}", station=station, t_end=3600.0, end_reason="completed")


A_LIVES = [life(0, t_life=2917.92), life(1, t_life=3064.34), life(2, t_life=3215.14),
           life(3, "aborted", n_slots=130000, stop=("STOPPED",)),
           life(4, "aborted", n_slots=145000, stop=("STOPPED",))]


def payload(station, lives, **over):
    doc = {**SL.snapshot(station, lives, "2026-03-01T08:00:00.000Z"), "seq": 7, **over}
    return json.dumps(doc).encode()


def test_topic_design():
    assert TOPIC_A == "hookwatch/plant/hall/l1/a/lives"
    assert SL.site_filter(BASE_A) == "hookwatch/plant/+/+/+/lives"
    assert SL.site_filter("a/b/plant/_/_/st9") == "a/b/plant/+/+/+/lives"
    assert SL.station_of("hookwatch/plant/x/y/b/lives") == "b"
    assert SL.station_of("hookwatch/plant/x/y/b/state") is None


def test_a_snapshot_round_trip_gives_the_same_prior():
    got, bad = SL.parse_snapshot(payload("a", A_LIVES), "a")
    assert bad == [] and got == A_LIVES
    p = resolve_prior([], got, "I", 0.5)
    assert (p.source, p.n, p.n_censored) == ("history", 3, 2)
    assert p == resolve_prior([], A_LIVES, "I", 0.5)
    # tests that give no life are not shared
    assert SL.record_of(life(9, "aborted", n_slots=5000, stop=("MISSING",))) is None
    assert SL.record_of(PastTest("I", 0.5, "failure", 10.0, test_id="x")) is None     # no t_end


def test_a_snapshot_keeps_the_newest_within_its_bounds():
    many = [life(i, t_life=1000.0 + i) for i in range(SL.MAX_LIVES_PER_STATION + 50)]
    doc = SL.snapshot("a", many, "2026-03-01T08:00:00.000Z")
    assert len(doc["lives"]) == SL.MAX_LIVES_PER_STATION
    assert doc["lives"][-1]["test_id"] == many[-1].test_id
    assert len(json.dumps(doc)) <= SL.MAX_LIVES_BYTES


BAD_RECORDS = {
    "a life ≤ 0": {"t_life": 0.0},
    "a negative life": {"t_life": -5.0},
    "beyond the planned duration": {"t_life": 5000.0},
    "a string life": {"t_life": "3000"},
    "a grade that is not one": {"grade": "I\n; rm"},
    "an unknown key": {"extra": 1},
    "no test id": {"test_id": None},
    "an implausible t_set": {"t_set": 1e9},
    "a planned duration of years": {"t_end": 1e12},
    "a status without life": {"status": "no_baseline"},
    "a censored life that is not n_slots · ts": {"status": "no_failure", "t_life": None,
                                                  "censored_s": 10.0},
    "a censored life beyond t_end": {"status": "no_failure", "t_life": None, "n_slots": 250000,
                                     "censored_s": 5000.0},
    "stopped by a protection stop": {"status": "aborted", "t_life": None, "censored_s": 3060.0,
                                     "stop_reasons": ["MISSING"]},
    "a boolean slot count": {"n_slots": True},
}


@pytest.mark.parametrize("what", list(BAD_RECORDS))
def test_an_implausible_record_is_refused_and_the_others_kept(what):
    good = SL.record_of(A_LIVES[0])
    bad = {**SL.record_of(A_LIVES[1]), **BAD_RECORDS[what]}
    doc = {"schema": 3, "seq": 1, "station": "a", "time": "x", "lives": [good, bad]}
    got, refused = SL.parse_snapshot(json.dumps(doc).encode(), "a")
    assert [t.test_id for t in got] == [A_LIVES[0].test_id] and len(refused) == 1


@pytest.mark.parametrize("raw,why", [
    (b'{"schema": 3, "station": "a", "lives": [{"t_life": NaN}]}', "NaN is not allowed"),
    (b'{"schema": 3, "station": "a", "lives": [], "x": "' + b"y" * (1 << 20) + b'"}', "bytes; at most"),
    (b'{"schema": 3, "station": "a", "lives": [{"grade": "' + b"I" * 200 + b'"}]}', "characters; at most"),
    (b"[" * 50 + b"]" * 50, "nested deeper"),
    (b'{"schema": 3, "station": "b", "lives": []}', "on the topic of"),
    (b'{"schema": 3, "station": "a"}', "not a lives message"),
    (b"\xff\xfe", "not UTF-8"),
    (b'{"schema": 3, "station": "a", "lives": [], "lives": []}', "given twice"),
])
def test_a_malformed_message_is_refused_whole(raw, why):
    with pytest.raises(Refused, match=why):
        SL.parse_snapshot(raw, "a")


def test_the_store_counts_refusals_in_one_line_keeps_bounds_and_persists(tmp_path, caplog, monkeypatch):
    path = str(tmp_path / SL.STORE_NAME)
    st = SL.SiteLives(path, "b")
    assert st.receive(TOPIC_A, payload("a", A_LIVES)) and len(st.tests()) == 5
    assert not st.receive(TOPIC_A, payload("a", A_LIVES, seq=9))      # the same again: no change
    assert not st.receive(SL.lives_topic("hookwatch/plant/hall/l1/b"), payload("b", A_LIVES))  # own
    # a flood of bad messages and records: counted, one line each kind per window
    with caplog.at_level(logging.WARNING, logger="hookwatch.site"):
        for _ in range(50):
            assert not st.receive("hookwatch/plant/h/l/c/lives", b'{"x": NaN}')
        bad = {**SL.record_of(A_LIVES[0]), "test_id": "X", "t_life": math.inf}
        doc = {"schema": 3, "seq": 2, "station": "d", "time": "t",
               "lives": [json.loads(json.dumps(SL.record_of(A_LIVES[1]))), bad]}
        raw = json.dumps(doc).replace("Infinity", "1e400").encode()
        for _ in range(20):
            st.receive("hookwatch/plant/h/l/d/lives", raw)
    st.refused.flush(force=True)
    assert st.counters["refused_messages"] == 50 and st.counters["refused_records"] == 20
    lines = [r.getMessage() for r in caplog.records]
    assert sum("station c refused" in m for m in lines) <= 2
    assert sum("of station d refused" in m for m in lines) <= 2
    # the same test shared twice (by a and d) counts once in a prior
    p = resolve_prior([], st.tests(), "I", 0.5)
    assert (p.n, p.n_censored) == (3, 2)
    # bounds: stations, lives in all
    monkeypatch.setattr(SL, "MAX_SITE_STATIONS", 2)
    assert not st.receive("hookwatch/plant/h/l/e/lives", payload("e", [life(0, station="e")]))
    monkeypatch.setattr(SL, "MAX_SITE_STATIONS", 256)
    monkeypatch.setattr(SL, "MAX_SITE_LIVES", 7)
    assert not st.receive("hookwatch/plant/h/l/f/lives", payload("f", [life(i, station="f") for i in range(3)]))
    monkeypatch.setattr(SL, "MAX_SITE_LIVES", 20000)
    # the local copy (saved by the intake's worker, coalesced): a gateway that restarts while the
    # broker is down has the site's lives
    assert st.save()
    again = SL.SiteLives(path, "b")
    assert again.load() == 6 and set(again.tests()) == set(st.tests())
    assert resolve_prior([], again.tests(), "I", 0.5) == p
    # a retired station's retained topic cleared
    assert st.receive(TOPIC_A, b"") and len(st.tests()) == 1
    assert st.save() and SL.SiteLives(path, "b").load() == 1
    # a damaged copy is not fatal: empty, one line
    (tmp_path / SL.STORE_NAME).write_text('{"stations": {"a": [{"t_life": ')
    with caplog.at_level(logging.WARNING, logger="hookwatch.site"):
        assert SL.SiteLives(path, "b").load() == 0
    assert any("cannot be read" in r.getMessage() for r in caplog.records)
    st.close()


def test_on_by_default_for_mqtt_stations_and_one_key_turns_it_off(tmp_path):
    from gateway.config import load_station
    from gateway.outputs.mqtt.output import MqttOutput
    from gateway.outputs.registry import mqtt_settings

    base = ("station: {id: s1, site: plant}\nmeter: {port: /dev/a-meter}\nstm32: {port: /dev/a-stm32}\n"
            f"recorder: {{dir: {tmp_path / 'rec'}}}\n")
    on = tmp_path / "on.yaml"
    on.write_text(base + "mqtt: {enabled: true}\n")
    off = tmp_path / "off.yaml"
    off.write_text(base + "mqtt: {enabled: true, share_lives: false}\n")
    s_on, s_off = mqtt_settings(load_station(str(on))), mqtt_settings(load_station(str(off)))
    assert s_on.share_lives and s_on.records_dir == str(tmp_path / "rec" / "s1")
    assert not s_off.share_lives
    out_on, out_off = MqttOutput(s_on), MqttOutput(s_off)
    try:
        # on: the pump subscribes to the site's lives and hands them to the store; off: neither
        assert out_on.site is not None and out_on.pump.inbound.on_lives is not None
        assert out_on.site.path == str(tmp_path / "rec" / "s1" / SL.STORE_NAME)
        assert out_off.site is None and out_off.pump.inbound.on_lives is None
    finally:
        out_on.pump.join(0)
        out_off.pump.join(0)
        out_on.site.close()


def test_the_intake_keeps_a_stations_newest_snapshot_counts_the_rest_and_saves_seldom(tmp_path, caplog):
    """Issue 34 item 1: 300 changing snapshots of one station, put as fast as a pump thread can:
    each is checked or dropped unread for a newer one (counted), the store ends with the newest,
    the file is written far fewer times, the log has one rate-limited line, and the station is
    given the lives (coalesced)."""
    import collections
    import threading

    from gateway.outputs.mqtt.site_intake import LivesIntake
    from kit.tools import wait_for

    path = tmp_path / "no" / "folder" / "yet" / SL.STORE_NAME     # made when needed
    site = SL.SiteLives(str(path), "b")
    counters: collections.Counter[str] = collections.Counter()
    given: list[int] = []
    lock = threading.Lock()

    def give(tests):
        with lock:
            given.append(len(tests))
    intake = LivesIntake(site, give, counters, save_interval_s=0.5, give_interval_s=0.2,
                         station_period_s=0.05, settle_s=0.0)
    intake.start()
    with caplog.at_level(logging.INFO, logger="hookwatch.site"):
        for i in range(300):
            intake.put(TOPIC_A, payload("a", A_LIVES[:4] + [life(100 + i, station="a")]))
        intake.put(SL.lives_topic("hookwatch/plant/hall/l1/b"), payload("b", A_LIVES))   # its own: ignored
        wait_for(lambda: counters["lives_checked"] + counters["lives_dropped"] == 300, 60,
                 what="every snapshot checked or dropped")
        wait_for(lambda: "T-a-399" in {t.test_id for t in site.tests()}, 60, what="the newest kept")
        wait_for(lambda: given and given[-1] == 5, 60, what="the station given the lives")
        intake.close()
    assert counters["lives_dropped"] > 0 and intake.box.replaced == counters["lives_dropped"]
    assert counters["lives_saves"] >= 1 and counters["lives_saves"] * 10 < 300
    again = SL.SiteLives(str(path), "b")
    assert again.load() == 5 and "T-a-399" in {t.test_id for t in again.tests()}
    assert len(given) < 300
    lines = [r.getMessage() for r in caplog.records if "the site's lives:" in r.getMessage()]
    assert 1 <= len(lines) <= 2, lines


def test_a_station_id_that_is_not_one_is_refused():
    """A topic level of 10,000 characters (or a control character) never reaches a prior's words,
    the state or a sidecar."""
    st = SL.SiteLives(None, "b")
    for bad in ("x" * 10_000, "a\tb"):
        assert not st.receive(f"hookwatch/plant/h/l/{bad}/lives", payload(bad, A_LIVES))
    assert st.counters["refused_messages"] == 2 and st.tests() == ()
    st.close()
