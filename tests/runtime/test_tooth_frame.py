"""Depth in the tooth's frame with the patient tracker: the working length holds when the
patient moves along the canal; a broken string with the file in the canal is a fault."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from sim_runs import harness

from dentibot.control.strings import ring_geometry
from dentibot.runtime.tooth import ToothConfig, ToothFrame
from dentibot.sim.faults import Jerk
from dentibot.sim.tracker_device import TrackerSimParams

WL = 16.0           # the default simulated canal's working length (mm)


def _pose(rotvec, p) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    t[:3, 3] = p
    return t


def test_a_reference_registered_in_the_tooth_frame_moves_with_the_tooth():
    """Synthetic: the tooth turns 10 deg about x and shifts 3 mm; the orifice and the canal
    axis registered before follow it exactly (a rigid motion applied to a point and a
    direction)."""
    tf = ToothFrame(ToothConfig(geometry=ring_geometry()))
    tf.pose_0t = _pose([0.0, 0.0, 0.0], [100.0, 0.0, 120.0])
    o, a = (101.0, 2.0, 118.0), (0.0, 0.0, -1.0)
    tf.register(o, a)
    move = _pose([np.radians(10.0), 0.0, 0.0], [0.0, 3.0, 0.0])
    tf.pose_0t = tf.pose_0t @ move
    o2, a2 = tf.reference_0()
    rel = np.array(o) - [100.0, 0.0, 120.0]                # the orifice in the tooth frame
    R = move[:3, :3]
    np.testing.assert_allclose(o2, np.array([100.0, 0.0, 120.0]) + R @ rel + [0.0, 3.0, 0.0],
                               atol=1e-12)
    np.testing.assert_allclose(a2, R @ np.array(a), atol=1e-12)
    assert np.linalg.norm(a2) == pytest.approx(1.0)


async def _drill_until_deep(h, depth_mm=8.0):
    assert await h.command("drill") is None
    assert await h.run_for(ticks=60_000, until=lambda r: r.last_row is not None
                           and r.last_row["true_depth_mm"] > depth_mm)


@pytest.mark.slow
async def test_the_tooth_moving_towards_the_robot_no_longer_takes_the_file_past_the_apex():
    """The tooth comes 4 mm towards the robot along the canal at 20 mm/s while the file is
    8 mm in, then drilling goes on. With the tracker the treatment stops at the working
    length measured in the tooth (the simulator's truth within 0.2 mm); without it the
    base-frame depth reads 4 mm short and the file is driven past the working length."""
    results = {}
    for tracked in (False, True):
        h, rows = harness(seed=3, tracker=TrackerSimParams() if tracked else None)
        w = h.world
        await _drill_until_deep(h)
        _, axis = w.canal_axis_0()
        w.motion = Jerk(w.motion, w.t, tuple(-x for x in axis), mm=4.0, mm_s=20.0)
        k0 = len(rows)
        await h.run_for(ticks=100_000, until=lambda r: r.state in ("done", "fault")
                        or r.last_row["true_depth_mm"] > WL + 0.3)
        after = rows[k0 + 500:]                            # the jerk is over (0.2 s)
        lag = np.median([r["true_depth_mm"] - r["depth_mm"] for r in after])
        results[tracked] = (h.runtime.state, max(r["true_depth_mm"] for r in rows), lag)
    state, deepest, lag = results[True]
    assert state == "done" and deepest <= WL + 0.2
    assert abs(lag) < 0.2                                  # depth reads the truth
    state, deepest, lag = results[False]
    assert deepest > WL + 0.3                              # past the working length
    assert lag == pytest.approx(4.0, abs=0.5)              # by the tooth's travel, unseen


async def test_a_broken_string_with_the_file_in_the_canal_stops_everything_within_10_ms():
    h, rows = harness(seed=3, tracker=TrackerSimParams())
    w = h.world
    await _drill_until_deep(h, 3.0)
    # the row carries the tracked tooth: the clamp frame is the phantom's ({T} = {P} in the
    # simulated tracker), so its origin is the simulator's orifice, to the encoders' accuracy
    np.testing.assert_allclose(rows[-1]["tooth_pose"][:3], w.phantom_origin_0(), atol=0.05)
    tracker = h.runtime.dev.tracker
    k0 = len(rows)
    tracker.model.broken.add(2)                            # string 3 snaps: winds in fully
    assert await h.run_for(ticks=50, until=lambda r: r.state == "fault")
    detected_ms = (len(rows) - k0) * 2.0
    assert detected_ms <= 10.0
    cause = h.runtime.treatment.fault_causes[0]
    assert cause.startswith("tracker") and "string 3" in cause
    await h.run_for(ticks=25)                              # 50 ms
    assert w.handpiece.cmd_rpm == 0.0 and max(abs(x) for x in w.arm.qdot) < 1.0


async def test_before_the_file_goes_in_a_broken_string_only_loses_the_tooth_pose():
    h, rows = harness(seed=3, tracker=TrackerSimParams())
    h.runtime.dev.tracker.model.broken.add(0)
    await h.run_for(ticks=20)
    assert h.runtime.state == "idle"
    assert h.runtime.ctx.tooth.pose_0t is None
    assert rows[-1]["tooth_pose"] is None


@pytest.mark.parametrize("speed, fed", [(20.0, True), (1.0, False)])
def test_the_feedforward_is_the_orifices_velocity_in_h_above_the_deadband(speed, fed):
    """The orifice moves at ``speed`` mm/s along base x for 0.2 s: hybrid control feeds that
    velocity forward, in {H} axes (here {H} is turned 90 deg about z: base x is -y in {H});
    below the 2 mm/s deadband nothing is fed (a still patient feeds no encoder noise)."""
    tf = ToothFrame(ToothConfig(geometry=ring_geometry(), feedforward=True), period_s=0.002)
    tf.pose_0t = np.eye(4)
    tf.register((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    for k in range(100):
        tf._track_velocity(np.array([speed * 0.002 * k, 0.0, 0.0]))
    r_0_h = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    ff = tf.feedforward_h(r_0_h)
    if not fed:
        assert ff is None
        return
    np.testing.assert_allclose(ff, [0.0, -speed, 0.0, 0.0, 0.0, 0.0], atol=1e-9)
    tf.forget()
    assert tf.feedforward_h(r_0_h) is None                   # the file is out: nothing


def test_without_hybrid_control_nothing_is_fed_forward():
    tf = ToothFrame(ToothConfig(geometry=ring_geometry()), period_s=0.002)
    tf.pose_0t = np.eye(4)
    tf.register((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    for k in range(100):
        tf._track_velocity(np.array([0.04 * k, 0.0, 0.0]))
    assert tf.feedforward_h(np.eye(3)) is None


async def test_the_tracker_follows_a_turning_patient():
    """The patient turns 3 deg about a hinge 60 mm from the orifice while the file is 3 mm in:
    the tracked tooth's orientation follows the simulator's within 0.05 deg, and the depth
    measured in the tooth stays the true depth."""
    h, rows = harness(seed=3, tracker=TrackerSimParams())
    w = h.world
    await _drill_until_deep(h, 3.0)
    o, _ = w.canal_axis_0()
    w.motion = Jerk(w.motion, w.t, mm=0.0, deg=3.0, axis=(0.0, 1.0, 0.0),
                    centre_mm=(o[0], o[1], o[2] - 60.0), deg_s=10.0)
    await h.run_for(ticks=300)                              # 0.6 s: the turn is over
    row = rows[-1]
    tracked = Rotation.from_euler("XYZ", row["tooth_pose"][3:], degrees=True)  # mobile XYZ
    error = tracked.inv() * Rotation.from_matrix(w.phantom_rotation)
    assert np.degrees(error.magnitude()) < 0.05
    turned = Rotation.from_matrix(w.phantom_rotation @ w.phantom_pose[:3, :3].T)
    assert np.degrees(turned.magnitude()) == pytest.approx(3.0, abs=1e-9)
    assert row["depth_mm"] == pytest.approx(row["true_depth_mm"], abs=0.2)


def test_a_turning_tooth_feeds_its_rigid_motion_forward_at_the_tip():
    """The tooth turns at 10 deg/s about the y axis through a hinge 60 mm below the orifice
    (the jaw), the file tip 5 mm into the canal. The feedforward is the tooth's twist at
    the tip, worked out by hand for a rigid body turning about a fixed centre c:
    omega = (0, w, 0) and v_tip = omega x (tip - c) = (65 w, 0, 0) mm/s with
    tip - c = (0, 0, 65) mm; in {H} (turned 90 deg about z) base x is -y and base y is x."""
    w = np.radians(10.0)                                   # rad/s
    centre = np.array([0.0, 0.0, -60.0])
    o_rest = np.zeros(3)
    tip = np.array([0.0, 0.0, 5.0])                        # a point fixed in {0}
    ts = 0.002
    tf = ToothFrame(ToothConfig(geometry=ring_geometry(), feedforward=True), period_s=ts)
    tf.pose_0t = np.eye(4)
    tf.register(o_rest, (0.0, 0.0, -1.0))
    n = 50                                                 # 0.1 s: 12 filter time constants
    for k in range(-n, 1):                                 # the turn ends at angle 0 (k = 0)
        R = Rotation.from_rotvec([0.0, w * ts * k, 0.0]).as_matrix()
        tf.pose_0t = _pose(Rotation.from_matrix(R).as_rotvec(), centre + R @ (o_rest - centre))
        tf._track_velocity(tf.pose_0t[:3, 3].copy(), R)
    r_0_h = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    ff = tf.feedforward_h(r_0_h, point_0=tip)
    np.testing.assert_allclose(ff[3:], [w, 0.0, 0.0], atol=1e-9)     # (0, w, 0) in {H}
    # the orifice's velocity is 60 w along x; the low-pass and the difference over
    # DIFF_TICKS periods (the chord's mid-point) lag its turning direction by about
    # w (tau + DIFF_TICKS ts / 2) = 2.8e-3 rad, hence 65 w 2.8e-3 = 0.03 mm/s
    np.testing.assert_allclose(ff[:3], [0.0, -65.0 * w, 0.0], atol=0.05)
    # the default point is the file tip of the last tick
    tf.point_0 = tip
    np.testing.assert_allclose(tf.feedforward_h(r_0_h), ff, atol=1e-12)
    # at the orifice itself, only the orifice's own velocity: 60 w along x
    np.testing.assert_allclose(tf.feedforward_h(np.eye(3), point_0=o_rest)[:3],
                               [60.0 * w, 0.0, 0.0], atol=0.05)


def test_a_tooth_turning_about_the_tip_feeds_a_rotation_with_no_translation_there():
    """Turning at 5 deg/s about the tip itself (centre = tip, 8 mm into the canal along -z):
    the tip's point of the tooth does not move, so the twist at the tip is (0, 0, 0, omega),
    though the orifice moves (at 8 mm x omega = 0.70 mm/s)."""
    w = np.radians(5.0)
    tip = np.array([0.0, 0.0, -8.0])
    ts = 0.002
    tf = ToothFrame(ToothConfig(geometry=ring_geometry(), feedforward=True), period_s=ts)
    tf.pose_0t = np.eye(4)
    tf.register((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    for k in range(-50, 1):
        R = Rotation.from_rotvec([w * ts * k, 0.0, 0.0]).as_matrix()
        tf._track_velocity(tip + R @ (np.zeros(3) - tip), R)
    ff = tf.feedforward_h(np.eye(3), point_0=tip)
    np.testing.assert_allclose(ff[3:], [w, 0.0, 0.0], atol=1e-9)
    # the filter lags the orifice velocity's direction by about w (tau + ts/2): 0.7 mm/s
    # x 8e-4 rad = 6e-4 mm/s
    np.testing.assert_allclose(ff[:3], [0.0, 0.0, 0.0], atol=1e-3)


def test_a_turn_slower_than_the_deadband_feeds_nothing():
    """1 deg/s about the orifice, below the 5 deg/s deadband, and the orifice still: nothing
    is fed forward (a still patient's orientation noise does not move the arm)."""
    ts = 0.002
    tf = ToothFrame(ToothConfig(geometry=ring_geometry(), feedforward=True), period_s=ts)
    tf.pose_0t = np.eye(4)
    tf.register((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    for k in range(100):
        R = Rotation.from_rotvec([0.0, 0.0, np.radians(1.0) * ts * k]).as_matrix()
        tf._track_velocity(np.zeros(3), R)
    assert tf.feedforward_h(np.eye(3), point_0=(0.0, 0.0, -5.0)) is None


def _angle_deg(u, v) -> float:
    c = float(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v)))
    return float(np.degrees(np.arccos(min(1.0, max(-1.0, c)))))


@pytest.mark.parametrize("hybrid", [True, False])
async def test_hybrid_control_turns_the_handpiece_with_a_turning_tooth(hybrid):
    """The patient turns 5 deg at 20 deg/s about a hinge 60 mm beyond the orifice along the
    canal while the file is 3 mm in (the canal-axis servo off: the feedforward alone). With
    hybrid control the handpiece turns with the tooth: by the tooth's 5 deg within a fifth
    of it, and the file never more than that fifth (1 deg) further from the canal's axis than
    before the turn; the treatment goes on and the depth stays the true depth. With the
    tracker alone (no feedforward) the handpiece turns by force only, which at this rate
    lags by more than that fifth."""
    from sim_runs import GAP_MM, MADE

    from dentibot.app.procedure import Procedure
    from dentibot.app.tracking import sim_tooth_config
    from dentibot.runtime.config import RuntimeConfig, TreatmentPlan
    from dentibot.sim.world import World, WorldConfig

    w = World(WorldConfig(seed=3))
    tp = TrackerSimParams()
    cfg = RuntimeConfig(plan=TreatmentPlan(orifice_gap_mm=GAP_MM, axis_servo=None),
                        tooth=sim_tooth_config(w, tp, feedforward=hybrid))
    h = Procedure.simulated(w, cfg, keep_rows=True, tracker=tp, hybrid=hybrid)
    MADE.append(h)
    await _drill_until_deep(h, 3.0)
    o, a = w.canal_axis_0()
    file_0 = np.array(w.axis_0)
    error_0 = _angle_deg(file_0, a)
    turn = np.cross(a, [1.0, 0.0, 0.0])
    w.motion = Jerk(w.motion, w.t, mm=0.0, deg=5.0, axis=tuple(turn / np.linalg.norm(turn)),
                    centre_mm=tuple(np.array(o) + 60.0 * np.array(a)), deg_s=20.0)
    errors = []
    for _ in range(250):                                    # 0.5 s: the turn takes 0.25 s
        await h.run_for(ticks=1)
        errors.append(_angle_deg(w.axis_0, w.canal_axis_0()[1]))
    assert _angle_deg(a, w.canal_axis_0()[1]) == pytest.approx(5.0, abs=1e-6)
    if not hybrid:
        assert max(errors) > error_0 + 1.0
        return
    assert _angle_deg(file_0, w.axis_0) == pytest.approx(5.0, abs=1.0)
    assert max(errors) <= error_0 + 1.0
    assert h.runtime.state.startswith("treating")
    row = h.rows[-1]
    assert row["depth_mm"] == pytest.approx(row["true_depth_mm"], abs=0.2)


def test_the_tooth_is_found_again_after_the_arm_swings_away_and_back():
    """A load calibration swings the mount through large poses; strings leave their range on
    the way (a lost stretch). A still tooth is then where it was: the pose is solved again
    from the arm's own known motion (the tooth's last pose seen from the mount now), within
    the strings' noise of the truth, and no pose reads as a jump while the arm alone moves.
    Before, the jump check compared every sample with the last good one and the tooth stayed
    lost after the swing."""
    import asyncio

    from dentibot.app.tracking import sim_tooth_config
    from dentibot.sim import World, WorldConfig
    from dentibot.sim.tracker_device import SimPatientTracker

    w = World(WorldConfig(seed=1))
    tp = TrackerSimParams()
    tf = ToothFrame(sim_tooth_config(w, tp))
    dev = SimPatientTracker(w, tp)
    q0 = np.array(w.arm.q)

    def sample_at(q):
        w.teleport_arm(q)
        w.steps += 1                            # the tracker samples once per world step
        w.t += w.ts
        qr = np.array(w.arm.reading()[0])
        t = w.kin.fk(qr)
        return tf.update(asyncio.run(dev.read()), t[:3, :3], t[:3, 3])

    assert sample_at(q0) is None
    truth = tf.pose_0t.copy()
    findings = []
    swing = [q0 + np.array([0.0, 0.0, 0.0, 0.0, 0.4 * k, 0.3 * k]) for k in range(1, 60)]
    for q in swing + swing[::-1] + [q0] * 20:                # 24 deg out and back
        f = sample_at(q)
        if f is not None:
            findings.append(f.detail)
    assert not any("jumped" in d for d in findings), findings[:3]
    np.testing.assert_allclose(tf.pose_0t[:3, 3], truth[:3, 3], atol=0.05)
    turn = Rotation.from_matrix(tf.pose_0t[:3, :3] @ truth[:3, :3].T).magnitude()
    assert np.degrees(turn) < 1.0


@pytest.mark.parametrize("tracked", [False, True])
async def test_an_axial_jerk_at_40_mm_s_breaks_no_file(tracked):
    """The tooth jumps 3 mm towards the robot along the canal at 40 mm/s while the file is
    8 mm in, turning (drilling), with and without the tracker (hybrid control): the file does
    not break, and its true torque (the simulator's) stays under its 62 mNm strength. The
    wrench norm peaks near the 1.5 N patient-moved trigger, too late to help: the file's
    torque rise reverses it first, and the drive's current limit bounds it."""
    from dentibot.control.feedrate import FILE_STRENGTH_MNM

    h, rows = harness(seed=3, tracker=TrackerSimParams() if tracked else None,
                      **({"hybrid": True} if tracked else {}))
    w = h.world
    await _drill_until_deep(h)
    _, axis = w.canal_axis_0()
    w.motion = Jerk(w.motion, w.t, tuple(-x for x in axis), mm=3.0, mm_s=40.0)
    peak = 0.0

    def watch(r) -> bool:
        nonlocal peak
        peak = max(peak, abs(w.handpiece.torque_mnm))
        return r.state == "fault"

    await h.run_for(ticks=500, until=watch)                # 1 s
    assert w.fractured is None
    assert 40.0 < peak < FILE_STRENGTH_MNM                 # loaded hard, and not past it
