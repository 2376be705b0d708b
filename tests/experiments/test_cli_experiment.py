"""``dentibot experiment``: the machine-readable output, figures, populations, parallel
workers (same numbers as one process), bad input."""

from __future__ import annotations

import json

import pytest

from dentibot.cli import main

pytestmark = pytest.mark.timeout(120)

PNG = b"\x89PNG\r\n\x1a\n"


def _json(capsys) -> dict:
    return json.loads(capsys.readouterr().out)


def test_alignment_json_and_figures(capsys, tmp_path):
    code = main(["experiment", "alignment", "--config", "C", "--speeds", "6", "--workers", "1",
                 "--json", "--quiet", "--out", str(tmp_path)])
    out = _json(capsys)
    assert out["experiment"] == "alignment" and list(out["configs"]) == ["C"]
    c = out["configs"]["C"]
    assert set(c["max_rel_mm"]) == {"x", "y", "z"}
    assert all(isinstance(v, float) and v >= 0.0 for v in c["max_rel_mm"].values())
    # one speed window, one detachment at 6 mm/s (config C), with its recovery
    (speed,) = c["speeds"]
    assert speed["speed_mm_s"] == 6.0 and len(speed["detachments"]) == 1
    assert speed["detachments"][0]["recovery_s"] > 0.0
    assert [ch["passed"] for ch in out["checks"]] == [True, True, True] and code == 0
    names = sorted(p.rsplit("/", 1)[-1] for p in out["figures"])
    assert names == ["alignment-C-force.png", "alignment-C-position.png", "alignment-ripple.png"]
    for name in names:
        assert (tmp_path / name).read_bytes()[:8] == PNG


def test_alignment_population_reports_the_worst_case(capsys):
    main(["experiment", "alignment", "--config", "A", "--speeds", "6", "--seeds", "2",
          "--seed", "5", "--workers", "1", "--json", "--quiet", "--no-figures"])
    a = _json(capsys)["configs"]["A"]
    runs = a["runs"]
    assert [r["seed"] for r in runs] == [5, 6]
    # different random patients (platform yaw, distortion, canal)
    assert runs[0]["patient"] != runs[1]["patient"]
    for axis in "xyz":
        assert a["max_rel_mm"][axis] == max(r["max_rel_mm"][axis] for r in runs)
        dist = a["population"]["max_rel_mm"][axis]
        assert dist["worst"] == a["max_rel_mm"][axis] and dist["n"] == 2


def test_preclinical_json_in_parallel_equals_one_process(capsys):
    args = ["experiment", "preclinical", "--phantom", "AE", "--rounds", "8", "--json",
            "--quiet", "--no-figures"]
    main([*args, "--workers", "2"])
    par = _json(capsys)
    main([*args, "--workers", "1"])
    one = _json(capsys)
    assert par["experiment"] == "preclinical" and par["strategy"] == "automated"
    assert [p["name"] for p in par["phantoms"]] == ["A", "E"]
    for p in par["phantoms"]:
        assert p["tau_d"] == {"A": 40.0, "E": 50.0}[p["name"]]
        assert 0.0 <= p["completeness"] <= 1.0 and isinstance(p["fracture"], bool)

    def numbers(out):
        return [{k: v for k, v in p.items() if k != "wall_s"} for p in out["phantoms"]]

    assert numbers(par) == numbers(one)          # lock-step and seeded: identical results


def test_preclinical_table_and_bad_input(capsys):
    code = main(["experiment", "preclinical", "--phantom", "D", "--rounds", "5",
                 "--strategy", "none", "--workers", "1", "--quiet", "--no-figures"])
    text = capsys.readouterr().out
    assert code == 0                              # an ablation asserts no claim
    assert "strategy none" in text and "99.67" in text          # Table 6.5's D beside ours
    assert main(["experiment", "preclinical", "--phantom", "DX"]) == 2
    assert "phantom 'X'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["experiment", "preclinical", "--seeds", "0"])
    with pytest.raises(SystemExit):
        main(["experiment", "alignment", "--speeds", "fast"])


def test_preclinical_all_strategies_side_by_side(capsys):
    main(["experiment", "preclinical", "--phantom", "D", "--rounds", "4", "--strategy", "all",
          "--json", "--quiet", "--no-figures", "--workers", "2"])
    out = _json(capsys)
    assert out["strategy"] == "all"
    assert list(out["strategies"]) == ["automated", "feedrate", "reversal", "none"]
    for name, s in out["strategies"].items():
        assert s["strategy"] == name and s["material"] == "acrylic"
        assert [p["name"] for p in s["phantoms"]] == ["D"]
        # the runtime's net: 90 % of the 62 mNm strength for automated, the strength itself
        # for the ablations (the strategy alone protects the file)
        assert s["torque_limit_mnm"] == pytest.approx(55.8 if name == "automated" else 62.0)
    claims = [c["claim"] for c in out["checks"]]
    assert claims[0] == "no file fracture"        # one tau_d group only: no comparison
    assert [c.split()[0] for c in claims if "fractures or stalls" in c] == \
        ["feedrate", "reversal", "none"]
