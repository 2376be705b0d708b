"""The built-in simulator as a procedure's devices: the world, its in-process devices, the
configuration that agrees with it, what only a simulation knows (:class:`Truth`), and the wire
simulators on loopback (:func:`serve_wire`). :meth:`dentibot.app.procedure.Procedure.simulated`
puts them under a runtime.
"""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np

from dentibot.control.depth import depth_along
from dentibot.control.kinematics import euler_xyz_deg
from dentibot.control.wrench import GravityModel
from dentibot.runtime.config import RuntimeConfig, ToolGeometry, TreatmentPlan
from dentibot.runtime.estimate import Devices
from dentibot.sim.devices import make_devices
from dentibot.sim.faults import Jerk
from dentibot.sim.tracker_device import SimPatientTracker, TrackerSimParams
from dentibot.sim.patient import JAW_HINGE_MM, SQUARE_MM, StewartSquare, jaw_hinge
from dentibot.sim.serve import ServePorts, VirtualDentiBot
from dentibot.sim.world import World, WorldConfig

#: The parts of the simulated world that workflows set up themselves (experiment 1's Stewart
#: platform square, a patient's jerk), handed on so that nothing above this layer imports the simulator.
__all__ = ["JAW_HINGE_MM", "Jerk", "SQUARE_MM", "StewartSquare", "Truth", "World", "WorldConfig",
           "jaw_hinge", "plan_config", "serve_wire", "sim_devices", "tool_geometry_of",
           "true_depth_mm", "true_gravity_model"]


def tool_geometry_of(world: World) -> ToolGeometry:
    """The tool geometry a perfect TCP calibration would find for this world."""
    tool = world.config.tool
    return ToolGeometry(tip_6_mm=tuple(float(x) for x in tool[:3, 3]),
                        R_6_H=tuple(float(x) for x in tool[:3, :3].ravel()),
                        sensor_origin_6_mm=(0.0, 0.0, world.sensor.p.offset_mm))


def true_gravity_model(world: World) -> GravityModel:
    """The simulated sensor's true offsets and load (what an ideal load calibration finds)."""
    s = world.sensor
    tare = np.asarray(s.tare)
    return GravityModel(
        f0_n=np.asarray(s.f0) - tare[:3], tau0_nm=np.asarray(s.tau0) - tare[3:],
        weight_n=s.p.mass_kg * 9.80665, centroid_mm=s.p.centroid_mm,
        mount_angle_deg=s.p.mount_angle_deg)


def plan_config(world: World, config: RuntimeConfig | None = None) -> RuntimeConfig:
    """``config`` completed by what the simulated world knows: without a configuration the plan
    is the simulated tooth's (the orifice gap the world puts between the tip and the canal, and
    the canal's working length: depth 0 is the canal orifice); without a tool geometry, the
    simulated tool's."""
    cfg = config or RuntimeConfig(plan=TreatmentPlan(
        working_length_mm=world.canal.p.working_length_mm,
        orifice_gap_mm=world.config.orifice_gap_mm))
    if cfg.tool == ToolGeometry():
        cfg = dataclasses.replace(cfg, tool=tool_geometry_of(world))
    if config is None:
        cfg = dataclasses.replace(cfg, file=world.file.beam)
    return cfg


def sim_devices(world: World, tracker: TrackerSimParams | None = None) -> Devices:
    """The world's in-process devices (arm, F/T sensor, handpiece, aux I/O, and the patient
    tracker when ``tracker`` gives its geometry)."""
    return Devices(*make_devices(world),
                   tracker=None if tracker is None else SimPatientTracker(world, tracker))


def true_depth_mm(world: World, axis: tuple | None = None) -> float:
    """The file tip's true depth along the canal's axis from the orifice (mm; the simulator's
    truth: the patient's motion included). ``axis``: ``world.canal_axis_0()`` if known."""
    return depth_along(world.tip_0, axis or world.canal_axis_0())


class Truth:
    """What only a simulation knows, added to every telemetry row (phantom pose, true depth,
    completeness, fracture); the control never reads it."""

    def __init__(self, world: World) -> None:
        self.world = world
        self._phantom_euler = euler_xyz_deg(world.phantom_pose[:3, :3].tolist())

    def __call__(self) -> dict:
        w = self.world
        axis = w.canal_axis_0()
        if hasattr(w.motion, "rotation_at"):          # a turning patient: its pose now
            self._phantom_euler = euler_xyz_deg(w.phantom_rotation.tolist())
        return {
            "phantom_pose": [*axis[0], *self._phantom_euler],
            "true_depth_mm": true_depth_mm(w, axis),
            "completeness": w.completeness(),
            "fractured": w.fractured is not None,
        }


@contextlib.asynccontextmanager
async def serve_wire(world: World | WorldConfig | None = None):
    """The four wire simulators over ``world`` on free ports of 127.0.0.1, in real time;
    yields the running :class:`~dentibot.sim.serve.VirtualDentiBot` (its
    ``devices_config()`` is what the drivers connect to)."""
    ports = ServePorts(host="127.0.0.1", meca_port=0, netft_port=0, netft_http_port=0,
                       modbus_port=0, can_port=0)
    async with VirtualDentiBot(world, ports) as bot:
        yield bot
