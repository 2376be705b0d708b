"""Admittance control (thesis 4.3-4.5): force -> tool twist -> joint targets.

Per axis, a mass-damper with no spring, ``v_i = k f_i / (m_i s + b_i)`` (eq 4.22, with the gain
``k`` of fig 4.2), discretised with Tustin (eq 4.23-4.25)::

    v[k+1] = ts/(ts b + 2m) (f[k+1] + f[k]) - (ts b - 2m)/(ts b + 2m) v[k]

The twist is taken to joint rates through the {H} Jacobian at the active reference point,
limited (``limits.JointLimiter``), and integrated with the trapezoid of eq 4.24-4.25 into the
next joint target (MoveJoints) and the joint rates (MoveJointsVel).

Unit system (kept from the thesis's experiments, write it down everywhere): forces in N and
torques in N*m go in; linear velocity comes out in mm/s and angular velocity in rad/s, i.e. the
steady state is ``v = k f / b`` mm/s per N and ``k tau / b`` rad/s per N*m. Self-alignment
(k = 500, b = 80) thus moves 6.25 mm/s per N of insertion force, as the thesis measured.
Angular rates stay in rad/s inside (``JointCommand.twist``); ``twist_mm_deg`` gives deg/s.

An axis with infinite m or b (Table 4.3's b6 = m6 = inf in self-alignment) is switched off
exactly: its velocity is identically zero, whatever the force.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dentibot.control.admittance_kernels import command, filter_step
from dentibot.control.kinematics import WRIST_CENTRE_FRAME, Meca500, SingularityMeasure
from dentibot.control.limits import JointLimiter, LimitReport, guarded_joints
from dentibot.errors import ConfigError

INF = math.inf
#: A file free length (mm, chuck to canal) below which to raise the lateral axes' damping
#: and mass as (this / free length)^3 on an arm that answers late
#: (:func:`~dentibot.control.admittance_kernels.lateral_scale`): from 7 mm deep with a 25 mm
#: file. Through a real Meca500's delay (16 ms in its queue, a 6.3 ms filter: the bench's
#: recordings) and a rigidly held tooth, the unscaled lateral loop rang at 12 Hz from about
#: 11 mm deep (12 mm free) and the main job faulted; scaled from 16 or 18 mm free it reaches
#: the working length. The protocols' default (the product runs on a real arm); it stiffens
#: the file's lateral compliance to a moving patient (thesis experiment 1 at full depth: peak
#: force 5.5 N against 3.4-3.6 on the bench, whose phantom sat in a compliant holder and did
#: not ring), so the thesis's reproductions run without it (docs/sim-to-real.md).
LATERAL_FREE_REF_MM = 18.0
#: Time constant (s) of the self-alignment and drilling admittance along the file, m_z/b_z,
#: for an arm that answers late in a canal that drags the file (:func:`with_axial_lag`).
#: Along the file a lagging admittance is a first-order low-pass of the force it reads
#: followed by k/b. Table 4.3's 1 ms leaves the axial loop a pure gain through the arm's
#: delay (the bench's Meca500: 16 ms in its queue, a 6.3 ms filter, 0.80 of the command):
#: the walls' drag on a turning file at full depth (0.21 N per mm/s) answered with k/b =
#: 6.25 mm/s per N is a velocity loop of gain 1.05, which the cutting's feed-dependent
#: resistance takes past 1, and the main job on the bench-fitted world ran away at about
#: 19 Hz from 11 mm deep. A lag brings the frequency where the delay and the lag turn the
#: loop by half a turn down, and the loop's gain there with it (with 60 ms, about 12 Hz and
#: a fifth). Measured on the fitted world, the main job (seeds 1-4) reaches the working
#: length every time with 60 ms, its peak force 1.23-1.35 N; with 30 ms it peaks at
#: 1.48-1.59 N, at the patient-moved trigger (1.5 N), and one seed faulted there; with
#: 113 ms (the bench's own low-pass on its force) three of the four did
#: (docs/sim-to-real.md).
AXIAL_LAG_S = 0.060
_ZERO6 = np.zeros(6)
DEFAULT_TS = 0.002  # s, 500 Hz (thesis: ts = 0.002)
AXES = ("x", "y", "z", "rx", "ry", "rz")


@dataclass(frozen=True)
class AdmittanceParams:
    """Gain k and per-axis inertia m and damping b (Table 4.3 / 6.4).

    Units: b in N per (mm/s) for linear axes and N*m per (rad/s) for angular axes, scaled by
    k; m in N per (mm/s^2) likewise. Only the ratios matter: time constant m/b (s) and steady
    gain k/b (eq 4.33).
    """

    k: float
    b: tuple[float, ...]
    m: tuple[float, ...]
    name: str = "custom"

    def __post_init__(self) -> None:
        object.__setattr__(self, "b", tuple(float(x) for x in self.b))
        object.__setattr__(self, "m", tuple(float(x) for x in self.m))
        if not (math.isfinite(self.k) and self.k > 0):
            raise ConfigError("admittance.k", self.k, "a finite number > 0")
        for name, vals in (("b", self.b), ("m", self.m)):
            if len(vals) != 6:
                raise ConfigError(f"admittance.{name}", vals, "exactly 6 values (x, y, z, rx, ry, rz)")
            for i, v in enumerate(vals):
                if math.isnan(v) or v <= 0:
                    raise ConfigError(f"admittance.{name}{i + 1}", v, "> 0 (inf switches the axis off)")

    def enabled(self, axis: int) -> bool:
        return math.isfinite(self.m[axis]) and math.isfinite(self.b[axis])

    def time_constant(self, axis: int) -> float:
        """m/b in s (eq 4.33); 0 for a disabled axis."""
        return self.m[axis] / self.b[axis] if self.enabled(axis) else 0.0

    def steady_gain(self, axis: int) -> float:
        """k/b: mm/s per N (linear) or rad/s per N*m (angular); 0 for a disabled axis."""
        return self.k / self.b[axis] if self.enabled(axis) else 0.0


# Table 4.3. The table's m:b = 1:1000 (tau = 1 ms) is what was run; section 4.5's text says
# 1:500 (tau = 2 ms).
DRAGGING = AdmittanceParams(
    k=1500.0, b=(80, 80, 80, 160, 160, 160), m=(0.08, 0.08, 0.08, 0.16, 0.16, 0.16), name="dragging"
)
SELF_ALIGNMENT = AdmittanceParams(
    k=500.0, b=(80, 80, 80, 80, 80, INF), m=(0.08, 0.08, 0.08, 0.08, 0.08, INF), name="self_alignment"
)


@dataclass(frozen=True)
class Experiment1Config:
    """One column of Table 6.4 (experiment 1, force-guided alignment).

    ``fz_n`` is the constant insertion force (N) or None when the feedrate controller sets it
    within ``fz_bounds_n``. m is not printed in Table 6.4; m = b/1000 as in Table 4.3.
    """

    name: str
    params: AdmittanceParams
    file_rotation: bool
    fz_n: float | None
    fz_bounds_n: tuple[float, float] | None


def _exp1_params(name: str, b6: float) -> AdmittanceParams:
    return AdmittanceParams(
        k=500.0, b=(80, 80, 80, 80, 80, b6), m=(0.08, 0.08, 0.08, 0.08, 0.08, b6 / 1000.0),
        name=f"experiment1_{name}",
    )


EXPERIMENT_1 = {
    "A": Experiment1Config("A", _exp1_params("A", 80.0), False, 1.0, None),
    "B": Experiment1Config("B", _exp1_params("B", INF), True, 1.0, None),
    "C": Experiment1Config("C", _exp1_params("C", INF), True, None, (-0.2, 0.5)),
}

PRESETS = {p.name: p for p in (DRAGGING, SELF_ALIGNMENT)} | {
    c.params.name: c.params for c in EXPERIMENT_1.values()
}


def with_axial_lag(params: AdmittanceParams, lag_s: float) -> AdmittanceParams:
    """``params`` with the z axis's mass set to ``b_z lag_s`` (time constant ``lag_s``, eq
    4.33; the gain k/b_z unchanged). Along the file a lag of the admittance acts as a
    first-order low-pass of the force it reads (:data:`AXIAL_LAG_S`)."""
    if not (math.isfinite(lag_s) and lag_s > 0.0):
        raise ConfigError("admittance.axial_lag_s", lag_s, "a finite time constant > 0 s")
    if not params.enabled(2):
        return params
    m = list(params.m)
    m[2] = params.b[2] * lag_s
    return AdmittanceParams(params.k, params.b, tuple(m), f"{params.name}_lag{lag_s * 1e3:g}ms")


class AdmittanceFilter:
    """The six Tustin mass-damper filters of eq 4.25, with the gain k applied.

    ``step(f)`` takes the wrench (N, N*m) at the reference point in {H} (sensor plus desired
    wrench) and returns the twist [mm/s x3, rad/s x3].
    """

    def __init__(self, params: AdmittanceParams, ts: float = DEFAULT_TS) -> None:
        if not (ts > 0 and math.isfinite(ts)):
            raise ConfigError("control.period_s", ts, "a finite number > 0")
        self.params = params
        self.ts = ts
        a = np.zeros(6)
        c = np.zeros(6)
        for i in range(6):
            if params.enabled(i):
                m, b = params.m[i], params.b[i]
                den = ts * b + 2.0 * m
                a[i] = params.k * ts / den
                c[i] = (ts * b - 2.0 * m) / den
        self._a = a
        self._c = c
        self.v = np.zeros(6)
        self._f_prev = np.zeros(6)

    def reset(self) -> None:
        self.v[:] = 0.0
        self._f_prev[:] = 0.0

    def step(self, f: np.ndarray) -> np.ndarray:
        """Advance one period with the wrench ``f``
        (:func:`~dentibot.control.admittance_kernels.filter_step`); the new twist (a copy)."""
        out = np.empty(6)
        filter_step(self._a, self._c, self.v, self._f_prev, np.asarray(f, dtype=float), 0.0,
                    out)
        return out


@dataclass(frozen=True)
class JointCommand:
    """One tick's result: the joint target (MoveJoints) and the joint rates (MoveJointsVel)."""

    q_target_deg: np.ndarray
    qdot_deg_s: np.ndarray
    twist: np.ndarray  # [mm/s x3, rad/s x3] in {H} at the reference point, before limits
    #: what the limiter did, as the kernel reports it: (singularity scale, speed scale,
    #: per-joint guarded mask, the six singularity factors and rates); read as ``limits``
    limited_by: tuple = field(repr=False)

    @property
    def limits(self) -> LimitReport:
        """What the limiter changed this tick (built when asked: the tick does not)."""
        s_scale, speed_scale, guarded, sing = self.limited_by
        return LimitReport(s_scale, speed_scale, guarded_joints(guarded),
                           SingularityMeasure(*sing))

    @property
    def twist_mm_deg(self) -> np.ndarray:
        """The twist as [mm/s x3, deg/s x3]."""
        return np.concatenate([self.twist[:3], np.degrees(self.twist[3:])])


@dataclass
class AdmittanceController:
    """Admittance filter + {H} Jacobian + limits + trapezoidal integration (fig 4.2).

    ``ref_point_h_mm`` is the point of {H} whose velocity the twist describes (reference point
    A for dragging, B for self-alignment: fig 4.7); the wrench handed to ``step`` must be
    expressed about the same point.
    """

    robot: Meca500
    params: AdmittanceParams
    ts: float = DEFAULT_TS
    ref_point_h_mm: tuple[float, float, float] | None = None
    limiter: JointLimiter | None = None
    singular_sigma: float = 0.05  # below this smallest singular value, damp (DLS)
    _filter: AdmittanceFilter = field(init=False)

    def __post_init__(self) -> None:
        self._filter = AdmittanceFilter(self.params, self.ts)
        if self.limiter is None:
            self.limiter = JointLimiter(self.robot, ts=self.ts)
        self._w_prev = np.zeros(6)
        self._half_ts_deg = math.degrees(0.5 * self.ts)
        self._q_lo = self.robot.joint_limits_deg[:, 0].copy()
        self._q_hi = self.robot.joint_limits_deg[:, 1].copy()
        self._set_ref(self.ref_point_h_mm)

    def _set_ref(self, ref_point_h_mm) -> None:
        self.ref_point_h_mm = ref_point_h_mm
        #: the reference point as the kernels take it (mm, {H}; the tip when None)
        self.ref_h = np.zeros(3) if ref_point_h_mm is None else \
            np.array(ref_point_h_mm, dtype=float)

    def set_params(self, params: AdmittanceParams, ref_point_h_mm=None) -> None:
        """Switch mode (e.g. dragging -> self-alignment): the filter restarts from rest."""
        self.params = params
        self._set_ref(ref_point_h_mm)
        self._filter = AdmittanceFilter(params, self.ts)
        self._w_prev[:] = 0.0

    def reset(self) -> None:
        self._filter.reset()
        self._w_prev[:] = 0.0

    def kinematics(self, q_deg):
        """``(J_H, frames)`` at ``q_deg`` for the reference point: pass it back to ``step``
        when the caller needs the chain too (one forward pass per tick)."""
        return self.robot.tool_jacobian(q_deg, self.ref_point_h_mm, with_frames=True)

    def step(self, q_deg, wrench: np.ndarray, kin=None,
             feedforward: np.ndarray | None = None, fz_n: float = 0.0,
             lateral: float = 1.0) -> JointCommand:
        """Advance one period from the joint angles ``q_deg`` with the wrench (N, N*m) plus
        ``fz_n`` along z_H (the desired insertion force, f_d of 4.4)
        (:func:`~dentibot.control.admittance_kernels.command`); ``lateral``: the lateral
        axes' damping and mass raised that many times this period
        (:func:`~dentibot.control.admittance_kernels.lateral_scale`).

        ``kin`` is ``self.kinematics(q_deg)`` if the caller already has it. ``feedforward``
        (mm/s, rad/s in {H} at the reference point) is added to the admittance's twist, after
        the filter: the motion of what the tool is in contact with (hybrid position/force
        control: the tracked tooth's velocity), so that the force law only has to correct
        the remainder."""
        robot, lim, filt = self.robot, self.limiter, self._filter
        jh, frames = kin if kin is not None else self.kinematics(q_deg)
        twist, q_next, qdot_deg_s, sing, s_scale, speed_scale, guarded = command(
            filt._a, filt._c, filt.v, filt._f_prev, np.asarray(wrench, dtype=float),
            float(fz_n), _ZERO6 if feedforward is None else
            np.asarray(feedforward, dtype=float), jh, frames, np.asarray(q_deg, dtype=float),
            self._w_prev, self._half_ts_deg, self._q_lo, self._q_hi, self.singular_sigma,
            robot.elbow_offset_rad, WRIST_CENTRE_FRAME, lim.thresholds, lim.lo_rad,
            lim.hi_rad, lim.vmax_rad_s, lim.margin_rad, lim.ts, float(lateral))
        return JointCommand(q_next, qdot_deg_s, twist, (s_scale, speed_scale, guarded, sing))
