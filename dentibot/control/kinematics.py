"""Meca500 kinematics (thesis section 3.3) in closed form.

The arm is described by Table 3.1 in the *modified* (Craig) Denavit-Hartenberg convention:
each row is (alpha_{i-1} deg, a_{i-1} mm, theta offset deg, d_i mm) and the link transform is
``Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i)``. Appendices A and B of the thesis are
OCR-garbled; everything here is computed from the table.

Speed matters: the forward chain and the Jacobian run every 2 ms tick. Instead of building six
4x4 matrices with numpy (about 110 us a call), the chain is propagated column by column,
exploiting that ``Rx(alpha) Rz(theta)`` has a fixed structure, in compiled kernels
(:mod:`dentibot.control.kinematics_kernels`); a chain is an array of shape (6, 4, 3), each
frame's rotation columns and origin. See ``benchmarks/``.

Units: lengths mm, public angles deg. Jacobians map joint rates in rad/s to
[linear mm/s; angular rad/s].
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dentibot.control.joint_rate_kernels import damped_least_squares  # noqa: F401 - API
from dentibot.control.kinematics_kernels import (
    dh_frames,
    point_jacobian,
    singularity_factors,
    tool_point_axes,
)
from dentibot.control.kinematics_kernels import euler_xyz_deg as _euler_xyz_deg
from dentibot.errors import KinematicsError

# Table 3.1: (alpha_{i-1} deg, a_{i-1} mm, theta offset deg, d_i mm), modified DH.
MECA500_DH: tuple[tuple[float, float, float, float], ...] = (
    (0.0, 0.0, 0.0, 135.0),
    (-90.0, 0.0, -90.0, 0.0),
    (0.0, 135.0, 0.0, 0.0),
    (-90.0, 38.0, 0.0, 120.0),
    (90.0, 0.0, 0.0, 0.0),
    (-90.0, 0.0, 180.0, 70.0),
)

# Joint ranges (deg), Meca500 R3 user manual / thesis notes. J6 turns +-100 revolutions.
MECA500_JOINT_LIMITS_DEG: tuple[tuple[float, float], ...] = (
    (-175.0, 175.0),
    (-70.0, 90.0),
    (-135.0, 70.0),
    (-170.0, 170.0),
    (-115.0, 115.0),
    (-36000.0, 36000.0),
)

# Maximum joint speeds (deg/s), Meca500 R3 user manual.
MECA500_JOINT_SPEED_LIMITS_DEG_S: tuple[float, ...] = (150.0, 150.0, 180.0, 300.0, 300.0, 500.0)

#: Index (0-based) of the joint frame whose origin is the wrist centre (axes 4, 5, 6 meet there).
WRIST_CENTRE_FRAME = 4


@dataclass(frozen=True)
class SingularityMeasure:
    """Distance from the three singularities of a spherical-wrist 6R arm.

    ``det(J) = shoulder_mm * elbow * wrist * a2 * l3`` (up to sign), so each factor is a
    singularity of its own (the test suite checks this identity against ``numpy.linalg.det``):

    - ``shoulder_mm``: horizontal distance of the wrist centre from the J1 axis (mm); zero when
      the wrist centre sits on the J1 axis.
    - ``elbow``: |cos(q3 - atan2(a3, d4))|, the sine of the angle between the upper arm (a2)
      and the forearm (joint 3 to wrist centre); zero when the arm is stretched or folded.
    - ``wrist``: |sin q5|; zero when axes 4 and 6 are aligned.

    ``*_rate`` are the time derivatives of the three measures for a given joint-rate vector:
    negative means moving toward that singularity.
    """

    shoulder_mm: float
    elbow: float
    wrist: float
    shoulder_rate: float = 0.0
    elbow_rate: float = 0.0
    wrist_rate: float = 0.0

    @property
    def value(self) -> float:
        """Worst normalised factor (shoulder scaled by 50 mm) in [0, 1]."""
        return min(self.shoulder_mm / 50.0, self.elbow, self.wrist, 1.0)


class Meca500:
    """Kinematic model of the Meca500 R3 (Table 3.1) with an optional tool frame {H}.

    ``tool`` is the 4x4 flange-to-tool transform 6T_H (mm); identity means {H} = {6}.
    """

    n_joints = 6

    def __init__(
        self,
        tool: np.ndarray | None = None,
        dh: tuple[tuple[float, float, float, float], ...] = MECA500_DH,
        joint_limits_deg: tuple[tuple[float, float], ...] = MECA500_JOINT_LIMITS_DEG,
        joint_speed_limits_deg_s: tuple[float, ...] = MECA500_JOINT_SPEED_LIMITS_DEG_S,
    ) -> None:
        # (cos alpha, sin alpha, a, theta offset rad, d) per joint, as the kernels take it
        self._dh_arr = np.array([
            (math.cos(math.radians(alpha)), math.sin(math.radians(alpha)), float(a),
             math.radians(offset), float(d))
            for alpha, a, offset, d in dh
        ])
        self.joint_limits_deg = np.array(joint_limits_deg, dtype=float)
        self.joint_speed_limits_deg_s = np.array(joint_speed_limits_deg_s, dtype=float)
        self.joint_speed_limits_rad_s = np.radians(self.joint_speed_limits_deg_s)
        # Lengths used by the closed-form singularity measure (upper arm, forearm to wrist).
        self._a2 = float(dh[2][1])
        self._l3 = math.hypot(dh[3][1], dh[3][3])
        self.elbow_offset_rad = math.atan2(dh[3][1], dh[3][3])
        self.set_tool(np.eye(4) if tool is None else tool)

    # ------------------------------------------------------------------ tool frame
    def set_tool(self, tool: np.ndarray) -> None:
        """Set the flange-to-tool transform 6T_H (4x4, mm)."""
        tool = np.asarray(tool, dtype=float)
        if tool.shape != (4, 4):
            raise KinematicsError(f"tool transform must be 4x4, got shape {tool.shape}")
        self.tool = np.ascontiguousarray(tool, dtype=float).copy()

    # ------------------------------------------------------------------ chain
    def _chain(self, q_deg) -> np.ndarray:
        """Frames {1}..{6} in {0}, shape (6, 4, 3): rotation columns and origin
        (:func:`~dentibot.control.kinematics_kernels.dh_frames`)."""
        return dh_frames(self._dh_arr, np.asarray(q_deg, dtype=float))

    def flange_floats(self, q_deg):
        """Flange rotation 0R_6 as three row tuples and position (mm), in Python floats: for
        callers that work on floats every step (the simulated arm)."""
        (c0, c1, c2, p) = self._chain(q_deg)[5].tolist()
        return ((c0[0], c1[0], c2[0]), (c0[1], c1[1], c2[1]), (c0[2], c1[2], c2[2])), tuple(p)

    def tool_tip_axis(self, frames) -> tuple[tuple, tuple]:
        """File tip 0p_H (mm) and file axis (the z axis of {H}) in {0}, from ``frames`` as
        returned by ``tool_jacobian(..., with_frames=True)`` (no second forward pass)."""
        pa = tool_point_axes(frames, self.tool, _ZERO3)
        return tuple(pa[3].tolist()), tuple(pa[2].tolist())

    def _check_q(self, q_deg) -> None:
        if len(q_deg) != 6:
            raise KinematicsError(f"expected 6 joint angles, got {len(q_deg)}")

    def fk(self, q_deg) -> np.ndarray:
        """Flange pose 0T_6 (4x4, mm) for joint angles in deg (eq 3.1)."""
        self._check_q(q_deg)
        return frame_matrix(self._chain(q_deg)[5])

    def fk_tool(self, q_deg) -> np.ndarray:
        """Tool pose 0T_H = 0T_6 6T_H (eq 3.19)."""
        return self.fk(q_deg) @ self.tool

    def frames(self, q_deg) -> list[np.ndarray]:
        """0T_i for i = 1..6 (useful for drawing and for tests)."""
        self._check_q(q_deg)
        return [frame_matrix(f) for f in self._chain(q_deg)]

    # ------------------------------------------------------------------ Jacobians
    def jacobian(self, q_deg) -> np.ndarray:
        """Geometric Jacobian 0J_g of the flange origin, in {0} (eq 3.6).

        Maps joint rates (rad/s) to [flange linear velocity mm/s; angular velocity rad/s].
        """
        self._check_q(q_deg)
        frames = self._chain(q_deg)
        return point_jacobian(frames, frames[5, 3], _EYE3, False)

    def tool_jacobian(self, q_deg, ref_point_h_mm=None, with_frames: bool = False):
        """Geometric Jacobian in {H} (eq 3.14), for a reference point fixed in {H}.

        Maps joint rates (rad/s) to the velocity of the reference point (default: the origin of
        {H}, the file tip) and the angular velocity, both expressed in {H} axes.

        Eq 3.14 only rotates 0J_g by diag(HR0, HR0); that gives the *flange* velocity in {H}
        axes. The admittance law commands the tool tip (or reference point A/B), so the linear
        rows are taken at that point first (``v_p = v_6 + w x (p - o_6)``), then rotated.
        """
        self._check_q(q_deg)
        frames = self._chain(q_deg)
        ref = _ZERO3 if ref_point_h_mm is None else np.asarray(ref_point_h_mm, dtype=float)
        pa = tool_point_axes(frames, self.tool, ref)
        j = point_jacobian(frames, pa[3], pa[:3], True)
        return (j, frames) if with_frames else j

    def analytical_jacobian(self, q_deg) -> np.ndarray:
        """Analytical Jacobian of the flange for mobile XYZ Euler rates (eq 3.15-3.18).

        ``J_a = diag(I, E^-1) J_g`` with ``w = E(alpha, beta) [alpha', beta', gamma']`` and
        ``E = [[1, 0, sb], [0, ca, -sa cb], [0, sa, ca cb]]`` (eq 3.15). The printed J_we of eq
        3.16 carries spurious angle-times-trig terms (it differentiates angles, not rates);
        eq 3.15's matrix is the correct one. Angular rows are Euler-angle rates (rad/s) per joint
        rate (rad/s). Raises KinematicsError at the
        representation singularity cos(beta) = 0 (which includes the zero pose, beta = 90 deg).
        """
        j = self.jacobian(q_deg)
        a, b, _ = np.radians(pose_from_matrix(self.fk(q_deg))[3:])
        cb = math.cos(b)
        if abs(cb) < 1e-9:
            raise KinematicsError(
                f"analytical Jacobian undefined: beta = {math.degrees(b):.3f} deg (XYZ Euler "
                "representation singularity at beta = +-90 deg)"
            )
        e = euler_rate_matrix(a, b)
        ja = j.copy()
        ja[3:] = np.linalg.solve(e, j[3:])
        return ja

    # ------------------------------------------------------------------ singularities
    def singularity(self, q_deg, qdot_rad_s=None, frames=None) -> SingularityMeasure:
        """Closed-form singularity factors and, given joint rates, their rates of change.

        ``frames`` (from ``tool_jacobian(..., with_frames=True)``) avoids recomputing the chain.
        """
        if frames is None:
            self._check_q(q_deg)
            frames = self._chain(q_deg)
        q = np.asarray(q_deg, dtype=float)
        if qdot_rad_s is None:
            r = singularity_factors(frames, q, _ZERO6, False, self.elbow_offset_rad,
                                    WRIST_CENTRE_FRAME)
            return SingularityMeasure(r[0], r[1], r[2])
        r = singularity_factors(frames, q, np.asarray(qdot_rad_s, dtype=float), True,
                                self.elbow_offset_rad, WRIST_CENTRE_FRAME)
        return SingularityMeasure(*r)

    def within_limits(self, q_deg) -> bool:
        q = np.asarray(q_deg, dtype=float)
        return bool(np.all(q >= self.joint_limits_deg[:, 0]) and np.all(q <= self.joint_limits_deg[:, 1]))


# ---------------------------------------------------------------------- helpers
_ZERO3 = np.zeros(3)
_ZERO6 = np.zeros(6)
_EYE3 = np.eye(3)


def frame_matrix(frame: np.ndarray) -> np.ndarray:
    """The 4x4 transform of one frame of a chain (rotation columns and origin, (4, 3))."""
    t = np.eye(4)
    t[:3, :3] = frame[:3].T
    t[:3, 3] = frame[3]
    return t


def euler_rate_matrix(alpha_rad: float, beta_rad: float) -> np.ndarray:
    """E(alpha, beta) of eq 3.15: angular velocity = E @ (alpha', beta', gamma') (mobile XYZ)."""
    ca, sa = math.cos(alpha_rad), math.sin(alpha_rad)
    cb, sb = math.cos(beta_rad), math.sin(beta_rad)
    return np.array([[1.0, 0.0, sb], [0.0, ca, -sa * cb], [0.0, sa, ca * cb]])


def matrix_from_pose(pose) -> np.ndarray:
    """4x4 transform from (x, y, z mm, alpha, beta, gamma deg), R = Rx Ry Rz (eq 3.2)."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (6,):
        raise KinematicsError(f"a pose has 6 values (x, y, z, a, b, g), got shape {pose.shape}")
    t = np.eye(4)
    t[:3, :3] = Rotation.from_euler("XYZ", pose[3:], degrees=True).as_matrix()
    t[:3, 3] = pose[:3]
    return t


def pose_from_matrix(t) -> np.ndarray:
    """(x, y, z mm, alpha, beta, gamma deg) from a 4x4 transform, mobile XYZ Euler (eq 3.2).

    At the representation singularity (beta = +-90 deg) gamma is set to 0 and the whole
    rotation about the aligned axes goes into alpha, as the Meca500 itself reports
    (the zero pose reads (190, 0, 308, 0, 90, 0)).
    """
    t = np.asarray(t, dtype=float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # scipy's "Gimbal lock detected"
        angles = Rotation.from_matrix(t[:3, :3]).as_euler("XYZ", degrees=True)
    return np.concatenate([t[:3, 3], angles])


def euler_xyz_deg(R) -> tuple[float, float, float]:
    """Mobile XYZ Euler angles (deg) of a rotation matrix (3x3, nested lists or an array), the
    same as :func:`pose_from_matrix` (scipy) gives, in closed form
    (:func:`~dentibot.control.kinematics_kernels.euler_xyz_deg`): for the 500 Hz telemetry,
    where scipy's per-call cost (about 50 us) would be most of the tick."""
    return _euler_xyz_deg(np.ascontiguousarray(R, dtype=np.float64))
