"""Tool calibration: tool-centre point and tool axis (thesis section 3.4, eq 3.19-3.26).

Frames: {0} robot base, {6} flange, {H} tool tip (origin at the file tip, z along the file).
Notation: ``R_0_6`` is the rotation matrix 0R_6 whose columns are the {6} axes in {0}
components, so ``v_0 = R_0_6 @ v_6``.

Units: lengths mm, public angles deg. Pure numpy/scipy: no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dentibot.control.linalg import as_rotation_stack, column_scaled_condition, pose_data, readonly
from dentibot.errors import ConfigError, IdentificationError

#: Default largest accepted condition number of the column-scaled TCP system.
#:
#: After scaling each column to unit norm the largest singular value is about sqrt(2), and
#: the error of the solution is about ``noise * cond / sqrt(2 N)`` (N poses). Pose sets that
#: tilt the tool by 15-40 deg in different directions give 5-15; tilts of only about 5 deg
#: give about 60, 1 deg about 250, 0.5 deg about 500. At 50 the noise gain is at most about
#: 18 for N = 4 (10 for N = 12), so a 0.02 mm touch error moves the tip by no more than
#: about 0.4 mm, still less than a root canal's diameter (about 1 mm). Ill-posed sets fail
#: loudly instead of returning a tip several mm out.
DEFAULT_TCP_MAX_CONDITION = 50.0

_TCP_ADVICE = (
    "add poses that tilt the tool by at least 20 deg about two different horizontal axes "
    "while the tip stays on the fixed point (turning about one axis only leaves the tip "
    "position along that axis undetermined)"
)


@dataclass(frozen=True, eq=False)
class TcpCalibration:
    """Result of :func:`calibrate_tcp`. Arrays are read-only.

    Attributes:
        p_6_H_mm: tool tip in the flange frame {6}, 6p_H (mm), shape (3,).
        p_0_H_mm: the fixed touched point in the base frame {0}, 0p_H (mm), shape (3,).
        residuals_mm: per-pose residual vectors ``R_i @ p_6_H + p_i - p_0_H`` (mm), (N, 3).
        residual_norms_mm: Euclidean norm of each row of ``residuals_mm`` (mm), (N,).
        residual_rms_mm: sqrt(mean(residual_norms**2)) (mm). With independent noise of
            standard deviation s per coordinate its expectation is about s*sqrt(3 - 6/N).
        residual_max_mm: largest per-pose residual norm (mm).
        p_6_H_std_mm: estimated standard deviation of each component of ``p_6_H_mm``
            from the residuals (mm), shape (3,). Zero for noiseless data.
        condition: condition number of the column-scaled 3N x 6 system.
    """

    p_6_H_mm: np.ndarray
    p_0_H_mm: np.ndarray
    residuals_mm: np.ndarray
    residual_norms_mm: np.ndarray
    residual_rms_mm: float
    residual_max_mm: float
    p_6_H_std_mm: np.ndarray
    condition: float


@dataclass(frozen=True, eq=False)
class ToolAxis:
    """Result of :func:`tool_axis_rotation`. Arrays are read-only.

    Attributes:
        t_hat: unit tool vector in {6} (the file direction), shape (3,).
        length_mm: length of the raw tool vector t = 6p_H,long - 6p_H,short (mm).
        R_6_H: rotation 6R_H = Rx(alpha) Ry(beta) (eq 3.25); columns are the {H} axes in
            {6} components, its third column equals ``t_hat``.
        alpha_deg, beta_deg: the angles of eq 3.26 (deg); with gamma = 0 they are the
            mobile-XYZ Euler angles of eq 3.2 that the arm's SetTRF takes.
    """

    t_hat: np.ndarray
    length_mm: float
    R_6_H: np.ndarray
    alpha_deg: float
    beta_deg: float





def calibrate_tcp(
    flange_rotations: object,
    flange_positions_mm: object,
    *,
    max_condition: float = DEFAULT_TCP_MAX_CONDITION,
) -> TcpCalibration:
    """N-point tool-centre-point calibration (eq 3.21-3.23), N >= 4.

    The tool tip touches one fixed point in N flange poses (0R_6^i, 0p_6^i), so for every
    pose (eq 3.21-3.22)::

        0R_6^i @ 6p_H + 0p_6^i = 0p_H      ->      [0R_6^i, -I] [6p_H; 0p_H] = -0p_6^i

    Stacking all poses gives a 3N x 6 linear least-squares problem in the tip 6p_H and the
    fixed point 0p_H, solved with ``numpy.linalg.lstsq``. Deviation from the thesis: eq 3.23
    subtracts every pose from pose 1, which makes pose 1 special (its noise enters every
    row, the rows become correlated) and drops 0p_H; the stacked form treats all poses
    alike and also returns 0p_H and honest per-pose residuals.

    Args:
        flange_rotations: N rotation matrices 0R_6 (flange orientation in {0}), (N, 3, 3).
        flange_positions_mm: N flange positions 0p_6 (mm), (N, 3).
        max_condition: largest accepted condition number of the column-scaled system
            (see :data:`DEFAULT_TCP_MAX_CONDITION`).

    Raises:
        ConfigError: field "poses" when N < 4 or the arrays do not match; a rotation that is
            not a rotation matrix.
        IdentificationError: the orientations are too alike to locate the tip.
    """
    R, p = pose_data(flange_rotations, flange_positions_mm, min_poses=4, width=3,
                     values_field="flange_positions_mm",
                     poses_need=">= 4 flange poses touching the same point")
    n = R.shape[0]

    A = np.concatenate([R, np.broadcast_to(-np.eye(3), (n, 3, 3))], axis=2).reshape(3 * n, 6)
    b = -p.reshape(3 * n)
    condition = column_scaled_condition(A)
    if not condition <= max_condition:
        raise IdentificationError("TCP calibration (eq 3.22)", condition, max_condition,
                                  _TCP_ADVICE)

    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    p6H, p0H = x[:3], x[3:]
    residuals = R @ p6H + p - p0H
    norms = np.linalg.norm(residuals, axis=1)
    dof = 3 * n - 6
    sigma2 = float(residuals.ravel() @ residuals.ravel()) / dof
    cov = sigma2 * np.linalg.inv(A.T @ A)
    return TcpCalibration(
        p_6_H_mm=readonly(p6H),
        p_0_H_mm=readonly(p0H),
        residuals_mm=readonly(residuals),
        residual_norms_mm=readonly(norms),
        residual_rms_mm=float(np.sqrt(np.mean(norms**2))),
        residual_max_mm=float(norms.max()),
        p_6_H_std_mm=readonly(np.sqrt(np.diag(cov)[:3])),
        condition=condition,
    )


def tool_axis_rotation(
    p_long_mm: object, p_short_mm: object, *, min_length_mm: float = 1e-6
) -> ToolAxis:
    """Tool axis and the flange-to-tool rotation 6R_H = Rx(alpha) Ry(beta) (eq 3.24-3.26).

    t = 6p_H,long - 6p_H,short (eq 3.24), both TCPs in {6} (mm), found with
    :func:`calibrate_tcp` for a long and a short file. The third column of
    Rx(alpha) Ry(beta) is (sin b, -sin a cos b, cos a cos b); equating it with t_hat gives::

        alpha = atan2(-t_y, t_z),    beta = atan2(t_x, hypot(t_y, t_z))

    with beta in [-90, 90] deg (cos b >= 0) and alpha in (-180, 180] deg. This equals eq
    3.26 (alpha = -sign(t_y) acos(t_z / hypot(t_y, t_z)), beta = sign(t_x) acos(hypot(t_y,
    t_z) / |t|)) wherever eq 3.26 is defined, including t_z < 0, but eq 3.26 fails in
    two places: t_y = 0 with t_z < 0 (sign(0) = 0 gives alpha = 0 instead of 180 deg, so
    z is sent to the mirror image of t) and t_y = t_z = 0 (0/0). The atan2 form handles
    both (alpha = 0, beta = +-90 deg for t along +-x).

    Raises ConfigError(field "tool_vector") if |t| < ``min_length_mm`` (the two TCPs
    coincide: no direction).
    """
    t = np.asarray(p_long_mm, dtype=float) - np.asarray(p_short_mm, dtype=float)
    if t.shape != (3,):
        raise ConfigError("tool_vector", f"array of shape {t.shape}", "shape (3,)")
    length = float(np.linalg.norm(t))
    if not length >= min_length_mm:
        raise ConfigError(
            "tool_vector",
            t.tolist(),
            f"length >= {min_length_mm:g} mm",
            "the long- and short-file TCPs coincide, so they give no direction",
        )
    t_hat = t / length
    alpha = np.arctan2(-t_hat[1], t_hat[2])
    beta = np.arctan2(t_hat[0], np.hypot(t_hat[1], t_hat[2]))
    R = Rotation.from_euler("XY", [alpha, beta]).as_matrix()  # intrinsic: Rx(alpha) Ry(beta)
    return ToolAxis(
        t_hat=readonly(t_hat),
        length_mm=length,
        R_6_H=readonly(R),
        alpha_deg=float(np.degrees(alpha)),
        beta_deg=float(np.degrees(beta)),
    )


def tool_transform(p_6_H_mm: object, R_6_H: object) -> np.ndarray:
    """Homogeneous flange-to-tool transform 6T_H (eq 3.19-3.20), 4x4, translation in mm.

    ``0T_H = 0T_6 @ 6T_H``; the upper-left block is 6R_H, the last column 6p_H.
    """
    p = np.asarray(p_6_H_mm, dtype=float)
    R = as_rotation_stack(np.asarray(R_6_H, dtype=float)[None], "R_6_H")[0]
    if p.shape != (3,):
        raise ConfigError("p_6_H_mm", f"array of shape {p.shape}", "shape (3,)")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T
