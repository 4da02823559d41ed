"""Issue 20 end to end (METHOD.md §5b, §7a): `hookwatch sim` + `hookwatch run` of a station with a
configured life prior (`forecast.priors`) and a lead, on the kit's compressed life. While the hook
is due, every door carries the forecast as found at its last window — the MES (mosquitto_sub:
state, telemetry, the wear_warning event and alarm), the PLC (mbpoll: remaining seconds to
e10/e50/e90, P, the due bit, the reasons as bits, the lead), a Sparkplug primary host with its
own decoder (DBIRTH and DDATA) and Debian's Prometheus (the gauges, and the shipped alert
`HookwatchHookDue` firing). Afterwards `hookwatch analyze` of the recorded log gives every §5b
key exactly as the gateway found it online (the prior came through the sidecar)."""
import math
import os

import yaml

from gateway.outputs.mqtt import schema as S
from gateway.outputs.plc import registers as R
from gateway.outputs.sparkplug import metrics as SM
from kit.broker import Broker, Sub
from kit.e2e import (
    QUICK_END,
    QUICK_METHOD,
    QUICK_PRIOR,
    analyze_cli,
    quick_scenario,
    read_json,
    run_gateway,
    station_yaml,
    test_dirs,
    virtual_station,
)
from kit.northbound import mbpoll
from kit.prometheus import prometheus, query, wait_for  # noqa: F401  (fixture)
from kit.sparkplug_host import PrimaryHost, metric_value
from kit.tools import free_port, require_tool

TUNED = {"dead_band_n": 0.01}
#: a lead of 10 s on the ~23 s life: the hook is due from ≈ 12 s until the end of life is detected
LEAD = 10.0
METHOD = {**QUICK_METHOD, "lead": LEAD}
IR = R.IR
#: the §5b keys of a result (METHOD.md §5b, §6)
KEYS_5B = ("warn_slot", "warn_reasons", "end_p10", "end_p50", "end_p90", "p_end", "headroom", "t_cross")


def plc_forecast(port: int, unit: int) -> dict:
    """The PLC's view: status word and the forecast registers (end_p*_left … lead), decoded."""
    first, last = IR["end_p10_left"], IR["lead"]
    n = last.address + last.count - first.address
    rc, v, err = mbpoll(port, "-t", "3", "-r", str(first.address), "-c", str(n), unit=unit)
    assert rc == 0, err
    rc, s, err = mbpoll(port, "-t", "3", "-r", str(IR["status"].address), unit=unit)
    assert rc == 0, err
    out = {"status": s[IR["status"].address]}
    for name in ("end_p10_left", "end_p50_left", "end_p90_left", "p_end", "warn_reasons", "lead"):
        r = IR[name]
        out[name] = R.decode_value(r, [v[a] for a in range(r.address, r.address + r.count)])
    return out


def test_the_forecast_reaches_every_door_and_online_equals_offline(tmp_path, prometheus):  # noqa: F811
    require_tool("mbpoll")
    mport, pport = free_port(), free_port()
    with Broker(tmp_path) as b:
        sub = Sub(b.port, "hookwatch/#")
        host = PrimaryHost(b.port, "unused", "lab", tmp_path)
        gw = None
        try:
            with virtual_station(tmp_path, quick_scenario(tmp_path, "quick.yaml")) as (_sim, links):
                st = station_yaml(
                    tmp_path, links, name="fc", control=TUNED, method=METHOD,
                    test={"t_end_s": QUICK_END}, mqtt={"enabled": True, "port": b.port},
                    modbus_tcp={"enabled": True, "port": mport, "unit_id": 3},
                    extra={"forecast": {"priors": [QUICK_PRIOR]},
                           "sparkplug": {"enabled": True, "port": b.port, "group_id": "lab",
                                         "edge_node_id": "hall-l1", "data_interval_s": 0.5},
                           "metrics": {"enabled": True, "port": pport}})
                api = prometheus(f"127.0.0.1:{pport}")
                gw = run_gateway(tmp_path, st, "--start", "--exit-when-done")
                # the early warning: the first due window, at most once per test
                # (or the gateway's end: then what happened is in its log, not in a 180 s wait)
                sub.wait(lambda s: s.messages("event/wear_warning") or gw.p.poll() is not None, 180,
                         what="the wear warning")
                ww = sub.messages("event/wear_warning")
                assert ww, ("no wear warning before the gateway ended: "
                            + " ".join(m[1] for m in sub.messages() if "/event/" in m[1]) + "\n" + gw.log())
                # while the hook is due: the PLC …
                plc = plc_forecast(mport, 3)
                # … and Prometheus: the gauge, and the shipped alert firing on it
                due = wait_for(lambda: query(api, 'hookwatch_hook_due{station="fc"} == 1'), 15,
                               "hookwatch_hook_due 1")
                firing = wait_for(lambda: query(api, 'ALERTS{alertname="HookwatchHookDue",'
                                                     'alertstate="firing"}'), 15, "the alert firing")
                p50 = query(api, 'hookwatch_end_p50_seconds{station="fc"}')
                lead = query(api, 'hookwatch_lead_seconds{station="fc"}')
                sub.wait(lambda s: s.messages("event/end_of_life"), 120, what="the end of life")
                res = sub.wait(lambda s: s.messages("result"), 120, what="the result")[0][2]
                assert gw.p.wait(60) == 0, gw.log()
        finally:
            if gw is not None:
                gw.stop()
            sub.stop()
            host.close()
    d = test_dirs(tmp_path, "fc")[0]
    online = read_json(os.path.join(d, "result.json"))["method"]

    # §7a: the configured prior, in the sidecar's method section (and its source beside it)
    with open(os.path.join(d, "log.meta.yaml")) as f:
        meta = yaml.safe_load(f)
    assert meta["method"]["prior_mean"] == QUICK_PRIOR["mean_s"]
    assert meta["method"]["prior_sd"] == QUICK_PRIOR["sd_s"]
    assert meta["method"]["lead"] == LEAD and meta["method"]["p_due"] == 0.1
    assert meta["prior_source"] == "config" and meta["prior_n"] == QUICK_PRIOR["n"]

    # online == offline for every key, the §5b ones included
    offline = analyze_cli(os.path.join(d, "log.csv.gz"))
    assert online == offline
    assert online["status"] == "failure" and online["warn_slot"] is not None
    assert "prior" in online["warn_reasons"]
    for k in KEYS_5B:
        assert k in online, k
    assert res["result"]["warn_slot"] == online["warn_slot"]
    assert (online["warn_slot"] + 1) * 0.02 < online["t_life"]         # the warning came first

    # the MES: one wear_warning with its reasons and the forecast; its alarm carries them too
    assert len(ww) == 1, [m[1] for m in sub.messages()]
    data = ww[0][2]["data"]
    assert {k for k, _ in S.EVENT_DATA[S.EventType.WEAR_WARNING]} - {"transitions"} <= set(data)
    assert data["warn_slot"] == online["warn_slot"] and data["reasons"] == online["warn_reasons"]
    assert data["lead_s"] == LEAD and data["p_end"] >= 0.1
    assert data["end_p10"] <= data["end_p50"] <= data["end_p90"]
    wa = [m[2] for m in sub.messages("alarm/warning") if m[2]["state"] == "unacknowledged"]
    assert wa and wa[0]["reasons"] == data["reasons"] and wa[0]["end_p50"] == data["end_p50"]
    states = [m[2] for m in sub.messages("state")]
    due_states = [s for s in states if s["due"]]
    assert due_states, states[-3:]
    for s in due_states:
        assert list(s) == S.field_names("state")
        assert s["prior_source"] == "config" and s["prior_mean"] == QUICK_PRIOR["mean_s"]
        assert s["lead_s"] == LEAD and s["p_due"] == 0.1 and s["test_started_utc"]
        assert s["end_p10"] <= s["end_p50"] <= s["end_p90"] and 0 <= s["p_end"] <= 1
    assert any(s["warn_reasons"] == online["warn_reasons"] for s in due_states)
    # no projection once the end of life was detected, nor after the test
    for s in states:
        if s["test_state"] in ("end_of_life", "completed", "aborted"):
            assert s["end_p50"] is None and s["p_end"] is None and not s["due"], s
            assert s["t_cross"] is None, s
    assert states[-1]["prior_source"] is None and states[-1]["warn_reasons"] == []
    tel = [m[2] for m in sub.messages("telemetry") if m[2]["end_p50"] is not None]
    assert tel and all(list(t) == S.field_names("telemetry") for t in tel)
    # the last forecast time's quantiles in the state are the result's
    last_fc = [s for s in states if s["end_p50"] is not None][-1]
    assert last_fc["end_p50"] == online["end_p50"] and last_fc["p_end"] == online["p_end"]

    # the PLC, while due: the due bit, the remaining seconds, P, the reasons as bits, the lead
    assert plc["status"] & (1 << R.STATUS_BIT["hook_due"]), plc
    assert plc["warn_reasons"] & (1 << R.WARN_REASON_BIT["prior"]), plc
    assert plc["lead"] == LEAD
    assert 0 <= plc["end_p10_left"] <= plc["end_p50_left"] <= plc["end_p90_left"], plc
    assert plc["end_p50_left"] < QUICK_PRIOR["mean_s"] and 0.1 <= plc["p_end"] <= 1.0, plc

    # Prometheus, while due
    assert float(due[0]["value"][1]) == 1.0 and firing[0]["metric"]["station"] == "fc"
    assert p50 and 0 <= float(p50[0]["value"][1]) < QUICK_PRIOR["mean_s"]
    assert float(lead[0]["value"][1]) == LEAD

    # Sparkplug: the forecast metrics in the DBIRTH, then DDATA on change (by alias)
    birth = [m for m in host.all("DBIRTH") if m.device == "fc"][-1]
    names = {m.name: m for m in birth.p.metrics}
    for n in (SM.FC_P10, SM.FC_P50, SM.FC_P90, SM.FC_P_END, SM.FC_DUE, SM.FC_HEADROOM,
              SM.FC_T_CROSS, SM.FC_WARNING, SM.FC_REASONS, SM.FC_PRIOR_SOURCE, SM.FC_LEAD):
        assert n in names, f"{n} missing from the DBIRTH"
    by_alias = {m.alias: m.name for m in birth.p.metrics}
    seen: dict[str, list] = {}
    for msg in host.all("DDATA"):
        if msg.device != "fc":
            continue
        for x in msg.p.metrics:
            seen.setdefault(by_alias.get(x.alias, "?"), []).append(metric_value(x))
    assert True in seen.get(SM.FC_DUE, []), sorted(seen)
    assert ",".join(online["warn_reasons"]) in seen.get(SM.FC_REASONS, [])
    assert "config" in seen.get(SM.FC_PRIOR_SOURCE, []) + [metric_value(names[SM.FC_PRIOR_SOURCE])]
    p50s = [v for v in seen.get(SM.FC_P50, []) if v is not None]
    assert p50s and online["end_p50"] in p50s and all(math.isfinite(v) for v in p50s)
