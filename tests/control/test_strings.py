"""The string (draw-wire) tracker's kinematics: synthetic cases with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dentibot.control import strings as s
from dentibot.control import strings_kernels as kernels
from dentibot.errors import ConfigError, IdentificationError

GEO = s.ring_geometry()              # mount ring r 40 mm, clamp ring r 15 mm
SIGMA = 0.01                         # mm, a 0.01 mm resolution class encoder


def pose(rx=0.0, ry=0.0, rz=0.0, x=0.0, y=0.0, z=90.0):
    R = Rotation.from_euler("xyz", [rx, ry, rz], degrees=True).as_matrix()
    return R, np.array([x, y, z])


def test_inverse_kinematics_of_a_hand_computed_case():
    geo = s.StringGeometry(np.array([[10.0, 0, 0], [0, 10, 0], [0, 0, 0]]),
                           np.array([[0.0, 0, 0], [1, 0, 0], [0, 0, 1]]))
    R = Rotation.from_euler("z", 90, degrees=True).as_matrix()   # x_T -> y_M
    p = np.array([0.0, 0.0, 50.0])
    # b_2 = (1,0,0) lands at (0,1,50); b_3 = (0,0,1) at (0,0,51)
    want = [math.hypot(10, 50), math.hypot(9, 50), 51.0]
    assert s.lengths(geo, (R, p)) == pytest.approx(want, abs=1e-12)
    assert s.lengths(geo, s.pose_matrix(R, p)) == pytest.approx(want, abs=1e-12)


def test_jacobian_matches_finite_differences():
    R, p = pose(4, -3, 7, 1, 2, 88)
    j = s.length_jacobian(GEO, (R, p))
    h = 1e-6
    for k in range(6):
        dp, dth = np.zeros(3), np.zeros(3)
        (dp if k < 3 else dth)[k % 3] = h
        Rp = Rotation.from_rotvec(dth).as_matrix() @ R
        num = (s.lengths(GEO, (Rp, p + dp)) - s.lengths(GEO, (R, p))) / h
        assert num == pytest.approx(j[:, k], abs=1e-5)


@pytest.mark.parametrize("truth", [pose(), pose(5, -4, 8, 3, -2, 85), pose(-10, 6, -15, -5, 4, 95)])
def test_round_trip_pose_lengths_pose(truth):
    R, p = truth
    start = (Rotation.from_euler("xyz", [1.5, -1, 2], degrees=True).as_matrix() @ R,
             p + np.array([0.8, -0.5, 0.6]))
    est = s.forward(GEO, s.lengths(GEO, truth), start)
    assert est.ok and not est.orientation_held
    assert np.abs(est.pose[:3, 3] - p).max() < 1e-9
    assert np.abs(est.pose[:3, :3] - R).max() < 1e-9
    assert np.nanmax(np.abs(est.residual_mm)) < 1e-9


def test_covariance_matches_monte_carlo_within_20_percent():
    truth = pose(3, -2, 5, 1, 2, 90)
    R, p = truth
    clean = s.lengths(GEO, truth)
    rng = np.random.default_rng(7)
    errs = []
    for _ in range(800):
        est = s.forward(GEO, clean + rng.normal(0, SIGMA, 6), truth, sigma_mm=SIGMA)
        dth = Rotation.from_matrix(est.pose[:3, :3] @ R.T).as_rotvec(degrees=True)
        errs.append(np.concatenate([est.pose[:3, 3] - p, dth]))
    mc = np.cov(np.array(errs).T)
    model = s.forward(GEO, clean, truth, sigma_mm=SIGMA).covariance
    ratio = np.diag(mc) / np.diag(model)
    assert np.all(np.abs(ratio - 1) < 0.2), ratio
    # and the correlations where they are strong
    strong = np.abs(model) > 0.3 * np.sqrt(np.outer(np.diag(model), np.diag(model)))
    assert np.allclose(mc[strong], model[strong], rtol=0.25)


def test_three_strings_give_position_with_the_orientation_held():
    geo = s.StringGeometry(GEO.mount_mm[::2], GEO.tooth_mm[::2])
    R, p = pose(2, 1, -3, 2, -1, 90)
    start = (R, p + np.array([0.5, 0.5, -0.5]))
    est = s.forward(geo, s.lengths(geo, (R, p)), start)
    assert est.ok and est.orientation_held
    assert np.abs(est.pose[:3, 3] - p).max() < 1e-9
    assert np.array_equal(est.pose[:3, :3], R)
    assert np.isnan(est.covariance[3:, :]).all() and np.isnan(est.covariance[:, 3:]).all()
    assert np.isfinite(est.covariance[:3, :3]).all()


def test_six_strings_with_three_masked_fall_back_to_position_only():
    truth = pose(0, 0, 0, 1, 1, 90)
    L = s.lengths(GEO, truth)
    L[0] = np.nan
    est = s.forward(GEO, L, truth, use=[True, True, False, True, True, True])
    assert est.ok and est.orientation_held and est.used.sum() == 4
    est = s.forward(GEO, np.full(6, np.nan), truth)
    assert not est.ok and "3 are needed" in est.reason


def test_a_broken_wire_a_jump_and_an_impossible_set_are_flagged():
    truth = pose(1, 2, 3, 0, 0, 90)
    L = s.lengths(GEO, truth)
    limits = s.LengthLimits(min_mm=20.0, max_mm=250.0, max_jump_mm=1.0, max_residual_mm=0.05)
    assert s.check_lengths(L, limits, previous_mm=L) == []
    broken = L.copy()
    broken[3] = 0.4                       # wire snapped: the drum wound it all in
    f = s.check_lengths(broken, limits, previous_mm=L)
    assert {(x.string, x.kind) for x in f} == {(3, "slack"), (3, "jump")}
    assert "string 4" in f[0].message and "slack minimum" in f[0].message
    over = L.copy()
    over[5] = 300.0
    assert [(x.string, x.kind) for x in s.check_lengths(over, limits)] == [(5, "over_range")]
    nan = L.copy()
    nan[1] = np.nan
    assert [(x.string, x.kind) for x in s.check_lengths(nan, limits)] == [(1, "not_finite")]
    # seven strings (a redundant one across the clamp): one caught wire reading 3 mm long
    # cannot be explained by any pose
    geo7 = s.StringGeometry(np.vstack([GEO.mount_mm, [[0.0, -40.0, 0.0]]]),
                            np.vstack([GEO.tooth_mm, [[0.0, 15.0, 0.0]]]))
    L7 = s.lengths(geo7, truth)
    L7[6] += 3.0
    est = s.forward(geo7, L7, truth)
    kinds = {(x.string, x.kind) for x in s.check_lengths(L7, limits, estimate=est)}
    assert (6, "inconsistent") in kinds
    # six strings far too short for the anchors' spread: no pose makes them straight
    est = s.forward(GEO, np.full(6, 21.0), truth)
    assert any(x.kind == "inconsistent" for x in s.check_lengths(np.full(6, 21.0), limits,
                                                                  estimate=est))


def _calibration_poses(n=14, seed=3):
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        out.append(pose(*rng.uniform(-15, 15, 3), *rng.uniform(-10, 10, 2),
                        90 + rng.uniform(-10, 10)))
    return out


def _perturbed(seed=5, size=1.0):
    rng = np.random.default_rng(seed)
    return s.StringGeometry(GEO.mount_mm + rng.normal(0, size, (6, 3)),
                            GEO.tooth_mm + rng.normal(0, size, (6, 3)))


def test_calibration_recovers_perturbed_anchors_exactly_from_noise_free_data():
    true = _perturbed()
    poses = _calibration_poses()
    L = np.array([s.lengths(true, t) for t in poses])
    cal = s.calibrate_anchors(GEO, poses, L)
    assert np.abs(cal.geometry.mount_mm - true.mount_mm).max() < 1e-8
    assert np.abs(cal.geometry.tooth_mm - true.tooth_mm).max() < 1e-8
    assert np.abs(cal.mount_correction_mm - (true.mount_mm - GEO.mount_mm)).max() < 1e-8
    assert cal.residuals_mm.shape == (len(poses), 6)
    assert cal.rms_by_pose_mm.max() < 1e-9 and cal.rms_by_string_mm.max() < 1e-9


def test_calibration_with_offsets_recovers_them_too():
    true = _perturbed(seed=9)
    offsets = np.array([0.3, -0.2, 0.5, 0.0, -0.4, 0.1])
    poses = _calibration_poses(20, seed=4)
    L = np.array([s.lengths(true, t) for t in poses]) + offsets
    cal = s.calibrate_anchors(GEO, poses, L, fit_offsets=True)
    assert cal.offsets_mm == pytest.approx(offsets, abs=1e-7)
    assert np.abs(cal.geometry.tooth_mm - true.tooth_mm).max() < 1e-6


def test_calibration_with_noise_lands_within_its_stated_sigma():
    true = _perturbed(seed=11)
    poses = _calibration_poses(30, seed=8)
    rng = np.random.default_rng(2)
    L = np.array([s.lengths(true, t) for t in poses])
    L += rng.normal(0, SIGMA, L.shape)
    cal = s.calibrate_anchors(GEO, poses, L, sigma_mm=SIGMA)
    z = np.concatenate([((cal.geometry.mount_mm - true.mount_mm) / cal.mount_std_mm).ravel(),
                        ((cal.geometry.tooth_mm - true.tooth_mm) / cal.tooth_std_mm).ravel()])
    assert np.abs(z).max() < 4.5, z                 # 36 normalised errors, none beyond 4.5
    assert 0.5 < np.sqrt(np.mean(z**2)) < 1.5       # and about unit scatter
    # residuals: 6 parameters per string out of 30 lengths -> rms ~ s sqrt(24/30)
    assert cal.rms_by_string_mm == pytest.approx(SIGMA * math.sqrt(24 / 30), rel=0.35)


def test_poses_of_one_orientation_are_refused_naming_rank_and_cure():
    rng = np.random.default_rng(1)
    poses = [pose(0, 0, 0, *rng.uniform(-10, 10, 2), 90 + rng.uniform(-10, 10))
             for _ in range(12)]
    L = np.array([s.lengths(GEO, t) for t in poses])
    with pytest.raises(IdentificationError) as e:
        s.calibrate_anchors(GEO, poses, L)
    msg = str(e.value)
    assert "rank 3 of 6" in msg and "same orientation" in msg and "two axes" in msg
    assert "string 1" in msg


def test_too_few_poses_are_refused():
    poses = _calibration_poses(4)
    L = np.array([s.lengths(GEO, t) for t in poses])
    with pytest.raises(IdentificationError, match="4 poses for 6 parameters"):
        s.calibrate_anchors(GEO, poses, L)


def test_bad_shapes_are_config_errors():
    with pytest.raises(ConfigError):
        s.StringGeometry(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ConfigError):
        s.forward(GEO, np.zeros(5), pose())
    with pytest.raises(ConfigError):
        s.LengthLimits(min_mm=10, max_mm=5)


def test_one_tracking_step_follows_a_tick_of_patient_motion():
    """A tick's motion (20 mm/s and 10 deg/s for 2 ms: 0.04 mm, 0.02 deg): one Gauss-Newton
    step of :func:`s.track` lands on the new pose far below the encoders' 0.01 mm step;
    two steps reach it to floating-point accuracy."""
    geo = s.ring_geometry()
    before = np.eye(4)
    before[:3, 3] = (1.0, -2.0, 92.0)
    after = before.copy()
    after[:3, 3] += (0.0, 0.0, -0.04)
    after[:3, :3] = Rotation.from_rotvec(np.radians([0.02, 0.0, 0.0])).as_matrix()
    measured = s.lengths(geo, after)
    one, res1 = s.track(geo, measured, before, iterations=1)
    assert np.abs(one[:3, 3] - after[:3, 3]).max() < 1e-4 and res1 < 1e-5
    two, res2 = s.track(geo, measured, before, iterations=2)
    np.testing.assert_allclose(two, after, atol=1e-9)
    assert res2 < 1e-9


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 1e-4, 0.3, 1.0, 2.5, 2.8, 3.0,
                                   math.pi - 1e-6, math.pi])
def test_the_compiled_rotation_vector_maps_agree_with_scipy(angle):
    """Rodrigues' formula and its inverse (the tracked tick's pose update and the tooth's
    turn between ticks) against scipy's, for random axes at angles from zero to pi, across
    the series and the near-pi branches; at pi, r and -r are the same rotation."""
    rng = np.random.default_rng(int(angle * 1e6) + 1)
    for _ in range(20):
        axis = rng.normal(size=3)
        r = axis / np.linalg.norm(axis) * angle
        m = Rotation.from_rotvec(r).as_matrix()
        np.testing.assert_allclose(kernels.rotvec_matrix(r), m, atol=1e-15)
        got = kernels.matrix_rotvec(m)
        if angle > 3.0:
            assert min(np.abs(got - r).max(), np.abs(got + r).max()) < 1e-7
        else:
            np.testing.assert_allclose(got, Rotation.from_matrix(m).as_rotvec(), atol=1e-14)
        assert np.linalg.norm(got) == pytest.approx(angle, abs=1e-12)


def test_a_tracking_step_on_a_missing_length_reports_a_non_finite_residual():
    before = np.eye(4)
    before[:3, 3] = (0.0, 0.0, 90.0)
    measured = s.lengths(GEO, before)
    measured[2] = np.nan
    pose_after, res = s.track(GEO, measured, before)
    assert not math.isfinite(res)
    np.testing.assert_array_equal(pose_after, before)          # the pose is left alone
