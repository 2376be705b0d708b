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

import dentibot.sim.handpiece_kernels as kern
from dentibot.control.feedrate import (
    GEAR_RATIO,
    KM_MNM_PER_A,
    file_torque_estimate_mnm,
    file_torque_from_current,
)
from dentibot.errors import ConfigError
from dentibot.sim.state_view import scalar

#: Samples of current noise drawn at a time (the seeded stream, block by block).
NOISE_BLOCK = 4096
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
    """The handpiece's motor and drive (its state in the arrays of
    :mod:`dentibot.sim.handpiece_kernels`, whose kernel :meth:`step` calls)."""

    def __init__(self, params: HandpieceParams, rng: np.random.Generator) -> None:
        self.p = params
        self.rng = rng
        self.hs = np.zeros(len(kern.STATE_FIELDS))
        self.enabled = True
        self.fault: str | None = None
        #: the drive's output current limit (A): the motor cannot give the file more torque
        self.current_limit_a = params.current_limit_a
        self._move_rpm = params.move_rpm
        self.noise = rng.standard_normal(NOISE_BLOCK) * params.current_noise_a
        wander_phase = 0.0
        if params.current_wander_a:
            wander_phase = float(np.random.default_rng(rng.integers(1 << 30)).uniform(
                0.0, 2.0 * math.pi))
        consts = {"torque_per_amp_mnm": params.torque_per_amp_mnm,
                  "wander_phase": wander_phase}
        self.hp = np.array([float(consts[k] if k in consts else getattr(params, k))
                            for k in kern.PARAM_FIELDS])

    omega_rpm = scalar("hs", kern.S["omega_rpm"], doc="File speed (rpm).")
    pos_deg = scalar("hs", kern.S["pos_deg"], doc="File position (deg).")
    cmd_rpm = scalar("hs", kern.S["cmd_rpm"], doc="Commanded file speed (rpm).")
    target_deg = scalar("hs", kern.S["target_deg"], doc="Target of a position move (deg).")
    current_a = scalar("hs", kern.S["current_a"], doc="The motor current reading (A).")
    torque_mnm = scalar("hs", kern.S["torque_mnm"],
                        doc="Signed torque the motor applies to the file.")
    current_limit_a = scalar("hs", kern.S["current_limit_a"],
                             doc="The drive's output current limit (A).")
    _move_rpm = scalar("hs", kern.S["move_rpm"], doc="Speed of a position move (rpm).")
    stalled = scalar("hs", kern.S["stalled"], bool,
                     "The load exceeds the torque of the current limit.", settable=False)

    @property
    def mode(self) -> str:
        """``vel`` (speed mode) or ``pos`` (a position move)."""
        return "pos" if self.hs[kern.S["pos_mode"]] else "vel"

    @mode.setter
    def mode(self, mode: str) -> None:
        self.hs[kern.S["pos_mode"]] = 1.0 if mode == "pos" else 0.0

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

    def refill(self) -> None:
        """The next block of the seeded noise stream, when this one is used up (before a
        step)."""
        if self.hs[kern.S["k"]] >= NOISE_BLOCK:
            self.noise = self.rng.standard_normal(NOISE_BLOCK) * self.p.current_noise_a
            self.hs[kern.S["k"]] = 0.0

    def step(self, ts: float, resist_fwd_mnm: float, resist_rev_mnm: float) -> float:
        """Advance one period against a load resisting forward (positive) rotation with
        ``resist_fwd_mnm`` and reverse rotation with ``resist_rev_mnm`` (both >= 0, mNm at the
        file). Returns the file rotation this period (deg)
        (:func:`dentibot.sim.handpiece_kernels.step`)."""
        self.refill()
        return kern.step(self.hs, self.hp, self.noise, ts, resist_fwd_mnm, resist_rev_mnm)
