"""Sensor wrench processing: load identification, gravity compensation, change of frame.

Thesis section 4.2 (eq 4.1-4.19) and section 4.4 (eq 4.26-4.31).

Frames: {0} base, {6} flange, {S} F/T sensor (z = flange z, turned by the mounting angle
th about it: 6R_S = Rz(th), eq 4.9), {H} tool tip. ``R_a_b`` is aRb: its columns are the
{b} axes in {a} components, ``v_a = R_a_b @ v_b``.

A wrench is ``[fx, fy, fz, tx, ty, tz]``: forces N, torques N*m (the Mini40's units).
Lengths are public in mm and converted to m wherever a torque r x f is formed.

Model (eq 4.1-4.3): measured = offset + gravity load + external, in {S}::

    f   = f0 + f_g + f_e
    tau = tau0 + r x f_g + tau_e,     f_g = Rz(th)^T 0R_6^T (0, 0, -g)

with r the load's centroid in {S} and g its weight (N).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dentibot.control.linalg import as_rotation_stack, column_scaled_condition, pose_data, readonly
from dentibot.control.wrench_kernels import external_wrench, gravity_wrench, transform_wrench
from dentibot.errors import ConfigError, IdentificationError

#: Standard gravity (m/s^2), to turn the identified weight into a mass.
STANDARD_GRAVITY = 9.80665

#: Default largest accepted condition number of each column-normalised least-squares matrix
#: of :func:`identify_load` (both steps).
#:
#: Rule of thumb (checked by Monte Carlo with the Mini40's 0.01 N noise): the weight's error
#: is about ``sigma_f * cond / sqrt(3 n)``, i.e. 0.002 N per unit of condition number for
#: n = 8. Random orientations give 1.5-4; 8 poses tilted 0-90 deg from vertical give 4-25;
#: tilts within 20 deg give 40-400 (weight errors of 0.1-0.3 N, 10-30 g). At 30 the weight
#: error stays below about 0.05 N (5 g) for n = 8, a phantom force small against the 1 N
#: forces the admittance loop works with, and sets that cannot separate the offset f0 from
#: the weight (the tool always pointing the same way) fail.
DEFAULT_LOAD_MAX_CONDITION = 30.0

_LOAD_ADVICE = (
    "add poses that point the tool in at least three clearly different directions relative "
    "to gravity (e.g. straight down, tilted 60-90 deg towards the front and towards the "
    "side), and turn the flange about its axis between poses"
)



def _skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: ``_skew(a) @ b == np.cross(a, b)`` (eq 4.28)."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _rot_z(theta_rad: float) -> np.ndarray:
    c, s = np.cos(theta_rad), np.sin(theta_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])




@dataclass(frozen=True, eq=False)
class GravityModel:
    """Sensor offset and tool weight, to remove them from every reading (eq 4.15, 4.18).

    Attributes:
        f0_n: force offset f0 in {S} (N), shape (3,).
        tau0_nm: torque offset tau0 in {S} (N*m), shape (3,).
        weight_n: the tool's weight g (N).
        centroid_mm: the tool's centre of mass r in {S} (mm), shape (3,).
        mount_angle_deg: sensor mounting angle th about the flange z axis, 6R_S = Rz(th)
            (deg).

    Everything the 2 ms control tick needs is folded into two cached arrays in
    ``__post_init__``: with e = 0R_6^T (0, 0, 1) (the third row of 0R_6),
    f_g = -g Rz(th)^T e and tau_g = r x f_g, so the gravity wrench is one 6x3 matrix times e.
    The methods do not validate their inputs (speed); pass float arrays.
    """

    f0_n: np.ndarray
    tau0_nm: np.ndarray
    weight_n: float
    centroid_mm: np.ndarray
    mount_angle_deg: float
    _offset: np.ndarray = field(init=False, repr=False)
    _gain: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("f0_n", "tau0_nm", "centroid_mm"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise ConfigError(name, getattr(self, name), "3 finite numbers")
            object.__setattr__(self, name, readonly(value))
        for name in ("weight_n", "mount_angle_deg"):
            value = float(getattr(self, name))
            if not np.isfinite(value):
                raise ConfigError(name, value, "a finite number")
            object.__setattr__(self, name, value)
        force_gain = -self.weight_n * _rot_z(np.radians(self.mount_angle_deg)).T
        torque_gain = _skew(self.centroid_mm * 1e-3) @ force_gain
        object.__setattr__(self, "_gain", readonly(np.vstack([force_gain, torque_gain])))
        object.__setattr__(self, "_offset", readonly(np.concatenate([self.f0_n, self.tau0_nm])))

    @property
    def mass_kg(self) -> float:
        """Tool mass (kg) = weight / standard gravity."""
        return self.weight_n / STANDARD_GRAVITY

    def gravity_wrench(self, R_0_6: np.ndarray) -> np.ndarray:
        """Wrench in {S} that the tool's weight produces at flange orientation 0R_6 (eq 4.15).

        ``[f_g; r x f_g]`` with f_g = Rz(th)^T 0R_6^T (0, 0, -g): N and N*m, shape (6,)
        (:func:`~dentibot.control.wrench_kernels.gravity_wrench`).
        """
        e = np.asarray(R_0_6, dtype=float)[2]
        return gravity_wrench(self._gain, e[0], e[1], e[2])

    def external_wrench(self, measured: np.ndarray, R_0_6: np.ndarray) -> np.ndarray:
        """External wrench in {S}, about the sensor origin (eq 4.18), N and N*m, shape (6,).

        ``f_e = f - f0 - f_g`` and ``tau_e = tau - tau0 - r x f_g``. The torque rows printed
        in eq 4.19 are garbled (they subtract tau0 from forces and use undefined g_x, g_y,
        g_z); this is the form eq 4.18 intends
        (:func:`~dentibot.control.wrench_kernels.external_wrench`).
        """
        e = np.asarray(R_0_6, dtype=float)[2]
        return external_wrench(np.asarray(measured, dtype=float), self._offset, self._gain,
                               e[0], e[1], e[2])


@dataclass(frozen=True, eq=False)
class LoadIdentification:
    """Result of :func:`identify_load`.

    Attributes:
        model: the identified :class:`GravityModel` (weight from the g column of eq 4.12,
            mounting angle from atan2).
        mass_kg: weight / standard gravity (kg).
        k_nm: the intermediate k = tau0 - r x f0 of eq 4.5 (N*m), shape (3,).
        g_cos_n, g_sin_n: the estimates of g cos(th) and g sin(th) (N).
        consistency_n: |g - hypot(g cos th, g sin th)| (N): the two independent estimates
            of the weight should agree to within the force noise.
        force_rms_n, torque_rms_nm: RMS over all components of the model's residual
            (measured minus offset minus gravity wrench) at the identification poses.
        torque_condition, force_condition: column-normalised condition numbers of the
            torque step (eq 4.7) and the force step (eq 4.13).
    """

    model: GravityModel
    mass_kg: float
    k_nm: np.ndarray
    g_cos_n: float
    g_sin_n: float
    consistency_n: float
    force_rms_n: float
    torque_rms_nm: float
    torque_condition: float
    force_condition: float


def _solve_checked(A: np.ndarray, b: np.ndarray, what: str, max_condition: float) -> tuple:
    condition = column_scaled_condition(A)
    if not condition <= max_condition:
        raise IdentificationError(what, condition, max_condition, _LOAD_ADVICE)
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    return x, condition


def _torque_step(forces: np.ndarray, torques: np.ndarray, max_condition: float) -> tuple:
    """Eq 4.5-4.7: tau_i = r x f_i + k, unknowns r (m) and k (N*m).

    Row block per pose: [-skew(f_i), I] [r; k] = tau_i, since r x f = -f x r.
    """
    n = forces.shape[0]
    A = np.zeros((n, 3, 6))
    A[:, :, :3] = -np.array([_skew(f) for f in forces])
    A[:, :, 3:] = np.eye(3)
    x, condition = _solve_checked(
        A.reshape(3 * n, 6), torques.reshape(3 * n), "load identification, torque step "
        "(eq 4.7: centroid r and k)", max_condition
    )
    return x[:3], x[3:], condition


def _force_step(e: np.ndarray, forces: np.ndarray, max_condition: float) -> tuple:
    """Eq 4.12-4.13: unknowns (g cos th, g sin th, g, f0x, f0y, f0z).

    ``e`` holds per pose the third row of 0R_6, i.e. (r13, r23, r33) of eq 4.10's 6R_0.
    Eq 4.12 is right; the unknown vector printed in eq 4.13 is garbled (it repeats the
    offsets per pose) and is read as the six unknowns of eq 4.12.
    """
    n = e.shape[0]
    A = np.zeros((n, 3, 6))
    A[:, 0, 0], A[:, 0, 1] = -e[:, 0], -e[:, 1]
    A[:, 1, 0], A[:, 1, 1] = -e[:, 1], e[:, 0]
    A[:, 2, 2] = -e[:, 2]
    A[:, :, 3:] = np.eye(3)
    x, condition = _solve_checked(
        A.reshape(3 * n, 6), forces.reshape(3 * n), "load identification, force step "
        "(eq 4.13: weight, mounting angle and force offset)", max_condition
    )
    return x[0], x[1], x[2], x[3:], condition


def identify_load(
    flange_rotations: object,
    wrenches: object,
    *,
    max_condition: float = DEFAULT_LOAD_MAX_CONDITION,
) -> LoadIdentification:
    """Identify the sensor offsets and the tool's weight and centroid (eq 4.5-4.17).

    Input: n >= 3 static poses without contact, each the flange orientation 0R_6 and the
    sensor reading [fx, fy, fz, tx, ty, tz] (N, N*m) in {S}.

    1. Torque step (eq 4.5-4.7): least squares for r (centroid in {S}) and
       k = tau0 - r x f0 from tau = tau0 + r x (f - f0) = r x f + k.
    2. Force step (eq 4.8-4.13): least squares for (g cos th, g sin th, g, f0).
    3. Decoupling: tau0 = k + r x f0. Eq 4.6 and its inverse eq 4.14 have sign errors
       (they read k1 = tau0x - (f0z y + f0y z) etc.); expanding r x f0 gives
       k1 = tau0x - (y f0z - z f0y), k2 = tau0y - (z f0x - x f0z), k3 = tau0z - (x f0y - y f0x).
    4. Mounting angle th = atan2(g sin th, g cos th). Eq 4.16-4.17 take arccos or arcsin of
       a ratio with g; Table 4.1 shows arccos amplifies a bias enormously near 0 (its slope
       is infinite there) and so picks arcsin, which only works near 0: it saturates at
       +-90 deg, is just as bad near +-90 deg as arccos is near 0, and mixes g from the
       z rows with g sin th from the x-y rows. atan2 uses the two estimates from the same
       rows, has error about sigma/g at every angle and covers the full circle.

    Args:
        flange_rotations: n rotation matrices 0R_6, (n, 3, 3).
        wrenches: n sensor readings, (n, 6), N and N*m.
        max_condition: largest accepted column-normalised condition number, applied to
            both steps (see :data:`DEFAULT_LOAD_MAX_CONDITION`).

    Raises:
        ConfigError: field "poses" when n < 3 or the arrays do not match; bad rotations.
        IdentificationError: either step is ill-conditioned (poses too alike).
    """
    R, w = pose_data(flange_rotations, wrenches, min_poses=3, width=6, values_field="wrenches",
                     poses_need=">= 3 static poses")
    forces, torques = w[:, :3], w[:, 3:]

    r_m, k, torque_condition = _torque_step(forces, torques, max_condition)
    e = R[:, 2, :]
    g_cos, g_sin, g, f0, force_condition = _force_step(e, forces, max_condition)
    tau0 = k + np.cross(r_m, f0)
    theta = np.arctan2(g_sin, g_cos)

    model = GravityModel(
        f0_n=f0,
        tau0_nm=tau0,
        weight_n=float(g),
        centroid_mm=r_m * 1e3,
        mount_angle_deg=float(np.degrees(theta)),
    )
    residual = w - model._offset - e @ model._gain.T
    return LoadIdentification(
        model=model,
        mass_kg=model.mass_kg,
        k_nm=readonly(k),
        g_cos_n=float(g_cos),
        g_sin_n=float(g_sin),
        consistency_n=float(abs(g - np.hypot(g_cos, g_sin))),
        force_rms_n=float(np.sqrt(np.mean(residual[:, :3] ** 2))),
        torque_rms_nm=float(np.sqrt(np.mean(residual[:, 3:] ** 2))),
        torque_condition=torque_condition,
        force_condition=force_condition,
    )


@dataclass(frozen=True, eq=False)
class WrenchTransform:
    """Change a wrench's frame {S} -> {H} and its reference point p -> q (eq 4.26-4.31).

    Attributes:
        R_H_S: rotation HR_S (the thesis's H_S R of eq 4.26/4.30): takes {S} components to
            {H} components, ``v_H = R_H_S @ v_S``. Its columns are the {S} axes in {H}.
        q_S_mm: the new reference point q in {S} components, measured from the sensor
            origin p (mm). For the tool tip this is Sp_H.

    Physics: the same force f has, about q, the moment tau_q = tau_p + (p - q) x f. So
    the u of eq 4.27 ("u from q to p", tau_q = tau_p + u x f) is right, u = p - q, and
    eq 4.31's u = Sp_H (the tip seen from S, i.e. from p to q) has the opposite sign. Eq
    4.30 also applies u in {H} components, but eq 4.31 gives it in {S}; and eq 4.31 adds
    Sp_6 + 6p_H, which are in different frames (right only if {S} and {6} are parallel).
    Here the shift is done in {S}, then the result is rotated::

        f_q^H   = R_H_S f^S
        tau_q^H = R_H_S (tau_p^S - q_S x f^S)

    ``matrix`` is that 6x6 map; ``apply`` is one matmul. Torques stay in N*m.
    """

    R_H_S: np.ndarray
    q_S_mm: np.ndarray
    matrix: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        R = as_rotation_stack(np.asarray(self.R_H_S, dtype=float)[None], "R_H_S")[0]
        q = np.asarray(self.q_S_mm, dtype=float)
        if q.shape != (3,) or not np.all(np.isfinite(q)):
            raise ConfigError("q_S_mm", self.q_S_mm, "3 finite numbers (mm)")
        W = np.zeros((6, 6))
        W[:3, :3] = R
        W[3:, 3:] = R
        W[3:, :3] = -R @ _skew(q * 1e-3)
        object.__setattr__(self, "R_H_S", readonly(R))
        object.__setattr__(self, "q_S_mm", readonly(q))
        object.__setattr__(self, "matrix", readonly(W))

    @classmethod
    def for_tool(
        cls,
        R_6_H: object,
        p_6_H_mm: object,
        *,
        mount_angle_deg: float = 0.0,
        p_6_S_mm: object = (0.0, 0.0, 0.0),
        q_H_mm: object = (0.0, 0.0, 0.0),
    ) -> WrenchTransform:
        """Build from the tool calibration (section 3.4) and the sensor mounting.

        Args:
            R_6_H: 6R_H from :func:`dentibot.control.calibration.tool_axis_rotation`.
            p_6_H_mm: tool tip 6p_H from the TCP calibration (mm).
            mount_angle_deg: sensor angle th about the flange z axis, 6R_S = Rz(th) (deg).
            p_6_S_mm: sensor origin p in {6} (mm), from the mechanical design (the thesis
                uses Sp_6 = -(6R_S)^T 6p_S).
            q_H_mm: reference point in {H} (mm); zero for the tool tip, a point on the
                handpiece (e.g. the grip, point A of fig 4.7) otherwise.

        Correct version of eq 4.31: Sp_q = (6R_S)^T (6p_H + 6R_H q_H - 6p_S), and
        HR_S = (6R_H)^T 6R_S.
        """
        R_6_H = np.asarray(R_6_H, dtype=float)
        R_6_S = _rot_z(np.radians(mount_angle_deg))
        q_6 = (
            np.asarray(p_6_H_mm, dtype=float)
            + R_6_H @ np.asarray(q_H_mm, dtype=float)
            - np.asarray(p_6_S_mm, dtype=float)
        )
        return cls(R_H_S=R_6_H.T @ R_6_S, q_S_mm=R_6_S.T @ q_6)

    def apply(self, wrench_S: np.ndarray) -> np.ndarray:
        """Wrench about q in {H} components (N, N*m) from a wrench about p in {S}
        (:func:`~dentibot.control.wrench_kernels.transform_wrench`)."""
        return transform_wrench(self.matrix, np.asarray(wrench_S, dtype=float))
