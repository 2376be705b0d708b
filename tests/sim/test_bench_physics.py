"""The bench-fitted mechanisms, checked against the preset's own parameters."""

import math
from dataclasses import replace
from itertools import pairwise

import numpy as np
import pytest

from dentibot.control.kinematics import Meca500
from dentibot.sim.arm import ArmParams, SimArmModel
from dentibot.sim.bench_physics import BENCH, axial_chase
from dentibot.sim.canal import CanalParams
from dentibot.sim.patient import BenchSquarePath
from dentibot.sim.world import HOME_Q_DEG

TS = 0.002


def _step_response(params, seconds=0.2):
    arm = SimArmModel(Meca500(), HOME_Q_DEG, params)
    cmd = [0.0, 0.0, 0.0, 0.0, 0.0, 10.0]
    out = []
    for k in range(round(seconds / TS)):
        t = (k + 1) * TS
        arm.command_velocity(cmd, t - TS)          # renewed every period, as the bench did
        arm.step(t, TS)
        out.append(arm.qdot[5])
    return out


def test_default_arm_is_unchanged():
    p = ArmParams()
    assert p.vel_dead_time_s == 0.0 and p.vel_gain == 1.0
    v = _step_response(p)
    assert v[0] > 0.0                                # no dead time
    assert abs(v[-1] - 10.0) < 1e-3                  # unit gain


def test_bench_arm_step_dead_time_lag_gain():
    b = BENCH
    v = _step_response(b.arm())
    n_dead = round(b.arm_dead_time_s / TS)
    assert all(x == 0.0 for x in v[:n_dead - 1])     # the queue delay
    assert v[n_dead + 2] > 0.0
    assert abs(v[-1] - 10.0 * b.arm_gain) < 1e-3     # the realised gain
    # first-order lag: 63 % of the final value one time constant after the dead time
    target = (1.0 - math.exp(-1.0)) * 10.0 * b.arm_gain
    k63 = next(i for i, x in enumerate(v) if x >= target)
    t63 = (k63 + 1) * TS - b.arm_dead_time_s
    assert abs(t63 - b.arm_lag_s) <= TS + 1e-9


def test_canal_drag_off_by_default():
    p = CanalParams()
    assert p.drag_n_s_per_mm == 0.0 and p.drag_coulomb_n == 0.0
    assert p.drag_lat_n_s_per_mm == 0.0 and p.bottom_torque_mnm_per_n == 0.0


def test_bench_platform_speeds():
    path = BENCH.platform()
    assert path.offset_mm(0.0) == (0.0, 0.0, 0.0)
    assert len(path.square_starts_s) == 4
    # the z travel of each square is about 15 mm, in its measured duration
    for t0, d in zip(path.square_starts_s, path.durations_s):
        zs = [path.stewart_mm(t0 + d * i / 200)[2] for i in range(200)]
        assert 13.5 < max(zs) - min(zs) < 16.0
    assert isinstance(path, BenchSquarePath)


def _ringing(lowpass_ms):
    """The seated file's contact force after the root steps 0.2 mm onto it (config B, the
    reduced axial model): the frequency of its first three cycles (Hz) and its half-cycle
    peaks (N)."""
    t = np.arange(0.0, 6.0, TS)
    r = axial_chase(t, np.where(t < 1.0, 0.0, 0.2), "B", lowpass_ms=lowpass_ms)
    x = r["fz_h_n"][t > 1.0]
    x = x - x[-500:].mean()
    zc = np.flatnonzero(np.diff(np.sign(x)))
    freq = 1.0 / (2 * TS * np.median(np.diff(zc)[:6]))
    peaks = [float(np.abs(x[a:b]).max()) for a, b in pairwise(zc[:7])]
    return freq, peaks


def test_the_seated_file_rings_where_its_loop_turns_half_round():
    """The admittance integrates (-90 deg); the arm's dead time and lag and the reading's
    low-pass add the rest of the half turn at one frequency, 3.1 Hz with the bench's values
    (the recordings chatter at 2.8-3.3 Hz with the file bottomed out). Knocked, the seated
    file rings there, slowly decaying; with an unfiltered reading it rings at 8 Hz and is
    gone within three cycles."""
    lp = BENCH.ft_lowpass_s

    def turn(w):
        return (math.pi / 2 + w * BENCH.arm_dead_time_s + math.atan(w * BENCH.arm_lag_s)
                + math.atan(w * lp) - math.pi)

    from scipy.optimize import brentq
    f180 = brentq(turn, 1.0, 200.0) / (2 * math.pi)
    assert 2.8 <= f180 <= 3.3
    freq, peaks = _ringing(1000 * lp)
    assert freq == pytest.approx(f180, rel=0.15)
    assert all(b / a > 0.8 for a, b in pairwise(peaks))
    freq0, peaks0 = _ringing(0.0)
    assert freq0 > 6.0 and peaks0[5] < 0.05 * peaks0[0]


def _loop_deviation(path, square, n=400):
    """The path's deviation from its mean loop over one square (n samples, Stewart mm)."""
    t0, d = path.square_starts_s[square], path.durations_s[square]
    plain = BenchSquarePath(path.knots[:-1], path.durations_s,
                            [b - a - dd for a, b, dd in zip(path.square_starts_s,
                                                            path.square_starts_s[1:],
                                                            path.durations_s)])
    ts = [t0 + d * i / n for i in range(n)]
    return np.array([np.subtract(path.stewart_mm(t), plain.stewart_mm(t)) for t in ts])


def test_platform_wander_has_its_rms_and_keeps_every_square_starting_at_rest():
    """Over many squares the wander's rms per axis is the one asked for (linear interpolation
    between independent offsets drawn with rms / sqrt(2/3) has the asked variance on
    average; the two end segments, towards a zero offset, have half of it: 11/12 of it over
    12 segments), every square starts and ends on the loop, and a seed gives the same
    path."""
    rms = (0.5, 0.4, 0.1)
    n_sq = 300
    knots = BENCH.platform_knots_mm

    def path(seed):
        return BenchSquarePath(knots, [10.0] * n_sq, [1.0] * (n_sq - 1), wander_mm=rms,
                               rng=np.random.default_rng(seed))

    p = path(7)
    dev = np.concatenate([_loop_deviation(p, k, 120) for k in range(n_sq)])
    got = np.sqrt((dev ** 2).mean(0))
    expected = np.array(rms) * math.sqrt(11.0 / 12.0)
    assert np.allclose(got, expected, rtol=0.06), (got, expected)
    for k in (0, 5, n_sq - 1):
        t0, d = p.square_starts_s[k], p.durations_s[k]
        assert p.stewart_mm(t0) == pytest.approx(knots[0], abs=1e-12)
        assert p.stewart_mm(t0 + d - 1e-9) == pytest.approx(knots[0], abs=1e-6)
    assert path(7).stewart_mm(12.3) == p.stewart_mm(12.3)
    assert path(8).stewart_mm(12.3) != p.stewart_mm(12.3)


def test_platform_without_wander_runs_the_loop_every_square():
    p = BenchSquarePath(BENCH.platform_knots_mm, [10.0, 10.0], [1.0])
    a = [p.stewart_mm(0.5 + 9.0 * i / 50) for i in range(50)]
    b = [p.stewart_mm(11.5 + 9.0 * i / 50) for i in range(50)]
    assert np.allclose(a, b, atol=1e-9)


def test_platform_wander_rejects_bad_values():
    with pytest.raises(ValueError, match="wander_mm"):
        BenchSquarePath(BENCH.platform_knots_mm, [10.0], [], wander_mm=(0.1, -0.1, 0.0))


def _turning_path(roll, pitch=0.0, centre=(10.0, 20.0, 30.0)):
    return BenchSquarePath(BENCH.platform_knots_mm, [20.0], [], frame_yaw_deg=12.0,
                           tilt_rad_per_mm=(roll, pitch), centre_mm=centre)


def test_a_rolling_platform_carries_a_point_below_its_centre_across_its_travel():
    """A roll of r rad per mm of x travel turns the platform by a = r x about x_S: a point h
    below the centre goes from (0, 0, -h) to (0, h sin a, -h cos a) in the Stewart frame
    (rotation about x), on top of the travel itself."""
    h, roll = 20.0, -0.003
    p = _turning_path(roll)
    t = 4.3                                    # on the bottom leg, x well away from 0
    x, _, _ = p.stewart_mm(t)
    assert x < -5.0
    R, c = p.rotation_at(t)
    assert c == (10.0, 20.0, 30.0)
    d = np.array(R) @ np.array([0.0, 0.0, -h])         # the point, from the centre, turned
    S = np.array([p.ex, p.ey, (0.0, 0.0, 1.0)])
    a = roll * x
    assert S @ d == pytest.approx([0.0, h * math.sin(a), -h * math.cos(a)], abs=1e-9)
    assert np.allclose(np.array(R) @ np.array(R).T, np.eye(3), atol=1e-12)
    moved = np.add(p.centre_at(t), d)
    assert moved - np.add(c, (0.0, 0.0, -h)) == pytest.approx(
        np.add(p.offset_mm(t), S.T @ [0.0, h * math.sin(a), h - h * math.cos(a)]), abs=1e-9)


def test_a_platform_at_rest_or_without_tilt_does_not_turn():
    assert np.array_equal(_turning_path(-0.003).rotation_at(-1.0)[0], np.eye(3))
    assert np.array_equal(_turning_path(0.0).rotation_at(4.3)[0], np.eye(3))
    with pytest.raises(ValueError, match="tilt_rad_per_mm"):
        BenchSquarePath(BENCH.platform_knots_mm, [20.0], [], tilt_rad_per_mm=(math.nan, 0.0))


def test_the_bench_world_turns_its_phantom_with_the_platform():
    """The bench's world: after 3 s of the first square the phantom's orientation is its
    orientation at rest turned by the preset's roll times the platform's x travel, about
    x_S."""
    from dentibot.sim.patient import axis_angle_matrix
    from dentibot.sim.world import World

    cfg = BENCH.world_config(seed=1, start_s=0.0)
    w = World(cfg)
    r0 = w.phantom_rotation.copy()
    for _ in range(1500):
        w.step()
    x, _, _ = w.motion.stewart_mm(w.t)
    assert x < -1.0
    turn = np.array(axis_angle_matrix(w.motion.ex, BENCH.platform_tilt_rad_per_mm[0] * x))
    assert w.phantom_rotation == pytest.approx(turn @ r0, abs=1e-12)


@pytest.mark.parametrize("turning", [True, False])
@pytest.mark.parametrize("depth_mm", [4.0, 12.0])
def test_the_axial_drag_acts_in_proportion_to_the_files_length_in_the_canal(depth_mm,
                                                                           turning):
    """A file sliding deeper at 1 mm/s through a lumen already of its shape (nothing to cut:
    the walls' drag alone pushes it out): (b v + C tanh(v / v0)) s / D at depth s, D the
    depth the drag was fitted at, C the still file's friction (0 for a turning file); without
    a depth, the same at any depth."""
    from dentibot.sim.canal import Canal
    from dentibot.sim.nitifile import NiTiFile

    file, v, b, c, v0 = NiTiFile(), 1.0, 0.21, 0.85, 0.5
    shaped = CanalParams(initial_apical_mm=CanalParams.target_apical_mm,
                         initial_taper=CanalParams.target_taper)
    for fitted_at in (16.5, 0.0):
        canal = Canal(replace(shaped, drag_n_s_per_mm=b, drag_still_coulomb_n=c,
                              drag_v0_mm_s=v0, drag_depth_mm=fitted_at))
        canal.turning = turning                   # as the world sets it each step
        s = depth_mm
        for _ in range(100):                      # the slip's 4 ms filter settles
            it = canal.interact((0.0, 0.0, s), (0.0, 0.0, 1.0), file, TS)
            s += v * TS
        assert it.engagement_mm2 == 0.0
        share = (s - v * TS) / fitted_at if fitted_at else 1.0
        held = 0.0 if turning else c * math.tanh(v / v0)
        assert it.f_axial_n == pytest.approx((b * v + held) * share, rel=1e-3)
