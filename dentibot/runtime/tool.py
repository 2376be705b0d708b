"""The tool's geometry as the control task uses it: the flange -> tool transform and the
{S} -> {H} wrench transforms of the two reference points (fig 4.7)."""

from __future__ import annotations

import dataclasses

import numpy as np

from dentibot.control.wrench import WrenchTransform
from dentibot.runtime.config import ToolGeometry


def tool_matrix(R_6_H: np.ndarray, tip_6_mm) -> np.ndarray:
    """6T_H (4x4, mm): the tool frame {H} at the file tip, in the flange frame."""
    T = np.eye(4)
    T[:3, :3] = R_6_H
    T[:3, 3] = tip_6_mm
    return T


def reference_transforms(tool: ToolGeometry, mount_angle_deg: float) -> dict[str, WrenchTransform]:
    """{S} -> {H} wrench transforms (eq 4.26-4.31) to reference point "A" (the grip, dragging)
    and "B" (the file tip, self-alignment)."""
    R = np.reshape(tool.R_6_H, (3, 3))
    common = {"mount_angle_deg": mount_angle_deg, "p_6_S_mm": tool.sensor_origin_6_mm}
    return {
        "A": WrenchTransform.for_tool(R, tool.tip_6_mm, q_H_mm=tool.grip_h_mm, **common),
        "B": WrenchTransform.for_tool(R, tool.tip_6_mm, **common),
    }


def set_tool_tip(rt, tip_6_mm) -> None:
    """A new tool tip 6p_H for the control task ``rt`` (TCP calibration): its kinematics,
    {S}->{H} transforms and configuration (``Runtime.set_tool_tip``)."""
    tool = dataclasses.replace(rt.cfg.tool, tip_6_mm=tuple(float(x) for x in tip_6_mm))
    rt.cfg = dataclasses.replace(rt.cfg, tool=tool)
    rt.kin.set_tool(tool_matrix(rt.R_6_H, tool.tip_6_mm))
    if rt.gravity is not None:
        rt.set_gravity(rt.gravity)
