"""Handpiece: Maxon motor through a 67:1 gear turning the file (thesis 5.1).

Speed loop: first order towards the commanded file speed (or a position profile for
``move_relative``), as long as the motor can supply the load torque; above the torque of its
current limit (the motor's own, or the lower one the drive is set to) the motor stalls
(decelerates to rest with the same time constant) and gives the file no more than that torque.

Current model::

    I = tau_file / (Km * GR * efficiency) + I_friction * sign(omega) + noise

so the file torque estimate that matches this simulator is
``tau = (I - I_friction * sign(omega)) * Km * GR * efficiency`` with
``efficiency = HandpieceParams.efficiency`` and ``I_friction = friction_current_a``. The
thesis's eq 5.4-5.5 (efficiency 1, no friction) overestimates the torque by about 1/0.7.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dentibot.control.feedrate import (
    GEAR_RATIO,
    KM_MNM_PER_A,
    file_torque_estimate_mnm,
    file_torque_from_current,
)
from dentibot.errors import ConfigError

#: Largest file speed (rpm) the handpiece accepts (thesis 5.1).
MAX_FILE_RPM = 200.0


@dataclass(frozen=True)
class HandpieceParams:
    gear_ratio: float = GEAR_RATIO            # thesis 5.1
    km_mnm_per_a: float = KM_MNM_PER_A        # thesis 5.1
    # assumption: gearhead efficiency 0.7 (Maxon planetary 3-stage gearheads: 0.59-0.75).
    efficiency: float = 0.7
    # assumption: no-load (friction) current 5 mA, typical of small Maxon DC motors.
    friction_current_a: float = 0.005
    # assumption: current limit 0.5 A (small Maxon DC motor continuous current 0.3-1 A):
    # 0.5 * 16 * 67 * 0.7 = 375 mNm at the file, far above the file's 62 mNm.
    current_limit_a: float = 0.5
    # assumption: speed-loop time constant 10 ms.
    tau_s: float = 0.010
    # assumption: current measurement noise 1 mA rms (about 0.75 mNm at the file).
    current_noise_a: float = 0.001
    # assumption: position moves (reversal) run at 100 rpm at the file.
    move_rpm: float = 100.0
    max_rpm: float = MAX_FILE_RPM
    # The current measurement only (not the motor's physics): a constant reading offset (A)
    # and a slow sinusoidal wander of ``current_wander_a`` amplitude and
    # ``current_wander_period_s`` period with a seeded phase. Defaults: none.
    current_offset_a: float = 0.0
    current_wander_a: float = 0.0
    current_wander_period_s: float = 30.0

    @property
    def torque_per_amp_mnm(self) -> float:
        """File torque per motor ampere, Km GR efficiency (mNm/A), eq 5.4-5.5."""
        return file_torque_from_current(1.0, self.efficiency, self.km_mnm_per_a, self.gear_ratio)

    def file_torque_estimate_mnm(self, current_a: float, velocity_rpm: float) -> float:
        """The estimate consistent with this model (see module docstring)."""
        return file_torque_estimate_mnm(current_a, velocity_rpm, self.efficiency,
                                        self.friction_current_a, self.km_mnm_per_a,
                                        self.gear_ratio)


class HandpieceModel:
    def __init__(self, params: HandpieceParams, rng: np.random.Generator) -> None:
        self.p = params
        self.rng = rng
        self.omega_rpm = 0.0
        self.pos_deg = 0.0
        self.cmd_rpm = 0.0
        self.mode = "vel"             # vel | pos
        self.target_deg = 0.0
        self.enabled = True
        self.current_a = 0.0
        self.torque_mnm = 0.0          # signed torque the motor applies to the file
        self.stalled = False
        self.fault: str | None = None
        #: the drive's output current limit (A): the motor cannot give the file more torque
        self.current_limit_a = params.current_limit_a
        self._noise = rng.standard_normal(4096) * params.current_noise_a
        self._k = 0
        self._t = 0.0
        self._wander_phase = 0.0
        if params.current_wander_a:
            self._wander_phase = float(np.random.default_rng(rng.integers(1 << 30)).uniform(
                0.0, 2.0 * math.pi))

    def set_velocity(self, rpm: float) -> None:
        rpm = float(rpm)
        if not abs(rpm) <= self.p.max_rpm:
            raise ConfigError("handpiece.rpm", rpm, f"|rpm| <= {self.p.max_rpm} at the file")
        self.mode = "vel"
        self.cmd_rpm = rpm

    def move_relative(self, deg: float, rpm: float | None = None) -> None:
        rpm = self.p.move_rpm if rpm is None else float(rpm)
        if not 0.0 < rpm <= self.p.max_rpm:
            raise ConfigError("handpiece.move_rpm", rpm, f"0 < rpm <= {self.p.max_rpm}")
        self.mode = "pos"
        self.target_deg = self.pos_deg + float(deg)
        self._move_rpm = rpm

    def stop(self) -> None:
        self.mode = "vel"
        self.cmd_rpm = 0.0

    def set_current_limit(self, amps: float) -> None:
        """The drive's output current limit (A), at most the motor's own."""
        if not 0.0 < amps <= self.p.current_limit_a:
            raise ConfigError("handpiece.current_limit_a", amps,
                              f"0 < A <= {self.p.current_limit_a} (the motor's limit)")
        self.current_limit_a = float(amps)

    @property
    def move_done(self) -> bool:
        return self.mode == "pos" and abs(self.target_deg - self.pos_deg) < 0.5 \
            and abs(self.omega_rpm) < 1.0

    def step(self, ts: float, resist_fwd_mnm: float, resist_rev_mnm: float) -> float:
        """Advance one period against a load resisting forward (positive) rotation with
        ``resist_fwd_mnm`` and reverse rotation with ``resist_rev_mnm`` (both >= 0, mNm at the
        file). Returns the file rotation this period (deg)."""
        p = self.p
        if self.mode == "pos":
            err = self.target_deg - self.pos_deg
            ref = err / (6.0 * 4.0 * p.tau_s)  # P loop, deg -> rpm (1 rpm = 6 deg/s)
            m = self._move_rpm
            ref = min(max(ref, -m), m)
        else:
            ref = self.cmd_rpm
        w = self.omega_rpm
        direction = w if abs(w) > 1e-6 else ref
        sgn = (direction > 0.0) - (direction < 0.0)
        resist_mnm = resist_fwd_mnm if sgn > 0 else resist_rev_mnm
        load = resist_mnm * sgn
        # the current limit covers the no-load current too (see the current model above)
        t_max = max(0.0, self.current_limit_a - p.friction_current_a) * p.torque_per_amp_mnm
        a = -math.expm1(-ts / p.tau_s)   # exact discretisation of the first-order loop
        if resist_mnm > t_max and sgn != 0:
            self.stalled = True
            w += (0.0 - w) * a
            self.torque_mnm = t_max * sgn if abs(w) > 1e-3 or ref else 0.0
        else:
            self.stalled = False
            w += (ref - w) * a
            self.torque_mnm = load if (abs(w) > 1e-3 or ref) else 0.0
        if abs(w) < 1e-6:
            w = 0.0
        self.omega_rpm = w
        dpos = w * 6.0 * ts
        self.pos_deg += dpos
        k = self._k
        if k == 4096:  # next block of the seeded noise stream
            self._noise = self.rng.standard_normal(4096) * p.current_noise_a
            k = 0
        self._k = k + 1
        fsgn = (w > 0.5) - (w < -0.5)
        self.current_a = (self.torque_mnm / p.torque_per_amp_mnm + p.friction_current_a * fsgn
                          + float(self._noise[k]))
        if p.current_offset_a or p.current_wander_a:
            self._t += ts
            self.current_a += p.current_offset_a + p.current_wander_a * math.sin(
                2.0 * math.pi * self._t / p.current_wander_period_s + self._wander_phase)
        return dpos
