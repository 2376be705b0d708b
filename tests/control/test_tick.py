"""The whole control computation of one tick, from raw sensor reading to joint target."""

import numpy as np
import pytest

from dentibot.control.admittance import SELF_ALIGNMENT, AdmittanceController
from dentibot.control.kinematics import Meca500, matrix_from_pose
from dentibot.control.tick import ControlComputation
from dentibot.control.wrench import GravityModel, WrenchTransform

TIP_6 = np.array([1.0, -0.5, 95.0])  # tool tip in the flange frame (mm)
MOUNT_DEG = 3.0


def make():
    robot = Meca500(tool=matrix_from_pose([*TIP_6, 0, 0, 0]))
    gravity = GravityModel(f0_n=[0.3, -0.2, 1.1], tau0_nm=[0.01, -0.02, 0.005], weight_n=1.363,
                           centroid_mm=[2.0, -1.5, 45.0], mount_angle_deg=MOUNT_DEG)
    to_h = WrenchTransform.for_tool(np.eye(3), TIP_6, mount_angle_deg=MOUNT_DEG)
    return robot, gravity, ControlComputation(gravity, to_h, AdmittanceController(robot, SELF_ALIGNMENT))


def sensor_reading(robot, gravity, q, force_h):
    """What the sensor reads: offset + tool weight + a force applied at the file tip.

    Written from the physics, independently of ControlComputation: the sensor frame is the
    flange frame turned by the mounting angle; the tip force's moment about the sensor origin
    (at the flange) is tip x F, everything in {S} components; torques in N*m.
    """
    c, s = np.cos(np.radians(MOUNT_DEG)), np.sin(np.radians(MOUNT_DEG))
    r_6_s = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    r_0_6 = robot.fk(q)[:3, :3]
    f_s = r_6_s.T @ force_h  # {H} axes = flange axes here
    tip_s = r_6_s.T @ TIP_6 * 1e-3
    weight_s = r_6_s.T @ r_0_6.T @ np.array([0, 0, -gravity.weight_n])
    r = np.asarray(gravity.centroid_mm) * 1e-3
    return np.concatenate([
        np.asarray(gravity.f0_n) + weight_s + f_s,
        np.asarray(gravity.tau0_nm) + np.cross(r, weight_s) + np.cross(tip_s, f_s),
    ])


@pytest.mark.parametrize("q", [[0, 10, 20, 0, 30, 0], [30, -10, 40, 20, -50, 70]])
def test_tip_force_is_recovered_at_the_tip_and_drives_the_admittance(q):
    robot, gravity, comp = make()
    force_h = np.array([0.4, -0.3, 0.2])
    raw = sensor_reading(robot, gravity, q, force_h)
    f_d = np.array([0, 0, 0.5, 0, 0, 0])
    comp.step(q, raw, f_d[2])
    res = comp.step(q, raw, f_d[2])
    np.testing.assert_allclose(res.wrench_h[:3], force_h, atol=1e-12)
    np.testing.assert_allclose(res.wrench_h[3:], 0.0, atol=1e-12)  # no moment about the tip
    # Deadbeat self-alignment filter: the second sample is the steady twist k/b (F + f_d).
    np.testing.assert_allclose(res.command.twist[:3], 500 / 80 * (force_h + f_d[:3]), rtol=1e-12)


def test_no_contact_means_no_motion_at_any_pose():
    robot, gravity, comp = make()
    for q in ([0, 10, 20, 0, 30, 0], [60, 20, -30, 90, 45, -120]):
        res = comp.step(q, sensor_reading(robot, gravity, q, np.zeros(3)))
        np.testing.assert_allclose(res.wrench_h, 0.0, atol=1e-12)
        np.testing.assert_allclose(res.command.qdot_deg_s, 0.0, atol=1e-9)
