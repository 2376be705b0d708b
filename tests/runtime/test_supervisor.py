"""Supervisor checks on synthetic data with known answers."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from dentibot.control.kinematics import Meca500
from dentibot.io.interfaces import WRENCH_SATURATED, AuxState, JointState, MotorState, Wrench
from dentibot.runtime.supervisor import Supervisor, SupervisorLimits

Q = (0.0, -10.0, 20.0, 0.0, 80.0, 0.0)
STALE = {"arm": 10, "ft": 5, "motor": 10, "aux": 50}


def samples(k, force=(0.0, 0.0, 0.0), status=0, estop=False, fault=None):
    return (JointState(0.0, k, Q, (0.0,) * 6), Wrench(0.0, k, force, (0.0, 0.0, 0.0), status),
            MotorState(0.0, k, 60.0, 0.0, 0.05, True, fault),
            AuxState(0.0, k, False, estop, (0.0, 0.0, 0.0)))


def kinds(findings):
    return [f.kind for f in findings]


def test_clean_inputs_give_no_finding_and_each_input_fault_is_named():
    s = Supervisor(STALE, 0.002)
    assert s.check_inputs(0, *samples(0)) == []
    assert kinds(s.check_inputs(1, *samples(1, status=WRENCH_SATURATED))) == ["ft_saturated"]
    assert kinds(s.check_inputs(2, *samples(2, estop=True))) == ["estop"]
    assert kinds(s.check_inputs(3, *samples(3, fault="EMCY 0x2310"))) == ["motor"]
    assert kinds(s.check_inputs(4, *samples(4, force=(math.inf, 0, 0)))) == ["nonfinite_wrench"]


def test_a_force_step_beyond_the_jump_limit_is_a_glitch():
    s = Supervisor(STALE, 0.002, SupervisorLimits(ft_jump_n=15.0))
    s.check_inputs(0, *samples(0, force=(1.0, 0.0, 0.0)))
    assert s.check_inputs(1, *samples(1, force=(15.9, 0.0, 0.0))) == []      # 14.9 N
    f = s.check_inputs(2, *samples(2, force=(31.0, 0.0, 0.0)))               # 15.1 N
    assert kinds(f) == ["ft_jump"] and "15.1 N" in f[0].detail


def test_a_stream_is_stale_after_its_bound_in_periods():
    s = Supervisor(STALE, 0.002)
    _, w, _, _ = samples(7)
    for k in range(6):   # the F/T seq stays 7 while the others advance
        out = s.check_inputs(k, JointState(0.0, k, Q, (0.0,) * 6), w,
                             MotorState(0.0, k, 0.0, 0.0, 0.0, True),
                             AuxState(0.0, k, False, False, (0.0,) * 3))
        assert out == [], k
    out = s.check_inputs(6, JointState(0.0, 6, Q, (0.0,) * 6), w,
                         MotorState(0.0, 6, 0.0, 0.0, 0.0, True),
                         AuxState(0.0, 6, False, False, (0.0,) * 3))
    assert kinds(out) == ["stale_ft"] and "6 periods (limit 5)" in out[0].detail


def _est(tau_current, tau_ft_nm, tip=(0.0, 0.0, 0.0), q=Q):
    return SimpleNamespace(file_torque_mnm=tau_current,
                           wrench_h=np.array([0, 0, 0, 0, 0, tau_ft_nm]), tip_0=tip,
                           q_deg=np.array(q))


def test_torque_sources_must_agree_within_the_grace_time():
    robot = Meca500()
    _, frames = robot.tool_jacobian(Q, with_frames=True)
    s = Supervisor(STALE, 0.002, SupervisorLimits(torque_disagreement_mnm=15.0,
                                                  torque_disagreement_s=0.1))
    # the sensor sees the canal's reaction: -30 mNm about the file axis for a 30 mNm cut
    for _ in range(100):
        assert s.check_estimate(_est(30.0, -0.030), robot, frames, None, 16.0, True) == []
    # current says 30 mNm, sensor says 10 mNm: 20 apart; a fault once longer than 0.1 s
    found = [s.check_estimate(_est(30.0, -0.010), robot, frames, None, 16.0, True)
             for _ in range(51)]
    assert all(f == [] for f in found[:50]) and kinds(found[50]) == ["torque_disagreement"]


def test_workspace_box_and_singularity_margin():
    robot = Meca500()
    lim = SupervisorLimits()
    _, frames = robot.tool_jacobian(Q, with_frames=True)
    s = Supervisor(STALE, 0.002)
    ref = ((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))            # orifice at 0, file pointing down
    ok = s.check_estimate(_est(0, 0, tip=(24.0, 0.0, -10.0)), robot, frames, ref, 16.0, False)
    assert ok == []
    out = s.check_estimate(_est(0, 0, tip=(26.0, 0.0, -10.0)), robot, frames, ref, 16.0, False)
    assert kinds(out) == ["workspace"]
    out = s.check_estimate(_est(0, 0, tip=(0.0, 0.0, -(16.0 + lim.workspace_past_wl_mm + 0.1))),
                           robot, frames, ref, 16.0, False)
    assert kinds(out) == ["workspace"]
    q_wrist = (0.0, -10.0, 20.0, 0.0, 0.5, 0.0)            # |sin q5| = 0.0087 < sin 1 deg
    _, fw = robot.tool_jacobian(q_wrist, with_frames=True)
    out = s.check_estimate(_est(0, 0, q=q_wrist), robot, fw, None, 16.0, False)
    assert kinds(out) == ["singularity"] and "wrist" in out[0].detail


def test_command_caps():
    s = Supervisor(STALE, 0.002, SupervisorLimits(tip_speed_cap_mm_s=50.0))
    limits = [150, 150, 180, 300, 300, 500]
    assert s.check_command([150, 0, 0, 0, 0, -500], np.zeros(6), limits) == []
    assert kinds(s.check_command([0, 0, 181, 0, 0, 0], np.zeros(6), limits)) == ["joint_speed"]
    assert kinds(s.check_command([0] * 6, np.array([30.0, 40.0, 0.1, 0, 0, 0]), limits)) == \
        ["tip_speed"]                                      # |(30, 40, 0.1)| = 50.0001 mm/s


def test_a_force_jump_is_measured_on_the_largest_component():
    s = Supervisor(STALE, 0.002, SupervisorLimits(ft_jump_n=15.0))
    s.check_inputs(0, *samples(0, force=(1.0, 2.0, -3.0)))
    assert s.check_inputs(1, *samples(1, force=(-13.0, 2.0, 11.0))) == []    # 14 N each
    f = s.check_inputs(2, *samples(2, force=(-13.0, -13.5, 11.0)))           # 15.5 N in y
    assert kinds(f) == ["ft_jump"] and "15.5 N" in f[0].detail


def test_the_tip_speed_cap_holds_relative_to_a_tracked_tooth():
    """Hybrid control: the file follows a tooth jerking at 40 mm/s; commanded 56 mm/s in the
    base frame, it moves 16 mm/s relative to the tooth, under the 50 mm/s cap. The same
    command without a tracked tooth is over the cap."""
    from dentibot.runtime.supervisor import Supervisor

    sup = Supervisor({}, 0.002)
    limits = [1000.0] * 6
    twist = [56.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert [f.kind for f in sup.check_command([0.0] * 6, twist, limits)] == ["tip_speed"]
    assert sup.check_command([0.0] * 6, twist, limits, [40.0, 0.0, 0.0, 0.0, 0.0, 0.0]) == []
    far = [-15.0, 0.0, 0.0, 0.0, 0.0, 0.0]            # the file against the tooth: 71 mm/s
    found = sup.check_command([0.0] * 6, twist, limits, far)
    assert len(found) == 1 and "relative to the tracked tooth" in found[0].detail


def test_the_kernels_saturation_bit_is_the_interfaces_and_its_streams_in_order():
    from dentibot.runtime import supervisor_kernels as sk

    assert sk.SATURATED_BIT == WRENCH_SATURATED
    assert sk.INPUT_OUT_FIELDS[:4] == tuple(f"stale_{n}" for n in sk.STREAMS)


def test_a_stale_stream_is_named_with_its_age_and_bound():
    """The F/T stream's sequence number stops changing at tick 1: with a bound of 5 periods
    (STALE), ticks 2-6 are within it (ages 1-5) and tick 7 (age 6) is the first finding."""
    s = Supervisor(STALE, 0.002)
    found = []
    for k in range(1, 9):
        js, _, m, aux = samples(k)
        found.append(s.check_inputs(k, js, Wrench(0.0, 1, (0.0,) * 3, (0.0,) * 3), m, aux))
    assert found[:6] == [[]] * 6
    assert kinds(found[6]) == ["stale_ft"]
    assert found[6][0].detail == "ft stream: seq 1 unchanged for 6 periods (limit 5)"
