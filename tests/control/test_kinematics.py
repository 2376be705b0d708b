"""Kinematics of the Meca500 (thesis 3.3) against independent references."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dentibot.control.kinematics import (
    MECA500_DH,
    Meca500,
    damped_least_squares,
    euler_rate_matrix,
    matrix_from_pose,
    pose_from_matrix,
)
from dentibot.errors import KinematicsError

RNG = np.random.default_rng(20261121)


def random_q(n=20):
    lim = np.array([(-170, 170), (-65, 85), (-130, 65), (-165, 165), (-110, 110), (-180, 180)])
    return RNG.uniform(lim[:, 0], lim[:, 1], size=(n, 6))


def dh_reference(q_deg):
    """Textbook modified-DH product of 4x4 matrices, written independently of the fast chain."""
    t = np.eye(4)
    for (alpha, a, off, d), q in zip(MECA500_DH, q_deg):
        al, th = math.radians(alpha), math.radians(q + off)
        rx = np.eye(4)
        rx[1:3, 1:3] = [[math.cos(al), -math.sin(al)], [math.sin(al), math.cos(al)]]
        tx = np.eye(4)
        tx[0, 3] = a
        rz = np.eye(4)
        rz[:2, :2] = [[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]]
        tz = np.eye(4)
        tz[2, 3] = d
        t = t @ rx @ tx @ rz @ tz
    return t


def numeric_twist_jacobian(f_t, q, eps=1e-6, in_frame=False):
    """Finite-difference Jacobian of a pose function; angular part from dR R^T."""
    t0 = f_t(q)
    j = np.zeros((6, 6))
    for i in range(6):
        dq = np.array(q, dtype=float)
        dq[i] += math.degrees(eps)
        t1 = f_t(dq)
        v = (t1[:3, 3] - t0[:3, 3]) / eps
        dr = t1[:3, :3] @ t0[:3, :3].T
        w = np.array([dr[2, 1] - dr[1, 2], dr[0, 2] - dr[2, 0], dr[1, 0] - dr[0, 1]]) / (2 * eps)
        if in_frame:
            v, w = t0[:3, :3].T @ v, t0[:3, :3].T @ w
        j[:3, i], j[3:, i] = v, w
    return j


def test_zero_joints_is_the_documented_home_pose():
    pose = pose_from_matrix(Meca500().fk([0] * 6))
    np.testing.assert_allclose(pose, [190, 0, 308, 0, 90, 0], atol=1e-9)


@pytest.mark.parametrize("q", random_q(10))
def test_fk_matches_plain_dh_product(q):
    np.testing.assert_allclose(Meca500().fk(q), dh_reference(q), atol=1e-9)


def test_link_lengths_are_invariant():
    # Whatever the joints, the links keep the lengths of Table 3.1: shoulder 135 mm above the
    # base, upper arm 135 mm, forearm to wrist centre hypot(38, 120) mm, wrist to flange 70 mm.
    m = Meca500()
    for q in random_q(50):
        frames = m.frames(q)
        assert frames[0][2, 3] == pytest.approx(135.0)
        wc = frames[4][:3, 3]
        elbow = frames[2][:3, 3]
        assert np.linalg.norm(elbow - frames[1][:3, 3]) == pytest.approx(135.0)
        assert np.linalg.norm(wc - elbow) == pytest.approx(math.hypot(38, 120))
        assert np.linalg.norm(frames[5][:3, 3] - wc) == pytest.approx(70.0)


@pytest.mark.parametrize("q", random_q(10))
def test_jacobian_matches_finite_differences(q):
    m = Meca500()
    np.testing.assert_allclose(m.jacobian(q), numeric_twist_jacobian(m.fk, q), atol=2e-3)


@pytest.mark.parametrize("q", random_q(5))
def test_tool_jacobian_is_velocity_of_the_tool_point_in_h(q):
    tool = matrix_from_pose([1.5, -2.0, 95.0, 4.0, -6.0, 30.0])
    m = Meca500(tool=tool)
    ref = np.array([0.0, 0.0, -12.0])
    shift = np.eye(4)
    shift[:3, 3] = ref
    numeric = numeric_twist_jacobian(lambda qq: m.fk_tool(qq) @ shift, q, in_frame=True)
    np.testing.assert_allclose(m.tool_jacobian(q, ref), numeric, atol=2e-3)


def test_tool_jacobian_without_tool_is_rotated_flange_jacobian():
    m = Meca500()
    q = [10, 20, -30, 40, 50, 60]
    r = m.fk(q)[:3, :3]
    expected = np.vstack([r.T @ m.jacobian(q)[:3], r.T @ m.jacobian(q)[3:]])  # eq 3.14
    np.testing.assert_allclose(m.tool_jacobian(q), expected, atol=1e-9)


@pytest.mark.parametrize("q", random_q(5))
def test_analytical_jacobian_gives_euler_rates(q):
    m = Meca500()
    ja = m.analytical_jacobian(q)
    qdot = RNG.normal(size=6) * 0.1
    h = 1e-6
    p0 = pose_from_matrix(m.fk(q))
    p1 = pose_from_matrix(m.fk(np.asarray(q) + np.degrees(qdot * h)))
    numeric = (p1 - p0) / h
    numeric[3:] = np.radians(numeric[3:])
    np.testing.assert_allclose(ja @ qdot, numeric, atol=1e-3)


def test_analytical_jacobian_refuses_gimbal_lock():
    with pytest.raises(KinematicsError, match="beta"):
        Meca500().analytical_jacobian([0] * 6)


def test_euler_rate_matrix_matches_scipy_angular_velocity():
    a, b, g = 0.3, -0.5, 1.1
    rates = np.array([0.2, -0.4, 0.7])
    h = 1e-7
    r0 = Rotation.from_euler("XYZ", [a, b, g]).as_matrix()
    r1 = Rotation.from_euler("XYZ", np.array([a, b, g]) + rates * h).as_matrix()
    dr = (r1 - r0) / h @ r0.T
    w = np.array([dr[2, 1], dr[0, 2], dr[1, 0]])
    np.testing.assert_allclose(euler_rate_matrix(a, b) @ rates, w, atol=1e-5)


@pytest.mark.parametrize("pose", [
    [190, 0, 308, 0, 90, 0],
    [100, -50, 200, 10, 20, 30],
    [0, 0, 0, -170, 80, 170],
    [5, 5, 5, 45, -89, -45],
])
def test_pose_conversions_round_trip(pose):
    t = matrix_from_pose(pose)
    np.testing.assert_allclose(matrix_from_pose(pose_from_matrix(t)), t, atol=1e-9)


def test_pose_convention_is_mobile_xyz():
    a, b, g = 10.0, 20.0, 30.0
    rx = Rotation.from_euler("x", a, degrees=True).as_matrix()
    ry = Rotation.from_euler("y", b, degrees=True).as_matrix()
    rz = Rotation.from_euler("z", g, degrees=True).as_matrix()
    np.testing.assert_allclose(matrix_from_pose([0, 0, 0, a, b, g])[:3, :3], rx @ ry @ rz, atol=1e-12)


@pytest.mark.parametrize("q", random_q(10))
def test_singularity_factors_multiply_to_the_jacobian_determinant(q):
    m = Meca500()
    s = m.singularity(q)
    product = s.shoulder_mm * s.elbow * s.wrist * 135.0 * math.hypot(38, 120)
    assert abs(np.linalg.det(m.jacobian(q))) == pytest.approx(product, rel=1e-9)


def test_singularity_rates_match_finite_differences():
    m = Meca500()
    q = np.array([20.0, 10.0, 30.0, 15.0, 25.0, 5.0])
    qdot = np.array([0.3, -0.2, 0.4, 0.1, -0.5, 0.2])
    s0 = m.singularity(q, qdot)
    h = 1e-6
    s1 = m.singularity(q + np.degrees(qdot * h))
    assert s0.shoulder_rate == pytest.approx((s1.shoulder_mm - s0.shoulder_mm) / h, rel=1e-4)
    assert s0.elbow_rate == pytest.approx((s1.elbow - s0.elbow) / h, rel=1e-4)
    assert s0.wrist_rate == pytest.approx((s1.wrist - s0.wrist) / h, rel=1e-4)


def test_wrist_singularity_at_q5_zero():
    s = Meca500().singularity([0, 0, 0, 0, 0, 0])
    assert s.wrist == pytest.approx(0.0)
    assert s.value == pytest.approx(0.0)


def test_damped_least_squares_is_exact_away_from_singularity_and_bounded_at_it():
    m = Meca500()
    q = [10, 20, -30, 40, 50, 60]
    j = m.jacobian(q)
    v = np.array([1.0, 2.0, -1.0, 0.01, 0.02, -0.03])
    np.testing.assert_allclose(damped_least_squares(j, v), np.linalg.solve(j, v), rtol=1e-9)
    js = m.jacobian([10, 20, -30, 40, 1e-9, 60])  # wrist singular
    qdot = damped_least_squares(js, v)
    assert np.all(np.isfinite(qdot))
    assert np.linalg.norm(qdot) < 100.0
    # The achievable part of the motion is still tracked.
    np.testing.assert_allclose(js @ qdot, v, atol=0.1)


def test_bad_input_is_refused():
    with pytest.raises(KinematicsError, match="6 joint"):
        Meca500().fk([0, 0, 0])
    with pytest.raises(KinematicsError, match="4x4"):
        Meca500(tool=np.eye(3))
    with pytest.raises(KinematicsError, match="6 values"):
        matrix_from_pose([1, 2, 3])


def test_limits_are_the_vendor_figures():
    m = Meca500()
    assert m.joint_limits_deg.tolist() == [[-175, 175], [-70, 90], [-135, 70], [-170, 170],
                                           [-115, 115], [-36000, 36000]]
    assert m.joint_speed_limits_deg_s.tolist() == [150, 150, 180, 300, 300, 500]
    assert m.within_limits([0, 90, 70, 0, 0, 0])
    assert not m.within_limits([0, 91, 0, 0, 0, 0])


def test_tool_tip_axis_from_frames_matches_fk_tool():
    tool = matrix_from_pose([3.0, -2.0, 95.0, 10.0, -20.0, 5.0])
    robot = Meca500(tool=tool)
    q = [20, -10, 30, 40, 50, 60]
    _, frames = robot.tool_jacobian(q, with_frames=True)
    tip, axis = robot.tool_tip_axis(frames)
    t = robot.fk(q) @ tool
    np.testing.assert_allclose(tip, t[:3, 3], atol=1e-9)
    np.testing.assert_allclose(axis, t[:3, 2], atol=1e-12)


def test_closed_form_euler_matches_scipy_including_gimbal_lock():
    from dentibot.control.kinematics import euler_xyz_deg

    rng = np.random.default_rng(5)
    mats = list(Rotation.random(200, random_state=7).as_matrix())
    mats += [Meca500().fk([0, 0, 0, 0, 0, 0])[:3, :3], np.eye(3)]
    mats += [Rotation.from_euler("XYZ", [rng.uniform(-180, 180), s * 90, rng.uniform(-180, 180)],
                                 degrees=True).as_matrix() for s in (-1, 1)]
    for R in mats:
        T = np.eye(4)
        T[:3, :3] = R
        mine = np.array(euler_xyz_deg(R.tolist()))
        ref = pose_from_matrix(T)[3:]
        # same rotation whatever the angles (gimbal lock shares a and g)
        np.testing.assert_allclose(
            Rotation.from_euler("XYZ", mine, degrees=True).as_matrix(), R, atol=1e-9)
        np.testing.assert_allclose(mine, ref, atol=1e-6)
