"""NiTi endodontic file: geometry, lateral stiffness, torsional strength, cyclic fatigue.

Geometry and bending: :class:`dentibot.control.filebeam.FileBeam` (the one model the
controller uses too).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.control.filebeam import NITI_E_MPA, FileBeam
from dentibot.errors import ConfigError

#: Total lengths available (mm), thesis chapter 5.
FILE_LENGTHS_MM = (21.0, 25.0, 28.0, 31.0)
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

    @cached_property
    def beam(self) -> FileBeam:
        """The file as a tapered cantilever (geometry and lateral compliance)."""
        return FileBeam(self.size, self.taper, self.length_mm, self.youngs_modulus_mpa)

    @property
    def tip_diameter_mm(self) -> float:
        return self.size / 100.0

    def diameter_mm(self, distance_from_tip_mm: float) -> float:
        """Diameter (mm) at a distance from the tip (:meth:`FileBeam.diameter_mm`)."""
        return self.beam.diameter_mm(distance_from_tip_mm)

    def compliance_mm_n(self, from_tip_1_mm: float, from_tip_2_mm: float) -> float:
        """:meth:`FileBeam.compliance_mm_n`."""
        return self.beam.compliance_mm_n(from_tip_1_mm, from_tip_2_mm)

    def lateral_stiffness_n_mm(self, contact_from_tip_mm: float) -> float:
        """:meth:`FileBeam.lateral_stiffness_n_mm`."""
        return self.beam.lateral_stiffness_n_mm(contact_from_tip_mm)

    @staticmethod
    def cycles_to_failure(strain: float) -> float:
        """Cycles to fatigue failure at surface strain amplitude ``strain`` (see FATIGUE_C)."""
        if strain <= 0.0:
            return math.inf
        return (FATIGUE_C / strain) ** (1.0 / FATIGUE_B)
