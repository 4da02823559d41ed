"""Metrics for Prometheus: the exposition served over HTTP, parsed with prometheus_client's parser."""
import asyncio
import json
import math
import os
import shutil
import socket
import time
import urllib.error
import urllib.request
from types import SimpleNamespace

import pytest
import yaml
from prometheus_client.parser import text_string_to_metric_families

from conftest import ROOT
from gateway.config import ConfigError, load_station
from gateway.core.records import Event, EventType, SlotRecord, StationState
from gateway.core.records import TestState as TS
from gateway.outputs import prometheus as M
from gateway.outputs.broker.outbox import Outbox, Row
from gateway.plumbing.doors import DoorLimits
from kit.tools import free_port, wait_for


def rec(k, *, present=True, lateness=0.0003, rtt=0.006, q=1, mu=0.2):
    return SlotRecord(k=k, t=k * 0.02, present=present, t1=1.0 if present else math.nan,
                      t2=1.2 if present else math.nan, q=q if present else 0, mask=0,
                      ratio=1.2 if present else None, mu=mu if (present and q) else None,
                      mean_filt=1.1, speed_cmd=100.0, speed_act=99.0, saturated=False,
                      lateness_s=lateness, rtt_s=rtt if present else math.nan)


def fake_station(name):
    return SimpleNamespace(
        id=name, ts=0.02,
        meter=SimpleNamespace(connected=True, counters={"reads": 10, "reads_ok": 8, "timeouts": 2,
                                                        "crc_errors": 1}),
        stm32=SimpleNamespace(connected=False, counters={"sent": 5, "acked": 4, "naks": 1}))


@pytest.fixture
def endpoints():
    yield
    M.shutdown_all()


def scrape(ep) -> dict:
    """{(sample name, sorted labels): value} of one scrape of ``ep``."""
    assert ep.listening.wait(5), ep.error
    host, port = ep.address
    with urllib.request.urlopen(f"http://{host}:{port}/metrics", timeout=5) as r:
        assert r.headers["Content-Type"].startswith("text/plain; version=0.0.4")
        text = r.read().decode()
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out[(s.name, tuple(sorted(s.labels.items())))] = s.value
    return out


def run(coro):
    return asyncio.run(coro)


def test_slot_figures_histograms_links_and_state(endpoints):
    name = f"st-{free_port()}"
    st = fake_station(name)
    out = M.MetricsOutput(st, "127.0.0.1", 0)

    async def feed():
        await out.start()
        for k in range(10):                      # filled, 0.3 ms late, RTT 6 ms
            out.on_record(rec(k))
        out.on_record(rec(10, lateness=0.0025, rtt=0.016, q=0))   # filled, not valid
        out.on_record(rec(11, present=False, lateness=0.001))      # meter silent
        out.on_record(rec(12, present=True, rtt=math.nan))         # no RTT known
        for k in (13, 14, 15):                    # an overrun of 30 ms: three slots lost
            out.on_record(rec(k, present=False, lateness=0.030))
        out.on_event(Event(EventType.PORT_LOST, name, time.time(), data={"port": "meter"}))
        out.on_event(Event(EventType.PORT_LOST, name, time.time(), data={"port": "stm32"}))
        out.on_state(StationState(name, state=TS.MONITORING, mu_ss=0.2, mu_th=0.25))

    run(feed())
    m = scrape(out.endpoint)
    lab = (("station", name),)
    assert m[("hookwatch_slots_total", lab)] == 16
    assert m[("hookwatch_slots_filled_total", lab)] == 12
    assert m[("hookwatch_slot_overruns_total", lab)] == 3
    # lateness: 13 polled slots (overruns are counted apart), cumulative buckets
    h = "hookwatch_slot_lateness_seconds"
    assert m[(h + "_count", lab)] == 13
    assert m[(h + "_bucket", (("le", "0.0005"), *lab))] == 11
    assert m[(h + "_bucket", (("le", "0.001"), *lab))] == 12     # le is inclusive
    assert m[(h + "_bucket", (("le", "0.003"), *lab))] == 13
    assert m[(h + "_bucket", (("le", "+Inf"), *lab))] == 13
    assert m[(h + "_sum", lab)] == pytest.approx(11 * 0.0003 + 0.0025 + 0.001)
    r = "hookwatch_meter_rtt_seconds"
    assert m[(r + "_count", lab)] == 11
    assert m[(r + "_bucket", (("le", "0.0075"), *lab))] == 10
    assert m[(r + "_bucket", (("le", "0.015"), *lab))] == 10
    assert m[(r + "_bucket", (("le", "0.0175"), *lab))] == 11
    assert m[(r + "_sum", lab)] == pytest.approx(10 * 0.006 + 0.016)
    # the drivers' counters: failures and traffic apart, per link
    assert m[("hookwatch_link_errors_total", (("kind", "timeouts"), ("link", "meter"), *lab))] == 2
    assert m[("hookwatch_link_errors_total", (("kind", "crc_errors"), ("link", "meter"), *lab))] == 1
    assert m[("hookwatch_link_errors_total", (("kind", "naks"), ("link", "stm32"), *lab))] == 1
    assert m[("hookwatch_link_operations_total", (("kind", "reads"), ("link", "meter"), *lab))] == 10
    assert ("hookwatch_link_errors_total", (("kind", "reads"), ("link", "meter"), *lab)) not in m
    assert m[("hookwatch_link_up", (("link", "meter"), *lab))] == 1
    assert m[("hookwatch_link_up", (("link", "stm32"), *lab))] == 0
    # state, μ, events
    assert m[("hookwatch_station_state", (("state", "monitoring"), *lab))] == 1
    assert m[("hookwatch_station_state", (("state", "idle"), *lab))] == 0
    assert m[("hookwatch_test_running", lab)] == 1
    assert m[("hookwatch_alarm", (("alarm", "normal"), *lab))] == 1   # ISA-18.2 state names
    assert m[("hookwatch_mu", lab)] == pytest.approx(0.2)
    assert m[("hookwatch_mu_ss", lab)] == pytest.approx(0.2)
    assert m[("hookwatch_mu_threshold", lab)] == pytest.approx(0.25)
    assert ("hookwatch_wear_headroom", lab) not in m          # not in the state: no series
    assert m[("hookwatch_events_total", (*lab, ("type", "port_lost")))] == 2
    assert m[("hookwatch_build_info", (("version", M.__version__),))] == 1
    # no MQTT, no PLC on this station: no outbox series for it
    assert ("hookwatch_outbox_messages", lab) not in m
    # the gateway process itself (CPU, memory) comes along
    assert any(k[0] == "process_cpu_seconds_total" for k in m)
    # the test ends: μ of the last test is no longer shown
    run_state = StationState(name, state=TS.COMPLETED)
    out.on_state(run_state)
    m = scrape(out.endpoint)
    assert ("hookwatch_mu", lab) not in m
    assert m[("hookwatch_test_running", lab)] == 0
    ep = out.endpoint
    run(out.stop())
    m = scrape(ep)
    assert ("hookwatch_slots_total", lab) not in m


def test_snapshot_is_plain_data_and_renders_the_same_after_json(endpoints):
    """A supervisor can receive a worker's snapshot as JSON and serve it unchanged."""
    name = f"st-{free_port()}"
    out = M.MetricsOutput(fake_station(name), "127.0.0.1", 0)
    for k in range(5):
        out.on_record(rec(k))
    snap = out.snapshot()
    wire = json.loads(json.dumps(snap))
    assert wire["v"] == M.SNAPSHOT_VERSION and wire["station"] == name and wire["slots"] == 5
    assert len(wire["lateness_s"]["counts"]) == len(wire["lateness_s"]["le"]) + 1

    def samples(s):
        return [(x.name, x.labels, x.value) for f in M.families([s]) for x in f.samples]

    assert samples(wire) == samples(snap)


def test_figures_survive_a_station_rebuild(endpoints):
    """A reload rebuilds the station and its outputs: the counters keep counting (no reset)."""
    name = f"st-{free_port()}"
    a = M.MetricsOutput(fake_station(name), "127.0.0.1", 0)
    for k in range(7):
        a.on_record(rec(k))
    b = M.MetricsOutput(fake_station(name), "127.0.0.1", 0)
    b.on_record(rec(7))
    assert b.snapshot()["slots"] == 8


def test_stations_share_one_endpoint_per_address(endpoints):
    port = free_port()
    outs = [M.MetricsOutput(fake_station(f"loom-{i}-{port}"), "127.0.0.1", port) for i in range(3)]

    async def go():
        for o in outs:
            await o.start()
    run(go())
    assert len({id(o.endpoint) for o in outs}) == 1
    m = scrape(outs[0].endpoint)
    stations = {dict(k[1]).get("station") for k in m if k[0] == "hookwatch_slots_total"}
    assert stations == {o.station_id for o in outs}


def test_outbox_depth_and_age_from_the_real_outbox(tmp_path, endpoints):
    ob = Outbox(str(tmp_path / "outbox.sqlite"))
    t0 = time.time()
    ob.add([Row(ob.next_seq(), "event", "t/e", b"{}", created=t0 - 30.0),
            Row(ob.next_seq(), "telemetry", "t/t", b"{}", created=t0 - 5.0)])
    mqtt = SimpleNamespace(connected=False, counters={"sent": 2, "disconnects": 1}, outbox=ob)
    name = f"st-{free_port()}"
    out = M.MetricsOutput(fake_station(name), "127.0.0.1", 0, mqtt=mqtt)
    run(out.start())
    m = scrape(out.endpoint)
    lab = (("station", name),)
    assert m[("hookwatch_outbox_messages", lab)] == 2
    # the oldest row's age: 30 s when it was added, plus however long this machine took since
    # (a bound from the clock itself, not a guess at how fast the scrape comes)
    assert 30.0 - 1e-3 <= m[("hookwatch_outbox_oldest_age_seconds", lab)] <= time.time() - t0 + 30.0 + 1e-3
    assert m[("hookwatch_link_up", (("link", "mqtt"), *lab))] == 0
    assert m[("hookwatch_link_errors_total", (("kind", "disconnects"), ("link", "mqtt"), *lab))] == 1
    ob.confirm([1, 2])
    m = scrape(out.endpoint)
    assert m[("hookwatch_outbox_messages", lab)] == 0
    assert m[("hookwatch_outbox_oldest_age_seconds", lab)] == 0
    run(out.stop())
    ob.close()


def test_console_clients_gauge(endpoints):
    out = M.MetricsOutput(fake_station(f"st-{free_port()}"), "127.0.0.1", 0)
    run(out.start())
    assert not any(k[0] == "hookwatch_console_clients" for k in scrape(out.endpoint))
    M.set_console_clients(3)
    try:
        assert scrape(out.endpoint)[("hookwatch_console_clients", ())] == 3
    finally:
        M.set_console_clients(None)


def _get(ep, path, method="GET", data=None):
    host, port = ep.address
    req = urllib.request.Request(f"http://{host}:{port}{path}", method=method, data=data)
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return r.status
    except urllib.error.HTTPError as e:
        return e.code


def test_endpoint_is_bounded(endpoints):
    out = M.MetricsOutput(fake_station(f"st-{free_port()}"), "127.0.0.1", 0)
    run(out.start())
    ep = out.endpoint
    assert ep.listening.wait(5)
    assert _get(ep, "/nope") == 404
    assert _get(ep, "/metrics", "POST", b"x" * 100) in (405, 413)
    host, port = ep.address
    # an over-long request line is refused, not read to its end
    with socket.create_connection((host, port), timeout=5) as s:
        s.sendall(b"GET /" + b"a" * (M.MAX_LINE + 100) + b" HTTP/1.0\r\n\r\n")
        assert s.recv(200)[:12] in (b"HTTP/1.0 400", b"HTTP/1.0 414", b"HTTP/1.1 400", b"HTTP/1.1 414")
    # idle connections hold at most MAX_CONNECTIONS; one more is closed at once (not held until a
    # slot frees). First the connections of the requests above must have ended (on a loaded
    # machine one may still be closing: a slot would then be taken and the count off by one)
    door = ep.door
    assert door is not None
    wait_for(lambda: door.connections == 0, 20, what="the earlier connections ended")
    # (one per client address: no address holds more than another, so the door makes no room by
    # closing one of the address holding the most — tests/gateway/plumbing/test_doors_fair.py)
    idle = [socket.create_connection((host, port), timeout=5, source_address=(f"127.0.4.{1 + i}", 0))
            for i in range(M.MAX_CONNECTIONS)]
    try:
        wait_for(lambda: door.connections == M.MAX_CONNECTIONS, 20, what="every idle connection held")
        with socket.create_connection((host, port), timeout=5, source_address=("127.0.4.100", 0)) as s:
            try:
                s.sendall(b"GET /metrics HTTP/1.0\r\n\r\n")
                data = s.recv(100)
            except (ConnectionResetError, BrokenPipeError):
                data = b""        # closed (reset), before or after the request went out
            except TimeoutError:
                data = None       # held, not closed: the client's timeout
            assert data == b"", (door.cap, door.connections)
    finally:
        for s in idle:
            s.close()

    def answers() -> bool:
        try:
            return _get(ep, "/metrics") == 200
        except OSError:           # a connection still being reset as the idle ones go
            return False

    wait_for(answers, 20, what="the endpoint answering again")


def test_port_in_use_is_a_state_then_recovers(monkeypatch, endpoints):
    monkeypatch.setattr(M.http, "RETRY_S", 0.2)
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    port = blocker.getsockname()[1]
    out = M.MetricsOutput(fake_station(f"st-{port}"), "127.0.0.1", port)
    run(out.start())          # does not raise, does not wait
    ep = out.endpoint
    t_end = time.monotonic() + 5
    while ep.error is None and time.monotonic() < t_end:
        time.sleep(0.05)
    assert ep.error and "cannot listen" in ep.error and not ep.listening.is_set()
    blocker.close()
    assert ep.listening.wait(5)
    assert scrape(ep)[("hookwatch_slots_total", (("station", f"st-{port}"),))] == 0


def _station_file(tmp_path, metrics):
    cfg = {"station": {"id": "m1"}, "meter": {"port": "/dev/null", "map": "zn-s.yaml"},
           "stm32": {"port": "/dev/zero"}, "recorder": {"dir": str(tmp_path)}, "metrics": metrics}
    p = tmp_path / "m1.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def test_config_section(tmp_path):
    shutil.copy(os.path.join(ROOT, "config", "meters", "zn-s.yaml"), tmp_path / "zn-s.yaml")
    cfg = load_station(str(_station_file(tmp_path, {"enabled": True})))
    assert (cfg.metrics.enabled, cfg.metrics.host, cfg.metrics.port) == (True, "127.0.0.1", 9620)
    with pytest.raises(ConfigError, match="metrics.port"):
        load_station(str(_station_file(tmp_path, {"enabled": True, "port": 70000})))


def _exposed_names() -> set[str]:
    snap = M.MetricsOutput(fake_station("docs"), "127.0.0.1", 0).snapshot()
    snap.update(outbox={"messages": 1, "oldest_age_s": 2.0, "dropped_telemetry": 0},
                plc={"listen": "127.0.0.1:5020", "listening": True, "counters": {"reads": 1}},
                headroom=0.5, t_cross=5400.0, warning=True, mu=0.2, mu_ss=0.2, mu_th=0.25, events={"port_lost": 1})
    snap["links"]["mqtt"] = {"up": True, "counters": {"sent": 1, "disconnects": 1}}
    return {f.name + ("_total" if f.type == "counter" else "")
            for f in M.families([snap], console_clients=1, sparkplug=[
                {"group": "g", "node": "n", "connected": True,
                 "counters": {"bad_state": 1, "births": 1}}],
                config={"box": "b1", "site": "s", "version": "abc", "sha256": "d", "drift": True,
                        "deferred": 1})}


def test_docs_and_shipped_rules_name_exactly_the_exposed_metrics():
    import re

    exposed = _exposed_names()
    with open(os.path.join(ROOT, "docs", "metrics.md"), encoding="utf-8") as f:
        doc = f.read()
    documented = set(re.findall(r"^\| `(hookwatch_[a-z0-9_]+)`", doc, re.M))
    assert documented == exposed
    with open(os.path.join(ROOT, "deploy", "prometheus", "hookwatch-rules.yml"), encoding="utf-8") as f:
        rules = f.read()
    used = {re.sub(r"_(bucket|sum|count)$", "", n)
            for n in re.findall(r"\b(hookwatch_[a-z0-9_]+)", rules + doc)}
    assert used <= exposed, used - exposed


def test_wear_figures_follow_the_state_when_it_carries_them(endpoints):
    """METHOD.md §5a: headroom, projection and warning are shown once the station state has them."""
    name = f"st-{free_port()}"
    out = M.MetricsOutput(fake_station(name), "127.0.0.1", 0)
    run(out.start())
    st = StationState(name, state=TS.MONITORING, mu_ss=0.2, mu_th=0.25)
    st.headroom, st.t_cross, st.wear_warning = 0.4, 5400.0, True
    st.end_p10, st.end_p50, st.end_p90, st.p_end, st.due, st.lead_s = 900.0, 1500.0, 2400.0, 0.3, True, 600.0
    st.elapsed_s = 500.0
    out.on_state(st)
    m = scrape(out.endpoint)
    lab = (("station", name),)
    assert m[("hookwatch_wear_headroom", lab)] == pytest.approx(0.4)
    assert m[("hookwatch_wear_projected_end_seconds", lab)] == 5400.0
    assert m[("hookwatch_wear_warning", lab)] == 1
    # METHOD.md §5b: the remaining time to each end quantile, P, the lead and the due gauge
    assert m[("hookwatch_end_p10_seconds", lab)] == 400.0
    assert m[("hookwatch_end_p50_seconds", lab)] == 1000.0
    assert m[("hookwatch_end_p90_seconds", lab)] == 1900.0
    assert m[("hookwatch_end_within_lead_probability", lab)] == pytest.approx(0.3)
    assert m[("hookwatch_lead_seconds", lab)] == 600.0
    assert m[("hookwatch_hook_due", lab)] == 1


def test_hostile_requests_get_an_answer_or_a_close_and_scrapes_go_on(monkeypatch, endpoints):
    out = M.MetricsOutput(fake_station(f"st-{free_port()}"), "127.0.0.1", 0,
                          limits=DoorLimits(8, request_timeout_s=0.5, idle_timeout_s=5.0))
    run(out.start())
    ep = out.endpoint
    assert ep.listening.wait(5)
    host, port = ep.address
    hostile = [
        bytes(range(256)) * 4,                                          # binary garbage
        b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n",                            # an HTTP/2 preface
        b"GET /metrics HTTP/1.1\r\n" + b"X-A: b\r\n" * 200 + b"\r\n",    # a header flood
        b"GET /metrics HTTP/1.0\r\nContent-Length: 99999999\r\n\r\n",    # a body announced
        b"GET /metrics HTTP/1.0\r\nX-Long: " + b"z" * 100_000 + b"\r\n\r\n",
    ]
    for data in hostile:
        with socket.create_connection((host, port), timeout=5) as s:
            try:
                s.sendall(data)
                reply = s.recv(100)
            except (ConnectionResetError, BrokenPipeError):
                reply = b""
            assert reply == b"" or reply[:10] in (b"HTTP/1.0 4", b"HTTP/1.0 5") and reply[9:12] != b"500", \
                (data[:40], reply)
    # a client that sends half a request and waits is dropped after the request timeout
    # (a client kept for ever would end in the client's own timeout, socket.timeout: a failure)
    with socket.create_connection((host, port), timeout=10) as s:
        s.sendall(b"GET /met")
        try:
            assert s.recv(100) == b""
        except ConnectionResetError:
            pass
    assert _get(ep, "/metrics") == 200


def test_trickling_sockets_cannot_hold_the_endpoint(endpoints):
    """Issue 21: more trickling clients than the endpoint has slots (each sends a byte of a
    request every 0.3 s, so no single recv ever waits long) are closed at the request deadline;
    scrapes are answered again while they still trickle."""
    lim = DoorLimits(4, request_timeout_s=1.0, idle_timeout_s=5.0)
    out = M.MetricsOutput(fake_station(f"st-{free_port()}"), "127.0.0.1", 0, limits=lim)
    run(out.start())
    ep = out.endpoint
    assert ep.listening.wait(5)
    host, port = ep.address
    req = b"GET /metrics HTTP/1.1\r\nHost: x\r\n" + b"X-Slow: y\r\n" * 50 + b"\r\n"
    socks = [socket.create_connection((host, port), timeout=5) for _ in range(8)]
    closed = [False] * len(socks)
    try:
        t0 = time.monotonic()
        answered = False
        for i in range(len(req)):
            for k, s in enumerate(socks):
                if closed[k]:
                    continue
                try:
                    s.sendall(req[i:i + 1])
                except OSError:
                    closed[k] = True
            if not answered and time.monotonic() - t0 > 2.5:
                answered = _get(ep, "/metrics") == 200
            if (answered and all(closed)) or time.monotonic() - t0 > 30:
                break
            time.sleep(0.3)
        assert answered, "the endpoint did not answer while the tricklers trickled"
        for k, s in enumerate(socks):        # every trickler was closed by the server
            if not closed[k]:
                s.settimeout(0.5)
                try:
                    closed[k] = s.recv(100) == b""
                except ConnectionResetError:
                    closed[k] = True
                except TimeoutError:
                    pass
        assert all(closed), closed
        assert ep.door.counters["request_timeouts"] + ep.refused >= len(socks)
    finally:
        for s in socks:
            s.close()
