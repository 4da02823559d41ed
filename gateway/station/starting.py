"""The start of a test on a station (METHOD.md §3a), beside its session: a state machine.

A :class:`StartAttempt` runs before slot 0 and records nothing. It wraps the method's pure
§3a sequence (:class:`gateway.core.method.start.StartSequence`) with what only a station knows: the
zero check judges the yarn at rest through an open port, so it first waits (at most
``start_timeout``) for the meter's port and for the take-up to have run down; then the spin-up
runs with the loop closed (its controller goes on into the :class:`~.session.TestSession`).

Pure: numbers in, numbers out (no I/O, no clock, no asyncio). The station feeds one
:meth:`StartAttempt.slot` per slot and carries out what :meth:`StartAttempt.next_step` says:

    WAIT          nothing to do;
    ENABLE_MOTOR  enable the take-up (the spin-up begins);
    SETTLED       the next slot is the test's slot 0 (``seq.sidecar()`` for the sidecar);
    FAILED        stop the take-up, ``start_failed`` with the reason, idle again.
"""
from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Any

from ..core.control import Controller, ControlParams
from ..core.method.params import MethodParams
from ..core.method.start import FAILED, SETTLED, SPIN_UP, ZERO_CHECK, StartSequence
from .session import TestPlan, plan_params

__all__ = ["REST_RPM", "REST_S", "StartAttempt", "StartStep"]

#: the zero check (METHOD.md §3a) measures the yarn at rest: it begins once the take-up has been
#: commanded off for REST_S and the STM32 reports no more than REST_RPM (a test stopped a moment
#: ago, a gateway restarted after a crash: the yarn is still under tension while the take-up
#: runs down)
REST_S = 1.0
REST_RPM = 1.0


class StartStep(enum.Enum):
    WAIT = "wait"
    ENABLE_MOTOR = "enable_motor"
    SETTLED = "settled"
    FAILED = "failed"


@dataclass
class StartAttempt:
    """A start in progress (§3a): nothing of it is recorded; the station's state is STARTING."""
    plan: TestPlan
    params: MethodParams
    seq: StartSequence
    controller: Controller
    source: str
    motor_enabled: bool = False      # the take-up was enabled for the spin-up
    wait_slots: int = 0              # slots waited (meter port, take-up at rest) before the zero check
    zero_begun: bool = False         # the zero check's window has begun
    reason: str | None = None        # a failure found by the station (not by the sequence)

    @classmethod
    def begin(cls, plan: TestPlan, method_values: dict[str, Any], control: ControlParams,
              station_id: str, source: str) -> StartAttempt:
        p = plan_params(plan, method_values, station_id)
        return cls(plan=plan, params=p, seq=StartSequence(p),
                   controller=Controller(control, plan.t_set), source=source)

    @property
    def motor_on(self) -> bool:
        """The take-up runs (enabled for the spin-up, and the sequence wants it on)."""
        return self.motor_enabled and bool(self.seq.motor_on)

    @property
    def waiting_for_rest(self) -> bool:
        """The zero check's window has not begun (the station reads the STM32's status meanwhile)."""
        return not self.zero_begun

    def slot(self, present: bool, t1: float, t2: float, *, port_open: bool, speed_act: float,
             speed_cmd: float, off_for_s: float) -> tuple[float, bool, float]:
        """One slot: the meter's reading, whether its port is open, the take-up's reported speed
        (NaN: unknown), the speed last commanded and how long the take-up has been commanded off.
        Returns (y, saturated, speed command) of the controller (y NaN while the motor is off)."""
        seq = self.seq
        if seq.phase == ZERO_CHECK:
            if not self.zero_begun and self.reason is None:
                self.wait_slots += 1
                moving = math.isfinite(speed_act) and abs(speed_act) > REST_RPM
                if port_open and not moving and off_for_s >= REST_S:
                    self.zero_begun = True
                else:
                    if self.wait_slots * self.params.ts >= self.params.start_timeout:
                        t = f"{self.params.start_timeout:g} s"
                        self.reason = (f"zero check not possible: the meter's port is not open after {t}"
                                       if not port_open else f"zero check not possible: the take-up "
                                       f"still turns after {t} ({speed_act:.0f} rpm)")
                    return math.nan, False, 0.0
            seq.zero_slot(present, t1, t2)
            return math.nan, False, 0.0
        if seq.phase != SPIN_UP:
            return math.nan, False, speed_cmd
        speed = speed_act if math.isfinite(speed_act) else speed_cmd
        c = self.controller.step((t1 + t2) / 2.0 if present else None, speed)
        seq.spin_slot(present, t1, t2, c.y)
        return c.y, c.saturated, c.u

    def next_step(self) -> tuple[StartStep, str | None]:
        """What the station does after the slot (and at the start: ENABLE_MOTOR when there is no
        zero check); with FAILED, the reason."""
        if self.reason is not None:
            return StartStep.FAILED, self.reason
        ph = self.seq.phase
        if ph == SPIN_UP and not self.motor_enabled:
            return StartStep.ENABLE_MOTOR, None
        if ph == SETTLED:
            return StartStep.SETTLED, None
        if ph == FAILED:
            return StartStep.FAILED, self.seq.reason or "start failed"
        return StartStep.WAIT, None

    def failure_data(self, ts: float) -> dict[str, Any]:
        """The figures of a failed start for its ``start_failed`` event."""
        extra: dict[str, Any] = {"zero_offsets_n": self.seq.offsets} if self.seq.offsets else {}
        return {"sample_id": self.plan.sample_id, "t_set": self.plan.t_set,
                "spin_up_s": self.seq.spin_slots * ts, **extra}
