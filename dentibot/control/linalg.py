"""Small linear-algebra helpers shared by the calibration and identification maths."""

from __future__ import annotations

import numpy as np

from dentibot.errors import ConfigError


def readonly(a: np.ndarray) -> np.ndarray:
    """A float copy of ``a`` that cannot be written to (results stay as computed)."""
    a = np.array(a, dtype=float)
    a.flags.writeable = False
    return a


def as_rotation_stack(rotations: object, field: str, tol: float = 1e-6) -> np.ndarray:
    """Check and return a stack of rotation matrices as an (N, 3, 3) float array.

    Raises ConfigError(field) when the shape is wrong or a matrix is not a proper rotation
    (R^T R = I and det R = +1 within ``tol``).
    """
    R = np.asarray(rotations, dtype=float)
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ConfigError(field, f"array of shape {R.shape}", "shape (N, 3, 3)")
    orth_err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    bad = np.flatnonzero((orth_err > tol) | (np.abs(det - 1.0) > tol))
    if bad.size:
        raise ConfigError(
            f"{field}[{bad[0]}]",
            R[bad[0]].tolist(),
            f"a rotation matrix (R^T R = I, det R = +1, within {tol:g})",
        )
    return R


def column_scaled_condition(A: np.ndarray) -> float:
    """Condition number of ``A`` after scaling every column to unit 2-norm.

    Column scaling removes the effect of units (mm vs m, N vs N*m) so the number measures
    only how independent the unknowns are. A zero column gives ``inf``.
    """
    norms = np.linalg.norm(A, axis=0)
    if np.any(norms == 0.0):
        return float("inf")
    s = np.linalg.svd(A / norms, compute_uv=False)
    return float(s[0] / s[-1]) if s[-1] > 0.0 else float("inf")


def pose_data(rotations: object, values: object, *, min_poses: int, width: int,
              values_field: str, poses_need: str) -> tuple[np.ndarray, np.ndarray]:
    """Check n flange rotations and n rows of ``width`` finite measurements taken with them.

    Returns ``(R (n, 3, 3), values (n, width))``; raises ConfigError naming "poses" when there
    are fewer than ``min_poses`` (``poses_need`` says what is needed), the rotations' field when
    one is not a rotation, and ``values_field`` when the shapes do not match.
    """
    R = np.asarray(rotations, dtype=float)
    v = np.asarray(values, dtype=float)
    n = R.shape[0] if R.ndim >= 1 else 0
    if n < min_poses:
        raise ConfigError("poses", n, poses_need)
    R = as_rotation_stack(R, "flange_rotations")
    if v.shape != (n, width) or not np.all(np.isfinite(v)):
        raise ConfigError(
            values_field, f"array of shape {v.shape}", f"shape ({n}, {width}) of finite numbers"
        )
    return R, v
