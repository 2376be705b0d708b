"""The file as a tapered cantilever: its compliance against the textbook beam formulas."""

from __future__ import annotations

import math

import pytest
from scipy.integrate import quad

from dentibot.control.filebeam import NITI_E_MPA, FileBeam


def _uniform(d_mm=1.0, length=21.0):
    """A beam with a negligible taper: EI of a 1 mm round section."""
    return FileBeam(size=100, taper=1e-9, length_mm=length), NITI_E_MPA * math.pi * d_mm**4 / 64


@pytest.mark.parametrize(("a", "b"), [(0.0, 0.0), (5.0, 0.0), (0.0, 5.0), (3.0, 10.0),
                                      (12.0, 12.0)])
def test_a_uniform_beam_has_the_cantilever_influence_coefficients(a, b):
    """c(x1, x2) = x1^2 (3 x2 - x1) / (6 EI) for x1 <= x2, x from the clamp (Gere, Mechanics
    of Materials, cantilever with a point load)."""
    beam, ei = _uniform()
    L = beam.length_mm
    x1, x2 = sorted((L - a, L - b))
    assert beam.compliance_mm_n(a, b) == pytest.approx(x1**2 * (3 * x2 - x1) / (6 * ei),
                                                       rel=2e-3)


def test_the_tapered_file_matches_the_unit_load_integral_and_is_reciprocal():
    """Maxwell's reciprocity, and the tip compliance of the real #25/.06 file against an
    independent quadrature of integral (L - x)^2 / EI(x) dx."""
    f = FileBeam(25, 0.06, 25.0)
    L = f.length_mm

    def inv_ei(x):
        d = f.diameter_mm(L - x)
        return 64.0 / (NITI_E_MPA * math.pi * d**4)

    want, _ = quad(lambda x: (L - x) ** 2 * inv_ei(x), 0.0, L, points=[L - 16.0], limit=200)
    assert f.compliance_mm_n(0.0, 0.0) == pytest.approx(want, rel=2e-3)
    assert f.compliance_mm_n(2.0, 9.0) == pytest.approx(f.compliance_mm_n(9.0, 2.0))
    # the thin tip bends most: stiffer the further from the tip the load acts
    ks = [f.lateral_stiffness_n_mm(d) for d in (0.0, 3.0, 8.0, 16.0)]
    assert ks == sorted(ks)
