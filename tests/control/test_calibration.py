"""Tests of dentibot.control.calibration (thesis section 3.4, eq 3.19-3.26).

Every expected value comes from the synthetic truth the test builds, never from the code.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dentibot.control.calibration import calibrate_tcp, tool_axis_rotation, tool_transform
from dentibot.errors import ConfigError, IdentificationError

P6H_TRUE = np.array([3.1, -2.4, 95.0])  # tool tip in {6}, mm
P0H_TRUE = np.array([180.0, 20.0, 90.0])  # touched point in {0}, mm
FLANGE_DOWN = Rotation.from_euler("x", 180, degrees=True)  # flange z pointing down


def tilted_poses(rng: np.random.Generator, n: int, tilt_min: float, tilt_max: float) -> np.ndarray:
    """n flange orientations: tool tilted tilt_min..tilt_max deg away from the vertical about
    a horizontal axis of random azimuth, and turned about its own axis at random."""
    azimuth = rng.uniform(0.0, 2 * np.pi, n)
    tilt = np.radians(rng.uniform(tilt_min, tilt_max, n))
    axes = np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros(n)], axis=1)
    spin = Rotation.from_euler("z", rng.uniform(-180.0, 180.0, (n, 1)), degrees=True)
    return (Rotation.from_rotvec(tilt[:, None] * axes) * FLANGE_DOWN * spin).as_matrix()


def flange_positions(R: np.ndarray) -> np.ndarray:
    """Flange positions that put the tip on P0H_TRUE: 0p_6 = 0p_H - 0R_6 6p_H (eq 3.21)."""
    return P0H_TRUE - R @ P6H_TRUE


def scaled_condition(R: np.ndarray) -> float:
    """Independent computation of the column-scaled condition number of [R_i, -I]."""
    A = np.vstack([np.hstack([r, -np.eye(3)]) for r in R])
    return float(np.linalg.cond(A / np.linalg.norm(A, axis=0)))


def rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(b: float) -> np.ndarray:
    c, s = np.cos(b), np.sin(b)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


# --- TCP -------------------------------------------------------------------------------


def test_tcp_with_noise_recovers_tip_and_residual_matches_noise() -> None:
    rng = np.random.default_rng(20240601)
    n, sigma = 12, 0.01
    R = tilted_poses(rng, n, 15.0, 40.0)
    p = flange_positions(R) + rng.normal(0.0, sigma, (n, 3))

    cal = calibrate_tcp(R, p)

    # Monte Carlo (2000 sets like this one): error std 0.003 mm in x, y and 0.007 mm in z.
    np.testing.assert_allclose(cal.p_6_H_mm, P6H_TRUE, atol=0.03)
    np.testing.assert_allclose(cal.p_0_H_mm, P0H_TRUE, atol=0.03)
    # E[sum of squared residuals] = (3n - 6) sigma^2 -> RMS of per-pose norms:
    expected_rms = sigma * np.sqrt((3 * n - 6) / n)
    assert 0.6 * expected_rms < cal.residual_rms_mm < 1.4 * expected_rms
    assert cal.residual_max_mm >= cal.residual_rms_mm
    assert cal.residuals_mm.shape == (n, 3)
    np.testing.assert_allclose(cal.residual_norms_mm, np.linalg.norm(cal.residuals_mm, axis=1))
    assert cal.condition == pytest.approx(scaled_condition(R))
    assert np.all(cal.p_6_H_std_mm < 0.02)


def test_tcp_four_noiseless_poses_is_exact() -> None:
    R = tilted_poses(np.random.default_rng(7), 4, 20.0, 35.0)
    cal = calibrate_tcp(R, flange_positions(R))
    np.testing.assert_allclose(cal.p_6_H_mm, P6H_TRUE, atol=1e-9)
    np.testing.assert_allclose(cal.p_0_H_mm, P0H_TRUE, atol=1e-9)
    assert cal.residual_max_mm < 1e-9


def test_tcp_near_identical_orientations_refused_with_condition_number() -> None:
    rng = np.random.default_rng(3)
    n = 8
    # all orientations within 0.5 deg of one another: rotation vectors of norm <= 0.25 deg
    small = rng.normal(size=(n, 3))
    small *= np.radians(rng.uniform(0.0, 0.25, n))[:, None] / np.linalg.norm(small, axis=1)[
        :, None
    ]
    R = (Rotation.from_rotvec(small) * FLANGE_DOWN).as_matrix()
    expected = scaled_condition(R)
    with pytest.raises(IdentificationError) as info:
        calibrate_tcp(R, flange_positions(R))
    assert f"{expected:.3g}" in str(info.value)
    assert info.value.condition == pytest.approx(expected)
    assert "20 deg" in info.value.advice


def test_tcp_rotation_about_a_single_axis_is_refused() -> None:
    # Turning only about the flange z axis cannot fix the tip's position along that axis.
    angles = np.array([[0.0], [60.0], [130.0], [210.0], [300.0]])
    R = (FLANGE_DOWN * Rotation.from_euler("z", angles, degrees=True)).as_matrix()
    with pytest.raises(IdentificationError):
        calibrate_tcp(R, flange_positions(R))


def test_tcp_three_poses_is_config_error() -> None:
    R = tilted_poses(np.random.default_rng(1), 3, 20.0, 40.0)
    with pytest.raises(ConfigError) as info:
        calibrate_tcp(R, flange_positions(R))
    assert info.value.field == "poses"


def test_tcp_rejects_non_rotation() -> None:
    R = tilted_poses(np.random.default_rng(2), 5, 20.0, 40.0)
    R[2] *= 1.01
    with pytest.raises(ConfigError):
        calibrate_tcp(R, flange_positions(R))


# --- tool axis -----------------------------------------------------------------------------


def thesis_eq_3_26(t: np.ndarray) -> tuple[float, float]:
    """Eq 3.26 transcribed literally (radians)."""
    proj = np.array([0.0, t[1], t[2]])
    k = np.array([0.0, 0.0, 1.0])
    alpha = -np.sign(t[1]) * np.arccos(k @ proj / np.linalg.norm(proj))
    beta = np.sign(t[0]) * np.arccos(t @ proj / (np.linalg.norm(t) * np.linalg.norm(proj)))
    return float(alpha), float(beta)


def test_tool_axis_positive_tz_matches_direction_and_thesis_formula() -> None:
    rng = np.random.default_rng(11)
    p_short = np.array([3.1, -2.4, 95.0])
    for _ in range(20):
        d = rng.normal(size=3)
        d[2] = abs(d[2]) + 0.2
        d /= np.linalg.norm(d)
        axis = tool_axis_rotation(p_short + 6.0 * d, p_short)

        np.testing.assert_allclose(axis.t_hat, d, atol=1e-12)
        assert axis.length_mm == pytest.approx(6.0)
        np.testing.assert_allclose(axis.R_6_H @ [0, 0, 1], d, atol=1e-12)
        a, b = np.radians(axis.alpha_deg), np.radians(axis.beta_deg)
        np.testing.assert_allclose(axis.R_6_H, rx(a) @ ry(b), atol=1e-12)
        alpha_thesis, beta_thesis = thesis_eq_3_26(d)
        assert a == pytest.approx(alpha_thesis, abs=1e-9)
        assert b == pytest.approx(beta_thesis, abs=1e-9)


@pytest.mark.parametrize(
    "t",
    [
        (0.3, -0.4, -0.8),
        (-0.5, 0.2, -0.1),
        (0.0, 0.0, -1.0),
        (0.2, 0.0, -0.9),  # t_y = 0, t_z < 0: eq 3.26 gives alpha = 0 here (wrong)
        (1.0, 0.0, 0.0),  # along +x: eq 3.26 divides 0 by 0
        (-1.0, 0.0, 0.0),
        (0.0, 1.0, 0.0),
        (0.0, -0.7, 0.0),
    ],
)
def test_tool_axis_any_direction_maps_z_onto_t(t: tuple[float, float, float]) -> None:
    t = np.array(t)
    t_hat = t / np.linalg.norm(t)
    axis = tool_axis_rotation(t, np.zeros(3))
    R = axis.R_6_H
    np.testing.assert_allclose(R @ [0, 0, 1], t_hat, atol=1e-12)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    a, b = np.radians(axis.alpha_deg), np.radians(axis.beta_deg)
    np.testing.assert_allclose(rx(a) @ ry(b), R, atol=1e-12)


def test_thesis_eq_3_26_fails_for_ty_zero_tz_negative() -> None:
    # Documents the thesis error the implementation avoids.
    t = np.array([0.2, 0.0, -0.9])
    a, b = thesis_eq_3_26(t)
    z_thesis = rx(a) @ ry(b) @ [0, 0, 1]
    assert not np.allclose(z_thesis, t / np.linalg.norm(t), atol=1e-3)


def test_tool_axis_zero_length_is_config_error() -> None:
    p = np.array([1.0, 2.0, 3.0])
    with pytest.raises(ConfigError) as info:
        tool_axis_rotation(p, p.copy())
    assert info.value.field == "tool_vector"


def test_tool_transform_composes_with_flange_pose() -> None:
    R_6_H = rx(np.radians(10.0)) @ ry(np.radians(-5.0))
    T_6_H = tool_transform(P6H_TRUE, R_6_H)
    R_0_6 = Rotation.from_euler("xyz", [170.0, 15.0, 30.0], degrees=True).as_matrix()
    T_0_6 = np.eye(4)
    T_0_6[:3, :3] = R_0_6
    T_0_6[:3, 3] = [150.0, -20.0, 200.0]
    T_0_H = T_0_6 @ T_6_H
    # eq 3.21: 0p_H = 0R_6 6p_H + 0p_6 ; eq 3.20: 0R_H = 0R_6 6R_H
    np.testing.assert_allclose(T_0_H[:3, 3], R_0_6 @ P6H_TRUE + [150.0, -20.0, 200.0])
    np.testing.assert_allclose(T_0_H[:3, :3], R_0_6 @ R_6_H)
    np.testing.assert_allclose(T_6_H[3], [0, 0, 0, 1])
