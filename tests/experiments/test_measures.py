"""The experiments' measures on synthetic data whose answers are known, and the protocols
they run checked against the shipped protocol files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from dentibot.experiments import alignment as al
from dentibot.experiments import preclinical as pc
from dentibot.experiments.common import distribution
from dentibot.protocol.loader import load_protocol
from dentibot.sim.patient import StewartSquare

PROTOCOLS = Path(__file__).parents[2] / "protocols"


# ---------------------------------------------------------------------------- experiment 1
def test_expected_ripple_follows_from_table_6_4_and_eq_4_35():
    # C: fz <= 0.5 N, k = 500, b3 = 80 -> the file follows a receding canal at 3.125 mm/s;
    # over a 15 mm side at 6 mm/s (2.5 s) it covers 7.8125 mm: 7.1875 mm behind
    assert al.chase_speed_mm_s("C") == pytest.approx(3.125)
    assert al.expected_ripple_mm("C", 6.0) == pytest.approx(15.0 - 3.125 * 2.5)
    assert al.expected_ripple_mm("C", 4.0) == pytest.approx(15.0 - 3.125 * 3.75)
    assert al.expected_ripple_mm("C", 3.0) == 0.0          # slower than it can follow
    # A and B: fz = 1 N -> 6.25 mm/s, faster than any platform speed of the thesis
    assert al.chase_speed_mm_s("A") == al.chase_speed_mm_s("B") == pytest.approx(6.25)
    assert all(al.expected_ripple_mm(c, v) == 0.0 for c in "AB" for v in al.SPEEDS_MM_S)


def test_relative_distance_removes_the_offset_at_the_reference_sample():
    t = np.linspace(0.0, 1.0, 11)
    root = np.stack([t, 0 * t, 2 * t], axis=1)
    tip = root + np.array([0.0, 0.0, 55.0])          # the thesis's vertical offset
    tip[7] += (0.3, -0.2, 1.0)
    rel = al.relative_distance(tip, root, i0=3)
    expected = np.zeros((11, 3))
    expected[7] = (0.3, -0.2, 1.0)
    np.testing.assert_allclose(rel, expected, atol=1e-12)


def test_detachments_with_hysteresis_peak_and_recovery():
    t = np.arange(0.0, 20.0, 0.01)
    # out: 0, ramp 0 -> 4 mm over 2..4 s, back to 0 over 4..6 s; a second bump of 0.8 mm
    # (below the 1 mm start) at 10 s; a third that never comes back, from 15 s
    out = np.interp(t, [0, 2, 4, 6, 9.9, 10, 10.1, 15, 17, 20], [0, 0, 4, 0, 0, 0.8, 0, 0, 3, 3])
    ev = al.detachments(t, out, start_mm=1.0, end_mm=0.5)
    assert len(ev) == 2
    a, b = ev
    assert a.t_start == pytest.approx(2.5, abs=0.011)        # crosses 1 mm at 2.5 s
    assert a.t_peak == pytest.approx(4.0, abs=0.011) and a.peak_mm == pytest.approx(4.0, abs=0.02)
    assert a.t_end == pytest.approx(5.75, abs=0.011)         # back under 0.5 mm at 5.75 s
    assert a.recovery_s == pytest.approx(1.75, abs=0.02)
    assert b.t_end is None and b.recovery_s is None and b.peak_mm == pytest.approx(3.0)


def test_analyse_splits_the_run_into_speed_windows_and_finds_a_known_lag():
    spec = al.AlignmentSpec(config="C", insertion_s=5.0, tail_s=5.0, keep_series=False)
    sq = spec.square()
    t = np.arange(0.0, spec.duration_s, 0.002)
    root = np.array([sq.offset_mm(x) for x in t])
    tip = root + (1.0, 2.0, 55.0)                           # perfect tracking, offset removed
    # a 2 mm excursion out of the canal (tip up along +z) during the 5 mm/s window only
    starts = al.square_starts(sq)
    bump = np.interp(t, [starts[2] + 9, starts[2] + 10, starts[2] + 12], [0, 2, 0])
    tip[:, 2] += bump
    tip[:, 0] += 0.25 * np.sin(t)                            # lateral wobble, 0.25 mm
    run = al.analyse(spec, t, tip, root, axis_in=(0.0, 0.0, -1.0))
    assert [s.speed_mm_s for s in run.speeds] == [3.0, 4.0, 5.0, 6.0]
    assert run.speeds[0].t0 == pytest.approx(5.0)
    assert [len(s.detachments) for s in run.speeds] == [0, 0, 1, 0]
    d = run.speeds[2].detachments[0]
    assert d.peak_mm == pytest.approx(2.0, abs=0.01)
    assert d.t_peak == pytest.approx(starts[2] + 10, abs=0.003)
    assert run.max_rel_mm["z"] == pytest.approx(2.0, abs=0.01)
    # |x| reaches the wobble's amplitude relative to its value at the square's start
    assert run.max_rel_mm["x"] == pytest.approx(0.25 * (1 + abs(math.sin(5.0))), abs=0.01)
    assert run.max_rel_mm["y"] == pytest.approx(0.0, abs=1e-9)
    assert run.speeds[2].expected_ripple_mm == pytest.approx(al.expected_ripple_mm("C", 5.0))


def test_square_starts_and_the_platform_variation():
    sq = StewartSquare(start_s=10.0)
    assert al.square_starts(sq) == pytest.approx([10.0, 40.0, 65.0, 87.0])   # 20+10, 15+10 ...
    turned = al.PlatformSquare(sq, yaw_deg=90.0)
    x, y, z = sq.offset_mm(12.0)                  # 2 s into the x side at 3 mm/s: x = 6
    assert (x, y, z) == pytest.approx((6.0, 0.0, 0.0))
    assert turned.offset_mm(12.0) == pytest.approx((0.0, 6.0, 0.0), abs=1e-12)
    bulged = al.PlatformSquare(sq, x_distortion_mm=3.0)
    # halfway up the first vertical side (z = 7.5 mm) the bulge is the full 3 mm
    t_mid = 10.0 + 5.0 + 2.5
    assert sq.offset_mm(t_mid) == pytest.approx((15.0, 0.0, 7.5))
    assert bulged.offset_mm(t_mid) == pytest.approx((18.0, 0.0, 7.5))
    a, b = al.variation(3), al.variation(3)
    assert a == b and a != al.variation(4)
    assert -20 <= a.yaw_deg <= 20 and 0 <= a.x_distortion_mm <= 3


def test_alignment_protocol_is_the_shipped_one_with_the_runs_duration():
    for cfg in al.CONFIGS:
        shipped = load_protocol(PROTOCOLS / f"experiment1-config-{cfg}.yaml")
        spec = al.AlignmentSpec(config=cfg, seed=shipped.seed)
        built = al.alignment_protocol(spec)
        assert built.phantom == shipped.phantom and built.patient == shipped.patient
        assert built.file == shipped.file and built.seed == shipped.seed
        step = built.steps[0].align
        assert step.config == cfg == shipped.steps[0].align.config
        assert step.duration_s == pytest.approx(10.0 + 87.0 + 10.0)


# ---------------------------------------------------------------------------- experiment 2
def test_preclinical_protocol_is_the_shipped_one_with_the_phantoms_canal():
    shipped = load_protocol(PROTOCOLS / "preclinical-phantom-D.yaml")
    d = next(p for p in pc.phantoms(1) if p.name == "D")
    built = pc.preclinical_protocol(pc.PreclinicalSpec(d))
    assert built.steps == shipped.steps                      # same calibration, align, rounds
    assert built.file == shipped.file
    assert built.phantom.working_length_mm == pytest.approx(d.working_length_mm)
    assert built.phantom.material == shipped.phantom.material
    assert shipped.phantom.material.name == pc.MATERIAL == "acrylic"


def test_phantoms_are_seeded_and_grouped_as_in_the_thesis():
    a, b = pc.phantoms(1), pc.phantoms(1)
    assert a == b and a != pc.phantoms(2)
    assert [p.name for p in a] == list("ABCDEF")
    assert [p.kind for p in a] == ["straight", "tilted", "curved"] * 2
    assert [p.tau_d_mnm for p in a] == [40.0] * 3 + [50.0] * 3
    assert len({p.seed for p in a}) == 6
    for p in pc.phantoms(7):
        assert 14.5 <= p.working_length_mm <= 16.0
        if p.kind == "tilted":
            assert 6.0 <= abs(p.tilt_deg) <= 12.0
        if p.kind == "curved":
            assert p.curve_start_mm < p.working_length_mm and 10.0 <= p.curve_radius_mm <= 14.0
        else:
            assert p.curve_start_mm is None
    assert [p.name for p in pc.phantoms(1, ("B", "E"))] == ["B", "E"]
    assert pc.phantoms(1, ("E",))[0] == pc.phantoms(1)[4]


def test_stalled_seconds_counts_feeding_without_new_depth_before_working_length():
    t = np.arange(0.0, 100.0, 0.1)
    # advances 1 mm/s for 10 s, sits at 10 mm for 40 s (feeding), then advances to 16 mm
    depth = np.interp(t, [0, 10, 50, 56, 100], [0, 10, 10, 16, 16])
    feeding = np.ones_like(t, dtype=bool)
    # stalled from 10 s + 10 s window (gain < 0.1 mm over the last 10 s) until 50 s; the
    # window after 50 s sees the new depth at once. Before 56 s (working length) only.
    assert pc.stalled_seconds(t, depth, feeding, until_s=56.0) == pytest.approx(30.0, abs=0.3)
    feeding[t < 30] = False                                   # not feeding: not stalled
    assert pc.stalled_seconds(t, depth, feeding, until_s=56.0) == pytest.approx(20.0, abs=0.3)


def test_distribution_median_and_worst():
    d = distribution([3.0, None, 1.0, float("nan"), 2.0, 10.0])
    assert d == {"median": 2.5, "worst": 10.0, "best": 1.0, "n": 4}
    d = distribution([0.9, 0.8, 0.95], worst="min")
    assert d["median"] == 0.9 and d["worst"] == 0.8
    assert distribution([])["median"] is None


def test_a_run_that_ends_before_the_square_is_reported_not_crashed():
    spec = al.AlignmentSpec(config="C", insertion_s=5.0, keep_series=False)
    t = np.arange(0.0, 3.0, 0.002)                       # a fault at 3 s, before the square
    z = np.zeros((len(t), 3))
    run = al.analyse(spec, t, z, z, axis_in=(0.0, 0.0, -1.0), status="fault",
                     reason="depth_limit")
    assert run.status == "fault" and run.speeds == [] and math.isnan(run.max_rel_mm["x"])
    assert [c.passed for c in al.checks({"C": [run]})] == [False, False, False]
    assert al.population_summary([run]) == {"n": 1, "not_ok": 1}


def _run(strategy: str, name: str, completeness: float, fracture: bool) -> pc.PhantomRun:
    ph = next(p for p in pc.phantoms(1) if p.name == name)
    return pc.PhantomRun(
        spec=pc.PreclinicalSpec(ph, strategy=strategy, keep_trace=False), status="ok",
        reason="", red_before_mm2=1.0, red_after_mm2=1.0 - completeness,
        completeness=completeness, shaping=0.5, fracture=fracture,
        fracture_cause="torsion" if fracture else None, peak_torque_mnm=50.0,
        peak_torque_estimate_mnm=50.0, reversals=0, limit_reversals=0, passes=0,
        depth_max_mm=10.0, t_first_wl_s=None, stalled_s=0.0, fatigue_damage=0.0, wall_s=1.0)


def test_ablation_checks_compare_with_the_automated_algorithm_on_the_same_phantoms():
    by = {
        "automated": [_run("automated", "A", 0.90, False), _run("automated", "D", 0.99, False)],
        # fractures one file the automated algorithm did not; better where it survived
        "feedrate": [_run("feedrate", "A", 0.99, False), _run("feedrate", "D", 0.40, True)],
        # no fracture, mean 0.930 < 0.945 - 0.01: stalls
        "reversal": [_run("reversal", "A", 0.87, False), _run("reversal", "D", 0.99, False)],
        # no fracture, mean 0.940 within 0.01 of 0.945: shows nothing
        "none": [_run("none", "A", 0.89, False), _run("none", "D", 0.99, False)],
    }
    got = {c.claim.split()[0]: c for c in pc.ablation_checks(by)}
    assert list(got) == ["feedrate", "reversal", "none"]
    f = got["feedrate"]
    assert f.passed and "1 of 2 files fractured" in f.detail and "stalls" not in f.detail
    assert "99.0 % on the 1 phantoms" in f.detail and "(automated: 90.0 %)" in f.detail
    r = got["reversal"]
    assert r.passed and "stalls: mean completeness 93.0 %" in r.detail
    assert "(automated: 94.5 %)" in r.detail
    assert not got["none"].passed and "fractured" not in got["none"].detail
    assert pc.ablation_checks({"feedrate": by["feedrate"]}) == []   # nothing to compare with


def test_ablations_run_without_the_runtimes_torque_net():
    assert pc.default_torque_limit("automated") is None
    for s in ("feedrate", "reversal", "none"):
        assert pc.default_torque_limit(s) == 62.0
    d = next(p for p in pc.phantoms(1) if p.name == "D")
    built = pc.preclinical_protocol(pc.PreclinicalSpec(d, strategy="none",
                                                       torque_limit_mnm=62.0))
    assert built.limits.torque_limit_mnm == 62.0
    assert built.steps[-1].spec.strategy == "none"
