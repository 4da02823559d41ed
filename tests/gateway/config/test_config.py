"""The configuration model: one schema → validation, defaults, docs; positions in errors; the
fleet merge rule; paths relative to the file that sets them; compatibility with the runtime;
sdnotify over a real unix datagram socket."""
import dataclasses
import os
import socket
import subprocess
import textwrap

import pytest

from conftest import ROOT, hookwatch_cmd
from gateway.config import ConfigError, load_fleet, load_station, validate_station
from gateway.config import sections as S
from gateway.core.control import ControlParams, NotchParams
from gateway.core.method.params import PARAMS, MethodParams, build_params

MINIMAL = "station: {id: s1}\nmeter: {port: /dev/a-meter}\nstm32: {port: /dev/a-stm32}\n"


def write(path, text):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(textwrap.dedent(text))
    return str(path)


# ---------------------------------------------------------------------------------- the schema

def test_contract_key_paths():
    """The key paths other parts code against (helper context, 'Station configuration')."""
    paths = {".".join(p) for p, _ in S.walk()}
    expected = """station.id station.site station.area station.line
        meter.port meter.map meter.baud meter.unit_id meter.parity meter.timeout_s meter.swap_channels
        stm32.port stm32.baud stm32.timeout_s stm32.retries stm32.watchdog_s method control control.notch
        test.sample_id test.grade test.t_set_n test.t_end_s test.autostart grades
        recorder.dir recorder.flush_interval_s
        mqtt.enabled mqtt.host mqtt.port mqtt.prefix mqtt.client_id mqtt.keepalive_s mqtt.username
        mqtt.password_env mqtt.password_file mqtt.tls.enabled mqtt.tls.ca_file mqtt.tls.cert_file
        mqtt.tls.key_file mqtt.telemetry_interval_s mqtt.outbox.path mqtt.outbox.telemetry_budget_mb
        modbus_tcp.enabled modbus_tcp.host modbus_tcp.port modbus_tcp.unit_id modbus_tcp.word_order
        modbus_tcp.writes.enabled modbus_tcp.writes.allowed_clients logging.level""".split()
    assert set(expected) <= paths, set(expected) - paths


def test_control_keys_come_from_the_control_dataclasses():
    ctrl = {p[1]: e for p, e in S.walk() if p[0] == "control" and len(p) == 2}
    notch = {p[2]: e for p, e in S.walk() if p[:2] == ("control", "notch") and len(p) == 3}
    assert set(ctrl) == {f.name for f in dataclasses.fields(ControlParams)} - {"ts"}
    assert set(notch) == {f.name for f in dataclasses.fields(NotchParams)}
    for f in dataclasses.fields(ControlParams):
        if f.name not in ("ts", "notch"):
            assert ctrl[f.name].default == f.default
            assert ctrl[f.name].doc != "(undocumented)", f"document control.{f.name} in CONTROL_KEYS"
    for f in dataclasses.fields(NotchParams):
        assert notch[f.name].default == f.default
        assert notch[f.name].doc != "(undocumented)", f"document control.notch.{f.name}"


def test_method_keys_come_from_the_method_params():
    assert set(S.METHOD_KEYS) == {p.name for p in PARAMS} - {"t_set", "t_end", "end_slot"}


def test_method_params_come_from_the_method_dataclass():
    """As the control keys above (issue 35 item 5): a row of PARAMS per MethodParams field and no
    other, each default the field's (written once, in the dataclass), the required parameter the
    one without a default, the parse kind and "may be none" those of the field's type."""
    fld = {f.name: f for f in dataclasses.fields(MethodParams)}
    assert set(fld) == {p.name for p in PARAMS} and len(PARAMS) == len(fld)
    for p in PARAMS:
        f = fld[p.name]
        has_default = f.default is not dataclasses.MISSING
        assert p.required == (not has_default) and p.default == (f.default if has_default else None), p.name
        kind, *rest = str(f.type).split(" | ")
        assert (p.kind, p.optional) == (kind, rest == ["None"]), f"{p.name}: {f.type}"
        assert p.default is None or type(p.default).__name__ == p.kind, p.name
        assert p.doc and p.unit, p.name
    assert [p.name for p in PARAMS if p.required] == ["t_set"]
    assert build_params({"t_set": 0.5}) == MethodParams(t_set=0.5)
    assert MethodParams(t_set=0.5).as_dict() == {**{p.name: p.default for p in PARAMS}, "t_set": 0.5}


def test_every_key_is_documented():
    for p, e in S.walk():
        assert e.doc, ".".join(p)
        if isinstance(e, S.Key) and e.default is None and e.nullable:
            assert e.null_means, f"{'.'.join(p)}: say what null means"


def test_generated_doc_is_current():
    from gateway.config import docs

    with open(os.path.join(ROOT, "docs", "configuration.md"), encoding="utf-8") as f:
        assert f.read() == docs.render(), "regenerate: python -m gateway.config.docs > docs/configuration.md"


# ---------------------------------------------------------------------------------- loading

def test_minimal_station_gets_every_default(tmp_path):
    cfg = load_station(write(tmp_path / "s.yaml", MINIMAL))
    assert cfg.station.id == "s1" and cfg.station.site == ""
    assert cfg.meter.baud is None and cfg.meter.timeout_s == 0.015
    assert os.path.isfile(cfg.meter.map) and cfg.meter.map.endswith("zn-s.yaml")
    assert cfg.stm32.baud == 115200 and cfg.stm32.watchdog_s is None
    # null: the protection stop (stop_after 1 s) + 0.5 s (docs/protocols/stm32.md, safety argument)
    assert cfg.stm32_watchdog_s() == 1.5
    assert cfg.method == {p.name: p.default for p in PARAMS if p.name not in ("t_set", "t_end", "end_slot")}
    assert cfg.control.kp == ControlParams().kp and cfg.control.notch.q_max == NotchParams().q_max
    assert cfg.test.t_set_n == 0.5 and cfg.test.t_end_s == 36000.0 and cfg.test.autostart is False
    assert cfg.grades == ("I", "II")
    assert cfg.recorder.dir == "/var/lib/hookwatch/records"
    assert cfg.mqtt.enabled is False and cfg.mqtt.port == 1883
    assert cfg.mqtt.outbox.path == "/var/lib/hookwatch/records/s1/outbox.sqlite"
    assert cfg.modbus_tcp.port == 5020 and cfg.modbus_tcp.writes.allowed_clients == ()
    assert cfg.logging.level == "info"
    assert cfg.source == str(tmp_path / "s.yaml") and cfg.fleet_file is None


def test_objects_work_with_the_runtime(tmp_path):
    """Attribute access, dataclasses.replace and the builders in gateway/station/build.py."""
    from gateway.station.build import control_params, method_values

    cfg = load_station(write(tmp_path / "s.yaml", MINIMAL + "control: {kp: 80, notch: {ratio_i: 2}}\n"
                             "method: {w_ss: 30}\n"))
    cfg2 = dataclasses.replace(cfg, test=dataclasses.replace(cfg.test, t_set_n=0.7, autostart=True))
    assert cfg2.test.t_set_n == 0.7 and cfg.test.t_set_n == 0.5
    cp = control_params(cfg, 0.02)
    assert isinstance(cp, ControlParams) and cp.kp == 80.0 and cp.notch.ratio_i == 2.0 and cp.ts == 0.02
    mv = method_values(cfg)
    assert isinstance(cfg.method, dict) and mv["w_ss"] == 30.0 and "t_set" not in mv
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.meter.port = "/dev/other"


def test_yaml_details(tmp_path):
    cfg = load_station(write(tmp_path / "s.yaml", """\
        station: {id: s1}
        meter: {port: /dev/a-meter, timeout_s: 2e-2}
        stm32: {port: /dev/a-stm32}
        logging: {level: WARNING}
        modbus_tcp: {writes: {enabled: true, allowed_clients: [10.0.0.5, 10.1.0.0/16]}}
        """))
    assert cfg.meter.timeout_s == 0.02          # 2e-2 is a number, not the string '2e-2'
    assert cfg.logging.level == "warning"        # enums are case-insensitive, stored canonical
    assert cfg.modbus_tcp.writes.allowed_clients == ("10.0.0.5", "10.1.0.0/16")
    with pytest.raises(ConfigError, match=r"s2.yaml:4: meter: key given twice \(first at line 2\)"):
        load_station(write(tmp_path / "s2.yaml", MINIMAL + "meter: {port: /dev/b}\n"))


def test_all_errors_at_once_with_positions(tmp_path):
    p = write(tmp_path / "s.yaml", """\
        station: {id: s1}
        meter:
          port: /dev/a-meter
          baud: 9601
        stm32:
          port: /dev/a-stm32
          retries: 9
        method:
          tau: -1
        """)
    with pytest.raises(ConfigError) as ei:
        load_station(p)
    e = ei.value
    assert [(i.line, i.key) for i in e.issues] == [(4, "meter.baud"), (7, "stm32.retries"), (9, "method.tau")]
    lines = str(e).splitlines()
    assert lines[0] == (f"{p}:4: meter.baud: 9601 is not allowed; allowed: one of 1200, 2400, 4800, "
                        "9600, 19200, 38400, 57600, 115200, 230400, or null")
    assert lines[1] == f"{p}:7: stm32.retries: 9 is out of range; allowed: an integer from 0 to 5"
    assert lines[2].startswith(f"{p}:9: method.tau: -1.0 is impossible; allowed: > 0")


def test_missing_file_raises_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_station(str(tmp_path / "nope.yaml"))
    with pytest.raises(FileNotFoundError):
        load_fleet(str(tmp_path / "nope"))


# ---------------------------------------------------------------------------------- the fleet

def _fleet(tmp_path):
    write(tmp_path / "fleet.yaml", """\
        defaults:
          station: {site: plant-a, area: hall-1}
          meter: {map: maps/m.yaml, baud: 38400}
          method: {w_ss: 30, delta: 0.3}
          grades: [I, II, III]
          recorder: {dir: records}
          mqtt: {enabled: true, prefix: hw}
        """)
    with open(os.path.join(ROOT, "config", "meters", "zn-s.yaml")) as f:
        write(tmp_path / "maps" / "m.yaml", f.read())
    write(tmp_path / "stations" / "a.yaml", """\
        station: {id: a, line: l1}
        meter: {port: /dev/a-m}
        stm32: {port: /dev/a-s}
        method: {delta: 0.2}
        grades: [X]
        control:
        """)
    write(tmp_path / "stations" / "b.yaml", """\
        station: {id: b}
        meter: {port: /dev/b-m, map: ../maps/m.yaml, baud: null}
        stm32: {port: /dev/b-s}
        recorder: {dir: ../b-records}
        test: {grade: III}
        """)
    return tmp_path


def test_fleet_deep_merge(tmp_path):
    a, b = load_fleet(str(_fleet(tmp_path)))
    assert (a.station.id, b.station.id) == ("a", "b")
    assert a.station.site == "plant-a" and a.station.line == "l1" and b.station.area == "hall-1"
    assert a.method["w_ss"] == 30.0 and a.method["delta"] == 0.2 and b.method["delta"] == 0.3
    assert a.grades == ("X",) and b.grades == ("I", "II", "III")     # lists are replaced
    assert a.control.kp == ControlParams().kp                         # empty section: defaults kept
    assert a.meter.baud == 38400 and b.meter.baud is None              # null overrides the default
    assert a.mqtt.enabled and a.mqtt.prefix == "hw"
    assert a.fleet_file == str(tmp_path / "fleet.yaml")


def test_paths_relative_to_the_file_that_sets_them(tmp_path):
    a, b = load_fleet(str(_fleet(tmp_path)))
    assert a.meter.map == str(tmp_path / "maps" / "m.yaml")       # set in fleet.yaml
    assert b.meter.map == str(tmp_path / "maps" / "m.yaml")       # set in stations/b.yaml
    assert a.recorder.dir == str(tmp_path / "records")
    assert b.recorder.dir == str(tmp_path / "b-records")
    assert a.mqtt.outbox.path == str(tmp_path / "records" / "a" / "outbox.sqlite")


def test_lone_station_file_takes_fleet_defaults_from_parent(tmp_path):
    _fleet(tmp_path)
    a = load_station(str(tmp_path / "stations" / "a.yaml"))
    assert a.station.site == "plant-a" and a.method["w_ss"] == 30.0
    # the same file outside a stations/ folder stands alone
    alone = write(tmp_path / "elsewhere" / "a.yaml", (tmp_path / "stations" / "a.yaml").read_text())
    c = load_station(alone)
    assert c.station.site == "" and c.method["w_ss"] == 60.0 and c.fleet_file is None
    # explicit: no fleet file
    d = load_station(str(tmp_path / "stations" / "a.yaml"), fleet_file=None)
    assert d.station.site == ""


def test_fleet_errors_point_into_fleet_yaml(tmp_path):
    _fleet(tmp_path)
    fy = tmp_path / "fleet.yaml"
    fy.write_text(fy.read_text().replace("delta: 0.3", "delta: lots"))
    with pytest.raises(ConfigError) as ei:
        load_fleet(str(tmp_path))
    # b inherits the bad value (a overrides it): reported at fleet.yaml's line
    assert str(ei.value) == (f"{tmp_path}/fleet.yaml:4: method.delta: 'lots' is not a number "
                             "(relative threshold increment δ, 1)")


def test_load_fleet_refuses_clashes(tmp_path):
    _fleet(tmp_path)
    sb = tmp_path / "stations" / "b.yaml"
    sb.write_text(sb.read_text().replace("/dev/b-s", "/dev/a-s"))
    with pytest.raises(ConfigError) as ei:
        load_fleet(str(tmp_path))
    assert "stm32.port: '/dev/a-s' is also the stm32.port of station a" in str(ei.value)


def test_empty_fleet_folder(tmp_path):
    assert load_fleet(str(tmp_path)) == []


def test_shipped_configs_load():
    cfgs = load_fleet(os.path.join(ROOT, "config"))
    assert [c.station.id for c in cfgs] == ["loom-01", "loom-02", "loom-03", "loom-04"]
    assert len({c.meter.port for c in cfgs} | {c.stm32.port for c in cfgs}) == 8
    assert [c.modbus_tcp.unit_id for c in cfgs] == [1, 2, 3, 4]
    assert len({c.modbus_tcp.port for c in cfgs}) == 1
    for c in cfgs:
        assert c.meter.port.startswith("/dev/hookwatch/")
        assert c.mqtt.password_env and not hasattr(c.mqtt, "password")
    demo = load_station(os.path.join(ROOT, "config", "demo", "station.yaml"))
    assert demo.meter.port == "/tmp/hookwatch-sim/meter" and demo.stm32.port == "/tmp/hookwatch-sim/stm32"
    assert (demo.method["w_ss"], demo.method["w_hold"], demo.method["tau"]) == (5.0, 30.0, 5.0)
    assert demo.test.t_end_s == 150.0 and demo.fleet_file is None


def test_validate_station_keeps_going(tmp_path):
    ld = validate_station(write(tmp_path / "s.yaml", MINIMAL + "mqtt: {password: x}\n"))
    assert ld.cfg is None and ld.name == "s1"
    assert [i.key for i in ld.errors] == ["mqtt.password"]


def test_hookwatch_run_refuses_a_bad_file_with_exit_1(tmp_path):
    p = write(tmp_path / "s.yaml", MINIMAL.replace("/dev/a-meter}", "/dev/a-meter, buad: 9600}"))
    r = subprocess.run(hookwatch_cmd() + ["run", p, "--duration", "1"], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert r.returncode == 1
    assert f"{p}:2: meter.buad: unknown key; did you mean 'baud'?" in r.stderr


# ---------------------------------------------------------------------------------- sdnotify

def _receiver(addr):
    s = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    s.bind(addr)
    s.settimeout(10)
    return s


@pytest.mark.parametrize("abstract", [False, True])
def test_sdnotify_real_socket(tmp_path, monkeypatch, abstract):
    from gateway.plumbing import sdnotify

    name = f"hookwatch-test-{os.getpid()}-{id(tmp_path)}"
    if abstract:
        bind, env = "\0" + name, "@" + name
    else:
        bind = env = str(tmp_path / "notify.sock")
    with _receiver(bind) as rx:
        monkeypatch.setenv("NOTIFY_SOCKET", env)
        assert sdnotify.enabled()
        assert sdnotify.ready("up\nand running")
        msg = rx.recv(4096).decode()
        assert msg.splitlines() == ["READY=1", f"MAINPID={os.getpid()}", "STATUS=up and running"]
        assert sdnotify.status("2 stations")
        assert rx.recv(4096) == b"STATUS=2 stations"
        assert sdnotify.watchdog()
        assert rx.recv(4096) == b"WATCHDOG=1"
        assert sdnotify.stopping()
        assert rx.recv(4096) == b"STOPPING=1"


def test_sdnotify_without_socket_is_a_no_op(monkeypatch, tmp_path):
    from gateway.plumbing import sdnotify

    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert not sdnotify.enabled()
    assert sdnotify.ready() is False and sdnotify.watchdog() is False
    # a socket that is gone: no exception
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "gone.sock"))
    assert sdnotify.watchdog() is False


def test_sdnotify_watchdog_interval(monkeypatch):
    from gateway.plumbing import sdnotify

    monkeypatch.setenv("WATCHDOG_USEC", "10000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert sdnotify.watchdog_interval_s() == 5.0
    monkeypatch.setenv("WATCHDOG_PID", "1")
    assert sdnotify.watchdog_interval_s() is None
    monkeypatch.delenv("WATCHDOG_USEC")
    assert sdnotify.watchdog_interval_s() is None
