"""The patient jerks towards the robot along the canal while the file works at the working
length: the tracker keeps the measured depth true, the force-only mode reads the tooth's
travel short."""

from __future__ import annotations

import json

import pytest

from dentibot.cli import main
from dentibot.control.feedrate import FILE_STRENGTH_MNM


@pytest.mark.slow
def test_patient_jerk_json_gives_both_modes_side_by_side(capsys):
    code = main(["experiment", "patient-jerk", "--json", "--quiet", "--workers", "3"])
    d = json.loads(capsys.readouterr().out)
    force, tracked, hybrid = (d["modes"][m] for m in ("force", "tracked", "hybrid"))
    # base-frame depth misses the tooth's 3 mm travel along the canal; the tooth frame not
    assert force["depth_error_mm"] == pytest.approx(3.0, abs=0.2)
    assert abs(tracked["depth_error_mm"]) <= 0.2
    # the force-only file stays pressed past the working length; the tracked one withdraws
    assert force["past_wl_s"] > 2.0 > 1.0 > tracked["past_wl_s"]
    assert tracked["final_state"] == "treating.retracting"
    # hybrid control: the file moves with the tooth, the working length holds within 0.2 mm
    assert hybrid["overshoot_mm"] <= 0.2 and abs(hybrid["depth_error_mm"]) <= 0.2
    for m in (force, tracked, hybrid):
        assert m["fractures"] == 0 and m["peak_torque_mNm"] < FILE_STRENGTH_MNM
        assert m["overshoot_mm"] >= 0.0
    checks = {c["claim"]: c["passed"] for c in d["checks"]}
    assert code == (0 if all(checks.values()) else 1)


def test_patient_jerk_refuses_a_jerk_out_of_range(capsys):
    assert main(["experiment", "patient-jerk", "--mm", "50"]) == 2
    assert "mm" in capsys.readouterr().err
