"""Wilson intervals, Miner's rule, the canals a file lasts, and the summary (no simulation)."""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa
import pytest

from dentibot.sim.nitifile import NiTiFile
from dentibot.trials import fatigue
from dentibot.trials.report import summarize, wilson
from dentibot.trials.runner import SCHEMA
from dentibot.trials.spec import parse_trial


@pytest.mark.parametrize("k, n, lo, hi", [
    # Newcombe 1998, Stat Med 17:857, Table I, method 3 (Wilson score, no continuity
    # correction)
    (81, 263, 0.2553, 0.3662),
    (15, 148, 0.0624, 0.1605),
    (0, 20, 0.0000, 0.1611),
    (1, 29, 0.0061, 0.1718),
])
def test_wilson_interval_matches_the_textbook(k, n, lo, hi):
    got = wilson(k, n)
    assert got[0] == pytest.approx(lo, abs=5e-5)
    assert got[1] == pytest.approx(hi, abs=5e-5)


def test_wilson_interval_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    for k, n in ((0, 4), (2, 4), (4, 4), (7, 31)):
        ci = stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert wilson(k, n) == pytest.approx((ci.low, ci.high), abs=1e-9)


def test_the_strain_life_law_is_the_simulators():
    for eps in (0.01, 0.03, 0.055, 0.08):
        assert fatigue.cycles_to_failure(eps) == pytest.approx(NiTiFile.cycles_to_failure(eps))
    # about 330 cycles at 5.5 % strain: 0.55 mm across bent to a 5 mm radius
    assert fatigue.cycles_to_failure(fatigue.bending_strain(0.55, 5.0)) == pytest.approx(
        (1 / 0.055) ** 2)


def test_miners_rule():
    # 100 cycles where 400 break the file and 150 where 300 do: 1/4 + 1/2
    eps400 = 1.0 / math.sqrt(400.0)
    eps300 = 1.0 / math.sqrt(300.0)
    assert fatigue.miner([100, 150], [eps400, eps300]) == pytest.approx(0.75)


def test_canals_until_failure():
    rng = np.random.default_rng(0)
    # 0.3 a canal: 0.9 after three, 1.2 after four
    assert set(fatigue.canals_until_failure([0.3, 0.3], [False, False], rng, 50, 20)) == {4}
    # a canal that breaks the file: the first
    assert set(fatigue.canals_until_failure([0.0], [True], rng, 50, 20)) == {1}
    # no damage: every file outlives the cap (censored)
    got = fatigue.canals_until_failure([0.0], [False], rng, 50, 20)
    assert set(got) == {21}
    assert fatigue.life_summary(got, 20)["censored"] == 1.0
    # half the canals break the file: geometric, P(first) = 1/2
    got = fatigue.canals_until_failure([0.0, 0.0], [True, False], rng, 4000, 50)
    assert np.mean(got == 1) == pytest.approx(0.5, abs=0.03)
    assert np.mean(got) == pytest.approx(2.0, abs=0.1)


def _row(arm_index, index, curvature, fracture, completeness, reached, t_wl, over):
    row = {f.name: None for f in SCHEMA}
    row.update({
        "arm": f"a{arm_index}", "arm_index": arm_index, "index": index, "curvature": curvature,
        "fracture": fracture, "fracture_cause": "torsion" if fracture else None,
        "completeness": completeness, "reached_wl": reached, "t_wl_s": t_wl,
        "over_instrumented": over, "overshoot_mm": 0.3 if over else 0.0,
        "peak_torque_mnm": 40.0 + index, "motor_stall_s": 0.0, "feed_stall_s": 0.0,
        "faults": 0, "status": "fracture" if fracture else "ok", "fatigue_damage": 0.1})
    return row


def test_the_summary_counts_per_arm_and_class():
    spec = parse_trial("name: s\nn: 4\narms: [{name: a0}, {name: a1, tau_d_mnm: 50}]\n")
    rows = [
        _row(0, 0, "moderate", False, 0.9, True, 30.0, False),
        _row(0, 1, "severe", True, 0.5, False, None, False),
        _row(0, 2, "severe", False, 0.8, True, 50.0, True),
        _row(0, 3, "moderate", False, 0.7, True, 40.0, False),
        *(_row(1, i, "moderate", False, 1.0, True, 20.0, False) for i in range(4)),
    ]
    s = summarize(pa.Table.from_pylist(rows, schema=SCHEMA), spec)
    a0, a1 = s["arms"]
    assert (a0["name"], a0["n"], a0["fractures"]) == ("a0", 4, 1)
    assert a0["fracture_rate"] == 0.25
    assert a0["fracture_rate_ci"] == pytest.approx(list(wilson(1, 4)))
    assert a0["completeness_median"] == pytest.approx(0.75)         # of 0.5 0.7 0.8 0.9
    assert a0["t_wl_s"]["median"] == 40.0 and a0["t_wl_s"]["n"] == 3
    assert a0["over_instrumentation_rate"] == 0.25
    assert a0["by_curvature"]["severe"]["n"] == 2
    assert a0["by_curvature"]["severe"]["fracture_rate"] == 0.5
    assert a0["by_curvature"]["moderate"]["fractures"] == 0
    assert a1["tau_d_mnm"] == 50.0 and a1["fracture_rate"] == 0.0
    assert a1["fracture_rate_ci"][0] == 0.0
    # files that never break in a canal and take 0.1 of damage each: the tenth ends them
    assert a1["file_life"]["median"] == 10.0
