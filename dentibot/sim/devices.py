"""In-process simulated devices implementing the :mod:`dentibot.io` protocols over a World.

Lock-step: whoever owns the World calls ``world.step()`` once per tick; ``read()`` returns the
newest sample, stamped with the world time and ``seq = world.steps`` (one sample per step).
"""

from __future__ import annotations

from dentibot.errors import DeviceFault
from dentibot.io.interfaces import AuxState, JointState, MotorState, Wrench
from dentibot.sim.world import World


class SimArm:
    """Meca500 over a World (implements ``dentibot.io.Arm``)."""

    def __init__(self, world: World) -> None:
        self.world = world

    async def read(self) -> JointState:
        w = self.world
        q, qd = w.arm.reading()
        return JointState(w.t, w.steps, q, qd)

    async def move_joints_vel(self, qdot_deg_s) -> None:
        if not self.world.arm.command_velocity(qdot_deg_s, self.world.t):
            raise DeviceFault("meca500", f"in error {self.world.arm.error_code}; reset first")

    async def move_joints(self, q_deg) -> None:
        if not self.world.arm.command_position(q_deg):
            raise DeviceFault("meca500", f"in error {self.world.arm.error_code}; reset first")

    async def stop(self) -> None:
        self.world.arm.stop()

    @property
    def error_code(self) -> int:
        """Latched Meca500 error code (0: none; 1007 joint limit, 1012 singularity)."""
        return self.world.arm.error_code

    async def reset_error(self) -> None:
        self.world.arm.reset_error()

    async def recover(self) -> None:
        self.world.arm.reset_error()


class SimForceSensor:
    """ATI Mini40 over a World (implements ``dentibot.io.ForceSensor``)."""

    def __init__(self, world: World) -> None:
        self.world = world

    async def read(self) -> Wrench:
        w = self.world
        s = w.sensor
        v = s.last
        return Wrench(w.t, w.steps, v[:3], v[3:], s.status)

    async def bias(self) -> None:
        self.world.sensor.bias()


class SimHandpiece:
    """Maxon handpiece over a World (implements ``dentibot.io.Handpiece``)."""

    def __init__(self, world: World) -> None:
        self.world = world

    async def read(self) -> MotorState:
        w = self.world
        h = w.handpiece
        # a real drive cannot know that the file broke: only its own faults are reported
        return MotorState(w.t, w.steps, h.omega_rpm, h.pos_deg, h.current_a, h.enabled, h.fault)

    async def set_velocity(self, rpm: float) -> None:
        self.world.handpiece.set_velocity(rpm)

    async def move_relative(self, deg: float) -> None:
        self.world.handpiece.move_relative(deg)

    async def stop(self) -> None:
        self.world.handpiece.stop()

    async def set_current_limit(self, amps: float) -> None:
        self.world.handpiece.set_current_limit(amps)

    async def recover(self) -> None:
        hp = self.world.handpiece
        hp.fault = None
        hp.enabled = True


class SimAux:
    """Pedal, e-stop, indicators and the patient platform (implements ``dentibot.io.AuxIO``)."""

    def __init__(self, world: World) -> None:
        self.world = world

    async def read(self) -> AuxState:
        w = self.world
        return AuxState(w.t, w.steps, w.pedal, w.estop, tuple(w.platform_mm))

    async def set_indicator(self, name: str, on: bool) -> None:
        self.world.indicators[str(name)] = bool(on)

    async def set_platform(self, mm) -> None:
        self.world.platform_mm = tuple(float(x) for x in mm)

    async def recover(self) -> None:
        """Nothing latches in the simulated aux I/O."""


def make_devices(world: World) -> tuple[SimArm, SimForceSensor, SimHandpiece, SimAux]:
    """The four devices over one world."""
    return SimArm(world), SimForceSensor(world), SimHandpiece(world), SimAux(world)
