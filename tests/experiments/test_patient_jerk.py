"""The patient jerks towards the robot along the canal while the file works at the working
length: the tracker keeps the measured depth true, the force-only mode reads the tooth's
travel short."""

from __future__ import annotations

import json

import pytest

from dentibot.app.simulated import jaw_hinge
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


def test_the_jaw_hinge_lies_along_the_canal_and_turns_it_across():
    """The hinge 60 mm beyond the orifice along the canal, its axis across the canal: a 5 deg
    turn tilts the canal by 5 deg and moves the working length's point (16 mm in) sideways by
    (60 - 16) sin 5 deg = 3.83 mm, and the orifice by 60 sin 5 deg = 5.23 mm."""
    import math

    import numpy as np
    from scipy.spatial.transform import Rotation

    from dentibot.experiments import patient_jerk as pj

    o, a = np.array([100.0, 0.0, 120.0]), np.array([0.0, 0.0, -1.0])
    centre, axis = jaw_hinge(o, a)
    np.testing.assert_allclose(centre, o + 60.0 * a, atol=1e-12)
    assert abs(np.dot(axis, a)) < 1e-12 and np.linalg.norm(axis) == pytest.approx(1.0)
    R = Rotation.from_rotvec(np.radians(5.0) * np.array(axis)).as_matrix()
    wl = o + 16.0 * a
    moved = centre + R @ (wl - centre)
    assert np.linalg.norm(moved - wl) == pytest.approx(2 * 44.0 * math.sin(math.radians(2.5)))
    assert abs(np.dot(moved - wl, a)) < 0.2                 # sideways, to first order
    assert pj.axis_angle_deg(a, R @ a) == pytest.approx(5.0)
    assert pj.axis_angle_deg((1.0, 0.0, 0.0), (0.0, 2.0, 0.0)) == pytest.approx(90.0)
    # a canal along base x takes base y for the hinge's axis
    _, axis_x = jaw_hinge(o, (1.0, 0.0, 0.0))
    assert abs(axis_x[0]) < 1e-12 and np.linalg.norm(axis_x) == pytest.approx(1.0)


def test_patient_jerk_refuses_a_turn_out_of_range(capsys):
    assert main(["experiment", "patient-jerk", "--deg", "45"]) == 2
    assert "deg" in capsys.readouterr().err
