"""Fault injection for the in-process simulated devices and the world.

:class:`FaultInjector` wraps the four in-process devices (same interfaces) and, on
``inject(name)``, makes them misbehave the way the real ones do:

====================  ======================================================================
``ft_packet_loss``    three F/T records lost in a row (the last one is seen again)
``ft_delay``          F/T delivery paused for 30 ms, then resumes (a delayed burst)
``ft_stream_stop``    the F/T stream stops for good
``ft_nan``            a NaN in the F/T force
``ft_saturation``     an F/T channel at the end of its range (status bit)
``ft_offset_drift``   the force offset drifts 1 N/s along the sensor's x axis
``arm_disconnect``    the Meca500 link drops (read raises ``DeviceFault``)
``arm_error``         the arm latches error 1007 (joint limit) and refuses motion
``can_silence``       the EPOS4 stops answering SYNC (no new TxPDO)
``emcy``              the EPOS4 sends EMCY 0x2310 (overcurrent) and goes to FAULT
``bus_off``           the CAN controller goes bus-off (read raises ``DeviceFault``)
``file_binding``      debris packs the flutes: +30 mNm of resistance at once
``patient_jerk``      the patient jerks the tooth 5 mm sideways at 100 mm/s
``handpiece_disabled``  the drive disables its output silently (no EMCY; statusword says so)
``handpiece_power_loss``  the motor loses its power: it coasts down, the drive still says
                      enabled (no EMCY)
``file_fracture``     the file breaks in the canal (nothing tells the controller: no oracle)
``foreign_spin``      a second master on the CAN bus commands the drive to 150 rpm
``command_error``     the arm's link refuses every command (reads still answer)
``arm_half_open``     the arm's link goes half-open: no new joint samples, and a stop is
                      never acknowledged (the driver waits 2 s for it)
``estop``             the operator presses the emergency stop (aux input)
====================  ======================================================================
"""

from __future__ import annotations

import asyncio
import dataclasses
import math

from dentibot.errors import DeviceFault
from dentibot.io.interfaces import WRENCH_SATURATED, Wrench
from dentibot.sim.arm import ERROR_JOINT_LIMIT
from dentibot.sim.patient import axis_angle_matrix
from dentibot.sim.world import World

FAULTS = ("ft_packet_loss", "ft_delay", "ft_stream_stop", "ft_nan", "ft_saturation",
          "ft_offset_drift", "arm_disconnect", "arm_error", "can_silence", "emcy", "bus_off",
          "file_binding", "patient_jerk", "handpiece_disabled", "handpiece_power_loss",
          "file_fracture", "foreign_spin", "command_error", "arm_half_open", "estop")
#: How long a half-open arm link keeps a stop command waiting for its acknowledgement (s).
HALF_OPEN_STOP_S = 2.0


class Jerk:
    """The phantom's motion with a jerk added from ``t0``: ``mm`` along the unit vector
    ``direction`` (base frame) at ``mm_s``, then held; with ``deg``, the patient also turns
    by ``deg`` about the unit ``axis`` through ``centre_mm`` (base frame: the jaw's hinge,
    say), in step with the translation (a jerk of ``mm`` = 0 turns at ``deg_s``)."""

    def __init__(self, base, t0: float, direction=(1.0, 0.0, 0.0), mm: float = 5.0,
                 mm_s: float = 100.0, deg: float = 0.0, axis=(1.0, 0.0, 0.0),
                 centre_mm=(0.0, 0.0, 0.0), deg_s: float = 100.0) -> None:
        self.base, self.t0, self.d, self.mm, self.v = base, t0, tuple(direction), mm, mm_s
        self.deg, self.centre = deg, tuple(float(x) for x in centre_mm)
        n = math.sqrt(sum(float(x) ** 2 for x in axis))
        self.axis = tuple(float(x) / n for x in axis)
        self.duration_s = mm / mm_s if mm > 0 else (abs(deg) / deg_s if deg else 0.0)
        if deg:
            self.rotation_at = self._rotation_at
        elif hasattr(base, "rotation_at"):    # a turning patient keeps turning under the jerk
            self.rotation_at = base.rotation_at

    def _progress(self, t: float) -> float:
        if self.duration_s <= 0.0:
            return 1.0 if t >= self.t0 else 0.0
        return min(max((t - self.t0) / self.duration_s, 0.0), 1.0)

    def offset_mm(self, t: float):
        b = self.base.offset_mm(t)
        s = self.mm * self._progress(t)
        return (b[0] + s * self.d[0], b[1] + s * self.d[1], b[2] + s * self.d[2])

    def _rotation_at(self, t: float):
        """(R, centre): the turn so far about ``axis``."""
        return axis_angle_matrix(self.axis, math.radians(self.deg * self._progress(t))), \
            self.centre


class _Wrapped:
    def __init__(self, inner, fi: FaultInjector) -> None:
        self.inner = inner
        self.fi = fi

    def __getattr__(self, name):
        return getattr(self.inner, name)


class _FaultyFT(_Wrapped):
    async def read(self) -> Wrench:
        fi = self.fi
        w = await self.inner.read()
        held = fi.held_ft
        if fi.active("ft_stream_stop") and held is not None:
            return held
        if fi.ft_hold_ticks > 0 and held is not None:
            fi.ft_hold_ticks -= 1
            return held
        if fi.active("ft_nan"):
            w = dataclasses.replace(w, force_n=(math.nan, *w.force_n[1:]))
        if fi.active("ft_saturation"):
            w = dataclasses.replace(w, status=w.status | WRENCH_SATURATED)
        if fi.active("ft_offset_drift"):
            dx = 1.0 * (fi.world.t - fi.t0)
            w = dataclasses.replace(w, force_n=(w.force_n[0] + dx, *w.force_n[1:]))
        fi.held_ft = w
        return w


class _FaultyArm(_Wrapped):
    async def read(self):
        fi = self.fi
        if fi.active("arm_disconnect"):
            raise DeviceFault("meca500", "control link lost (connection reset by peer)")
        if fi.active("arm_half_open") and fi.held_arm is not None:
            return fi.held_arm
        fi.held_arm = await self.inner.read()
        return fi.held_arm

    async def move_joints_vel(self, qdot_deg_s) -> None:
        if self.fi.active("arm_disconnect"):
            raise DeviceFault("meca500", "control link lost (connection reset by peer)")
        if self.fi.active("command_error"):
            raise DeviceFault("meca500", "command not delivered (socket write failed)")
        if self.fi.active("arm_half_open"):
            return                       # written into a link nobody reads
        await self.inner.move_joints_vel(qdot_deg_s)

    async def stop(self) -> None:
        if self.fi.active("arm_half_open"):
            await asyncio.sleep(HALF_OPEN_STOP_S)
            raise DeviceFault("meca500", f"no answer to the stop within {HALF_OPEN_STOP_S} s")
        await self.inner.stop()


class _FaultyMotor(_Wrapped):
    async def read(self):
        fi = self.fi
        if fi.active("bus_off"):
            raise DeviceFault("epos4", "CAN controller bus-off (too many transmit errors)")
        m = await self.inner.read()
        if fi.active("can_silence") and fi.held_motor is not None:
            return fi.held_motor
        if fi.active("emcy"):
            m = dataclasses.replace(m, enabled=False,
                                    fault="EMCY 0x2310 overcurrent, drive in FAULT")
        fi.held_motor = m
        return m


class FaultInjector:
    """Wraps the in-process devices of ``world``; ``inject(name)`` starts a fault now."""

    def __init__(self, world: World, arm, ft, motor, aux) -> None:
        self.world = world
        self.arm = _FaultyArm(arm, self)
        self.ft = _FaultyFT(ft, self)
        self.motor = _FaultyMotor(motor, self)
        self.aux = aux
        self.faults: set[str] = set()
        self.t0 = 0.0
        self.held_ft: Wrench | None = None
        self.held_motor = None
        self.held_arm = None
        self.ft_hold_ticks = 0

    def active(self, name: str) -> bool:
        return name in self.faults

    def inject(self, name: str) -> None:
        if name not in FAULTS:
            raise ValueError(f"unknown fault {name!r}; one of {', '.join(FAULTS)}")
        w = self.world
        self.t0 = w.t
        if name == "ft_packet_loss":
            self.ft_hold_ticks = 3
        elif name == "ft_delay":
            self.ft_hold_ticks = round(0.030 / w.ts)
        elif name == "arm_error":
            w.arm.error_code = ERROR_JOINT_LIMIT
            w.arm.stop()
        elif name == "emcy":
            w.handpiece.stop()           # the drive disables its output stage
        elif name == "file_binding":
            w.canal.debris_mm3 += 1.0
        elif name == "patient_jerk":
            w.motion = Jerk(w.motion, w.t)
        elif name == "handpiece_disabled":
            w.handpiece.enabled = False
            w.handpiece.stop()
        elif name == "handpiece_power_loss":
            w.handpiece.stop()           # coasts down; the drive still reports enabled
        elif name == "file_fracture":
            w.fracture_now("injected")
        elif name == "foreign_spin":
            w.handpiece.set_velocity(150.0)
        elif name == "estop":
            w.estop = True
        self.faults.add(name)
