"""The patient tracker as the runtime sees it: the tooth-frame depth's configuration from a
device file's ``tracker:`` section (:func:`tooth_config_from_devices`) or from the simulated
tracker's geometry (:func:`sim_tooth_config`), and what a protocol asks for."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial.transform import Rotation

from dentibot.control.strings import LengthLimits, StringGeometry
from dentibot.errors import ConfigError
from dentibot.io.devices import DevicesConfig, TrackerConfig
from dentibot.protocol.schema import Protocol
from dentibot.runtime.config import RuntimeConfig
from dentibot.runtime.tooth import ToothConfig
from dentibot.sim.tracker_device import StringModel, TrackerSimParams
from dentibot.sim.world import World


def tooth_config_from_devices(t: TrackerConfig, feedforward: bool = False) -> ToothConfig:
    """Anchors, the mount on the flange (mobile x-y-z Euler angles, as the Meca500 states
    poses), the clamp's set-up position as the first guess, and the strings' limits. Depth in
    the tooth's frame needs the full pose: six strings (three give the position only)."""
    if len(t.mount_anchors_mm) < 6:
        raise ConfigError("tracker.mount_anchors_mm", len(t.mount_anchors_mm),
                          "six strings for depth in the tooth's frame (three give the "
                          "tooth's position only, not the canal axis's direction)")
    mount = np.eye(4)
    mount[:3, :3] = Rotation.from_euler("XYZ", t.mount_in_flange_deg, degrees=True).as_matrix()
    mount[:3, 3] = t.mount_in_flange_mm
    start = np.eye(4)
    start[:3, 3] = t.tooth_in_mount_mm
    return ToothConfig(geometry=StringGeometry(np.array(t.mount_anchors_mm, float),
                                               np.array(t.tooth_anchors_mm, float)),
                       mount_in_flange=mount, start_pose=start,
                       limits=LengthLimits(min_mm=t.min_length_mm, max_mm=t.max_length_mm),
                       sigma_mm=t.resolution_mm, feedforward=feedforward)


def sim_tracking(p: Protocol) -> dict:
    """What a protocol asks of the built-in simulator's tracker, as the keyword arguments of
    :meth:`~dentibot.app.procedure.Procedure.simulated` (``tracker``, ``hybrid``)."""
    return {"tracker": TrackerSimParams() if p.patient.tracker else None,
            "hybrid": p.patient.tracking == "hybrid"}


def tracked_config(p: Protocol, cfg: RuntimeConfig, devices: DevicesConfig) -> RuntimeConfig:
    """``cfg`` with depth in the tooth's frame when the protocol asks for the tracker; a
    ConfigError, before anything connects, when the device file has no tracker section."""
    if not p.patient.tracker:
        return cfg
    if devices.tracker is None:
        raise ConfigError("patient.tracker", True, "a tracker section in the device file "
                          "(depth in the tooth's frame needs the patient tracker)")
    return dataclasses.replace(cfg, tooth=tooth_config_from_devices(
        devices.tracker, feedforward=p.patient.tracking == "hybrid"))


def sim_tooth_config(world: World, tracker: TrackerSimParams,
                     feedforward: bool = False) -> ToothConfig:
    """What the runtime knows of the simulated tracker: its anchors and mount (as a calibration
    would have identified them), and the clamp's pose at set-up as the first guess;
    ``feedforward``: hybrid control."""
    return ToothConfig(geometry=tracker.geometry, mount_in_flange=tracker.mount_in_flange,
                       start_pose=StringModel(world, tracker).tooth_in_mount(),
                       limits=LengthLimits(min_mm=tracker.min_length_mm,
                                           max_mm=tracker.max_length_mm),
                       sigma_mm=tracker.resolution_mm, feedforward=feedforward)
