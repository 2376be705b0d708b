"""Patient tracking by strings: the kinematics of a six-string parallel mechanism.

Six draw-wire (string) encoders run from anchors ``a_i`` on the handpiece mount to anchors
``b_i`` on a clamp on the patient's teeth, like the legs of a cable-driven Stewart platform.

Frames: {M} the mount (rigid with the robot's flange), {T} the tooth clamp. ``a_i`` is given
in {M}, ``b_i`` in {T}; the pose of {T} in {M} is ``(R, p)`` (``R = MR_T``, ``p = Mp_T``) or
the 4x4 matrix ``MT_T``. Units: mm; rotations in the covariance and in public angles deg.

Inverse kinematics (one string per row)::

    l_i = || d_i ||,   d_i = p + R b_i - a_i,   u_i = d_i / l_i

Jacobian of the lengths for a pose error ``(dp, dth)`` with ``R -> exp([dth]x) R`` (a small
rotation about {M} axes, rad)::

    dl_i = u_i . dp + ((R b_i) x u_i) . dth          (row i of J, n x 6)

Forward kinematics: ``min_x sum_i ((l_i(x) - m_i) / s_i)^2`` over ``x = (p, r)`` with
``R = exp([r]x) R_0`` (``r`` a rotation vector, scipy ``Rotation.from_rotvec``), started from
the previous pose ``(R_0, p_0)`` (Levenberg-Marquardt, analytic Jacobian). The covariance of
the pose error is ``C = (J^T W J)^-1``, ``W = diag(1/s_i^2)`` (Gauss-Newton, first order),
reported in mm^2 / deg^2. With 3 to 5 usable strings only the position is solved; the
orientation is held at the start pose and its rows and columns of ``C`` are NaN.

Consistency (:func:`check_lengths`): a length below the slack minimum (a broken or fully
retracted wire), above the range, not finite, a jump from the previous sample, and a
residual of the forward kinematics beyond a bound (the strings cannot all be straight at
once). With exactly six strings the forward problem is square and a single wrong length
usually still has an exact (wrong) solution: the residual check needs redundancy (seven or
more strings, or position-only tracking with four or five), and the jump check carries the
load otherwise. Findings are returned, never raised.

Anchor calibration (:func:`calibrate_anchors`): with the clamp at known poses ``(R_k, p_k)``
(e.g. on a calibration block while the robot moves the mount), the corrections
``da_i, db_i`` (and optionally a length offset ``c_i`` per string) minimise
``sum_k,i (|| p_k + R_k (b_i + db_i) - (a_i + da_i) || + c_i - m_ki)^2``. Each string is
its own 6- (or 7-) parameter problem; it is identifiable only when the poses turn the clamp
about at least two axes (with one orientation only ``R b_i - a_i`` is seen, never ``a_i``
and ``b_i`` apart).

Pure numpy/scipy, the per-tick formulas compiled (:mod:`~dentibot.control.strings_kernels`):
no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from dentibot.control import strings_kernels as kernels
from dentibot.errors import ConfigError, IdentificationError

#: Fewest strings for the full pose, and for position only.
FULL_POSE_STRINGS = 6
POSITION_STRINGS = 3
#: Default largest accepted condition number of one string's calibration Jacobian.
DEFAULT_CALIBRATION_MAX_CONDITION = 1e4

_DEG = 180.0 / np.pi


def _c(a: np.ndarray) -> np.ndarray:
    """A writable C-ordered float copy, the one array type the compiled kernels are built
    for (a slice of a 4x4 pose is neither)."""
    return np.array(a, dtype=np.float64, order="C")


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class StringGeometry:
    """Anchors of ``n`` strings: ``mount_mm[i] = a_i`` in {M}, ``tooth_mm[i] = b_i`` in {T}
    (mm, shape (n, 3) each, n >= 3)."""

    mount_mm: np.ndarray
    tooth_mm: np.ndarray

    def __post_init__(self) -> None:
        a = np.asarray(self.mount_mm, dtype=float)
        b = np.asarray(self.tooth_mm, dtype=float)
        if a.ndim != 2 or a.shape[1] != 3 or a.shape != b.shape or a.shape[0] < POSITION_STRINGS:
            raise ConfigError("strings.anchors", (a.shape, b.shape),
                              "two arrays of n >= 3 xyz triples (mm), the same n")
        if not (np.isfinite(a).all() and np.isfinite(b).all()):
            raise ConfigError("strings.anchors", "non-finite", "finite coordinates (mm)")
        object.__setattr__(self, "mount_mm", _ro(a))
        object.__setattr__(self, "tooth_mm", _ro(b))

    @property
    def n(self) -> int:
        return int(self.mount_mm.shape[0])


def as_pose(pose) -> tuple[np.ndarray, np.ndarray]:
    """``(R, p)`` of a 4x4 matrix or of an ``(R, p)`` pair."""
    if isinstance(pose, tuple | list) and len(pose) == 2:
        R, p = np.asarray(pose[0], float), np.asarray(pose[1], float).reshape(3)
    else:
        t = np.asarray(pose, float)
        if t.shape != (4, 4):
            raise ConfigError("strings.pose", t.shape, "a 4x4 matrix or an (R, p) pair")
        R, p = t[:3, :3], t[:3, 3]
    if R.shape != (3, 3):
        raise ConfigError("strings.pose.R", R.shape, "a 3x3 rotation matrix")
    return R, p


def pose_matrix(R, p) -> np.ndarray:
    """The 4x4 homogeneous matrix of ``(R, p)``."""
    t = np.eye(4)
    t[:3, :3] = R
    t[:3, 3] = p
    return t


def lengths(geometry: StringGeometry, pose) -> np.ndarray:
    """Inverse kinematics: ``l_i = || p + R b_i - a_i ||`` (mm), shape (n,)."""
    R, p = as_pose(pose)
    return kernels.lengths(geometry.mount_mm, geometry.tooth_mm, _c(R), _c(p))


def length_jacobian(geometry: StringGeometry, pose) -> np.ndarray:
    """``J`` (n x 6): ``dl = J @ (dp mm, dth rad)``, row ``[u_i, (R b_i) x u_i]``."""
    R, p = as_pose(pose)
    return kernels.jacobian(geometry.mount_mm, geometry.tooth_mm, _c(R), _c(p))


def _left_jacobian(r: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian: ``d exp([r]x) = [J_l(r) dr]x exp([r]x)``."""
    th = float(np.linalg.norm(r))
    k = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if th < 1e-8:
        return np.eye(3) + 0.5 * k
    return (np.eye(3) + (1.0 - np.cos(th)) / th**2 * k
            + (th - np.sin(th)) / th**3 * (k @ k))


@dataclass(frozen=True, eq=False)
class PoseEstimate:
    """Result of :func:`forward`.

    Attributes:
        pose: ``MT_T`` (4x4, mm).
        residual_mm: measured minus model length per string (mm; NaN for unused strings).
        rms_mm: RMS of the used residuals (mm).
        covariance: 6x6 covariance of ``(dp mm, dth deg)`` about {M} axes; the orientation
            rows and columns are NaN when ``orientation_held``.
        orientation_held: fewer than six usable strings: the start orientation was kept.
        used: which strings entered the solution.
        ok: the solver converged; False also when fewer than three strings were usable
            (then ``pose`` is the start pose and ``reason`` says why).
        reason: why not ``ok`` ("" otherwise).
        evaluations: model evaluations spent.
    """

    pose: np.ndarray
    residual_mm: np.ndarray
    rms_mm: float
    covariance: np.ndarray
    orientation_held: bool
    used: np.ndarray
    ok: bool
    reason: str = ""
    evaluations: int = 0

    @property
    def position_std_mm(self) -> np.ndarray:
        """Standard deviations of x, y, z (mm)."""
        return np.sqrt(np.diag(self.covariance)[:3])


def _sigmas(sigma_mm, n: int) -> np.ndarray:
    s = np.broadcast_to(np.asarray(sigma_mm, dtype=float), (n,)).copy()
    if not (np.isfinite(s).all() and (s > 0).all()):
        raise ConfigError("strings.sigma_mm", sigma_mm, "finite standard deviations > 0 mm")
    return s


def forward(geometry: StringGeometry, lengths_mm: Sequence[float], start_pose, *,
            sigma_mm: float | Sequence[float] = 0.01, use: Sequence[bool] | None = None,
            xtol: float = 1e-14) -> PoseEstimate:
    """Forward kinematics: the pose ``MT_T`` that best explains ``lengths_mm``, from
    ``start_pose`` (the previous pose; 4x4 or ``(R, p)``).

    ``sigma_mm`` is the length noise (one value or one per string, mm); ``use`` masks
    strings out (e.g. those :func:`check_lengths` flagged; non-finite lengths are always
    left out). Six or more strings: full pose; three to five: position only, orientation
    held. Never raises for measurement problems: see ``ok``/``reason``."""
    n = geometry.n
    m = np.asarray(lengths_mm, dtype=float).reshape(-1)
    if m.shape != (n,):
        raise ConfigError("strings.lengths_mm", m.shape, f"{n} lengths")
    s = _sigmas(sigma_mm, n)
    R0, p0 = as_pose(start_pose)
    used = np.isfinite(m) if use is None else (np.asarray(use, bool) & np.isfinite(m))
    k = int(used.sum())
    nan_cov = np.full((6, 6), np.nan)
    if k < POSITION_STRINGS:
        return PoseEstimate(_ro(pose_matrix(R0, p0)), _ro(np.full(n, np.nan)), float("nan"),
                            _ro(nan_cov), True, _ro(used), False,
                            f"{k} usable strings: at least {POSITION_STRINGS} are needed")
    full = k >= FULL_POSE_STRINGS
    a, b, mu, su = geometry.mount_mm[used], geometry.tooth_mm[used], m[used], s[used]

    def rot(x):
        return Rotation.from_rotvec(x[3:]).as_matrix() @ R0 if full else R0

    def fun(x):
        d = x[:3] + b @ rot(x).T - a
        return (np.linalg.norm(d, axis=1) - mu) / su

    def jac(x):
        rb = b @ rot(x).T
        d = x[:3] + rb - a
        u = d / np.linalg.norm(d, axis=1)[:, None]
        if not full:
            return u / su[:, None]
        return np.hstack([u, np.cross(rb, u) @ _left_jacobian(x[3:])]) / su[:, None]

    x0 = np.concatenate([p0, np.zeros(3)]) if full else p0.copy()
    sol = least_squares(fun, x0, jac=jac, method="lm", xtol=xtol, ftol=xtol, gtol=xtol)
    R, p = rot(sol.x), sol.x[:3]
    pose = pose_matrix(R, p)
    res = np.full(n, np.nan)
    res[used] = m[used] - lengths(StringGeometry(a, b), pose)
    j = length_jacobian(StringGeometry(a, b), pose) / su[:, None]
    cov = nan_cov.copy()
    scale = np.array([1.0, 1.0, 1.0, _DEG, _DEG, _DEG])
    if full:
        info = j.T @ j
        cov = np.linalg.pinv(info) * np.outer(scale, scale)
    else:
        cov[:3, :3] = np.linalg.pinv(j[:, :3].T @ j[:, :3])
    ok = bool(sol.success) and bool(np.isfinite(sol.x).all())
    return PoseEstimate(_ro(pose), _ro(res), float(np.sqrt(np.mean(res[used] ** 2))),
                        _ro(cov), not full, _ro(used), ok,
                        "" if ok else f"solver did not converge: {sol.message}", int(sol.nfev))


def track(geometry: StringGeometry, lengths_mm: Sequence[float], previous_pose, *,
          iterations: int = 2) -> tuple[np.ndarray, float]:
    """One control tick's pose update: ``iterations`` Gauss-Newton steps of the same model
    as :func:`forward` (``l_i = || p + R b_i - a_i ||``, Jacobian :func:`length_jacobian`,
    rotation updated on the left, ``R <- exp([dth]x) R``) from ``previous_pose``, all six
    strings. The tooth moves a fraction of a millimetre between two ticks, so two steps
    reach the least-squares pose to well under the encoders' resolution; :func:`forward`
    gives the covariance and handles masked strings when that is needed.

    Returns ``(MT_T 4x4, rms residual mm)``; a singular Jacobian (strings aligned) gives
    a non-finite residual rather than an exception."""
    R, p = as_pose(previous_pose)
    m = np.asarray(lengths_mm, dtype=float).reshape(-1)
    if m.shape != (geometry.n,) or geometry.n < FULL_POSE_STRINGS:
        raise ConfigError("strings.lengths_mm", m.shape,
                          f"{geometry.n} lengths, at least {FULL_POSE_STRINGS}")
    try:
        R, p, rms = kernels.track(geometry.mount_mm, geometry.tooth_mm, _c(m), _c(R), _c(p),
                                  int(iterations))
    except np.linalg.LinAlgError:
        return pose_matrix(R, p), float("nan")
    return pose_matrix(R, p), float(rms)


# ============================================================================ consistency
@dataclass(frozen=True)
class LengthLimits:
    """Bounds of one string's reading (mm): ``min_mm`` the slack minimum (shorter: broken or
    fully retracted wire), ``max_mm`` the end of the range, ``max_jump_mm`` the largest
    change between consecutive samples, ``max_residual_mm`` the largest forward-kinematics
    residual."""

    min_mm: float = 20.0
    max_mm: float = 250.0
    max_jump_mm: float = 2.0
    max_residual_mm: float = 0.1

    def __post_init__(self) -> None:
        for name in ("min_mm", "max_mm", "max_jump_mm", "max_residual_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"strings.limits.{name}", v, "a finite number >= 0 mm")
        if self.max_mm <= self.min_mm:
            raise ConfigError("strings.limits.max_mm", self.max_mm, f"> min_mm ({self.min_mm})")


@dataclass(frozen=True)
class LengthFinding:
    """One string's problem: ``string`` (0-based), ``kind`` ("not_finite", "slack",
    "over_range", "jump", "inconsistent"), the value and the limit (mm), and a sentence."""

    string: int
    kind: str
    value_mm: float
    limit_mm: float
    message: str = field(default="")


def check_lengths(lengths_mm: Sequence[float], limits: LengthLimits = LengthLimits(), *,
                  previous_mm: Sequence[float] | None = None,
                  estimate: PoseEstimate | None = None) -> list[LengthFinding]:
    """Findings for a set of lengths (empty: consistent). ``previous_mm``: the last sample
    (for jumps); ``estimate``: its :func:`forward` solution (for residuals). Never raises for
    bad readings."""
    m = np.asarray(lengths_mm, dtype=float).reshape(-1)
    out: list[LengthFinding] = []
    prev = None if previous_mm is None else np.asarray(previous_mm, dtype=float).reshape(-1)
    for i, v in enumerate(m):
        no = i + 1
        if not np.isfinite(v):
            out.append(LengthFinding(i, "not_finite", float(v), float("nan"),
                                     f"string {no}: no valid length"))
            continue
        if v < limits.min_mm:
            out.append(LengthFinding(i, "slack", float(v), limits.min_mm,
                                     f"string {no}: {v:.2f} mm is below the slack minimum "
                                     f"{limits.min_mm:g} mm (broken or unhooked wire)"))
        elif v > limits.max_mm:
            out.append(LengthFinding(i, "over_range", float(v), limits.max_mm,
                                     f"string {no}: {v:.2f} mm is beyond the range "
                                     f"{limits.max_mm:g} mm"))
        if prev is not None and i < prev.size and np.isfinite(prev[i]) \
                and abs(v - prev[i]) > limits.max_jump_mm:
            out.append(LengthFinding(i, "jump", float(v - prev[i]), limits.max_jump_mm,
                                     f"string {no}: jumped {v - prev[i]:+.2f} mm in one sample "
                                     f"(limit {limits.max_jump_mm:g} mm)"))
    if estimate is not None:
        for i, r in enumerate(np.asarray(estimate.residual_mm)):
            if np.isfinite(r) and abs(r) > limits.max_residual_mm:
                out.append(LengthFinding(i, "inconsistent", float(r), limits.max_residual_mm,
                                         f"string {i + 1}: residual {r:+.3f} mm beyond "
                                         f"{limits.max_residual_mm:g} mm: the strings cannot "
                                         "all be straight at this pose (slack or caught wire)"))
    return out


# ============================================================================ calibration
@dataclass(frozen=True, eq=False)
class AnchorCalibration:
    """Result of :func:`calibrate_anchors` (mm). Arrays are read-only.

    Attributes:
        geometry: the calibrated anchors.
        mount_correction_mm, tooth_correction_mm: ``da_i``, ``db_i`` (n, 3).
        offsets_mm: ``c_i`` (n,); zeros unless fitted.
        residuals_mm: measured minus model, (N poses, n strings).
        rms_by_pose_mm (N,), rms_by_string_mm (n,): RMS of the residuals.
        mount_std_mm, tooth_std_mm (n, 3), offsets_std_mm (n,): standard deviations from
            ``sigma_mm`` and the Jacobian, ``sqrt(diag(s^2 (J^T J)^-1))``.
        condition: largest condition number among the strings' Jacobians.
    """

    geometry: StringGeometry
    mount_correction_mm: np.ndarray
    tooth_correction_mm: np.ndarray
    offsets_mm: np.ndarray
    residuals_mm: np.ndarray
    rms_by_pose_mm: np.ndarray
    rms_by_string_mm: np.ndarray
    mount_std_mm: np.ndarray
    tooth_std_mm: np.ndarray
    offsets_std_mm: np.ndarray
    condition: float


_PARAM_NAMES = ("mount anchor x", "mount anchor y", "mount anchor z",
                "tooth anchor x", "tooth anchor y", "tooth anchor z", "length offset")


def _string_model(a, b, c, Rs, ps):
    d = ps + np.einsum("kij,j->ki", Rs, b) - a
    return np.linalg.norm(d, axis=1) + c


def _string_jacobian(a, b, Rs, ps, offsets: bool) -> np.ndarray:
    d = ps + np.einsum("kij,j->ki", Rs, b) - a
    u = d / np.linalg.norm(d, axis=1)[:, None]
    cols = [-u, np.einsum("ki,kij->kj", u, Rs)]           # dl/da = -u, dl/db = R^T u
    if offsets:
        cols.append(np.ones((len(ps), 1)))
    return np.hstack(cols)


def calibration_condition(geometry: StringGeometry, i: int, poses, offsets: bool = False
                          ) -> float:
    """Condition number of string ``i``'s calibration Jacobian at ``geometry`` over the poses
    ``MT_T`` (N x 4 x 4; rows ``[-u_k, R_k^T u_k (, 1)]``, the model of
    :func:`calibrate_anchors`): how far its anchors are from undetermined."""
    t = np.asarray(poses, dtype=float)
    j = _string_jacobian(geometry.mount_mm[i], geometry.tooth_mm[i], t[:, :3, :3],
                         t[:, :3, 3], offsets)
    s = np.linalg.svd(j, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0 else float("inf")


def _identifiability_advice(Rs: np.ndarray, n_poses: int, n_params: int, rank: int,
                            weak: list[str]) -> str:
    spread = max(float(np.degrees(Rotation.from_matrix(R @ Rs[0].T).magnitude())) for R in Rs)
    parts = [f"rank {rank} of {n_params}"]
    if n_poses < n_params:
        parts.append(f"{n_poses} poses for {n_params} parameters per string: use at least "
                     f"{n_params + 2}")
    if spread < 1.0:
        parts.append("all poses have the same orientation, so only R b_i - a_i is seen: "
                     "turn the mount about at least two axes (10-20 deg)")
    elif spread < 5.0:
        parts.append(f"the orientations differ by {spread:.1f} deg at most: turn the mount "
                     "by 10-20 deg about at least two axes")
    parts.append("undetermined: " + ", ".join(weak))
    return "; ".join(parts)


def calibrate_anchors(nominal: StringGeometry, poses: Sequence, lengths_mm, *,
                      sigma_mm: float = 0.01, fit_offsets: bool = False,
                      max_condition: float = DEFAULT_CALIBRATION_MAX_CONDITION
                      ) -> AnchorCalibration:
    """Anchors (and optionally length offsets) from ``lengths_mm`` (N x n) measured at the
    known poses ``MT_T`` (N of them, 4x4 or ``(R, p)``), started from ``nominal``.

    Raises:
        IdentificationError: a string's Jacobian at the nominal anchors has a condition
            number above ``max_condition`` (naming the rank and the undetermined
            parameters, and what the pose set lacks).
        ConfigError: shapes that do not match.
    """
    n = nominal.n
    m = np.asarray(lengths_mm, dtype=float)
    pairs = [as_pose(t) for t in poses]
    if m.shape != (len(pairs), n) or not np.isfinite(m).all():
        raise ConfigError("strings.calibration.lengths_mm", m.shape,
                          f"({len(pairs)} poses, {n} strings) finite lengths")
    Rs = np.array([R for R, _ in pairs])
    ps = np.array([p for _, p in pairs])
    k = 7 if fit_offsets else 6
    da, db = np.zeros((n, 3)), np.zeros((n, 3))
    c, std = np.zeros(n), np.zeros((n, k))
    worst = 1.0
    for i in range(n):
        a0, b0 = nominal.mount_mm[i], nominal.tooth_mm[i]
        j0 = _string_jacobian(a0, b0, Rs, ps, fit_offsets)
        sv, vt = np.linalg.svd(j0, full_matrices=True)[1:]
        full_sv = np.concatenate([sv, np.zeros(k - sv.size)])
        cond = float(full_sv[0] / full_sv[-1]) if full_sv[-1] > 0 else float("inf")
        if cond > max_condition:
            rank = int((full_sv > full_sv[0] / max_condition).sum())
            weak = []
            for v in vt[rank:]:
                top = np.argsort(-np.abs(v))[:2]
                weak.append(" with ".join(f"string {i + 1} {_PARAM_NAMES[t]}" for t in top))
            raise IdentificationError(
                f"anchor calibration, string {i + 1}", cond, max_condition,
                _identifiability_advice(Rs, len(pairs), k, rank, weak))
        worst = max(worst, cond)

        def fun(x, a0=a0, b0=b0, i=i):
            cc = x[6] if fit_offsets else 0.0
            return _string_model(a0 + x[:3], b0 + x[3:6], cc, Rs, ps) - m[:, i]

        def jac(x, a0=a0, b0=b0):
            return _string_jacobian(a0 + x[:3], b0 + x[3:6], Rs, ps, fit_offsets)

        sol = least_squares(fun, np.zeros(k), jac=jac, method="lm",
                            xtol=1e-15, ftol=1e-15, gtol=1e-15)
        da[i], db[i] = sol.x[:3], sol.x[3:6]
        if fit_offsets:
            c[i] = sol.x[6]
        jj = jac(sol.x)
        std[i] = sigma_mm * np.sqrt(np.diag(np.linalg.inv(jj.T @ jj)))
    geo = StringGeometry(nominal.mount_mm + da, nominal.tooth_mm + db)
    model = np.array([lengths(geo, (R, p)) for R, p in pairs]) + c
    res = m - model
    return AnchorCalibration(
        geometry=geo, mount_correction_mm=_ro(da), tooth_correction_mm=_ro(db),
        offsets_mm=_ro(c), residuals_mm=_ro(res),
        rms_by_pose_mm=_ro(np.sqrt(np.mean(res**2, axis=1))),
        rms_by_string_mm=_ro(np.sqrt(np.mean(res**2, axis=0))),
        mount_std_mm=_ro(std[:, :3]), tooth_std_mm=_ro(std[:, 3:6]),
        offsets_std_mm=_ro(std[:, 6] if fit_offsets else np.zeros(n)), condition=worst)


# ============================================================================ a geometry
def ring_geometry(mount_radius_mm: float = 40.0, tooth_radius_mm: float = 15.0,
                  mount_z_mm: float = 0.0, tooth_z_mm: float = 0.0,
                  half_angle_deg: float = 10.0) -> StringGeometry:
    """A 6-6 arrangement (as a Stewart platform's): mount anchors in pairs at
    ``90 + 120 k +/- half_angle`` deg on a circle in the {M} xy plane at ``z = mount_z``,
    tooth anchors at ``30 + 120 k +/- half_angle`` deg on a circle in the {T} xy plane, each
    string joining neighbours so that the strings cross-brace (twist is observable)."""
    a, b = [], []
    for k in range(3):
        for sgn in (-1.0, 1.0):
            am = np.radians(90.0 + 120.0 * k + sgn * half_angle_deg)
            bt = np.radians(90.0 + 120.0 * k + sgn * (60.0 - half_angle_deg))
            a.append((mount_radius_mm * np.cos(am), mount_radius_mm * np.sin(am), mount_z_mm))
            b.append((tooth_radius_mm * np.cos(bt), tooth_radius_mm * np.sin(bt), tooth_z_mm))
    return StringGeometry(np.array(a), np.array(b))


__all__ = ["DEFAULT_CALIBRATION_MAX_CONDITION", "FULL_POSE_STRINGS", "POSITION_STRINGS",
           "AnchorCalibration", "LengthFinding", "LengthLimits", "PoseEstimate",
           "StringGeometry", "as_pose", "calibrate_anchors", "calibration_condition",
           "check_lengths", "forward", "length_jacobian", "lengths", "pose_matrix",
           "ring_geometry"]
