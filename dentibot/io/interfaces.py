"""Sample types and device interfaces shared by the real drivers and the simulators.

Every sample carries ``t`` (s, on the monotonic clock of its source) and ``seq`` (a sequence
number that grows by one per new sample), so that the control task can detect stale or missing
samples. Units: lengths mm, angles deg, forces N, sensor torques N*m, speeds at the file rpm.

The interfaces are ``typing.Protocol`` classes with async methods (real drivers are asyncio);
they are ``runtime_checkable`` so tests can check a device against them with ``isinstance``
(which only checks that the methods exist).

:class:`ConnectTimeout` is the typed error every driver raises when a device does not complete
its connection in time (a peer that accepts the TCP connection and then says nothing).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from dentibot.errors import DeviceFault

Vec3 = tuple[float, float, float]
Vec6 = tuple[float, float, float, float, float, float]


@dataclass(frozen=True, slots=True)
class JointState:
    """Arm joint positions ``q_deg`` (deg) and velocities ``qdot_deg_s`` (deg/s), J1..J6."""

    t: float
    seq: int
    q_deg: Vec6
    qdot_deg_s: Vec6


@dataclass(frozen=True, slots=True)
class Wrench:
    """F/T sensor reading in the sensor frame {S}: ``force_n`` (N), ``torque_nm`` (N*m).

    ``status`` is a bit field; bit 0 (:data:`WRENCH_SATURATED`) means a channel is saturated.
    """

    t: float
    seq: int
    force_n: Vec3
    torque_nm: Vec3
    status: int = 0

    def as_array(self) -> np.ndarray:
        """``[fx, fy, fz, tx, ty, tz]`` (N, N*m) as a float array of shape (6,)."""
        return np.array(self.force_n + self.torque_nm, dtype=float)


#: ``Wrench.status`` bit: at least one channel is at the end of its range.
WRENCH_SATURATED = 0x1


@dataclass(frozen=True, slots=True)
class MotorState:
    """Handpiece motor, expressed at the file (after the gear).

    ``velocity_rpm`` and ``position_deg`` are at the file; ``current_a`` is the motor current
    (A); ``fault`` is a human-readable fault text or None.
    """

    t: float
    seq: int
    velocity_rpm: float
    position_deg: float
    current_a: float
    enabled: bool
    fault: str | None = None


@dataclass(frozen=True, slots=True)
class AuxState:
    """Auxiliary I/O: foot pedal, emergency stop, patient platform position (mm)."""

    t: float
    seq: int
    pedal: bool
    estop: bool
    platform_mm: Vec3


class ConnectTimeout(DeviceFault):
    """A device did not complete its connection within its bound: nothing answered at
    ``address`` ("host:port") what the driver was ``waiting_for`` within ``timeout_s``.

    Every driver bounds its connection (TCP connect, greeting, identification, first answer):
    a peer that accepts the TCP connection and then says nothing is a fault, never a hang."""

    def __init__(self, device: str, address: str, waiting_for: str, timeout_s: float) -> None:
        self.address = address
        self.waiting_for = waiting_for
        self.timeout_s = float(timeout_s)
        super().__init__(device, f"{address}: no {waiting_for} within {timeout_s:g} s")


@runtime_checkable
class Arm(Protocol):
    """A 6-DoF arm driven in joint space (Meca500: MoveJointsVel / MoveJoints)."""

    async def read(self) -> JointState:
        """Newest joint state."""
        ...

    async def move_joints_vel(self, qdot_deg_s) -> None:
        """Joint velocities (deg/s); they time out (SetVelTimeout) unless repeated."""
        ...

    async def move_joints(self, q_deg) -> None:
        """Move to joint positions (deg)."""
        ...

    async def stop(self) -> None:
        """Decelerate to rest and drop pending motion."""
        ...

    async def recover(self) -> None:
        """On the operator's reset after a fault: back to ready (the error reset, motion resumed with an empty queue, the link reconnected if it dropped); never starts
        motion. Raises a :class:`~dentibot.errors.DeviceFault` when it cannot."""
        ...


@runtime_checkable
class ForceSensor(Protocol):
    """A 6-axis force/torque sensor (ATI Mini40), readings in its frame {S}."""

    async def read(self) -> Wrench:
        """Newest wrench (N, N*m)."""
        ...

    async def bias(self) -> None:
        """Tare: the current load reads zero from now on."""
        ...


@runtime_checkable
class Handpiece(Protocol):
    """The motorised handpiece turning the file; speeds and angles at the file.

    A drive on a bus with a cyclic exchange of its own (the EPOS4's SYNC) may also offer
    ``cycle_soon()``: the real-time control task calls it after each tick, so that the
    tick's commands go out in that tick's cycle."""

    async def read(self) -> MotorState:
        """Newest motor state."""
        ...

    async def set_velocity(self, rpm: float) -> None:
        """Turn the file at ``rpm`` (positive = cutting direction, clockwise)."""
        ...

    async def move_relative(self, deg: float) -> None:
        """Turn the file by ``deg`` (e.g. -90 for the reversal), then hold."""
        ...

    async def stop(self) -> None:
        """Stop turning."""
        ...

    async def recover(self) -> None:
        """On the operator's reset after a fault: back to ready (a latched drive fault reset and the output enabled); never starts
        motion. Raises a :class:`~dentibot.errors.DeviceFault` when it cannot."""
        ...

    async def set_current_limit(self, amps: float) -> None:
        """Limit the motor current (A), hence the torque the file can be given (the drive's
        own bound, set before the first tick)."""
        ...


@runtime_checkable
class AuxIO(Protocol):
    """Pedal, emergency stop, indicators and the patient platform."""

    async def read(self) -> AuxState:
        """Newest auxiliary state."""
        ...

    async def recover(self) -> None:
        """On the operator's reset after a fault: back to ready (a latched watchdog fault acknowledged); never starts
        motion. Raises a :class:`~dentibot.errors.DeviceFault` when it cannot."""
        ...

    async def set_indicator(self, name: str, on: bool) -> None:
        """Switch an indicator (lamp, buzzer) on or off."""
        ...

    async def set_platform(self, mm) -> None:
        """Command the platform position (x, y, z mm)."""
        ...


#: ``StringSample.status`` values, one per string: the length is valid ...
STRING_OK = "ok"
#: ... no new reading from its encoder within the staleness bound (the last one is kept);
STRING_STALE = "stale"
#: ... shorter than the slack minimum (a broken, unhooked or fully retracted wire);
STRING_SLACK = "slack"
#: ... beyond the encoder's measuring range;
STRING_OVER_RANGE = "over_range"
#: ... no reading yet (the length is NaN);
STRING_NO_DATA = "no_data"
#: ... its encoder is not operational (heartbeat lost, NMT state, emergency message).
STRING_FAULT = "fault"


@dataclass(frozen=True, slots=True)
class StringSample:
    """The patient tracker's string lengths, one per draw-wire encoder (string 1 first).

    ``lengths_mm`` (mm; NaN before a string's first reading), ``counts`` (the encoders' raw
    position values, measuring units), ``status`` (one of the ``STRING_*`` values per
    string). ``seq`` grows by one per new set of readings."""

    t: float
    seq: int
    lengths_mm: tuple[float, ...]
    counts: tuple[int, ...]
    status: tuple[str, ...]

    @property
    def usable(self) -> tuple[bool, ...]:
        """Per string: the length may enter the pose (status ``STRING_OK``)."""
        return tuple(s == STRING_OK for s in self.status)

    @property
    def ok(self) -> bool:
        return all(s == STRING_OK for s in self.status)


@runtime_checkable
class PatientTracker(Protocol):
    """The string-based patient tracking module: string lengths between the handpiece mount
    and a clamp on the patient's teeth (the pose follows from ``dentibot.control.strings``)."""

    async def read(self) -> StringSample:
        """Newest string lengths, without waiting; per-string problems are in ``status``."""
        ...

    async def recover(self) -> None:
        """On the operator's reset after a fault: the encoders back to operational. Raises a
        :class:`~dentibot.errors.DeviceFault` when it cannot."""
        ...
