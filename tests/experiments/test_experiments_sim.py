"""Short variants of the experiments on the simulator, against numbers derived from the thesis
and the admittance law rather than from earlier runs."""

from __future__ import annotations

import dataclasses
import logging

import pytest
import structlog

from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.experiments import alignment as al
from dentibot.experiments import preclinical as pc
from dentibot.app.batch import run_all

pytestmark = pytest.mark.timeout(120)

#: One square at the thesis's fastest speed: 8 s to seat the file, 10 s of square, 6 s after.
FAST = {"speeds_mm_s": (6.0,), "insertion_s": 8.0, "tail_s": 6.0}


@pytest.fixture(autouse=True)
def _quiet():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))


@pytest.fixture(scope="module")
def fast_runs():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    return {c: al.run_alignment(al.AlignmentSpec(config=c, keep_series=c == "C", **FAST))
            for c in "AC"}


def test_the_file_follows_the_root_laterally_within_the_thesis_3_mm(fast_runs):
    for run in fast_runs.values():
        assert run.status == "ok", run.reason
        # seated at the canal bottom before the square: working length + 0.5 mm margin
        assert run.seated_depth_mm == pytest.approx(16.5, abs=0.1)
        assert run.max_rel_mm["x"] <= al.THESIS["max_rel_xy_mm"]
        assert run.max_rel_mm["y"] <= al.THESIS["max_rel_xy_mm"]
        # and it does move: the lateral lag at 6 mm/s is a fraction of a mm, not zero
        assert run.max_rel_mm["x"] > 0.05


def test_config_c_detaches_as_the_admittance_law_predicts_and_recovers(fast_runs):
    run = fast_runs["C"]
    (d,) = run.detachments
    vc = al.chase_speed_mm_s("C")                         # 3.125 mm/s
    expected = 15.0 * (1.0 - vc / 6.0)                     # 7.19 mm
    assert d.peak_mm == pytest.approx(expected, abs=0.5)
    # the peak comes when the root stops at the end of its 2.5 s descent (the last side of
    # the square), and the file then closes the gap at v_c
    t_descent_end = FAST["insertion_s"] + 10.0
    assert d.t_peak == pytest.approx(t_descent_end, abs=0.3)
    assert d.recovery_s == pytest.approx((expected - al.DETACH_END_MM) / vc, abs=0.5)
    assert run.speeds[0].max_out_mm == pytest.approx(run.max_out_mm)
    # the figures' series: decimated, the insertion seen as a drop of the relative z
    assert run.series is not None and len(run.series["t"]) > 100


def test_config_a_holds_the_file_seated_at_6_mm_s(fast_runs):
    run = fast_runs["A"]
    assert run.detachments == []
    assert run.max_out_mm < al.DETACH_START_MM
    assert run.peak_force_n < 5.0


def test_a_short_preparation_is_consistent_and_tau_d_50_feeds_faster():
    """Two copies of acrylic phantom A for 60 s, tau_d 40 and 50 (the same canal and seed):
    the higher desired torque lets the feedrate controller feed faster (fig 5.5: fz* = kp
    (tau_d - tau)), so the file gets deeper in the same time, with a higher peak torque, still
    under the 62 mNm strength."""
    a = pc.phantoms(1, ("A",))[0]
    specs = [pc.PreclinicalSpec(dataclasses.replace(a, tau_d_mnm=tau), rounds_s=(60.0,))
             for tau in (40.0, 50.0)]
    r40, r50 = run_all(pc.run_phantom, specs, workers=1)
    for r in (r40, r50):
        assert r.status == "ok" and not r.fracture
        assert 0.0 < r.completeness < 1.0
        # eq 6.1 from the run's own red volumes
        assert r.completeness == pytest.approx(1.0 - r.red_after_mm2 / r.red_before_mm2)
        assert r.peak_torque_mnm < FILE_STRENGTH_MNM
        assert r.trace is not None and r.trace["t"][-1] > 60.0
    assert r40.red_before_mm2 == pytest.approx(r50.red_before_mm2)
    assert r50.depth_max_mm > r40.depth_max_mm + 0.5
    assert r50.peak_torque_mnm > r40.peak_torque_mnm
    # the acrylic's flutes screw in (more than the PD pulls back, deep enough), so reversals
    # cap the torque: near tau_d + 8 mNm (the reversal torque), plus what the file adds while
    # the motor stops it (a few mNm), never at the strength
    for r, tau in ((r40, 40.0), (r50, 50.0)):
        assert r.peak_torque_mnm < tau + 8.0 + 3.0
