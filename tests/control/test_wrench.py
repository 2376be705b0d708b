"""Tests of dentibot.control.wrench (thesis section 4.2 eq 4.1-4.19, section 4.4 eq 4.26-4.31).

Synthetic truth is generated here from first principles (weight vector, lever arm,
cross product), independently of the module under test.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dentibot.control.wrench import (
    STANDARD_GRAVITY,
    GravityModel,
    WrenchTransform,
    identify_load,
)
from dentibot.errors import ConfigError, IdentificationError

MASS_KG = 0.139
CENTROID_MM = np.array([2.0, -1.5, 45.0])
F0_N = np.array([0.3, -0.2, 1.1])
TAU0_NM = np.array([0.01, -0.02, 0.005])
# ATI Mini40 resolutions used as noise standard deviations: 1/100 N, 1/4000 N*m
NOISE = np.array([0.01, 0.01, 0.01, 0.00025, 0.00025, 0.00025])


def rot_z_deg(theta: float) -> np.ndarray:
    return Rotation.from_euler("z", theta, degrees=True).as_matrix()


def true_wrench(R_0_6: np.ndarray, mount_deg: float, external=None) -> np.ndarray:
    """Sensor reading from first principles: the weight m*g0 acts down in {0}; in {S} it is
    (0R_6 6R_S)^T (0, 0, -m g0) with 6R_S = Rz(mount); its moment about the sensor origin is
    r x f_g with r in m. ``external`` = (force in {S} N, application point in {S} mm)."""
    R_0_S = R_0_6 @ rot_z_deg(mount_deg)
    f_g = R_0_S.T @ np.array([0.0, 0.0, -MASS_KG * STANDARD_GRAVITY])
    f = F0_N + f_g
    tau = TAU0_NM + np.cross(CENTROID_MM / 1000.0, f_g)
    if external is not None:
        force, point_mm = external
        f = f + force
        tau = tau + np.cross(np.asarray(point_mm) / 1000.0, force)
    return np.concatenate([f, tau])


def readings(rng, R, mount_deg, noise=True) -> np.ndarray:
    w = np.array([true_wrench(r, mount_deg) for r in R])
    if noise:
        w = w + rng.normal(size=w.shape) * NOISE
    return w


# --- identification ------------------------------------------------------------------------


@pytest.mark.parametrize("mount_deg", [3.0, 30.0, -120.0])
def test_identification_noiseless_is_exact(mount_deg: float) -> None:
    R = Rotation.random(8, random_state=np.random.default_rng(5)).as_matrix()
    res = identify_load(R, readings(None, R, mount_deg, noise=False))
    m = res.model
    assert res.mass_kg == pytest.approx(MASS_KG, abs=1e-9)
    assert m.weight_n == pytest.approx(MASS_KG * STANDARD_GRAVITY, abs=1e-9)
    np.testing.assert_allclose(m.centroid_mm, CENTROID_MM, atol=1e-9)
    assert m.mount_angle_deg == pytest.approx(mount_deg, abs=1e-9)
    np.testing.assert_allclose(m.f0_n, F0_N, atol=1e-9)
    np.testing.assert_allclose(m.tau0_nm, TAU0_NM, atol=1e-9)
    assert res.force_rms_n < 1e-9 and res.torque_rms_nm < 1e-9
    assert res.consistency_n < 1e-9


@pytest.mark.parametrize("mount_deg", [3.0, 30.0, -120.0])
def test_identification_with_sensor_noise(mount_deg: float) -> None:
    """Tolerances from a 2000-trial Monte Carlo of this set-up (12 uniform random
    orientations, Mini40 noise), standard deviations: mass 0.57 g, centroid 0.11-0.14 mm,
    angle 0.16 deg, f0 0.003 N, tau0 0.00009 N*m. Tolerances are about 5 sigma (mass 3.5
    sigma: 2 g, the load identification's required mass accuracy)."""
    rng = np.random.default_rng(1000 + int(mount_deg))
    n = 12
    R = Rotation.random(n, random_state=rng).as_matrix()
    res = identify_load(R, readings(rng, R, mount_deg))
    m = res.model
    assert res.mass_kg == pytest.approx(MASS_KG, abs=0.002)
    np.testing.assert_allclose(m.centroid_mm, CENTROID_MM, atol=0.75)
    assert m.mount_angle_deg == pytest.approx(mount_deg, abs=0.75)
    np.testing.assert_allclose(m.f0_n, F0_N, atol=0.015)
    np.testing.assert_allclose(m.tau0_nm, TAU0_NM, atol=0.0005)
    # residual of a 6-parameter fit to 3n values: sigma * sqrt((3n - 6) / 3n)
    shrink = np.sqrt((3 * n - 6) / (3 * n))
    assert 0.6 * 0.01 * shrink < res.force_rms_n < 1.4 * 0.01 * shrink
    assert 0.6 * 0.00025 * shrink < res.torque_rms_nm < 1.4 * 0.00025 * shrink
    assert res.consistency_n < 0.03  # two weight estimates, each with error ~0.005 N


def test_tau0_uses_the_correct_sign_not_eq_4_6() -> None:
    # f0 and r are both non-zero, so r x f0 (7.35e-3, -1.3e-2, -3.0e-4 N*m) matters.
    R = Rotation.random(6, random_state=np.random.default_rng(9)).as_matrix()
    res = identify_load(R, readings(None, R, 3.0, noise=False))
    np.testing.assert_allclose(res.model.tau0_nm, TAU0_NM, atol=1e-9)
    # k = tau0 - r x f0 (the corrected eq 4.6)
    r_m = CENTROID_MM / 1000.0
    np.testing.assert_allclose(res.k_nm, TAU0_NM - np.cross(r_m, F0_N), atol=1e-9)
    # The printed eq 4.14 (tau0x = k1 + (f0z y + f0y z), ...) would be off by > 1e-2 N*m.
    x, y, z = r_m
    f0x, f0y, f0z = F0_N
    k1, k2, k3 = res.k_nm
    thesis = np.array([k1 + (f0z * y + f0y * z), k2 + (f0x * z + f0z * x), k3 + (f0y * x + f0x * y)])
    assert np.max(np.abs(thesis - TAU0_NM)) > 0.01


def test_mount_angle_beyond_90_deg_needs_atan2() -> None:
    # arcsin (eq 4.17) cannot return -120 deg; atan2 does.
    R = Rotation.random(8, random_state=np.random.default_rng(4)).as_matrix()
    res = identify_load(R, readings(None, R, -120.0, noise=False))
    assert res.model.mount_angle_deg == pytest.approx(-120.0, abs=1e-9)
    g = res.model.weight_n
    assert np.degrees(np.arcsin(res.g_sin_n / g)) == pytest.approx(-60.0, abs=1e-6)


def test_tool_always_pointing_the_same_way_is_refused() -> None:
    # Tool tilted 30 deg from vertical, turned about its own axis only: gravity's component
    # along the tool never changes, so g cannot be told from the offset f0z.
    rng = np.random.default_rng(8)
    tilt = Rotation.from_euler("x", 150.0, degrees=True)
    spins = Rotation.from_euler("z", rng.uniform(-180.0, 180.0, (10, 1)), degrees=True)
    R = (tilt * spins).as_matrix()
    with pytest.raises(IdentificationError) as info:
        identify_load(R, readings(rng, R, 3.0))
    assert info.value.condition > info.value.limit
    assert f"{info.value.condition:.3g}" in str(info.value)
    assert "three clearly different directions" in info.value.advice


def test_single_direction_refused_even_noiseless() -> None:
    # Tool straight down in every pose: both steps are singular.
    spins = Rotation.from_euler("z", [[0.0], [90.0], [200.0], [290.0]], degrees=True)
    R = (Rotation.from_euler("x", 180.0, degrees=True) * spins).as_matrix()
    with pytest.raises(IdentificationError):
        identify_load(R, readings(None, R, 3.0, noise=False))


def test_fewer_than_three_poses_is_config_error() -> None:
    R = Rotation.random(2, random_state=np.random.default_rng(0)).as_matrix()
    with pytest.raises(ConfigError) as info:
        identify_load(R, readings(None, R, 3.0, noise=False))
    assert info.value.field == "poses"


# --- gravity compensation ------------------------------------------------------------------


@pytest.fixture(scope="module")
def identified() -> GravityModel:
    rng = np.random.default_rng(77)
    R = Rotation.random(12, random_state=rng).as_matrix()
    return identify_load(R, readings(rng, R, 3.0)).model


def test_gravity_wrench_matches_first_principles() -> None:
    m = GravityModel(F0_N, TAU0_NM, MASS_KG * STANDARD_GRAVITY, CENTROID_MM, 30.0)
    for R in Rotation.random(5, random_state=np.random.default_rng(2)).as_matrix():
        expected = true_wrench(R, 30.0) - np.concatenate([F0_N, TAU0_NM])
        np.testing.assert_allclose(m.gravity_wrench(R), expected, atol=1e-12)


def test_external_wrench_recovers_known_contact(identified: GravityModel) -> None:
    """Error budget: identification (f0 0.003 N, weight 0.006 N, centroid 0.15 mm ->
    0.0002 N*m) plus one reading's noise (0.01 N, 0.00025 N*m): tolerances about 4 sigma."""
    rng = np.random.default_rng(31)
    tip_S_mm = np.array([1.0, 0.5, 95.0])  # contact at the file tip, in {S}
    for R in Rotation.random(6, random_state=rng).as_matrix():
        force = rng.normal(0.0, 1.0, 3)
        measured = true_wrench(R, 3.0, (force, tip_S_mm)) + rng.normal(size=6) * NOISE
        ext = identified.external_wrench(measured, R)
        np.testing.assert_allclose(ext[:3], force, atol=0.04)
        np.testing.assert_allclose(ext[3:], np.cross(tip_S_mm / 1000.0, force), atol=0.0015)


def test_external_wrench_is_zero_without_contact(identified: GravityModel) -> None:
    rng = np.random.default_rng(32)
    for R in Rotation.random(20, random_state=rng).as_matrix():
        measured = true_wrench(R, 3.0) + rng.normal(size=6) * NOISE
        ext = identified.external_wrench(measured, R)
        np.testing.assert_allclose(ext[:3], 0.0, atol=0.04)
        np.testing.assert_allclose(ext[3:], 0.0, atol=0.0015)


def test_gravity_model_is_frozen() -> None:
    m = GravityModel(F0_N, TAU0_NM, 1.0, CENTROID_MM, 0.0)
    with pytest.raises(AttributeError):
        m.weight_n = 2.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        m.f0_n[0] = 1.0


# --- change of frame and reference point ----------------------------------------------------


def test_force_at_q_gives_zero_moment_about_q() -> None:
    rng = np.random.default_rng(41)
    for _ in range(5):
        R_H_S = Rotation.random(random_state=rng).as_matrix()
        q_S_mm = rng.uniform(-20.0, 20.0, 3) + [0.0, 0.0, 90.0]
        F_H = rng.normal(0.0, 2.0, 3)
        F_S = R_H_S.T @ F_H
        measured = np.concatenate([F_S, np.cross(q_S_mm / 1000.0, F_S)])  # (q - p) x F
        out = WrenchTransform(R_H_S, q_S_mm).apply(measured)
        np.testing.assert_allclose(out[:3], F_H, atol=1e-12)
        np.testing.assert_allclose(out[3:], 0.0, atol=1e-12)


def test_pure_couple_is_only_rotated() -> None:
    rng = np.random.default_rng(42)
    R_H_S = Rotation.random(random_state=rng).as_matrix()
    couple = np.array([0.02, -0.01, 0.03])
    out = WrenchTransform(R_H_S, [5.0, -3.0, 100.0]).apply(np.concatenate([np.zeros(3), couple]))
    np.testing.assert_allclose(out[:3], 0.0, atol=1e-15)
    assert np.linalg.norm(out[3:]) == pytest.approx(np.linalg.norm(couple))
    np.testing.assert_allclose(out[3:], R_H_S @ couple, atol=1e-15)


def test_hand_computed_case() -> None:
    # {H} turned +90 deg about z from {S}: S x-axis = H y-axis, so HR_S = Rz(90).
    # q 100 mm above p on z. A 1 N force along S x through p. By hand:
    #   moment about q = (p - q) x f = (0, 0, -0.1 m) x (1, 0, 0) N = (0, -0.1, 0) N*m in {S}
    #   in {H}: force (0, 1, 0) N, moment (0.1, 0, 0) N*m.
    R_H_S = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    out = WrenchTransform(R_H_S, [0.0, 0.0, 100.0]).apply(np.array([1.0, 0, 0, 0, 0, 0]))
    np.testing.assert_allclose(out, [0.0, 1.0, 0.0, 0.1, 0.0, 0.0], atol=1e-15)
    # Eq 4.31 read literally (u = Sp_H, from p to q) would give the opposite moment.
    assert not np.allclose(out[3:], [-0.1, 0.0, 0.0])


def test_for_tool_builds_the_chain_with_mount_angle() -> None:
    """Sensor 20 mm above the flange along z, turned 30 deg; tool tip and axis from the
    calibration. A force at the tip, written in {6}, must come out as the same force in {H}
    with no moment."""
    rng = np.random.default_rng(43)
    mount = 30.0
    R_6_S = rot_z_deg(mount)
    p_6_S = np.array([0.0, 0.0, 20.0])
    R_6_H = Rotation.from_euler("XY", [12.0, -7.0], degrees=True).as_matrix()
    p_6_H = np.array([3.1, -2.4, 95.0])
    T = WrenchTransform.for_tool(R_6_H, p_6_H, mount_angle_deg=mount, p_6_S_mm=p_6_S)
    for _ in range(4):
        F_6 = rng.normal(0.0, 1.0, 3)
        lever_6 = (p_6_H - p_6_S) / 1000.0
        measured = np.concatenate([R_6_S.T @ F_6, R_6_S.T @ np.cross(lever_6, F_6)])
        out = T.apply(measured)
        np.testing.assert_allclose(out[:3], R_6_H.T @ F_6, atol=1e-12)
        np.testing.assert_allclose(out[3:], 0.0, atol=1e-12)


def test_for_tool_grip_point() -> None:
    # Reference point 13.2 mm up the handpiece from the tip (-z in {H}). A 1 N force at the
    # tip along H x has about it the moment (tip - grip) x F = (0, 0, 0.0132 m) x (1, 0, 0) N
    # = (0, 0.0132, 0) N*m.
    R_6_H = np.eye(3)
    p_6_H = np.array([0.0, 0.0, 100.0])
    T = WrenchTransform.for_tool(R_6_H, p_6_H, q_H_mm=[0.0, 0.0, -13.2])
    measured = np.array([1.0, 0.0, 0.0, 0.0, 0.1, 0.0])  # 1 N along x at 100 mm: (0, 0.1, 0)
    np.testing.assert_allclose(T.apply(measured), [1.0, 0, 0, 0, 0.0132, 0], atol=1e-12)


def test_transform_matrix_is_read_only_and_input_checked() -> None:
    T = WrenchTransform(np.eye(3), [0.0, 0.0, 50.0])
    with pytest.raises(ValueError):
        T.matrix[0, 0] = 2.0
    with pytest.raises(ConfigError):
        WrenchTransform(2.0 * np.eye(3), [0.0, 0.0, 50.0])
