"""The NiTi file as a beam: geometry and lateral compliance of a tapered cantilever.

One model for the simulated file (its bending in the canal) and for the controller (what the
measured lateral loads say about where the file's tip and its part in the canal are).

Geometry (ISO 3630-1 / thesis ch. 5): tip diameter = size/100 mm, the diameter grows by
``taper`` mm per mm from the tip over the 16 mm working part and stays constant on the shank.
Bending: the file is clamped at its shank end (the handpiece's chuck) and loaded laterally;
its section is taken as a solid round one, ``I = pi d^4 / 64`` (real flutes make the file
softer, so its stiffness is an upper bound).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit

#: Working (fluted) part length (mm), ISO 3630-1 / thesis chapter 5.
WORKING_PART_MM = 16.0
# Young's modulus of austenitic NiTi: 40-75 GPa (Thompson 2000, Int Endod J 33:297); 50 GPa
# is the value usually taken for superelastic files. In N/mm^2 (MPa).
NITI_E_MPA = 50_000.0


@dataclass(frozen=True)
class FileBeam:
    """A rotary NiTi file as a tapered cantilever: ``size`` ISO, ``taper`` mm/mm, ``length_mm``
    from the tip to the chuck."""

    size: int = 25
    taper: float = 0.06
    length_mm: float = 25.0
    youngs_modulus_mpa: float = NITI_E_MPA

    @property
    def tip_diameter_mm(self) -> float:
        return self.size / 100.0

    def diameter_mm(self, distance_from_tip_mm: float) -> float:
        """Diameter (mm) at a distance from the tip (the tip's below 0, the shank's beyond
        the working part)."""
        x = min(max(distance_from_tip_mm, 0.0), WORKING_PART_MM)
        return self.tip_diameter_mm + self.taper * x

    @cached_property
    def integrals(self) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """``(step, I0, I1, I2)``: ``Ik(x) = integral_0^x xi^k / (E I(xi)) dxi`` from the clamp
        (x = 0) every ``step`` mm (trapezoid rule over 400 intervals), the tables
        :func:`beam_compliance` interpolates."""
        L = self.length_mm
        x = np.linspace(0.0, L, 401)
        d = np.array([self.diameter_mm(L - xi) for xi in x])
        inv_ei = 1.0 / (self.youngs_modulus_mpa * math.pi * d**4 / 64.0)
        dx = np.diff(x)
        out = []
        for k in range(3):
            y = x**k * inv_ei
            out.append(np.concatenate(([0.0], np.cumsum((y[1:] + y[:-1]) * dx / 2.0))))
        return float(x[1] - x[0]), out[0], out[1], out[2]

    def compliance_mm_n(self, from_tip_1_mm: float, from_tip_2_mm: float) -> float:
        """Lateral deflection (mm) at ``from_tip_1_mm`` from the tip per N of lateral load at
        ``from_tip_2_mm`` (symmetric in its arguments): :func:`beam_compliance`."""
        step, i0, i1, i2 = self.integrals
        return beam_compliance(self.length_mm, step, i0, i1, i2,
                               float(from_tip_1_mm), float(from_tip_2_mm))

    def lateral_stiffness_n_mm(self, contact_from_tip_mm: float) -> float:
        """Lateral stiffness (N/mm) at a point ``contact_from_tip_mm`` from the tip:
        ``1 / c(a, a)`` (:meth:`compliance_mm_n`)."""
        return 1.0 / self.compliance_mm_n(contact_from_tip_mm, contact_from_tip_mm)


@njit(cache=True)
def beam_compliance(length_mm: float, step: float, i0: np.ndarray, i1: np.ndarray,
                    i2: np.ndarray, from_tip_1_mm: float, from_tip_2_mm: float) -> float:
    """Lateral deflection (mm) at ``from_tip_1_mm`` from the tip of a cantilever of
    ``length_mm`` per N of lateral load at ``from_tip_2_mm``, from the tables of
    :attr:`FileBeam.integrals` (``step``, ``I0``, ``I1``, ``I2``; compiled: the simulated
    canal calls it inside its contact kernel).

    Unit-load method for a cantilever of varying section, x measured from the clamp:
    ``c(x1, x2) = integral_0^min(x1, x2) (x1 - xi)(x2 - xi) / (E I(xi)) dxi
    = x1 x2 I0 - (x1 + x2) I1 + I2`` at ``min(x1, x2)``, interpolated linearly in the tables;
    ``L^3 / 3EI`` at the tip of a uniform beam. At least 1e-9 mm/N (a load at the clamp)."""
    L = length_mm
    x1 = L - min(max(from_tip_1_mm, 0.0), L)
    x2 = L - min(max(from_tip_2_mm, 0.0), L)
    lo = min(x1, x2)
    j = min(int(lo / step), len(i0) - 2)
    w = lo / step - j
    a0 = i0[j] + (i0[j + 1] - i0[j]) * w
    a1 = i1[j] + (i1[j + 1] - i1[j]) * w
    a2 = i2[j] + (i2[j + 1] - i2[j]) * w
    return max(x1 * x2 * a0 - (x1 + x2) * a1 + a2, 1e-9)


def warm_up() -> None:
    """Compile (or load from the cache) :func:`beam_compliance` (a control loop must not pay
    a compilation at its first tick). Called once, at import."""
    FileBeam().compliance_mm_n(1.0, 2.0)


warm_up()      # at import: before any device streams or loop runs
