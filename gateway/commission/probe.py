"""`hookwatch check --probe`: ask every device and service a station needs, once, before it runs.

- a serial port a running station (or any program) holds — its exclusive lock taken — is left
  alone: the probe names the holder (the lock's process from /proc/locks; the station from the
  station file or fleet folder on its command line), sends nothing and changes no setting;
- the meter: its port opened with the station's settings and both channels read once through
  pymodbus' client (an independent Modbus master: a meter this client reads is no artefact of our
  own driver), then through the station's own driver (drivers/meter/driver.py): "meter answered" means
  both read it; ``scan`` tries the usual bauds and unit IDs and says where the meter answered
  (the port's settings as found are put back after it); the latency timer of a USB serial
  adapter (FTDI) against the slot; the kernel's RS-485 mode
  when ``meter.rs485`` asks for it;
- the STM32: a PING through the project's own link driver (drivers/stm32/driver.py);
- each configured broker (``mqtt:``, ``sparkplug:`` and every member of its server set): TCP
  connect, CONNECT with the station's user, password and TLS, and the broker's CONNACK;
- the Modbus TCP, console and metrics ports: free to listen on.

Every result is a :class:`Finding`: one plain sentence, a failure's ending with its fix. Bounded:
one attempt per thing (the scan: at most ``len(SCAN_BAUDS) × len(SCAN_UNITS)`` short reads), each
with its timeout; nothing is written to a device but the requests themselves (no ENABLE).
"""
from __future__ import annotations

import asyncio
import errno
import logging
import os
import socket
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, ClassVar

import paho.mqtt.client as mqtt
import serial
from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from drivers.meter.driver import FAST_RUN, Reading, ZnsMeter
from drivers.meter.meter_map import DEFAULT_MAP_PATH, DecodeError, MapError, MeterMap, load_map
from drivers.serial.ttyio import (
    describe_holders,
    keep_settings,
    latency_timer_ms,
    latency_timer_path,
    port_holders,
    port_in_use,
    process_args,
    set_rs485,
)
from drivers.stm32.driver import Stm32Link
from drivers.stm32.protocol import Cmd, exchange_time_s

from ..config import validate_fleet, validate_station
from ..config.sections import parse_server
from ..outputs.broker.settings import BrokerSettings, SecretError, broker_kwargs
from ..outputs.registry import brokers, listen_doors
from ..plumbing.ratelog import safe

log = logging.getLogger("hookwatch.probe")

#: bauds `--scan` tries (the configured one first), most common first
SCAN_BAUDS: tuple[int, ...] = (115200, 57600, 38400, 19200, 9600)
#: unit IDs `--scan` tries (the configured one first)
SCAN_UNITS: tuple[int, ...] = tuple(range(1, 17))
#: a read's timeout beyond the wire time of request and reply (the probe is not the slot loop)
METER_MARGIN_S = 0.25
SCAN_MARGIN_S = 0.1
BROKER_TIMEOUT_S = 5.0
STM32_ATTEMPTS = 3
SLOT_S = 0.02


@dataclass(frozen=True)
class Finding:
    what: str          # meter | stm32 | mqtt | sparkplug | port
    ok: bool
    text: str          # one plain sentence; a failure's ends with the fix

    def __str__(self) -> str:
        return f"{'ok' if self.ok else 'FAILED'}: {self.text}"


def _is_pty(path: str) -> bool:
    return os.path.realpath(path).startswith("/dev/pts/")


def _quiet_pymodbus() -> None:
    # pymodbus logs every missing reply as an error of its own; the probe says it in one sentence
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


# ----------------------------------------------------------------------------------- the meter
def meter_map_of(meter_cfg: Any) -> MeterMap:
    m = load_map(getattr(meter_cfg, "map", None) or DEFAULT_MAP_PATH)
    return m.with_overrides(baud=meter_cfg.baud, unit_id=meter_cfg.unit_id, parity=meter_cfg.parity)


def settings_text(port: str, m: MeterMap, parity: str, unit: int, baud: int | None = None) -> str:
    return f"{port} at {baud or m.baud} {m.bytesize}{parity}{m.stopbits}, unit {unit}"


@dataclass(frozen=True)
class MeterAnswer:
    ok: bool
    kind: str                        # ok | no_reply | port | exception | decode
    detail: str = ""
    ch: tuple[float, float] | None = None
    echo: bool | None = None         # the adapter handed our own request back (None: nothing came)


def read_meter(port: str, m: MeterMap, *, baud: int, unit: int, parity: str, timeout_s: float) -> MeterAnswer:
    """One read of the map's block through pymodbus' serial client (a fresh client, closed after).
    The client's framer reads past an echo of our request by itself; the raw bytes are watched
    (``trace_packet``) to say whether the adapter echoes, which our own driver must be told
    (``meter.local_echo``)."""
    _quiet_pymodbus()
    if "://" not in port and not os.path.exists(port):
        return MeterAnswer(False, "port", "no such device")
    a, echo = _traced_read(port, m, baud=baud, unit=unit, parity=parity, timeout_s=timeout_s)
    if echo and not a.ok:
        # the framer does not always find the reply behind the echo: skip the echo as it comes
        a, _ = _traced_read(port, m, baud=baud, unit=unit, parity=parity, timeout_s=timeout_s, skip_echo=True)
    return MeterAnswer(a.ok, a.kind, a.detail, a.ch, echo=echo)


def _traced_read(port: str, m: MeterMap, *, baud: int, unit: int, parity: str, timeout_s: float,
                 skip_echo: bool = False) -> tuple[MeterAnswer, bool | None]:
    sent: list[bytes] = []
    rx: list[bytes] = []

    def trace(sending: bool, data: bytes) -> bytes:
        (sent if sending else rx).append(bytes(data))
        return data

    c = ModbusSerialClient(port, baudrate=baud, bytesize=m.bytesize, parity=parity, stopbits=m.stopbits,
                           timeout=timeout_s, retries=0, trace_packet=trace, handle_local_echo=skip_echo)
    try:
        a = _read_once(c, m, unit)
    finally:
        c.close()
    echo = None
    if sent and rx:
        first = next((b for b in rx if len(b) >= 3), rx[0])
        n = min(len(first), len(sent[0]))
        echo = first[:n] == sent[0][:n]
    return a, echo


def _read_once(c: ModbusSerialClient, m: MeterMap, unit: int) -> MeterAnswer:
    try:
        if not c.connect():
            return MeterAnswer(False, "port", "cannot be opened")
        fc, address, count = m.read_block
        fn = c.read_holding_registers if fc == 3 else c.read_input_registers
        try:
            rr = fn(address, count=count, device_id=unit)
        except ModbusIOException:
            return MeterAnswer(False, "no_reply")
        except ConnectionException as e:
            return MeterAnswer(False, "port", f"lost ({e})")
        except ModbusException as e:
            return MeterAnswer(False, "no_reply", str(e))
        if rr.isError():
            code = getattr(rr, "exception_code", 0)
            return MeterAnswer(False, "exception", f"{code:02d}")
        try:
            ch = m.decode(rr.registers)
        except DecodeError as e:
            return MeterAnswer(False, "decode", str(e))
        return MeterAnswer(True, "ok", ch=ch)
    except (OSError, serial.SerialException) as e:
        return MeterAnswer(False, "port", str(e))


def scan_meter(port: str, m: MeterMap, parity: str,
               bauds: Iterable[int] = SCAN_BAUDS, units: Iterable[int] = SCAN_UNITS,
               ) -> tuple[int, int, MeterAnswer] | None:
    """(baud, unit, answer) where the meter answered, trying the configured baud and unit first."""
    order_b = [m.baud] + [b for b in bauds if b != m.baud]
    order_u = [m.unit_id] + [u for u in units if u != m.unit_id]
    for b in order_b:
        t = m.with_overrides(baud=b).poll_time_s() + SCAN_MARGIN_S
        for u in order_u:
            a = read_meter(port, m, baud=b, unit=u, parity=parity, timeout_s=t)
            if a.kind == "port":
                return None
            if a.kind != "no_reply":             # an answer, even an exception, is the meter
                return b, u, a
    return None


# ----------------------------------------------------------------------------------- ports in use
def _station_of(pid: int, port: str) -> str | None:
    """The station a process runs that uses ``port``: from the station file or fleet folder on
    its command line (``hookwatch run …``, a fleet worker ``gateway.supervisor.worker FILE``)."""
    args = process_args(pid)
    try:
        cwd = os.readlink(f"/proc/{pid}/cwd")
    except OSError:
        cwd = None
    want = os.path.realpath(port)
    for a in args[1:]:
        if a.startswith("-") or len(a) > 4096:
            continue
        path = a if os.path.isabs(a) else (os.path.join(cwd, a) if cwd else None)
        if path is None:
            continue
        try:
            if os.path.isfile(path) and path.endswith((".yaml", ".yml")):
                loaded = [validate_station(path)]
            elif os.path.isdir(path):
                loaded = validate_fleet(path)
            else:
                continue
        except (OSError, ValueError):
            continue
        for ld in loaded:
            c = ld.cfg
            if c is not None and want in (os.path.realpath(c.meter.port), os.path.realpath(c.stm32.port)):
                return safe(c.station.id, 64)
    return None


def port_holder_text(port: str) -> str | None:
    """None when ``port`` is free (or cannot be asked); else who holds it: ``station line-1
    (pid 1234)`` when the holder runs a station file that names this port, else the process and
    its command line. Asking takes the port's lock for a moment and changes nothing of it."""
    if port_in_use(port) is not True:
        return None
    pids = port_holders(port)
    if not pids:
        return describe_holders(port)
    parts = []
    for pid in pids[:4]:
        st = _station_of(pid, port)
        parts.append(f"station {st} (pid {pid})" if st else describe_holders_of(pid))
    return ", ".join(parts)


def describe_holders_of(pid: int) -> str:
    args = process_args(pid)
    cmd = " ".join(os.path.basename(a) if i == 0 else a for i, a in enumerate(args))
    return f"pid {pid} ({safe(cmd, 120)})" if cmd else f"pid {pid}"


def _in_use(what: str, port: str, holder: str) -> Finding:
    label = "STM32" if what == "stm32" else what
    return Finding(what, False, f"{label} port {port} is in use by {holder}: the probe leaves a port "
                   "in use as it is (no request sent, no setting changed); the running station's "
                   "console and metrics show its link, or stop it before probing.")


# ----------------------------------------------------------------------------------- the meter
async def _driver_reads(meter_cfg: Any) -> tuple[Reading | None, str | None]:
    """The station's own driver (drivers/meter/driver.py, the station's settings and timeout) reads the
    meter: the first good reading of up to FAST_RUN + 1 polls one slot apart, or why none."""
    d = ZnsMeter.from_config(meter_cfg)
    await d.open()
    try:
        for _ in range(FAST_RUN + 1):
            r = await d.read()
            if r is not None:
                return r, None
            await asyncio.sleep(SLOT_S)
        return None, d.diagnosis()
    finally:
        await d.close()


def driver_read(meter_cfg: Any) -> tuple[Reading | None, str | None]:
    return asyncio.run(_driver_reads(meter_cfg))


def probe_meter(meter_cfg: Any, *, scan: bool = False, sysfs: str = "/sys") -> list[Finding]:
    port = meter_cfg.port
    try:
        m = meter_map_of(meter_cfg)
    except (MapError, OSError) as e:
        return [Finding("meter", False, f"the meter's register map cannot be read ({e}): fix meter.map.")]
    holder = port_holder_text(port)
    if holder is not None:
        return [_in_use("meter", port, holder)]
    with keep_settings(port):
        # pymodbus' client opens the port exclusively for each read (a station starting meanwhile
        # finds it in use); the bauds a scan tried are undone at the end
        out = _probe_meter_free(meter_cfg, m, port, scan, sysfs)
    if out and out[0].ok and out[0].text.startswith("meter answered"):
        # what answers pymodbus' client must answer the station's own driver too
        r, why = driver_read(meter_cfg)
        if r is None:
            timeout = float(getattr(meter_cfg, "timeout_s", 0.015))
            said = out[0].text[len("meter answered "):-1]
            out[0] = Finding("meter", False, f"pymodbus' client reads the meter ({said}) but the "
                             f"station's own driver does not: {why or 'no reading'}; check "
                             f"meter.timeout_s ({timeout * 1e3:g} ms) and meter.local_echo.")
        else:
            out[0] = Finding("meter", True, out[0].text[:-1] + "; the station's driver read it too "
                             f"(channel 1 {r.ch1:.3f} N).")
    return out


def _probe_meter_free(meter_cfg: Any, m: MeterMap, port: str, scan: bool, sysfs: str) -> list[Finding]:
    parity = "N" if _is_pty(port) else m.parity       # a pty carries no parity (as the driver)
    where = settings_text(port, m, parity, m.unit_id)
    out: list[Finding] = []
    local_echo = bool(getattr(meter_cfg, "local_echo", False))
    a = read_meter(port, m, baud=m.baud, unit=m.unit_id, parity=parity,
                   timeout_s=m.poll_time_s() + METER_MARGIN_S)
    if a.ok and a.ch is not None:
        out.append(Finding("meter", True, f"meter answered on {where}: channel 1 {a.ch[0]:.3f} N, "
                                          f"channel 2 {a.ch[1]:.3f} N."))
    elif a.kind == "port":
        out.append(Finding("meter", False, f"meter port {port} {a.detail}: check the cable and the "
                           "adapter (ls -l /dev/hookwatch/, the udev rules in docs/deploy.md) and meter.port."))
        return out
    elif a.kind == "exception":
        out.append(Finding("meter", False, f"the meter on {where} answers Modbus exception {a.detail}: "
                           "its register map does not fit this meter; check meter.map."))
    elif a.kind == "decode":
        out.append(Finding("meter", False, f"the meter on {where} gives registers that make no tension "
                           f"({a.detail}): check meter.map against the meter's manual."))
    else:
        hint = ("run `hookwatch check --probe --scan` to find its baud and unit ID" if not scan else "")
        found = scan_meter(port, m, parity) if scan else None
        if found is not None:
            b, u, fa = found
            keys = ", ".join(f"meter.{k}: {v}" for k, v, c in (("baud", b, m.baud), ("unit_id", u, m.unit_id))
                             if v != c)
            out.append(Finding("meter", False, f"meter not answering on {where}; it answered at "
                               f"{settings_text(port, m, parity, u, b)}: set {keys}."))
        elif scan:
            out.append(Finding("meter", False, f"meter not answering on {where}, nor at any of "
                               f"{', '.join(map(str, SCAN_BAUDS))} baud with unit IDs "
                               f"{SCAN_UNITS[0]}–{SCAN_UNITS[-1]}: check the meter's power, the A/B "
                               "wiring and the bus termination."))
        else:
            out.append(Finding("meter", False, f"meter not answering on {where}: check the meter's "
                               f"power and A/B wiring, its baud and unit ID; {hint}."))
    if a.echo is not None and a.echo != local_echo:
        out.append(Finding("meter", False, f"the adapter on {port} hands our own request back before "
                           "the reply (echo on a 2-wire bus): set meter.local_echo: true." if a.echo else
                           f"meter.local_echo is set but the adapter on {port} does not echo: set "
                           "meter.local_echo: false."))
    out += _latency_findings(port, m, float(getattr(meter_cfg, "timeout_s", 0.015)), sysfs)
    rs = getattr(meter_cfg, "rs485", None)
    if rs is not None and getattr(rs, "enabled", False):
        out.append(_rs485_finding(port, rs))
    return out


def _latency_findings(port: str, m: MeterMap, timeout_s: float, sysfs: str) -> list[Finding]:
    lt = latency_timer_ms(port, sysfs)
    if lt is None:
        return []
    arrive = m.poll_time_s() + lt / 1000.0
    path = latency_timer_path(port, sysfs)
    if arrive > timeout_s or lt > SLOT_S * 1000 / 4:
        return [Finding("meter", False, f"the USB adapter behind {port} holds received bytes for "
                        f"{lt} ms (its latency timer): a reply would reach the gateway {arrive * 1e3:.1f} "
                        f"ms after the request, against a {timeout_s * 1e3:.0f} ms timeout in a "
                        f"{SLOT_S * 1e3:.0f} ms slot; install deploy/udev/99-hookwatch.rules (sets 1 ms) "
                        f"or run `echo 1 > {path}`.")]
    return [Finding("meter", True, f"the USB adapter behind {port} has a {lt} ms latency timer.")]


def _rs485_finding(port: str, rs: Any) -> Finding:
    try:
        ser = serial.Serial(port, timeout=0)
    except (OSError, ValueError, serial.SerialException) as e:
        return Finding("meter", False, f"meter.rs485: {port} cannot be opened ({e}).")
    try:
        err = set_rs485(ser.fileno(), rs.rts_on_send, rs.rts_after_send, rs.delay_before_send_s,
                        rs.delay_after_send_s)
    finally:
        ser.close()
    if err:
        return Finding("meter", False, f"meter.rs485: {port}: {err}.")
    return Finding("meter", True, f"{port} is in the kernel's RS-485 mode (RTS {rs.rts_on_send} while sending).")


# ----------------------------------------------------------------------------------- the STM32
async def _ping(stm32_cfg: Any) -> tuple[bool, str]:
    link = Stm32Link.from_config(stm32_cfg)
    link.keepalive_enabled = False
    await link.open()
    try:
        if not link.connected:
            return False, "port"
        for _ in range(STM32_ATTEMPTS):
            st = await link.ping()
            if st is not None:
                return True, f"{'enabled' if st.enabled else 'disabled'}, {st.actual_rpm:.0f} rpm"
        return False, "silent"
    finally:
        await link.close()


def stm32_latency_finding(stm32_cfg: Any, sysfs: str = "/sys") -> Finding | None:
    """The latency timer of a USB adapter on the STM32 link against its reply timeout."""
    port = stm32_cfg.port
    lt = latency_timer_ms(port, sysfs)
    if lt is None:
        return None
    timeout_s = float(stm32_cfg.timeout_s)
    arrive = exchange_time_s(Cmd.SET_SPEED, int(stm32_cfg.baud)) + lt / 1000.0
    if arrive > timeout_s:
        return Finding("stm32", False, f"the USB adapter behind {port} holds received bytes for {lt} ms "
                       f"(its latency timer): an ACK would come {arrive * 1e3:.1f} ms after the command, "
                       f"against the {timeout_s * 1e3:.0f} ms stm32.timeout_s; install "
                       f"deploy/udev/99-hookwatch.rules (sets 1 ms) or run `echo 1 > "
                       f"{latency_timer_path(port, sysfs)}`.")
    return Finding("stm32", True, f"the USB adapter behind {port} has a {lt} ms latency timer.")


def probe_stm32(stm32_cfg: Any) -> Finding:
    port = stm32_cfg.port
    if "://" not in port and not os.path.exists(port):
        return Finding("stm32", False, f"STM32 port {port} does not exist: check the cable and the "
                       "adapter (ls -l /dev/hookwatch/) and stm32.port.")
    holder = port_holder_text(port)
    if holder is not None:
        return _in_use("stm32", port, holder)
    ok, detail = asyncio.run(_ping(stm32_cfg))
    where = f"{port} at {stm32_cfg.baud} baud"
    if ok:
        return Finding("stm32", True, f"STM32 answered a PING on {where} (motor {detail}).")
    if detail == "port":
        return Finding("stm32", False, f"STM32 port {port} cannot be opened (in use by a running "
                       "gateway, or no permission: the user must be in group dialout).")
    return Finding("stm32", False, f"STM32 not answering on {where}: check its power, the TX/RX "
                   "wiring and stm32.baud.")


# ----------------------------------------------------------------------------------- brokers
_AUTH_CODES = {4, 5, 134, 135}     # 3.1.1 bad user/password, not authorized; 5.0 the same


class _SparkplugBroker(BrokerSettings):
    section: ClassVar[str] = "sparkplug"      # the messages name the section


_Settings: dict[str, type[BrokerSettings]] = {"mqtt": BrokerSettings, "sparkplug": _SparkplugBroker}


def broker_addresses(name: str, section: Any) -> list[tuple[str, int]]:
    """The brokers a section connects to: host:port, or each of its server list (``mqtt.servers``,
    a Sparkplug server set)."""
    servers = getattr(section, "servers", None)
    if not servers:
        return [(section.host, int(section.port))]
    out = [hp for hp in (parse_server(str(x), int(section.port)) for x in servers) if hp is not None]
    return out or [(section.host, int(section.port))]


def probe_broker(name: str, section: Any, address: tuple[str, int] | None = None) -> Finding:
    """Connect and authenticate to the broker of ``section`` (``mqtt`` or ``sparkplug``), or to
    ``address`` with that section's credentials (a member of a Sparkplug server set)."""
    kw = broker_kwargs(section)
    if address is not None:
        # this member alone (the settings' server list would put its first server first)
        kw["host"], kw["port"] = address
        kw["servers"] = [address]
    s = _Settings[name](**kw)
    where = f"{s.host}:{s.port}"
    c = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=f"hookwatch-check-{os.getpid()}",
                    protocol=mqtt.MQTTv311)
    got: dict[str, Any] = {}
    c.on_connect = lambda _c, _u, _f, rc, _p: got.setdefault("rc", rc)
    c.on_disconnect = lambda _c, _u, _f, rc, _p: got.setdefault("rc", rc)
    try:
        s.apply(c)
    except SecretError as e:
        return Finding(name, False, f"{e}: set it (the unit's EnvironmentFile=) before running.")
    except (OSError, ValueError) as e:
        return Finding(name, False, f"{name}.tls: {e}: check the certificate files.")
    try:
        c.connect(s.host, s.port, keepalive=10)
    except (ConnectionRefusedError, socket.gaierror, TimeoutError, OSError) as e:
        text = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
        return Finding(name, False, f"{name} broker {where} cannot be reached ({text}): start the "
                       f"broker (systemctl status mosquitto) or fix {name}.host / {name}.port.")
    try:
        t_end = time.monotonic() + BROKER_TIMEOUT_S
        while "rc" not in got and time.monotonic() < t_end:
            c.loop(timeout=0.1)
    finally:
        c.disconnect()
    rc = got.get("rc")
    if rc is None:
        return Finding(name, False, f"{name} broker {where} did not answer CONNECT within "
                       f"{BROKER_TIMEOUT_S:g} s: is it an MQTT broker (TLS on a plain port, or the reverse)?")
    if rc.is_failure:
        val = int(rc.value)
        if val in _AUTH_CODES:
            who = f"user {s.username!r}" if s.username else "an anonymous client"
            return Finding(name, False, f"{name} broker {where} refused {who} ({rc}): check "
                           f"{name}.username and the password ({name}.password_env / password_file) "
                           "against the broker's password file and ACL.")
        return Finding(name, False, f"{name} broker {where} refused the connection ({rc}).")
    return Finding(name, True, f"{name} broker {where} accepted "
                   f"{'user ' + repr(s.username) if s.username else 'an anonymous client'}.")


# ----------------------------------------------------------------------------------- ports
def port_free(host: str, port: int) -> str | None:
    """None when (host, port) can be listened on now, else the reason."""
    fam = socket.AF_INET6 if ":" in host else socket.AF_INET
    s = socket.socket(fam, socket.SOCK_STREAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, port))
        s.listen(1)
    except OSError as e:
        return errno.errorcode.get(e.errno or 0, str(e))
    finally:
        s.close()
    return None


def probe_listen(key: str, host: str, port: int) -> Finding:
    why = port_free(host, port)
    if why is None:
        return Finding("port", True, f"{key}: {host}:{port} is free to listen on.")
    if why == "EADDRINUSE":
        return Finding("port", False, f"{key}: {host}:{port} is already in use by another program (a "
                       f"running gateway?): stop it (`ss -ltnp 'sport = :{port}'` shows which) or "
                       "choose another port.")
    if why == "EADDRNOTAVAIL":
        return Finding("port", False, f"{key}: {host} is no address of this machine: use one of its "
                       "addresses, 127.0.0.1 or 0.0.0.0.")
    if why == "EACCES":
        return Finding("port", False, f"{key}: port {port} needs privileges: choose a port ≥ 1024.")
    return Finding("port", False, f"{key}: cannot listen on {host}:{port} ({why}).")


def listen_ports(cfg: Any) -> list[tuple[str, str, int]]:
    """(key, host, port) the station's services listen on (the doors of the output registry)."""
    return listen_doors(cfg)


# ----------------------------------------------------------------------------------- stations
def probe_station(cfg: Any, *, scan: bool = False, sysfs: str = "/sys",
                  seen: set[tuple[Any, ...]] | None = None) -> list[Finding]:
    """Everything one station needs; ``seen`` skips brokers and ports already probed (a fleet
    shares them)."""
    seen = set() if seen is None else seen
    out = probe_meter(cfg.meter, scan=scan, sysfs=sysfs)
    out.append(probe_stm32(cfg.stm32))
    lat = stm32_latency_finding(cfg.stm32, sysfs)
    if lat is not None:
        out.append(lat)
    for name, sec in brokers(cfg):
        for host, port in broker_addresses(name, sec):
            kb = (name, host, port, sec.username)
            if kb not in seen:
                seen.add(kb)
                out.append(probe_broker(name, sec, (host, port)))
    for key, host, port in listen_ports(cfg):
        kl = ("listen", host, port)
        if kl not in seen:
            seen.add(kl)
            out.append(probe_listen(key, host, port))
    return out
