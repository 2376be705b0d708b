"""File feedrate control and the reversal trigger (thesis 5.3-5.4, fig 5.5, 5.6, 5.8).

A PD controller on the torque error ``e = tau_d - tau`` (file torque, mNm) gives the insertion
force ``fz*`` (N) that the admittance law turns into feed along the file axis; ``fz = sat(fz*)``
(eq 5.7). When the file torque is far over ``tau_d`` the PD output drops below the reversal
threshold and inverse rotation control takes over (section 5.4: ``fz* < -0.2``).

Eq 5.7 prints its bounds inconsistently (-0.2 .. 0.2 .. 0.5); section 5.4 runs with -0.5 .. 0.5,
which are the defaults here; experiment 1 config C used -0.2 .. 0.5 (Table 6.4).

The thesis gives no PD gains. The defaults are assumptions chosen from the thesis's numbers:
with ``kp = 0.025 N/mNm`` the feed saturates at +0.5 N when the torque is 20 mNm or more
below ``tau_d`` and reversal triggers when it is more than 8 mNm above (48 mNm for
tau_d = 40, 58 mNm for tau_d = 50: below the 62 mNm strength). The derivative acts on the
measured torque (no kick when tau_d changes) through a first-order filter (``kd_filter_s``)
so that motor-current noise is not amplified.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from dentibot.errors import ConfigError

#: Torsional strength of a NiTi file (thesis eq 5.5, ref [37]): 6.20 Ncm.
FILE_STRENGTH_MNM = 62.0
#: Handpiece motor: gear ratio and torque constant (thesis 5.1).
GEAR_RATIO = 67.0
KM_MNM_PER_A = 16.0
#: Below this motor speed (rpm) the file counts as still: no friction current is removed.
MOVING_RPM = 0.5


@njit(cache=True)
def file_torque_from_current(current_a: float, efficiency: float = 1.0,
                             km_mnm_per_a: float = KM_MNM_PER_A, gear_ratio: float = GEAR_RATIO) -> float:
    """File torque (mNm) from motor current (A): ``T = Km I GR eta`` (eq 5.4-5.5)."""
    return current_a * km_mnm_per_a * gear_ratio * efficiency


@njit(cache=True)
def file_torque_estimate_mnm(current_a: float, velocity_rpm: float, efficiency: float = 1.0,
                             friction_current_a: float = 0.0, km_mnm_per_a: float = KM_MNM_PER_A,
                             gear_ratio: float = GEAR_RATIO,
                             moving_rpm: float = MOVING_RPM) -> float:
    """File torque (mNm) from the motor current with the no-load (friction) current removed:
    ``T = (I - I_f sign(w)) Km GR eta`` (eq 5.4-5.5 plus friction; ``sign(w)`` is 0 below
    ``moving_rpm``). With ``efficiency = 1`` and no friction this is eq 5.4-5.5 as printed.
    (Compiled: the control tick's estimate calls it inside its kernel.)"""
    sgn = 1.0 if velocity_rpm > moving_rpm else (-1.0 if velocity_rpm < -moving_rpm else 0.0)
    return file_torque_from_current(current_a - friction_current_a * sgn, efficiency,
                                    km_mnm_per_a, gear_ratio)


def current_limit_a(torque_limit_mnm: float = FILE_STRENGTH_MNM, efficiency: float = 1.0,
                    km_mnm_per_a: float = KM_MNM_PER_A, gear_ratio: float = GEAR_RATIO) -> float:
    """Motor current (A) at which the file reaches ``torque_limit_mnm`` (eq 5.6)."""
    return torque_limit_mnm / (km_mnm_per_a * gear_ratio * efficiency)


@dataclass(frozen=True)
class FeedrateParams:
    """Gains and bounds of the feedrate controller (units: mNm in, N out)."""

    tau_d_mnm: float = 40.0
    kp_n_per_mnm: float = 0.025
    kd_n_s_per_mnm: float = 0.0005
    kd_filter_s: float = 0.02
    fz_min_n: float = -0.5
    fz_max_n: float = 0.5
    reversal_threshold_n: float = -0.2

    def __post_init__(self) -> None:
        if not 0.0 < self.tau_d_mnm < FILE_STRENGTH_MNM:
            raise ConfigError("feedrate.tau_d_mnm", self.tau_d_mnm,
                              f"0 < tau_d < {FILE_STRENGTH_MNM} mNm (the file's strength)")
        if not self.kp_n_per_mnm > 0.0:
            raise ConfigError("feedrate.kp_n_per_mnm", self.kp_n_per_mnm, "> 0")
        if self.kd_n_s_per_mnm < 0.0:
            raise ConfigError("feedrate.kd_n_s_per_mnm", self.kd_n_s_per_mnm, ">= 0")
        if self.kd_filter_s <= 0.0:
            raise ConfigError("feedrate.kd_filter_s", self.kd_filter_s, "> 0 s")
        if not self.fz_min_n < self.fz_max_n:
            raise ConfigError("feedrate.fz_min_n", self.fz_min_n, f"< fz_max_n = {self.fz_max_n}")
        # The threshold applies to the unsaturated fz*, so it may lie below fz_min; a value
        # >= 0 would reverse while the torque is still under tau_d.
        if not self.reversal_threshold_n < 0.0:
            raise ConfigError("feedrate.reversal_threshold_n", self.reversal_threshold_n,
                              "< 0 N (reversal is for torque above tau_d)")

    @property
    def reversal_torque_mnm(self) -> float:
        """Steady torque above which reversal triggers (derivative term at rest)."""
        return self.tau_d_mnm - self.reversal_threshold_n / self.kp_n_per_mnm


@dataclass(frozen=True)
class FeedrateOutput:
    fz_star_n: float  # unsaturated PD output
    fz_n: float  # saturated, fed to the admittance law (eq 5.7)
    reverse: bool  # fz* below the reversal threshold (section 5.4)


#: :class:`FeedrateController`'s state array: whether a torque was taken, the last torque
#: (mNm) and the filtered derivative (mNm/s).
PD_HAS, PD_TAU, PD_DTAU = 0, 1, 2
#: Its parameter array: gains, set-point, bounds and the derivative filter's coefficients.
PD_KP, PD_KD, PD_TAU_D, PD_FZ_MIN, PD_FZ_MAX, PD_D_A, PD_D_B = range(7)


@njit(cache=True)
def pd_step(st, par, tau_mnm: float) -> tuple[float, float]:
    """One period of the feedrate PD (fig 5.5) on the state ``st`` with the parameters
    ``par`` (:data:`PD_HAS` ..., :data:`PD_KP` ...): the derivative of the measured torque
    through ``D(s) = s / (T s + 1)`` (Tustin, ``y[k] = a (u[k] - u[k-1]) + b y[k-1]``, no
    kick on the first sample), ``fz* = kp (tau_d - tau) - kd dtau`` and ``fz = sat(fz*)``
    (eq 5.7). Returns ``(fz*, fz)`` (N)."""
    if st[PD_HAS] == 0.0:
        st[PD_TAU] = tau_mnm
        st[PD_HAS] = 1.0
    st[PD_DTAU] = par[PD_D_A] * (tau_mnm - st[PD_TAU]) + par[PD_D_B] * st[PD_DTAU]
    st[PD_TAU] = tau_mnm
    fz_star = par[PD_KP] * (par[PD_TAU_D] - tau_mnm) - par[PD_KD] * st[PD_DTAU]
    return fz_star, min(max(fz_star, par[PD_FZ_MIN]), par[PD_FZ_MAX])


class FeedrateController:
    """PD on (tau_d - tau) -> fz (fig 5.5), discretised at period ``ts``; its state in
    ``st`` and its compiled step :func:`pd_step`."""

    def __init__(self, params: FeedrateParams | None = None, ts: float = 0.002) -> None:
        self.params = p = params or FeedrateParams()
        if not ts > 0.0:
            raise ConfigError("control.period_s", ts, "> 0")
        self.ts = ts
        # Filtered derivative of the measured torque, Tustin: D(s) = s / (T s + 1).
        t = p.kd_filter_s
        self.par = np.array([p.kp_n_per_mnm, p.kd_n_s_per_mnm, p.tau_d_mnm, p.fz_min_n,
                             p.fz_max_n, 2.0 / (2.0 * t + ts), (2.0 * t - ts) / (2.0 * t + ts)])
        self.st = np.zeros(3)

    def reset(self) -> None:
        self.st[:] = 0.0

    def step(self, tau_mnm: float) -> FeedrateOutput:
        if not math.isfinite(tau_mnm):
            raise ValueError(f"file torque is not finite: {tau_mnm}")
        fz_star, fz = pd_step(self.st, self.par, float(tau_mnm))
        return FeedrateOutput(fz_star, fz, fz_star < self.params.reversal_threshold_n)


def warm_up() -> None:
    """Compile (or load from the cache) the two compiled torque laws for the argument lists
    their Python callers pass (each list of omitted defaults is a signature of its own to
    numba). Called once, at import."""
    file_torque_from_current(1.0, 1.0)
    file_torque_from_current(1.0, 1.0, 16.0, 67.0)
    file_torque_estimate_mnm(0.1, 100.0, 1.0, 0.0)
    file_torque_estimate_mnm(0.1, 100.0, 1.0, 0.0, 16.0, 67.0)
    FeedrateController().step(1.0)


warm_up()      # at import: before any device streams or loop runs
