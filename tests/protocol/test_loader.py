"""Protocol files: every shipped one validates; broken ones fail with file, line, field, value
and the allowed range or choices, before anything starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from dentibot.protocol.loader import ProtocolFileError, load_protocol, parse_protocol

PROTOCOLS = sorted((Path(__file__).parents[2] / "protocols").glob("*.yaml"))
GOOD = """\
name: t
steps:
  - drill: {tau_d_mnm: 40}
"""


@pytest.mark.parametrize("path", PROTOCOLS, ids=[p.stem for p in PROTOCOLS])
def test_shipped_protocols_validate(path):
    p = load_protocol(path)
    assert p.steps and p.name


def test_defaults_are_the_thesis_values():
    p = parse_protocol(GOOD)
    d = p.steps[0].drill
    assert (d.rpm, d.fz_min_n, d.fz_max_n, d.strategy) == (60.0, -0.5, 0.5, "automated")
    assert p.control.rate_hz == 500.0 and p.limits.patient_moved_n == 1.5
    assert p.file.torsional_strength_mnm == 62.0


@pytest.mark.parametrize("text, line, field, words", [
    # unknown key (typo)
    ("name: t\nsteps:\n  - drill:\n      tau_d: 40\n", 4, "steps.0.drill.tau_d", "unknown key"),
    # value out of range, with its limit (a unit mistake: tau_d in uNm, rpm at the motor)
    ("name: t\nsteps:\n  - drill:\n      tau_d_mnm: 500\n", 4, "steps.0.drill.tau_d_mnm",
     "500 is out of range: must be <= 200"),
    ("name: t\nsteps:\n  - drill:\n      rpm: 20000\n", 4, "steps.0.drill.rpm",
     "20000 is out of range: must be <= 200"),
    # wrong type
    ("name: t\nseed: many\nsteps:\n  - drill: {}\n", 2, "seed", "valid integer"),
    # bad choice
    ("name: t\nsteps:\n  - drill: {strategy: fast}\n", 3, "steps.0.drill.strategy",
     "'fast' is not one of"),
    # missing required field
    ("steps:\n  - drill: {}\n", None, "name", "required field is missing"),
    # a step with two actions
    ("name: t\nsteps:\n  - {drill: {}, align: {}}\n", 3, "steps.0", "exactly one of"),
])
def test_broken_protocols_are_refused_with_line_field_value_and_limit(text, line, field, words):
    with pytest.raises(ProtocolFileError) as e:
        parse_protocol(text, "broken.yaml")
    problems = e.value.problems
    hit = [p for p in problems if p[1] == field]
    assert hit, problems
    got_line, _, message = hit[0]
    assert words in message
    if line is not None:
        assert got_line == line
    assert f"broken.yaml:{line if line else '?'}" in str(e.value) or line is None


def test_every_problem_is_reported_at_once():
    text = "name: t\nfile: {size: 2, tapr: 0.06}\nsteps:\n  - drill: {rpm: -1}\n"
    with pytest.raises(ProtocolFileError) as e:
        parse_protocol(text)
    fields = {p[1] for p in e.value.problems}
    assert {"file.size", "file.tapr", "steps.0.drill.rpm"} <= fields


def test_malformed_yaml_names_the_line():
    with pytest.raises(ProtocolFileError) as e:
        parse_protocol("name: t\nsteps: [\n  - drill\n", "bad.yaml")
    assert e.value.problems[0][1] == "yaml" and e.value.problems[0][0] is not None


def test_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(ProtocolFileError) as e:
        load_protocol(tmp_path / "nope.yaml")
    assert "cannot read" in str(e.value)
