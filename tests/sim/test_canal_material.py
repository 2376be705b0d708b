"""Canal physics: cutting by energy, rubbing, screw-in, debris flushing, the photographed red
area of eq 6.1, and phantom materials. Each number is derived here from the geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dentibot.errors import ConfigError
from dentibot.sim.canal import MATERIALS, Canal, CanalParams, material_params
from dentibot.sim.nitifile import NiTiFile

FILE = NiTiFile()          # #25/.06
AXIS = (0.0, 0.0, 1.0)     # straight canal along {P} z
DT = 0.002


def _overlap(canal: Canal, depth: float) -> np.ndarray:
    """r_file - R per slice (positive: the file overlaps the lumen), from the definitions."""
    r_file = (FILE.tip_diameter_mm + FILE.taper * (depth - canal.s)) / 2.0
    inside = (canal.s < depth) & (canal.s > depth - 16.0)
    return np.where(inside, r_file - canal.R, -np.inf)


def _at(canal: Canal, depth: float):
    """Put the file tip at ``depth`` on the axis (first call: zero feed)."""
    return canal.interact((0.0, 0.0, depth), AXIS, FILE, DT)


def test_engagement_and_cutting_torque_follow_the_overlap():
    c = Canal(CanalParams())
    it = _at(c, 8.0)
    g = _overlap(c, 8.0)
    area = float(np.maximum(g, 0.0).sum()) * 0.25
    assert area > 0.3
    assert it.engagement_mm2 == pytest.approx(area, rel=1e-9)
    # no feed yet, no debris, no rubbing in resin: the torque is k_A A
    assert it.resist_mnm == pytest.approx(8.0 * area, rel=1e-9)


def test_a_forward_turn_removes_torque_times_angle_over_the_cutting_energy():
    p = CanalParams(cutting_energy_mj_mm3=2000.0)
    c = Canal(p)
    it = _at(c, 10.0)
    r_before = c.R.copy()
    rev = 0.01
    dv = c.cut(rev)
    # energy balance: W = tau_c * 2 pi rev (mNm * rad = mJ) = u_s * V
    assert dv == pytest.approx(it.resist_mnm * 2 * math.pi * rev / 2000.0, rel=1e-9)
    # the volume came off the engaged slices, in proportion to their overlap
    g = np.maximum(_overlap(Canal(p), 10.0), 0.0)
    dr = c.R - r_before
    assert np.all(dr[g == 0.0] == 0.0)
    ratio = dr[g > 0] / g[g > 0]
    assert ratio == pytest.approx(np.full(ratio.shape, ratio[0]), rel=1e-9)
    assert dv == pytest.approx(float(np.sum(2 * math.pi * r_before * dr)) * 0.25, rel=1e-9)
    assert c.debris_mm3 == pytest.approx(dv, rel=1e-9)


def test_a_turn_never_cuts_beyond_the_file():
    c = Canal(CanalParams(cutting_energy_mj_mm3=1.0))   # absurdly easy to cut
    _at(c, 6.0)
    g = _overlap(c, 6.0)
    c.cut(10.0)
    touched = g > 0.0
    np.testing.assert_allclose(c.R[touched], (c.R0 + g)[touched])   # exactly the file's shape


def test_rubbing_counts_the_contact_length():
    p = CanalParams(rub_mnm_per_mm=2.0)
    c = Canal(p)
    _at(c, 8.0)
    g = _overlap(c, 8.0)
    c.cut(1e6)                        # the lumen now has the file's shape where it was wider
    c.debris_mm3 = 0.0                # (flushed)
    it = _at(c, 8.0)
    assert it.engagement_mm2 == pytest.approx(0.0, abs=1e-12)
    # the slices it cut touch it; near the tip the #15/.02 lumen is wider than the file
    touching = int(np.count_nonzero(g > -0.01))
    assert 20 < touching < 32
    assert it.resist_mnm == pytest.approx(2.0 * 0.25 * touching, rel=1e-9)
    withdrawn = _at(c, 7.5)           # 0.5 mm back: the taper clears every wall by 15 um
    assert withdrawn.resist_mnm == pytest.approx(0.0, abs=1e-12)


def test_screw_in_pulls_forward_and_pushes_back_turning_back():
    p = CanalParams(screw_n_per_mnm=0.01, rub_mnm_per_mm=1.0)
    c = Canal(p)
    it = _at(c, 8.0)
    g = _overlap(c, 8.0)
    touching = int(np.count_nonzero(g > -p.rub_clearance_mm))
    edges = 8.0 * float(np.maximum(g, 0.0).sum()) * 0.25 + 1.0 * 0.25 * touching
    assert it.resist_mnm == pytest.approx(edges, rel=1e-9)   # no debris yet
    assert c.screw_in_n(0.01) == pytest.approx(0.01 * edges, rel=1e-9)
    assert c.screw_in_n(-0.01) == pytest.approx(-0.3 * 0.01 * edges, rel=1e-9)
    assert c.screw_in_n(0.0) == 0.0


def test_jitter_does_not_flush_debris_but_a_withdrawal_does():
    c = Canal(CanalParams())
    _at(c, 10.0)
    c.debris_mm3 = 1.0
    rng = np.random.default_rng(0)
    for d in 10.0 + rng.uniform(-0.05, 0.05, 5000):   # 10 s of +-50 um jitter at 500 Hz
        c.interact((0.0, 0.0, float(d)), AXIS, FILE, DT)
    assert c.debris_mm3 == 1.0
    c = Canal(CanalParams())
    _at(c, 10.0)
    c.debris_mm3 = 1.0
    for d in np.linspace(10.0, 9.0, 101)[1:]:          # withdraw 1 mm
        c.interact((0.0, 0.0, float(d)), AXIS, FILE, DT)
    # only the withdrawal beyond the 0.1 mm dead band counts: exp(-(1 - 0.1) / 0.5)
    assert c.debris_mm3 == pytest.approx(math.exp(-0.9 / 0.5), rel=1e-6)


def test_the_red_area_is_the_photographed_stained_canal():
    p = CanalParams(working_length_mm=10.0)
    c = Canal(p)
    s = (np.arange(40) + 0.5) * 0.25                    # slice centres to the working length
    r0 = (0.15 + 0.02 * (10.0 - s)) / 2.0
    width = 2.0 * (r0 + 0.02) * 0.25                   # projected width x slice height
    np.testing.assert_allclose(c.red_area_mm2()[:40], width)
    assert c.red0 == pytest.approx(width.sum())
    assert c.completeness() == 0.0
    # cut the upper 6 mm deeper than the stain, and the next 2 mm half the stain deep
    c.R[c.s < 6.0] += 0.03
    c.R[(c.s > 6.0) & (c.s < 8.0)] += 0.01
    left = width[s > 6.0].sum() - 0.5 * width[(s > 6.0) & (s < 8.0)].sum()
    assert c.completeness() == pytest.approx(1.0 - left / width.sum(), rel=1e-9)


def test_shaping_measures_the_volume_to_the_target():
    c = Canal(CanalParams(working_length_mm=10.0))
    assert c.shaping() == 0.0
    c.R[:] = np.maximum(c.R, c.Rt)
    assert c.shaping() == pytest.approx(1.0)
    pre = Canal(CanalParams(initial_apical_mm=0.25, initial_taper=0.06))
    assert pre.pulp0 == 0.0 and pre.shaping() == 1.0


def test_materials_are_overrides_of_the_canal_constants():
    acrylic = CanalParams(**material_params("acrylic"))
    for name, value in MATERIALS["acrylic"].items():
        assert getattr(acrylic, name) == value
    assert CanalParams(**material_params("resin")) == CanalParams()
    tuned = material_params("acrylic", rub_mnm_per_mm=0.5)
    assert tuned["rub_mnm_per_mm"] == 0.5
    with pytest.raises(ConfigError, match="phantom.material.*granite"):
        material_params("granite")
    with pytest.raises(ConfigError, match="wall_n_mm_per_mm"):
        material_params("resin", wall_n_mm_per_mm=3.0)
    with pytest.raises(ConfigError, match="cutting_energy_mj_mm3"):
        CanalParams(cutting_energy_mj_mm3=0.0)
