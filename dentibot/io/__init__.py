"""Device interfaces (typing.Protocol) and, later, the real drivers.

``dentibot.io`` must not import ``dentibot.control``, ``dentibot.states`` or ``dentibot.sim``.
"""

from dentibot.io.interfaces import (
    Arm,
    AuxIO,
    AuxState,
    ForceSensor,
    Handpiece,
    JointState,
    MotorState,
    Wrench,
)

__all__ = [
    "Arm",
    "AuxIO",
    "AuxState",
    "ForceSensor",
    "Handpiece",
    "JointState",
    "MotorState",
    "Wrench",
]
