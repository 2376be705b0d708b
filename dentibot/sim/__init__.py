"""The simulated world: arm, F/T sensor, handpiece, NiTi file, tooth phantom, patient.

``World.step()`` advances everything by exactly one control period; the device objects in
:mod:`dentibot.sim.devices` implement the :mod:`dentibot.io` protocols over a World.
May import ``dentibot.io`` and ``dentibot.control``; never runtime, states, cli or protocol.
"""

from dentibot.sim.arm import ArmParams, SimArmModel
from dentibot.sim.canal import Canal, CanalParams
from dentibot.sim.devices import SimArm, SimAux, SimForceSensor, SimHandpiece, make_devices
from dentibot.sim.ftsensor import FTSensorModel, FTSensorParams
from dentibot.sim.handpiece import HandpieceModel, HandpieceParams
from dentibot.sim.nitifile import FileFractured, NiTiFile
from dentibot.sim.patient import HeadMotion, MotionProfile, StaticPose, StewartSquare
from dentibot.sim.timing import RealTimeStepper
from dentibot.sim.tracker_device import SimPatientTracker, StringModel, TrackerSimParams
from dentibot.sim.world import World, WorldConfig

__all__ = [
    "ArmParams", "Canal", "CanalParams", "FTSensorModel", "FTSensorParams", "FileFractured",
    "HandpieceModel", "HandpieceParams", "HeadMotion", "MotionProfile", "NiTiFile",
    "RealTimeStepper", "SimArm", "SimArmModel", "SimAux", "SimForceSensor", "SimHandpiece",
    "SimPatientTracker", "StaticPose", "StewartSquare", "StringModel", "TrackerSimParams",
    "World", "WorldConfig", "make_devices",
]
