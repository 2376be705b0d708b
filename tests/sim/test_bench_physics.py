"""The bench-fitted mechanisms, checked against the preset's own parameters."""

import math

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


def test_fz_oscillation_emerges_at_the_bottom():
    """With Fz_des 1 N and the file bottomed out on a still root, the axial loop (dead time,
    lag, contact stiffness) is not silent: the force settles near -1 N."""
    t = [0.0, 5.0]
    r = axial_chase(t, [0.0, 0.0], "A")
    assert abs(r["fz_h_n"][-1] + 1.0) < 0.3
