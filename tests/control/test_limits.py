"""Joint-rate limits: speed clamping, range guarding, singularity slowing."""

import math

import numpy as np
import pytest

from dentibot.control.kinematics import Meca500
from dentibot.control.limits import JointLimiter, SingularityThresholds
from dentibot.errors import ConfigError

ROBOT = Meca500()
Q = [0.0, 10.0, 20.0, 0.0, 30.0, 0.0]


def test_free_motion_is_untouched():
    qdot = np.array([0.1, -0.2, 0.1, 0.3, -0.1, 0.2])
    out, rep = JointLimiter(ROBOT).apply(Q, qdot)
    np.testing.assert_array_equal(out, qdot)
    assert not rep.limited


def test_speed_clamp_is_uniform_and_respects_vendor_limits():
    qdot = np.radians([300.0, 0.0, 90.0, 0.0, 0.0, 0.0])  # J1 at twice its 150 deg/s
    out, rep = JointLimiter(ROBOT).apply(Q, qdot)
    np.testing.assert_allclose(np.degrees(out), [150.0, 0, 45.0, 0, 0, 0])
    assert rep.speed_scale == pytest.approx(0.5)


def test_speed_fraction_scales_the_limits():
    qdot = np.radians([0, 0, 0, 0, 0, 400.0])
    out, _ = JointLimiter(ROBOT, speed_fraction=0.5).apply(Q, qdot)
    assert np.degrees(out[5]) == pytest.approx(250.0)


def test_joint_range_guard_stops_at_the_limit_but_lets_the_joint_leave():
    lim = JointLimiter(ROBOT, range_margin_deg=5.0)
    q = list(Q)
    q[1] = 89.0  # J2 max is 90: 1 deg left, margin 5 deg -> 1/5 of 150 deg/s toward it
    toward = np.radians([0, 100.0, 0, 0, 0, 0])
    out, rep = lim.apply(q, toward)
    assert np.degrees(out[1]) == pytest.approx(30.0)
    assert rep.guarded_joints == (1,)
    away = -toward
    out, rep = lim.apply(q, away)
    assert np.degrees(out[1]) == pytest.approx(-100.0)
    assert not rep.guarded_joints
    q[1] = 90.0
    out, _ = lim.apply(q, toward)
    assert out[1] == 0.0


def test_integrated_motion_never_passes_a_joint_limit():
    lim = JointLimiter(ROBOT)
    q = np.array([0.0, 80.0, 0.0, 0.0, 30.0, 0.0])
    for _ in range(2000):
        out, _ = lim.apply(q, np.radians([0, 150.0, 0, 0, 0, 0]))
        q = q + np.degrees(out) * 0.002
        assert q[1] <= 90.0 + 1e-9
    assert q[1] == pytest.approx(90.0, abs=0.01)


def test_singularity_slowing_only_when_approaching():
    lim = JointLimiter(ROBOT)
    q = [0.0, 10.0, 20.0, 0.0, 5.0, 0.0]  # wrist 5 deg from singular (q5 = 0)
    toward = np.radians([0, 0, 0, 0, -20.0, 0])
    away = -toward
    out, rep = lim.apply(q, toward)
    th = SingularityThresholds()
    expected = (math.sin(math.radians(5)) - th.wrist_stop) / (th.wrist_start - th.wrist_stop)
    assert rep.singularity_scale == pytest.approx(expected)
    np.testing.assert_allclose(out, toward * expected)
    out, rep = lim.apply(q, away)
    assert rep.singularity_scale == 1.0
    np.testing.assert_array_equal(out, away)


def test_approach_to_wrist_singularity_stops_short_of_it():
    lim = JointLimiter(ROBOT)
    q = np.array([0.0, 10.0, 20.0, 0.0, 20.0, 0.0])
    for _ in range(5000):
        out, _ = lim.apply(q, np.radians([0, 0, 0, 0, -50.0, 0]))
        q = q + np.degrees(out) * 0.002
    assert q[4] >= 2.0 - 1e-6  # stop threshold: 2 deg
    assert q[4] < 2.5


def test_bad_limiter_settings():
    with pytest.raises(ConfigError, match="speed_fraction"):
        JointLimiter(ROBOT, speed_fraction=1.5)
    with pytest.raises(ConfigError, match="wrist_start"):
        SingularityThresholds(wrist_start=0.01, wrist_stop=0.02)
