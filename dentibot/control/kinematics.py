"""Meca500 kinematics (thesis section 3.3) in closed form.

The arm is described by Table 3.1 in the *modified* (Craig) Denavit-Hartenberg convention:
each row is (alpha_{i-1} deg, a_{i-1} mm, theta offset deg, d_i mm) and the link transform is
``Rx(alpha_{i-1}) Tx(a_{i-1}) Rz(theta_i) Tz(d_i)``. Appendices A and B of the thesis are
OCR-garbled; everything here is computed from the table.

Speed matters: the forward chain and the Jacobian run every 2 ms tick. Instead of building six
4x4 matrices with numpy (about 110 us a call), the chain is propagated with Python floats,
column by column, exploiting that ``Rx(alpha) Rz(theta)`` has a fixed structure; one numpy
array is built at the end. See ``benchmarks/``.

Units: lengths mm, public angles deg. Jacobians map joint rates in rad/s to
[linear mm/s; angular rad/s].
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

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
        self._dh = tuple(
            (
                math.cos(math.radians(alpha)),
                math.sin(math.radians(alpha)),
                float(a),
                math.radians(offset),
                float(d),
            )
            for alpha, a, offset, d in dh
        )
        self.joint_limits_deg = np.array(joint_limits_deg, dtype=float)
        self.joint_speed_limits_deg_s = np.array(joint_speed_limits_deg_s, dtype=float)
        self.joint_speed_limits_rad_s = np.radians(self.joint_speed_limits_deg_s)
        # Lengths used by the closed-form singularity measure (upper arm, forearm to wrist).
        self._a2 = float(dh[2][1])
        self._l3 = math.hypot(dh[3][1], dh[3][3])
        self._elbow_offset = math.atan2(dh[3][1], dh[3][3])
        self.set_tool(np.eye(4) if tool is None else tool)

    # ------------------------------------------------------------------ tool frame
    def set_tool(self, tool: np.ndarray) -> None:
        """Set the flange-to-tool transform 6T_H (4x4, mm)."""
        tool = np.asarray(tool, dtype=float)
        if tool.shape != (4, 4):
            raise KinematicsError(f"tool transform must be 4x4, got shape {tool.shape}")
        self.tool = tool.copy()
        self._tool_p = tuple(float(x) for x in tool[:3, 3])
        self._tool_cols = tuple(tuple(float(x) for x in tool[:3, k]) for k in range(3))

    # ------------------------------------------------------------------ chain
    def _chain(self, q_deg, all_frames: bool = True):
        """Rotation columns and origin of frames {1}..{6} in {0}, as Python floats.

        Each link is ``R <- R Rx(alpha) Rz(theta)``, ``p <- p + a x + d z'``, unrolled on
        scalars (numpy's per-call overhead dominates for 3x3 matrices). With ``all_frames``
        false only the flange ``(cols, p)`` is returned (the simulator's per-step call).
        """
        x0, x1, x2 = 1.0, 0.0, 0.0
        y0, y1, y2 = 0.0, 1.0, 0.0
        z0, z1, z2 = 0.0, 0.0, 1.0
        p0 = p1 = p2 = 0.0
        cos, sin, rad = math.cos, math.sin, math.pi / 180.0
        frames = []
        for (ca, sa, a, off, d), qi in zip(self._dh, q_deg):
            # R Rx(alpha): y' = ca y + sa z, z' = -sa y + ca z
            u0, u1, u2 = ca * y0 + sa * z0, ca * y1 + sa * z1, ca * y2 + sa * z2
            z0, z1, z2 = -sa * y0 + ca * z0, -sa * y1 + ca * z1, -sa * y2 + ca * z2
            p0 += a * x0 + d * z0
            p1 += a * x1 + d * z1
            p2 += a * x2 + d * z2
            th = qi * rad + off
            ct, st = cos(th), sin(th)
            # Rz(theta): x'' = ct x + st y', y'' = -st x + ct y'
            x0, x1, x2, y0, y1, y2 = (ct * x0 + st * u0, ct * x1 + st * u1, ct * x2 + st * u2,
                                      -st * x0 + ct * u0, -st * x1 + ct * u1, -st * x2 + ct * u2)
            if all_frames:
                frames.append((((x0, x1, x2), (y0, y1, y2), (z0, z1, z2)), (p0, p1, p2)))
        if all_frames:
            return frames
        return ((x0, x1, x2), (y0, y1, y2), (z0, z1, z2)), (p0, p1, p2)

    def flange_floats(self, q_deg):
        """Flange rotation 0R_6 as three row tuples and position (mm), in Python floats.

        The cheapest forward kinematics (no numpy): for callers that need it every step.
        """
        (c0, c1, c2), p = self._chain(q_deg, all_frames=False)
        return ((c0[0], c1[0], c2[0]), (c0[1], c1[1], c2[1]), (c0[2], c1[2], c2[2])), p

    def tool_tip_axis(self, frames) -> tuple[tuple, tuple]:
        """File tip 0p_H (mm) and file axis (the z axis of {H}) in {0}, from ``frames`` as
        returned by ``tool_jacobian(..., with_frames=True)`` (no second forward pass)."""
        cols, o6 = frames[-1]
        return _add(o6, _mul_cols(cols, self._tool_p)), _mul_cols(cols, self._tool_cols[2])

    def _check_q(self, q_deg) -> None:
        if len(q_deg) != 6:
            raise KinematicsError(f"expected 6 joint angles, got {len(q_deg)}")

    def fk(self, q_deg) -> np.ndarray:
        """Flange pose 0T_6 (4x4, mm) for joint angles in deg (eq 3.1)."""
        self._check_q(q_deg)
        cols, p = self._chain(q_deg)[-1]
        return _matrix(cols, p)

    def fk_tool(self, q_deg) -> np.ndarray:
        """Tool pose 0T_H = 0T_6 6T_H (eq 3.19)."""
        return self.fk(q_deg) @ self.tool

    def frames(self, q_deg) -> list[np.ndarray]:
        """0T_i for i = 1..6 (useful for drawing and for tests)."""
        self._check_q(q_deg)
        return [_matrix(c, p) for c, p in self._chain(q_deg)]

    # ------------------------------------------------------------------ Jacobians
    def _jacobian_at(self, frames, point, axes=None) -> np.ndarray:
        """Geometric Jacobian for the velocity of ``point`` (in {0}) (eq 3.5-3.7).

        With ``axes`` (the three column vectors of a frame's rotation in {0}) the rows are
        expressed in that frame instead of {0} (eq 3.10-3.14).
        """
        px, py, pz = point
        cols_out = []
        for cols, o in frames:
            zx, zy, zz = cols[2]
            dx, dy, dz = px - o[0], py - o[1], pz - o[2]
            lx, ly, lz = zy * dz - zz * dy, zz * dx - zx * dz, zx * dy - zy * dx
            if axes is None:
                cols_out.append((lx, ly, lz, zx, zy, zz))
            else:
                h0, h1, h2 = axes
                cols_out.append((
                    h0[0] * lx + h0[1] * ly + h0[2] * lz,
                    h1[0] * lx + h1[1] * ly + h1[2] * lz,
                    h2[0] * lx + h2[1] * ly + h2[2] * lz,
                    h0[0] * zx + h0[1] * zy + h0[2] * zz,
                    h1[0] * zx + h1[1] * zy + h1[2] * zz,
                    h2[0] * zx + h2[1] * zy + h2[2] * zz,
                ))
        return np.array(cols_out).T

    def jacobian(self, q_deg) -> np.ndarray:
        """Geometric Jacobian 0J_g of the flange origin, in {0} (eq 3.6).

        Maps joint rates (rad/s) to [flange linear velocity mm/s; angular velocity rad/s].
        """
        self._check_q(q_deg)
        frames = self._chain(q_deg)
        return self._jacobian_at(frames, frames[-1][1])

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
        cols, o6 = frames[-1]
        if ref_point_h_mm is None:
            p_h = self._tool_p
        else:
            p_h = _add(self._tool_p, _mul_cols(self._tool_cols, ref_point_h_mm))
        point = _add(o6, _mul_cols(cols, p_h))
        axes = tuple(_mul_cols(cols, tc) for tc in self._tool_cols)
        j = self._jacobian_at(frames, point, axes)
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
        wc = frames[WRIST_CENTRE_FRAME][1]
        rho = math.hypot(wc[0], wc[1])
        elbow_angle = math.radians(q_deg[2]) - self._elbow_offset
        elbow = abs(math.cos(elbow_angle))
        q5 = math.radians(q_deg[4])
        wrist = abs(math.sin(q5))
        if qdot_rad_s is None:
            return SingularityMeasure(rho, elbow, wrist)
        # Wrist-centre velocity: only joints 1-3 move it.
        v = [0.0, 0.0]
        for (cols, o), qd in zip(frames[:3], qdot_rad_s[:3]):
            zx, zy, zz = cols[2]
            v[0] += (zy * (wc[2] - o[2]) - zz * (wc[1] - o[1])) * qd
            v[1] += (zz * (wc[0] - o[0]) - zx * (wc[2] - o[2])) * qd
        if rho > 1e-9:
            rho_rate = (wc[0] * v[0] + wc[1] * v[1]) / rho
        else:
            rho_rate = -math.hypot(v[0], v[1])
        elbow_rate = -math.copysign(1.0, math.cos(elbow_angle)) * math.sin(elbow_angle) * float(qdot_rad_s[2])
        wrist_rate = math.copysign(1.0, math.sin(q5)) * math.cos(q5) * float(qdot_rad_s[4])
        return SingularityMeasure(rho, elbow, wrist, rho_rate, elbow_rate, wrist_rate)

    def within_limits(self, q_deg) -> bool:
        q = np.asarray(q_deg, dtype=float)
        return bool(np.all(q >= self.joint_limits_deg[:, 0]) and np.all(q <= self.joint_limits_deg[:, 1]))


# ---------------------------------------------------------------------- helpers
def _mul_cols(cols, v) -> tuple[float, float, float]:
    """R @ v for R given by its columns, in Python floats."""
    c0, c1, c2 = cols
    a, b, c = v
    return (
        c0[0] * a + c1[0] * b + c2[0] * c,
        c0[1] * a + c1[1] * b + c2[1] * c,
        c0[2] * a + c1[2] * b + c2[2] * c,
    )


def _add(u, v) -> tuple[float, float, float]:
    return (u[0] + v[0], u[1] + v[1], u[2] + v[2])


def _rot(cols) -> np.ndarray:
    return np.array(cols).T


def _matrix(cols, p) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3] = _rot(cols)
    t[:3, 3] = p
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
    """Mobile XYZ Euler angles (deg) of a rotation matrix, the same as :func:`pose_from_matrix`
    (scipy) gives, in closed form for one matrix: ``R = Rx(a) Ry(b) Rz(g)`` has
    ``R[0][2] = sin b``, ``R[1][2] = -sin a cos b``, ``R[2][2] = cos a cos b``,
    ``R[0][1] = -cos b sin g``, ``R[0][0] = cos b cos g``. At ``cos b = 0`` g is 0 and
    ``a = atan2(R[2][1], R[1][1])``. For the 500 Hz telemetry, where scipy's per-call cost
    (about 50 us) would be most of the tick."""
    sb = max(-1.0, min(1.0, R[0][2]))
    b = math.asin(sb)
    if math.hypot(R[0][0], R[0][1]) > 1e-9:
        a = math.atan2(-R[1][2], R[2][2])
        g = math.atan2(-R[0][1], R[0][0])
    else:
        a, g = math.atan2(R[2][1], R[1][1]), 0.0
    return math.degrees(a), math.degrees(b), math.degrees(g)


def damped_least_squares(j: np.ndarray, v: np.ndarray, sigma_min_ok: float = 0.05,
                         lambda_max: float = 0.05) -> np.ndarray:
    """Solve ``J qdot = v`` with damping that grows smoothly near a singularity.

    Far from singularities (smallest singular value >= ``sigma_min_ok``) this is the exact
    solution. Closer, ``lambda^2 = (1 - (s/sigma_min_ok)^2) lambda_max^2`` (Nakamura, Chiaverini)
    trades tracking accuracy for bounded joint rates: the result never blows up.
    """
    u, s, vt = np.linalg.svd(j)
    smin = s[-1]
    if smin >= sigma_min_ok:
        lam2 = 0.0
    else:
        lam2 = (1.0 - (smin / sigma_min_ok) ** 2) * lambda_max**2
    return vt.T @ ((s / (s * s + lam2)) * (u.T @ v))
