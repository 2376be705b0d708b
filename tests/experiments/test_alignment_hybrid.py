"""Experiment 1 with the patient tracker and hybrid control: the tooth's tracked motion fed
forward, the file follows the platform's square without the admittance law's chase-speed
limit (eq 4.35)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
import structlog

from dentibot.cli import main
from dentibot.experiments import alignment as al

pytestmark = pytest.mark.timeout(120)

#: The bench's fastest square (7.46 mm/s measured), well above config C's chase speed.
FAST_MM_S = 7.4


@pytest.fixture(autouse=True)
def _quiet():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))


@pytest.mark.slow
def test_hybrid_control_holds_the_tip_on_the_fastest_square():
    """Config C (fz <= 0.5 N): by force alone the file can chase a receding canal at
    k fz_max / b3 = 3.125 mm/s, so at 7.4 mm/s the admittance law predicts an 8.7 mm ripple
    along the insertion axis. With the tooth's motion fed forward the targets hold: the tip
    within 0.5 mm of its seated position across the canal and along it, no detachment."""
    assert al.expected_ripple_mm("C", FAST_MM_S) > 8.0          # what force alone gives
    spec = al.AlignmentSpec(config="C", speeds_mm_s=(FAST_MM_S,), insertion_s=8.0,
                            pause_s=1.0, tail_s=1.0, keep_series=False, tracking="hybrid")
    run = al.run_alignment(spec)
    assert run.status == "ok", run.reason
    assert run.seated_depth_mm == pytest.approx(16.5, abs=0.1)   # seated at the bottom
    (s,) = run.speeds
    assert s.max_lateral_mm <= al.HYBRID_TARGETS["lateral_mm"]
    assert s.max_rel_mm["z"] <= al.HYBRID_TARGETS["z_ripple_mm"]
    assert s.max_out_mm <= al.HYBRID_TARGETS["z_ripple_mm"]
    assert not s.detachments and not run.detachments
    assert run.to_dict()["tracking"] == "hybrid"
    checks = al.hybrid_checks({"C": [run]})
    assert checks and all(c.passed for c in checks)


def test_the_lateral_distance_is_the_part_across_the_axis():
    """(3, 4, 12) mm against the axis -z: 12 mm along it, 5 mm across."""
    lat = al.lateral_distance(np.array([[3.0, 4.0, 12.0], [0.0, 0.0, -2.0]]), (0.0, 0.0, -1.0))
    assert lat == pytest.approx([5.0, 0.0])


def test_the_hybrid_protocol_turns_the_tracker_on_and_force_stays_the_thesis():
    force = al.alignment_protocol(al.AlignmentSpec(config="B"))
    hybrid = al.alignment_protocol(al.AlignmentSpec(config="B", tracking="hybrid"))
    assert not force.patient.tracker and force.patient.tracking == "force"
    assert hybrid.patient.tracker and hybrid.patient.tracking == "hybrid"
    assert hybrid.patient.motion == force.patient.motion == "square"
    with pytest.raises(ValueError, match="tracking"):
        al.AlignmentSpec(tracking="position")


def test_the_cli_refuses_an_unknown_tracking(capsys):
    with pytest.raises(SystemExit) as e:
        main(["experiment", "alignment", "--tracking", "position"])
    assert e.value.code == 2
    assert "tracking" in capsys.readouterr().err


def _synthetic_run(spec: al.AlignmentSpec) -> al.AlignmentRun:
    """A run whose tip follows the root exactly but for a 0.3 mm lateral offset in the
    first square: what the measures must report without any simulation."""
    t = np.arange(0.0, spec.duration_s, 0.01)
    sq = spec.square()
    root = np.array([sq.offset_mm(x) for x in t])
    tip = root + (0.0, 0.0, 20.0)
    starts = al.square_starts(sq)
    tip[(t > starts[0] + 1.0) & (t < starts[0] + 2.0), 1] += 0.3
    return al.analyse(spec, t, tip, root, axis_in=(0.0, 0.0, -1.0))


def test_the_cli_reports_hybrid_tracking_in_todays_json_shape(capsys, monkeypatch):
    """The command's hybrid path on a synthetic run (no simulation): today's keys, plus the
    tracking and the lateral distance; the targets pass for a 0.3 mm lateral offset."""
    monkeypatch.setattr(al, "run_alignment", _synthetic_run)
    code = main(["experiment", "alignment", "--tracking", "hybrid", "--config", "A",
                 "--speeds", "3,7.4", "--workers", "1", "--no-figures", "--json", "--quiet"])
    d = json.loads(capsys.readouterr().out)
    assert d["tracking"] == "hybrid" and d["configs"]["A"]["tracking"] == "hybrid"
    a = d["configs"]["A"]
    assert set(a["max_rel_mm"]) == {"x", "y", "z"}
    assert a["max_rel_mm"]["y"] == pytest.approx(0.3)
    assert [s["speed_mm_s"] for s in a["speeds"]] == [3.0, 7.4]
    first, second = a["speeds"]
    assert first["max_lateral_mm"] == pytest.approx(0.3) and second["max_lateral_mm"] == 0.0
    assert first["max_out_mm"] == pytest.approx(0.0) and first["detachments"] == []
    assert code == 0 and all(c["passed"] for c in d["checks"])
