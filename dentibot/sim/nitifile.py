"""NiTi endodontic file: geometry, lateral stiffness, torsional strength, cyclic fatigue.

Geometry (ISO 3630-1 / thesis ch. 5): tip diameter = size/100 mm, diameter grows by ``taper``
mm per mm from the tip over the 16 mm working part, then stays constant (shank).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.errors import ConfigError

#: Working (fluted) part length (mm), ISO 3630-1 / thesis chapter 5.
WORKING_PART_MM = 16.0
#: Total lengths available (mm), thesis chapter 5.
FILE_LENGTHS_MM = (21.0, 25.0, 28.0, 31.0)
# Young's modulus of austenitic NiTi: 40-75 GPa (Thompson 2000, Int Endod J 33:297); 50 GPa
# is the value usually taken for superelastic files. In N/mm^2 (MPa).
NITI_E_MPA = 50_000.0
# assumption: strain-life (Coffin-Manson form) for NiTi files, eps_a = C * N_f**-b with
# C = 1.0, b = 0.5: about 330 cycles at 5.5 % surface strain (a #25/.06 file 5 mm from the tip in
# a 5 mm radius curve), the order of the cycles to failure reported for such curves
# (Pruett et al. 1997, J Endod 23:77: a few hundred cycles for 5 mm radius).
FATIGUE_C = 1.0
FATIGUE_B = 0.5


@dataclass(frozen=True)
class FileFractured:
    """The file broke: ``cause`` is "torsion" or "fatigue"; ``t`` (s); ``torque_mnm`` then."""

    cause: str
    t: float
    torque_mnm: float
    depth_mm: float


@dataclass(frozen=True)
class NiTiFile:
    """A rotary NiTi file. ``size`` ISO (tip diameter size/100 mm), ``taper`` (mm/mm)."""

    size: int = 25
    taper: float = 0.06
    length_mm: float = 25.0
    # thesis eq 5.5 (ref [37]): 6.20 Ncm torsional strength.
    torsional_strength_mnm: float = FILE_STRENGTH_MNM
    youngs_modulus_mpa: float = NITI_E_MPA

    def __post_init__(self) -> None:
        if not 6 <= self.size <= 140:
            raise ConfigError("file.size", self.size, "ISO 6..140")
        if not 0.0 < self.taper <= 0.12:
            raise ConfigError("file.taper", self.taper, "0 < taper <= 0.12")
        if self.length_mm not in FILE_LENGTHS_MM:
            raise ConfigError("file.length_mm", self.length_mm, f"one of {FILE_LENGTHS_MM}")

    @property
    def tip_diameter_mm(self) -> float:
        return self.size / 100.0

    def diameter_mm(self, distance_from_tip_mm: float) -> float:
        """Diameter (mm) at a distance from the tip (0 outside the file's length)."""
        x = min(max(distance_from_tip_mm, 0.0), WORKING_PART_MM)
        return self.tip_diameter_mm + self.taper * x

    @cached_property
    def _compliance_table(self) -> tuple[float, list[float]]:
        """Lateral compliance (mm/N) at contact points every 0.25 mm from the tip."""
        step = 0.25
        L = self.length_mm
        x = np.linspace(0.0, L, 401)                    # from the clamp (shank end)
        d = np.array([self.diameter_mm(L - xi) for xi in x])
        inv_ei = 1.0 / (self.youngs_modulus_mpa * np.pi * d**4 / 64.0)
        table = []
        for c in np.arange(0.0, L + step, step):
            a = L - c
            m = x <= a
            y = (a - x[m]) ** 2 * inv_ei[m]
            xm = x[m]
            table.append(float(np.sum((y[1:] + y[:-1]) * np.diff(xm))) / 2.0
                         if m.sum() > 1 else 1e-9)
        return step, table

    def lateral_stiffness_n_mm(self, contact_from_tip_mm: float) -> float:
        """Lateral stiffness (N/mm) of the file clamped at its shank end, loaded at a point
        ``contact_from_tip_mm`` from the tip: 1 / integral((a - x)^2 / (E I(x)) dx) over the
        tapered beam (unit-load method; 3EI/L^3 for a uniform one). I = pi d^4 / 64 of a solid
        round section (real flutes make it softer, so this is an upper bound)."""
        step, table = self._compliance_table
        i = min(max(int(contact_from_tip_mm / step + 0.5), 0), len(table) - 1)
        return 1.0 / max(table[i], 1e-9)

    @staticmethod
    def cycles_to_failure(strain: float) -> float:
        """Cycles to fatigue failure at surface strain amplitude ``strain`` (see FATIGUE_C)."""
        if strain <= 0.0:
            return math.inf
        return (FATIGUE_C / strain) ** (1.0 / FATIGUE_B)
