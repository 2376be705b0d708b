"""Admittance law (thesis 4.3-4.5): discrete response, presets, disabled axes, joint targets."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dentibot.control.admittance import (
    DRAGGING,
    EXPERIMENT_1,
    PRESETS,
    SELF_ALIGNMENT,
    AdmittanceController,
    AdmittanceFilter,
    AdmittanceParams,
    with_axial_lag,
)
from dentibot.control.kinematics import Meca500, matrix_from_pose
from dentibot.errors import ConfigError

Q0 = [0.0, 10.0, 20.0, 0.0, 30.0, 0.0]


def test_table_4_3_presets():
    assert DRAGGING.k == 1500 and DRAGGING.b == (80, 80, 80, 160, 160, 160)
    assert DRAGGING.m == (0.08, 0.08, 0.08, 0.16, 0.16, 0.16)
    assert SELF_ALIGNMENT.k == 500 and SELF_ALIGNMENT.b[:5] == (80,) * 5
    assert math.isinf(SELF_ALIGNMENT.b[5]) and math.isinf(SELF_ALIGNMENT.m[5])
    assert SELF_ALIGNMENT.time_constant(0) == pytest.approx(0.001)  # m:b = 1:1000 as run


def test_table_6_4_configs():
    assert EXPERIMENT_1["A"].params.b == (80,) * 6 and not EXPERIMENT_1["A"].file_rotation
    assert math.isinf(EXPERIMENT_1["B"].params.b[5]) and EXPERIMENT_1["B"].fz_n == 1.0
    assert EXPERIMENT_1["C"].fz_n is None and EXPERIMENT_1["C"].fz_bounds_n == (-0.2, 0.5)
    assert all(c.params.k == 500 for c in EXPERIMENT_1.values())
    assert "experiment1_C" in PRESETS and "dragging" in PRESETS


def test_self_alignment_moves_6_25_mm_s_per_newton():
    # The thesis's own figure: k = 500, b = 80 -> 6.25 mm/s per N of insertion force.
    filt = AdmittanceFilter(SELF_ALIGNMENT)
    for _ in range(50):
        v = filt.step([0, 0, 1.0, 0, 0, 0])
    assert v[2] == pytest.approx(6.25, rel=1e-12)


def first_order_response_to_sampled_step(k, b, tau, f, ts, t):
    """Exact continuous response of k/(m s + b) to the input Tustin assumes between samples.

    The discrete step starts from f[0] = 0, and Tustin (trapezoidal) integration treats the
    input as linear between samples: a ramp from 0 to f over the first period, then constant.
    Unit-ramp response of 1/(m s + b): (t - tau (1 - exp(-t/tau))) / (b ts).
    """
    def ramp(tt):
        tt = np.maximum(tt, 0.0)
        return (tt - tau * (1.0 - np.exp(-tt / tau))) / (b * ts)

    return k * f * (ramp(t) - ramp(t - ts))


@pytest.mark.parametrize("m,b,k,f", [(0.8, 80.0, 500.0, 2.0), (1.6, 160.0, 1500.0, -0.7),
                                     (0.4, 20.0, 100.0, 1.0)])
def test_step_response_matches_first_order_analytic(m, b, k, f):
    # Analytic (eq 4.32): time constant m/b, final value k f / b.
    ts = 0.002
    params = AdmittanceParams(k=k, b=(b,) * 6, m=(m,) * 6)
    filt = AdmittanceFilter(params, ts)
    tau = m / b
    n = int(10 * tau / ts)
    v = np.array([filt.step([f] * 6)[0] for _ in range(n)])
    t = ts * np.arange(1, n + 1)
    final = k * f / b
    analytic = first_order_response_to_sampled_step(k, b, tau, f, ts, t)
    # Tustin's error is second order in ts/tau (0.1 here at most): under 1 % of the final value.
    assert np.max(np.abs(v - analytic)) < 0.01 * abs(final)
    assert v[-1] == pytest.approx(final, rel=1e-3)
    # Time constant: 63.2 % of the final value is reached within one period of tau (+ the
    # half period the sampled step lags).
    idx = np.argmax(np.abs(v) >= 0.632 * abs(final))
    assert abs(t[idx] - (tau + ts / 2)) <= ts


def test_the_lag_along_the_file_is_a_first_order_low_pass_of_the_axial_force():
    """with_axial_lag(SELF_ALIGNMENT, 0.113): the z axis follows a force step as the first
    order of eq 4.32 with time constant 0.113 s and the same 6.25 mm/s per N; x, y keep
    Table 4.3's 1 ms."""
    ts, tau, f = 0.002, 0.113, 1.0
    params = with_axial_lag(SELF_ALIGNMENT, tau)
    assert params.time_constant(2) == pytest.approx(tau) and params.steady_gain(2) == 6.25
    assert params.time_constant(0) == pytest.approx(0.001) and params.m[3:] == \
        SELF_ALIGNMENT.m[3:]
    filt = AdmittanceFilter(params, ts)
    n = int(8 * tau / ts)
    v = np.array([filt.step([f, 0.0, f, 0.0, 0.0, 0.0]) for _ in range(n)])
    t = ts * np.arange(1, n + 1)
    analytic = first_order_response_to_sampled_step(500.0, 80.0, tau, f, ts, t)
    assert np.max(np.abs(v[:, 2] - analytic)) < 1e-3 * 6.25
    assert v[0, 0] == pytest.approx(3.125) and v[1, 0] == pytest.approx(6.25)


@pytest.mark.parametrize("lag_s", [0.0, -0.1, math.nan, math.inf])
def test_a_lag_along_the_file_must_be_a_time_constant(lag_s):
    with pytest.raises(ConfigError, match="axial_lag_s"):
        with_axial_lag(SELF_ALIGNMENT, lag_s)


def test_tustin_recursion_exact_values():
    # Hand computation of eq 4.25 for m = 0.08, b = 80, ts = 0.002: ts b = 2 m, so the
    # recursion is deadbeat: v1 = k ts/(ts b + 2m) (f1 + f0) = 500*0.002/0.32 * 1 = 3.125.
    filt = AdmittanceFilter(SELF_ALIGNMENT, 0.002)
    assert filt.step([1.0, 0, 0, 0, 0, 0])[0] == pytest.approx(3.125)
    assert filt.step([1.0, 0, 0, 0, 0, 0])[0] == pytest.approx(6.25)


def test_disabled_axis_never_moves():
    filt = AdmittanceFilter(SELF_ALIGNMENT)
    rng = np.random.default_rng(1)
    for _ in range(1000):
        v = filt.step(rng.normal(scale=50.0, size=6))
        assert v[5] == 0.0
    robot = Meca500(tool=matrix_from_pose([0, 0, 80, 0, 0, 0]))
    # A torque about the file axis alone moves nothing at all.
    ctl = AdmittanceController(robot, SELF_ALIGNMENT)
    q = np.array(Q0)
    for _ in range(100):
        cmd = ctl.step(q, np.array([0, 0, 0, 0, 0, 5.0]))
        assert np.all(cmd.qdot_deg_s == 0.0)
        q = cmd.q_target_deg
    np.testing.assert_array_equal(q, Q0)
    # With every other axis pushed too, the commanded joint rates never turn {H} about z.
    for _ in range(100):
        cmd = ctl.step(q, np.array([0.3, -0.2, 0.5, 0.01, -0.02, 5.0]))
        w_h = robot.tool_jacobian(q) @ np.radians(cmd.qdot_deg_s)
        assert w_h[5] == pytest.approx(0.0, abs=1e-12)
        assert np.linalg.norm(w_h[3:5]) > 0.0
        q = cmd.q_target_deg


def test_bad_parameters_are_refused_with_field_and_limit():
    with pytest.raises(ConfigError, match=r"admittance\.b3"):
        AdmittanceParams(k=500, b=(80, 80, -1, 80, 80, 80), m=(0.08,) * 6)
    with pytest.raises(ConfigError, match="exactly 6"):
        AdmittanceParams(k=500, b=(80,) * 5, m=(0.08,) * 6)
    with pytest.raises(ConfigError, match=r"admittance\.k"):
        AdmittanceParams(k=0, b=(80,) * 6, m=(0.08,) * 6)


def test_controller_moves_the_tool_tip_along_the_commanded_axis():
    # f_d = (0, 0, 1 N) in {H}: the tip advances along the file axis at 6.25 mm/s and does not
    # drift sideways (the Jacobian in {H} and the trapezoidal integration are consistent).
    tool = matrix_from_pose([0, 0, 60, 0, 0, 0])
    robot = Meca500(tool=tool)
    ctl = AdmittanceController(robot, SELF_ALIGNMENT)
    q = list(Q0)
    t0 = robot.fk_tool(q)
    n = 500  # 1 s
    for _ in range(n):
        q = ctl.step(q, np.array([0, 0, 1.0, 0, 0, 0])).q_target_deg
    t1 = robot.fk_tool(q)
    moved = t0[:3, :3].T @ (t1[:3, 3] - t0[:3, 3])
    # Trapezoid over v = 3.125, 6.25, 6.25, ... mm/s (eq 4.25 from rest):
    # ts * (3.125 + 6.25 * (n - 1)) - ts/2 * 6.25 = 6.2375 mm.
    assert moved[2] == pytest.approx(6.2375, rel=1e-4)
    assert np.hypot(moved[0], moved[1]) < 1e-2


def test_controller_reference_point_rotation_about_that_point():
    # A pure torque about x at reference point B must rotate about B: B stays where it is.
    tool = matrix_from_pose([0, 0, 60, 0, 0, 0])
    robot = Meca500(tool=tool)
    ref = (0.0, 0.0, -10.0)
    ctl = AdmittanceController(robot, SELF_ALIGNMENT, ref_point_h_mm=ref)
    q = list(Q0)
    shift = np.eye(4)
    shift[:3, 3] = ref
    b0 = (robot.fk_tool(q) @ shift)[:3, 3]
    for _ in range(200):
        q = ctl.step(q, np.array([0, 0, 0, 0.02, 0, 0])).q_target_deg
    b1 = (robot.fk_tool(q) @ shift)[:3, 3]
    # B stays put to within 10 um (the arm's repeatability is 5 um): the trapezoid of eq 4.25
    # mixes the rates of two neighbouring configurations, a second-order drift.
    assert np.linalg.norm(b1 - b0) < 0.01
    # 500/80 rad/s per N*m * 0.02 N*m = 0.125 rad/s; trapezoid from rest over 200 periods:
    # 0.002 * (0.0625 + 0.125 * 199) - 0.001 * 0.125 = 0.04975 rad, about the x axis of {H}.
    rel = robot.fk_tool(Q0)[:3, :3].T @ robot.fk_tool(q)[:3, :3]
    rotvec = Rotation.from_matrix(rel).as_rotvec()
    np.testing.assert_allclose(rotvec, [0.04975, 0.0, 0.0], atol=1e-4)  # 0.2 % (same drift)


def test_a_twist_beyond_the_joints_speeds_is_scaled_uniformly_and_reported():
    """A 1000 N push along x: the first filtered twist is k ts / (ts b + 2 m) x 1000 =
    500 x 0.002 / 0.32 x 1000 = 3125 mm/s, far beyond the joints' speeds. The limiter scales
    every joint by one factor, so the fastest joint runs exactly at its limit; the report
    says so. With no force nothing is limited."""
    robot = Meca500()
    ctl = AdmittanceController(robot, SELF_ALIGNMENT)
    calm = ctl.step(Q0, np.zeros(6))
    assert not calm.limits.limited and np.allclose(calm.qdot_deg_s, 0.0)
    ctl = AdmittanceController(robot, SELF_ALIGNMENT)
    cmd = ctl.step(Q0, np.array([1000.0, 0, 0, 0, 0, 0]))
    assert cmd.twist[0] == pytest.approx(3125.0)
    ratio = np.abs(cmd.qdot_deg_s) / robot.joint_speed_limits_deg_s
    assert ratio.max() == pytest.approx(1.0, rel=1e-9)
    assert cmd.limits.limited and 0.0 < cmd.limits.speed_scale < 1.0
    assert cmd.limits.singularity is not None


def test_the_lateral_axes_stiffen_with_the_file_s_shorter_free_part():
    """The scale is (L_ref / L)^3 below L_ref, L = file length - depth (a cantilever's
    lateral stiffness, 3EI/L^3), else 1; none without a depth or with the schedule off."""
    from dentibot.control.admittance_kernels import lateral_scale

    assert lateral_scale(5.0, 25.0, 18.0) == 1.0                 # 20 mm free
    assert lateral_scale(7.0, 25.0, 18.0) == 1.0                 # 18 mm: the edge
    assert lateral_scale(13.0, 25.0, 18.0) == pytest.approx(1.5 ** 3)        # 12 mm free
    assert lateral_scale(16.0, 25.0, 18.0) == pytest.approx(8.0)             # 9 mm free
    assert lateral_scale(math.nan, 25.0, 18.0) == 1.0
    assert lateral_scale(16.0, 25.0, 0.0) == 1.0
    assert lateral_scale(40.0, 25.0, 18.0) == pytest.approx(1000.0)  # capped at 0.1 L_ref


def test_a_lateral_scale_divides_the_lateral_gain_and_keeps_the_time_constant():
    """Raising b and m of x and y s times: the steady velocity k f / (b s) there, reached
    with the same time constant m/b; z (and the rotations) untouched."""
    from dentibot.control.admittance_kernels import filter_step

    p = AdmittanceParams(k=500.0, b=(80.0,) * 6, m=(8.0,) * 6)       # m/b = 0.1 s
    ts, s = 0.002, 4.0
    filt = AdmittanceFilter(p, ts)
    f = np.array([1.0, -2.0, 1.0, 0.0, 0.0, 0.0])
    out, trace = np.empty(6), []
    for _ in range(5000):                                             # 10 s: 100 tau
        filter_step(filt._a, filt._c, filt.v, filt._f_prev, f, 0.0, out, s)
        trace.append(out.copy())
    assert out[0] == pytest.approx(500.0 / (80.0 * s), rel=1e-9)
    assert out[1] == pytest.approx(-2.0 * 500.0 / (80.0 * s), rel=1e-9)
    assert out[2] == pytest.approx(500.0 / 80.0, rel=1e-9)
    # one time constant (50 ticks) in: 1 - e^-1 of the way on x, as on z without the scale
    x = np.array(trace)
    assert x[49, 0] / x[-1, 0] == pytest.approx(x[49, 2] / x[-1, 2], rel=1e-12)
    assert x[49, 2] / x[-1, 2] == pytest.approx(1.0 - math.exp(-1.0), abs=0.02)
