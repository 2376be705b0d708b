"""The recordings' /tf in CDR (tf2_msgs/msg/TFMessage): Foxglove's own ROS 2 codec writes the
same bytes and reads the frames the JSON view places; a block of ticks is written bit for bit
as its rows one by one."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic
from scipy.spatial.transform import Rotation

from dentibot.telemetry.foxglove import FoxgloveView, quat_from_euler_xyz_deg
from dentibot.telemetry.tf_cdr import TF_DEFINITION, TF_SCHEMA_NAME, tf_encoder

ENCODE = serialize_dynamic(TF_SCHEMA_NAME, TF_DEFINITION)[TF_SCHEMA_NAME]
DECODE = generate_dynamic(TF_SCHEMA_NAME, TF_DEFINITION)[TF_SCHEMA_NAME]
TOOL_6_H = [[0.0, -1.0, 0.0, 1.5], [1.0, 0.0, 0.0, -2.0], [0.0, 0.0, 1.0, 150.0],
            [0.0, 0.0, 0.0, 1.0]]
LOG_NS = 1_700_000_000_123_456_789


def _poses(n: int, seed: int = 3) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float]]:
    rng = np.random.default_rng(seed)
    tool = np.column_stack([rng.uniform(-200, 200, (n, 3)), rng.uniform(-180, 180, (n, 3))])
    return tool, rng.uniform(-100, 100, (n, 3)), (-180.0, 3.2e-15, 179.5)


def _row(tool, xyz, euler) -> dict:
    return {"tool_pose": list(map(float, tool)), "phantom_pose": [*map(float, xyz), *euler]}


def test_a_message_is_the_bytes_of_foxglove_s_encoder():
    enc = tf_encoder([("base", "flange"), ("flange", "file_tip")])
    values = [(0.1, -0.2, 0.3, 0.0, 0.0, 0.6, 0.8), (0.0, 0.0, 0.15, 0.0, 0.0, 0.0, 1.0)]
    data = enc.encode(LOG_NS, values)
    sec, nsec = divmod(LOG_NS, 1_000_000_000)
    theirs = ENCODE({"transforms": [
        {"header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": parent},
         "child_frame_id": child,
         "transform": {"translation": dict(zip("xyz", v[:3])),
                       "rotation": dict(zip("xyzw", v[3:]))}}
        for (parent, child), v in zip(enc.names, values)]})
    assert data == bytes(theirs)


@pytest.mark.parametrize("tool_6_h", [TOOL_6_H, None])
def test_the_frames_read_by_foxglove_s_decoder_are_the_json_view_s(tool_6_h):
    view = FoxgloveView(tool_6_h=tool_6_h)
    tool, xyz, euler = _poses(1)
    row = _row(tool[0], xyz[0], euler)
    msg = DECODE(view.transforms_cdr(row, LOG_NS))
    json_tf = view.transforms(row, LOG_NS)["transforms"]
    assert len(msg.transforms) == len(json_tf) == (3 if tool_6_h else 2)
    for got, want in zip(msg.transforms, json_tf):
        assert (got.header.frame_id, got.child_frame_id) == (want["parent_frame_id"],
                                                              want["child_frame_id"])
        assert (got.header.stamp.sec, got.header.stamp.nanosec) == (
            want["timestamp"]["sec"], want["timestamp"]["nsec"])
        for axis in "xyz":                   # the JSON's are written to 1e-9
            assert getattr(got.transform.translation, axis) == pytest.approx(
                want["translation"][axis], abs=1e-9)
        for axis in "xyzw":
            assert getattr(got.transform.rotation, axis) == pytest.approx(
                want["rotation"][axis], abs=1e-9)


@pytest.mark.parametrize("tool_6_h", [TOOL_6_H, None])
def test_a_block_is_written_bit_for_bit_as_its_rows(tool_6_h):
    view = FoxgloveView(tool_6_h=tool_6_h)
    tool, xyz, euler = _poses(40)
    log_ns = LOG_NS + np.arange(40, dtype=np.int64) * 2_000_000
    block = view.block_transforms_cdr(tool, xyz, euler, log_ns)
    rows = [view.transforms_cdr(_row(t, p, euler), int(ns))
            for t, p, ns in zip(tool, xyz, log_ns)]
    assert block == rows


def test_a_block_with_a_non_finite_pose_or_frames_of_the_caller_s_goes_row_by_row():
    tool, xyz, euler = _poses(5)
    log_ns = LOG_NS + np.arange(5, dtype=np.int64)
    bad = tool.copy()
    bad[2, 4] = math.nan
    assert FoxgloveView().block_transforms_cdr(bad, xyz, euler, log_ns) is None
    assert FoxgloveView().block_transforms_cdr(tool, xyz, (0.0, math.inf, 0.0), log_ns) is None
    eye = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
    view = FoxgloveView(frames=lambda row: [("base", "extra", eye)])
    assert view.block_transforms_cdr(tool, xyz, euler, log_ns) is None


def test_the_rotations_are_scipy_s_mobile_xyz_euler_angles():
    """The compiled quaternion of mobile XYZ Euler angles is scipy's intrinsic "XYZ" one (up
    to the sign), and the flange it places carries the tool geometry back to the tip."""
    tool, _xyz, _euler = _poses(50, seed=9)
    for pose in tool:
        q = np.array(quat_from_euler_xyz_deg(*pose[3:6]))
        want = Rotation.from_euler("XYZ", pose[3:6], degrees=True).as_quat()
        assert min(np.abs(q - want).max(), np.abs(q + want).max()) < 1e-12
    view = FoxgloveView(tool_6_h=TOOL_6_H)
    row = _row(tool[0], _xyz[0], _euler)
    frames = {child: (parent, p, q) for parent, child, p, q in view._frames(row)}
    _parent, p_06, q_06 = frames["flange"]
    r_06 = Rotation.from_quat(q_06)              # 0T_H = 0T_6 6T_H: back to the tip
    tip = np.array(p_06) + r_06.apply(np.array(TOOL_6_H)[:3, 3])
    assert np.allclose(tip, tool[0, :3], atol=1e-9)
    r_0h = r_06 * Rotation.from_matrix(np.array(TOOL_6_H)[:3, :3])
    assert np.allclose(r_0h.as_matrix(), Rotation.from_euler(
        "XYZ", tool[0, 3:6], degrees=True).as_matrix(), atol=1e-12)
