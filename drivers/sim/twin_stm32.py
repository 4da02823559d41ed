"""The virtual STM32 motor controller: the firmware as a pure state machine, served on a pty.

``Stm32Firmware`` implements docs/protocols/stm32.md (commands, duplicate detection, watchdog,
stall/overspeed trips). It is pure: frames and the time ``now`` in, reply frames out; the drive
outputs (``drive_enabled``, ``drive_rpm``) and the measured inputs (``measure(actual_rpm,
stalled, now)``) connect it to a motor model.

``VirtualStm32`` serves a firmware on a :class:`~drivers.sim.pty.PtyLink` with asyncio: it answers
after the real wire time of the request + a processing delay + the wire time of the reply at the
link's baud rate, ticks the firmware (watchdog, trips) every ``tick_s`` and drives a motor object
with ``set_command(rpm)``, ``enable(bool)``, ``speed_rpm`` and ``stalled`` (the simulator's plant;
:class:`SimpleMotor` here is a first-order stand-in for tests).

``python -m drivers.sim.twin_stm32 --link PATH`` serves one with a SimpleMotor, prints
``stm32: /dev/pts/N`` and takes control lines on stdin (see ``_control``).
"""
from __future__ import annotations

import asyncio
import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..stm32.protocol import (
    DEFAULT_BAUD,
    DEFAULT_MAX_RPM,
    RUNNING_RPM,
    WATCHDOG_MS_MAX,
    WATCHDOG_MS_MIN,
    Cmd,
    Flag,
    FrameParser,
    NakCode,
    ProtocolError,
    Status,
    StopReason,
    decode_frame,
    decode_request,
    encode_ack,
    encode_nak,
    wire_time_s,
)
from .pty import PtyLink

log = logging.getLogger("hookwatch.sim.stm32")

#: stop reasons a STOP command may carry
GATEWAY_STOP_REASONS = (StopReason.COMMAND, StopReason.PROTECTION, StopReason.TEST_END,
                        StopReason.GATEWAY)

#: frames read at once after the simulator itself did not look at its pty for longer than this
#: are taken to have arrived one after another since the previous look (see ``_on_readable``)
STALL_SPREAD_S = 0.015


class Stm32Firmware:
    """The firmware's state machine. All times are seconds on the caller's monotonic clock."""

    def __init__(self, watchdog_s: float = 0.2, *, max_rpm: float = DEFAULT_MAX_RPM,
                 overspeed_rpm: float | None = None, stall_trip_s: float | None = 0.5,
                 dup_window_s: float = 0.5):
        ms = int(round(watchdog_s * 1000))
        if not WATCHDOG_MS_MIN <= ms <= WATCHDOG_MS_MAX:
            raise ValueError(f"watchdog_s {watchdog_s}: allowed {WATCHDOG_MS_MIN / 1000:g} … "
                             f"{WATCHDOG_MS_MAX / 1000:g} s")
        self.watchdog_ms = ms
        self.max_rpm = float(max_rpm)
        self.overspeed_rpm = float(overspeed_rpm) if overspeed_rpm is not None else 1.1 * self.max_rpm
        self.stall_trip_s = stall_trip_s
        self.dup_window_s = dup_window_s
        # state
        self.enabled = False
        self.command_rpm = 0.0
        self.stop_reason: StopReason = StopReason.POWER_ON
        self.watchdog_tripped = False
        self.fault = False
        self.overspeed = False
        # measured
        self.actual_rpm = 0.0
        self.stalled = False
        self._stall_since: float | None = None
        # link
        self.last_valid_rx: float | None = None
        self._last: tuple[int, int, bytes, float, bytes] | None = None  # seq, cmd, payload, t, reply kind
        self.counters = {"frames": 0, "executed": 0, "duplicates": 0, "naks": 0, "rx_errors": 0,
                         "watchdog_trips": 0, "stall_trips": 0, "overspeed_trips": 0}

    # ------------------------------------------------------------------ drive outputs
    @property
    def watchdog_s(self) -> float:
        return self.watchdog_ms / 1000.0

    @property
    def drive_enabled(self) -> bool:
        return self.enabled

    @property
    def drive_rpm(self) -> float:
        return self.command_rpm if self.enabled else 0.0

    def status(self) -> Status:
        f = Flag(0)
        if self.enabled:
            f |= Flag.ENABLED
        if abs(self.actual_rpm) >= RUNNING_RPM:
            f |= Flag.RUNNING
        if self.watchdog_tripped:
            f |= Flag.WATCHDOG
        if self.stalled:
            f |= Flag.STALL
        if self.fault:
            f |= Flag.FAULT
        if self.overspeed:
            f |= Flag.OVERSPEED
        return Status(actual_rpm=self.actual_rpm, command_rpm=self.drive_rpm, enabled=self.enabled,
                      flags=f, stop_reason=self.stop_reason, watchdog_ms=self.watchdog_ms,
                      rx_errors=self.counters["rx_errors"] & 0xFFFF)

    # ------------------------------------------------------------------ inputs
    def _stop(self, reason: StopReason) -> None:
        self.enabled = False
        self.command_rpm = 0.0
        self.stop_reason = reason

    def measure(self, actual_rpm: float, stalled: bool, now: float) -> None:
        """The drive's measurements (speed, stall detection) at time ``now``; applies the trips."""
        if math.isfinite(actual_rpm):
            self.actual_rpm = float(actual_rpm)
        self.stalled = bool(stalled)
        if self.stalled and self.enabled:
            if self._stall_since is None:
                self._stall_since = now
            if self.stall_trip_s is not None and now - self._stall_since >= self.stall_trip_s:
                self._stop(StopReason.STALL)
                self.fault = True
                self.counters["stall_trips"] += 1
        else:
            self._stall_since = None
        if self.enabled and abs(self.actual_rpm) > self.overspeed_rpm:
            self._stop(StopReason.OVERSPEED)
            self.fault = self.overspeed = True
            self.counters["overspeed_trips"] += 1

    def count_rx_error(self, n: int = 1) -> None:
        """Frames dropped for a bad CRC before they reached ``handle`` (never answered)."""
        self.counters["rx_errors"] += n

    def tick(self, now: float) -> None:
        """Apply the watchdog: enabled and no valid command for watchdog_s → stop (WATCHDOG)."""
        if self.enabled and self.last_valid_rx is not None \
                and now - self.last_valid_rx >= self.watchdog_s - 1e-9:
            self._stop(StopReason.WATCHDOG)
            self.watchdog_tripped = True
            self.counters["watchdog_trips"] += 1

    def watchdog_deadline(self) -> float | None:
        if self.enabled and self.last_valid_rx is not None:
            return self.last_valid_rx + self.watchdog_s
        return None

    # ------------------------------------------------------------------ commands
    def handle(self, frame_bytes: bytes, now: float) -> bytes | None:
        """One received frame → the reply frame, or None (bad CRC / not a frame: not answered)."""
        try:
            frame = decode_frame(bytes(frame_bytes))
        except ProtocolError:
            self.counters["rx_errors"] += 1
            return None
        self.tick(now)           # a command arriving after the deadline does not undo the trip
        self.counters["frames"] += 1
        last = self._last
        if last is not None and last[0] == frame.seq and last[1] == frame.cmd \
                and last[2] == frame.payload and now - last[3] <= self.dup_window_s:
            # a retry of the previous command (its reply was lost): answer again, do not act
            self.counters["duplicates"] += 1
            if last[4]:
                self.counters["naks"] += 1
                return encode_nak(frame.seq, frame.cmd, last[4][0])
            self.last_valid_rx = now
            return encode_ack(frame.seq, frame.cmd, self.status())
        reply_nak: int | None = None
        try:
            req = decode_request(frame)
        except ProtocolError as e:
            reply_nak = getattr(e, "code", NakCode.UNKNOWN_COMMAND)
        else:
            reply_nak = self._execute(req, now)
        if reply_nak is not None:
            self.counters["naks"] += 1
            self._last = (frame.seq, frame.cmd, frame.payload, now, bytes((int(reply_nak),)))
            return encode_nak(frame.seq, frame.cmd, reply_nak)
        self.counters["executed"] += 1
        self.last_valid_rx = now
        self._last = (frame.seq, frame.cmd, frame.payload, now, b"")
        return encode_ack(frame.seq, frame.cmd, self.status())

    def _execute(self, req, now: float) -> int | None:
        c = req.cmd
        if c == Cmd.SET_SPEED:
            if not 0.0 <= req.rpm <= self.max_rpm:
                return NakCode.OUT_OF_RANGE
            if self.enabled:     # while stopped: acknowledged, not applied (stays stopped until ENABLE)
                self.command_rpm = req.rpm
        elif c == Cmd.ENABLE:
            self.enabled = True
            self.command_rpm = 0.0
            self.stop_reason = StopReason.NONE
            self.watchdog_tripped = self.fault = self.overspeed = False
            self._stall_since = None
        elif c == Cmd.DISABLE:
            if self.enabled:
                self._stop(StopReason.DISABLE)
        elif c == Cmd.STOP:
            if req.reason not in [int(r) for r in GATEWAY_STOP_REASONS]:
                return NakCode.OUT_OF_RANGE
            if self.enabled:
                self._stop(StopReason(req.reason))
        elif c == Cmd.SET_WATCHDOG:
            if not WATCHDOG_MS_MIN <= req.watchdog_ms <= WATCHDOG_MS_MAX:
                return NakCode.OUT_OF_RANGE
            self.watchdog_ms = req.watchdog_ms
        # PING, READ_STATUS: nothing to do (they feed the watchdog)
        return None


# ---------------------------------------------------------------------------------------- motor
class SimpleMotor:
    """First-order motor (time constant ``tau_s``) evaluated lazily on a monotonic clock.

    A stand-in for the simulator's plant: ``set_command(rpm)``, ``enable(bool)``, ``speed_rpm``,
    ``stalled`` (set it to simulate a blocked take-up: the speed then decays to 0)."""

    def __init__(self, tau_s: float = 0.05, clock=time.monotonic):
        self.tau_s = tau_s
        self.clock = clock
        self._cmd = 0.0
        self._enabled = False
        self._speed = 0.0
        self._t = clock()
        self.stalled = False

    def _advance(self) -> None:
        now = self.clock()
        dt = max(0.0, now - self._t)
        self._t = now
        target = self._cmd if (self._enabled and not self.stalled) else 0.0
        self._speed = target + (self._speed - target) * math.exp(-dt / self.tau_s)

    def set_command(self, rpm: float) -> None:
        self._advance()
        self._cmd = float(rpm)

    def enable(self, on: bool) -> None:
        self._advance()
        self._enabled = bool(on)

    @property
    def speed_rpm(self) -> float:
        self._advance()
        return self._speed

    @property
    def enabled(self) -> bool:
        return self._enabled

    @property
    def command_rpm(self) -> float:
        return self._cmd


# ---------------------------------------------------------------------------------------- device
@dataclass
class Stm32Faults:
    silent: bool = False            # receives nothing, answers nothing (the watchdog still runs)
    drop_next_replies: int = 0      # act on the next n commands but lose their replies
    corrupt_crc: bool = False       # replies with a broken CRC (the gateway must not accept them)
    extra_delay_s: float = 0.0      # added before every reply


class VirtualStm32:
    """A firmware + motor served on a pty.

    Both call forms work: ``VirtualStm32(firmware_or_params, motor, link_path)`` (the simulator's:
    a :class:`Stm32Firmware`, a dict of its keyword arguments, a number = watchdog_s, an object
    with ``watchdog_s`` such as the stm32 config, or None) and ``VirtualStm32(motor, link_path,
    watchdog_s=0.2, baud=115200)``.
    """

    def __init__(self, *args, firmware=None, motor=None, link_path: str | None = None,
                 watchdog_s: float = 0.2, baud: int = DEFAULT_BAUD, processing_s: float = 0.0002,
                 tick_s: float = 0.005, gap_s: float = 0.005, link: Any = None,
                 on_drive: Callable[[dict[str, Any]], None] | None = None):
        rest = list(args)
        if rest and not hasattr(rest[0], "set_command"):
            firmware = rest.pop(0)
        if rest:
            motor = rest.pop(0)
        if rest:
            link_path = rest.pop(0)
        if rest:
            raise TypeError("VirtualStm32: too many positional arguments")
        if motor is None:
            raise TypeError("VirtualStm32: a motor (set_command, enable, speed_rpm, stalled) is required")
        self.firmware = self._make_firmware(firmware, watchdog_s)
        self.motor = motor
        # a pty by default; any link with PtyLink's interface (drivers.sim.loopback) may be given
        self.link = link if link is not None else PtyLink(link_path)
        self.baud = int(baud)
        self.processing_s = processing_s
        self.tick_s = tick_s
        self.gap_s = gap_s
        self.faults = Stm32Faults()
        self.parser = FrameParser()
        self.counters = {"rx_frames": 0, "replies": 0, "dropped_replies": 0, "ignored_bytes": 0,
                         "corrupted_replies": 0}
        self._loop: asyncio.AbstractEventLoop | None = None  # set by start()
        self._tick_task: asyncio.Task | None = None
        self._reader_fd: int | None = None
        self._rx_free = 0.0          # when the receive line is free again (frames arrive in turn)
        self._tx_free = 0.0
        self._last_rx = 0.0
        self._last_look: float | None = None   # when the pty was last read (empty or not)
        # what the motor was last told: (enabled, rpm)
        self._out: tuple[bool | None, float | None] = (None, None)
        self._handles: set[asyncio.TimerHandle] = set()
        #: called with a record whenever the drive is enabled or stops (see ``_apply``)
        self.on_drive = on_drive
        self.drive_log: list[dict[str, Any]] = []

    @staticmethod
    def _make_firmware(spec, watchdog_s: float) -> Stm32Firmware:
        if isinstance(spec, Stm32Firmware):
            return spec
        if spec is None:
            return Stm32Firmware(watchdog_s)
        if isinstance(spec, dict):
            kw = dict(spec)
            return Stm32Firmware(kw.pop("watchdog_s", watchdog_s), **kw)
        if isinstance(spec, (int, float)):
            return Stm32Firmware(float(spec))
        wd = getattr(spec, "watchdog_s", None)
        return Stm32Firmware(float(wd) if wd is not None else watchdog_s)

    # ------------------------------------------------------------------ lifecycle
    @property
    def device(self) -> str | None:
        return self.link.device

    @property
    def _running_loop(self) -> asyncio.AbstractEventLoop:
        loop = self._loop
        if loop is None:
            raise RuntimeError("VirtualStm32 is not started")
        return loop

    async def start(self, own_ticker: bool = True) -> str:
        """Open the pty and start. ``own_ticker=False``: the caller calls :meth:`tick` every
        ``tick_s`` itself (a simulator hosting many devices ticks them all from one task)."""
        self._loop = asyncio.get_running_loop()
        self._apply()
        dev = self.link.open()
        self._attach()
        if own_ticker:
            self._tick_task = self._loop.create_task(self._ticker())
        return dev

    async def stop(self) -> None:
        self._detach()
        for h in list(self._handles):
            h.cancel()
        self._handles.clear()
        if self._tick_task is not None:
            self._tick_task.cancel()
            try:
                await self._tick_task
            except asyncio.CancelledError:
                pass
            self._tick_task = None
        self.link.close()

    def vanish(self) -> None:
        """The USB adapter is pulled: the device node disappears (the firmware runs on)."""
        self._detach()
        self.link.vanish()
        self.parser.reset()

    def restore(self) -> str:
        dev = self.link.restore()
        self._attach()
        return dev

    def _attach(self) -> None:
        if self._loop is not None and self.link.master is not None and self._reader_fd is None:
            self._reader_fd = self.link.master
            self._loop.add_reader(self._reader_fd, self._on_readable)

    def _detach(self) -> None:
        if self._loop is not None and self._reader_fd is not None:
            self._loop.remove_reader(self._reader_fd)
        self._reader_fd = None

    # ------------------------------------------------------------------ motor
    def _apply(self) -> None:
        fw = self.firmware
        en, rpm = fw.drive_enabled, fw.drive_rpm
        if en != self._out[0]:
            self.motor.enable(en)
            if self._out[0] is not None:
                self._report_drive(en)
        if rpm != self._out[1]:
            self.motor.set_command(rpm)
        self._out = (en, rpm)

    def _report_drive(self, enabled: bool) -> None:
        """The drive was enabled or stopped: one log line and record (a stop by the watchdog
        says how long the line had been silent: the gateway's silence, as the firmware saw it)."""
        fw = self.firmware
        now = self._loop.time() if self._loop is not None else time.monotonic()
        rec: dict[str, Any] = {"enabled": enabled, "reason": fw.stop_reason.name,
                               "watchdog_ms": fw.watchdog_ms}
        if not enabled and fw.last_valid_rx is not None:
            rec["silent_s"] = round(now - fw.last_valid_rx, 4)
        if enabled:
            log.info("stm32: drive enabled (watchdog %d ms)", fw.watchdog_ms)
        elif fw.stop_reason == StopReason.WATCHDOG:
            log.warning("stm32: drive stopped: WATCHDOG (no valid command for %.3f s; watchdog "
                        "%d ms)", rec.get("silent_s", math.nan), fw.watchdog_ms)
        else:
            log.info("stm32: drive stopped: %s", fw.stop_reason.name)
        if len(self.drive_log) < 1000:
            self.drive_log.append(rec)
        if self.on_drive is not None:
            try:
                self.on_drive(rec)
            except Exception:  # a broken observer must not stop the device
                log.exception("stm32: on_drive")

    def _measure(self, now: float) -> None:
        try:
            self.firmware.measure(float(self.motor.speed_rpm), bool(getattr(self.motor, "stalled", False)), now)
        except Exception:  # a broken motor model must not stop the device
            pass

    async def _ticker(self) -> None:
        while True:
            await asyncio.sleep(self.tick_s)
            self.tick()

    def tick(self) -> None:
        """One firmware tick: watchdog, trips, the motor, idle-gap framing."""
        loop = self._loop
        if loop is not None:
            # a real MCU takes each byte in its UART interrupt as it arrives: credit the frames
            # already waiting in the pty before judging the watchdog (a busy host can delay this
            # process; that must not look like a silent gateway)
            self._on_readable()
            now = loop.time()
            self._measure(now)
            self.firmware.tick(now)
            self._apply()
            if self.parser.pending and now - self._last_rx >= self.gap_s:
                # an idle gap ends any partial frame: rescan what is left
                for fr in self.parser.flush():
                    self._schedule(fr.encode(), now)
                self._sync_rx_errors()

    # ------------------------------------------------------------------ serial line
    def _sync_rx_errors(self) -> None:
        n = self.parser.crc_errors
        if n:
            self.firmware.count_rx_error(n)
            self.parser.crc_errors = 0

    def _on_readable(self) -> None:
        data = self.link.read_available()
        now = self._running_loop.time()
        look, self._last_look = self._last_look, now
        if not data:
            return
        self._last_rx = now
        if self.faults.silent:
            self.counters["ignored_bytes"] += len(data)
            self.parser.reset()
            return
        frames = self.parser.feed(data)
        self._sync_rx_errors()
        # A real MCU takes each byte in its UART interrupt as it arrives. This process reads the
        # pty when the host lets it: after a stall of its own (a loaded machine), frames that came
        # one by one are read at once. They arrived after the previous look, so they are spread
        # over the time since then, the last one now: the watchdog judges the gateway's silence
        # on the wire, not this process' (a 0.3 s stall of the simulator used to trip it).
        n = len(frames)
        first = look if look is not None and n > 1 and now - look > STALL_SPREAD_S else now
        for i, fr in enumerate(frames):
            self._schedule(fr.encode(), first + (now - first) * (i + 1) / n)

    def _call_at(self, when: float, fn, *args) -> None:
        h: asyncio.TimerHandle | None = None

        def run():
            self._handles.discard(h)
            fn(*args)

        h = self._running_loop.call_at(when, run)
        self._handles.add(h)

    def _schedule(self, raw: bytes, arrived: float) -> None:
        """The client wrote the frame at ``arrived``: it is on the wire for its length at the baud,
        the firmware takes ``processing_s``, the reply is on the wire for its length. The firmware
        acts at once with the logical time the frame is complete (one timer per exchange: the
        pty reply then leaves at the right time, within the loop's ~1 ms timer granularity)."""
        self.counters["rx_frames"] += 1
        done = max(arrived, self._rx_free) + wire_time_s(len(raw), self.baud)
        self._rx_free = done
        now = done + self.processing_s
        self._measure(self._running_loop.time())
        reply = self.firmware.handle(raw, now)
        self._apply()
        if reply is None:
            return
        if self.faults.drop_next_replies > 0:
            self.faults.drop_next_replies -= 1
            self.counters["dropped_replies"] += 1
            return
        if self.faults.corrupt_crc:
            reply = reply[:-1] + bytes(((reply[-1] ^ 0x5A) & 0xFF,))
            self.counters["corrupted_replies"] += 1
        start = max(now, self._tx_free)
        sent = start + wire_time_s(len(reply), self.baud) + max(0.0, self.faults.extra_delay_s)
        self._tx_free = sent
        self._call_at(sent, self._send, reply)

    def _send(self, reply: bytes) -> None:
        if self.link.write(reply):
            self.counters["replies"] += 1

    def snapshot(self) -> dict[str, Any]:
        fw = self.firmware
        return {"device": self.device, "status": fw.status().as_dict(),
                "motor_rpm": float(self.motor.speed_rpm), "firmware": dict(fw.counters),
                "counters": dict(self.counters),
                "faults": {"silent": self.faults.silent, "corrupt_crc": self.faults.corrupt_crc,
                           "drop_next_replies": self.faults.drop_next_replies,
                           "extra_delay_s": self.faults.extra_delay_s}}


# ---------------------------------------------------------------------------------------- __main__
def _control(dev: VirtualStm32, line: str) -> dict[str, Any]:
    """One stdin control line: ``silent 1|0``, ``corrupt 1|0``, ``drop N``, ``delay S``,
    ``stall 1|0``, ``vanish``, ``restore``, ``status``."""
    parts = line.split()
    if not parts:
        return {"ok": False, "error": "empty line"}
    cmd, arg = parts[0], (parts[1] if len(parts) > 1 else "")
    on = arg not in ("0", "off", "false")
    if cmd == "silent":
        dev.faults.silent = on
    elif cmd == "corrupt":
        dev.faults.corrupt_crc = on
    elif cmd == "drop":
        dev.faults.drop_next_replies = int(arg or 1)
    elif cmd == "delay":
        dev.faults.extra_delay_s = float(arg or 0)
    elif cmd == "stall":
        dev.motor.stalled = on
    elif cmd == "vanish":
        dev.vanish()
    elif cmd == "restore":
        dev.restore()
    elif cmd != "status":
        return {"ok": False, "error": f"unknown control {cmd!r}; allowed: silent, corrupt, drop, "
                                      "delay, stall, vanish, restore, status"}
    return {"ok": True, **dev.snapshot()}


async def _serve(args) -> int:
    import signal
    import sys

    loop = asyncio.get_running_loop()
    dev = VirtualStm32(SimpleMotor(tau_s=args.tau_s), args.link, watchdog_s=args.watchdog_s,
                       baud=args.baud)
    done = asyncio.Event()
    for s in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(s, done.set)
    path = await dev.start()
    print(f"stm32: {path}", flush=True)

    def on_stdin():
        line = sys.stdin.readline()
        if not line:
            loop.remove_reader(sys.stdin.fileno())
            return
        try:
            out = _control(dev, line.strip())
        except Exception as e:  # bad control input: say so, keep serving
            out = {"ok": False, "error": str(e)}
        print("ctl: " + json.dumps(out), flush=True)

    if not sys.stdin.closed:
        loop.add_reader(sys.stdin.fileno(), on_stdin)
    try:
        await done.wait()
    finally:
        try:
            loop.remove_reader(sys.stdin.fileno())
        except Exception:
            pass
        await dev.stop()
    return 0


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m drivers.sim.twin_stm32",
                                 description="Serve a virtual STM32 (SimpleMotor) on a pty.")
    ap.add_argument("--link", default=None, help="stable symlink to create for the pty")
    ap.add_argument("--watchdog-s", type=float, default=0.2)
    ap.add_argument("--baud", type=int, default=DEFAULT_BAUD)
    ap.add_argument("--tau-s", type=float, default=0.05, help="motor time constant")
    args = ap.parse_args(argv)
    return asyncio.run(_serve(args))


if __name__ == "__main__":
    raise SystemExit(main())
