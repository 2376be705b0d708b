"""The population's draws and the trial file's checks (no simulation)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dentibot.trials import population as pop
from dentibot.trials.runner import plan, procedures_of
from dentibot.trials.spec import TrialFileError, parse_trial

BASE = """name: t
seed: 11
n: 5
rounds_s: [1]
arms: [{name: a, tau_d_mnm: 40}]
"""


def test_every_default_distribution_fits_its_field_and_cites_a_source():
    for key, field in pop.TABLE.items():
        assert field.check(field.default) is None, key
        assert len(field.default.source) > 20, key


def test_procedure_i_is_the_same_subject_whatever_the_batch_split_or_arm():
    one = parse_trial(BASE + "batch_size: 1\n")
    five = parse_trial(BASE + "batch_size: 5\n")
    two_arms = parse_trial(BASE.replace("arms: [{name: a, tau_d_mnm: 40}]",
                                        "arms: [{name: b, tau_d_mnm: 30}, {name: a}]"))
    by_one = [p.subject for b in plan(one) for p in b.procedures]
    by_five = [p.subject for b in plan(five) for p in b.procedures]
    assert len(plan(one)) == 5 and len(plan(five)) == 1
    assert by_one == by_five
    # the other arm treats the same patients (paired design)
    assert [p.subject for p in procedures_of(two_arms, 0, range(5))] == by_one
    # and the procedures differ from one another
    assert len({s.working_length_mm for s in by_one}) == 5


def test_each_field_has_its_own_stream_from_seed_index_and_name():
    # independently: numpy's generator seeded as the module says
    import zlib
    table = parse_trial(BASE).table()
    s = pop.draw(table, 11, 3)
    want = pop.TABLE["anatomy.curve_radius_mm"].default
    rng = np.random.default_rng([11, 3, zlib.crc32(b"anatomy.curve_radius_mm")])
    assert s.curve_radius_mm == rng.uniform(want.low, want.high)
    assert s.sim_seed == int(np.random.SeedSequence([11, 3]).generate_state(1)[0])


def test_an_override_changes_its_field_only():
    base = parse_trial(BASE).table()
    over = parse_trial(BASE + "population:\n  anatomy:\n    working_length_mm: "
                       "{dist: fixed, value: 13.25}\n").table()
    for i in range(5):
        a, b = pop.draw(base, 11, i), pop.draw(over, 11, i)
        assert b.working_length_mm == 13.25
        # the curve start is a fraction of the working length; all else is unchanged
        assert b.curve_start_mm / 13.25 == pytest.approx(a.curve_start_mm / a.working_length_mm)
        same = {f.name for f in dataclasses.fields(pop.Subject)} - {
            "working_length_mm", "curve_start_mm"}
        assert all(getattr(a, k) == getattr(b, k) for k in same)


def test_schneider_classes():
    assert [pop.schneider_class(a) for a in (0, 5, 7, 10, 20, 22, 25, 70)] == [
        "straight", "straight", "moderate", "moderate", "moderate", "severe", "severe",
        "severe"]


def test_choice_weights_are_respected():
    d = pop.Distribution(dist="choice", values=["moderate", "severe"], weights=[0, 1])
    rng = np.random.default_rng(0)
    assert {d.sample(rng) for _ in range(50)} == {"severe"}


@pytest.mark.parametrize("extra, field, words", [
    ("arms: [{name: a, tau_d_mnm: 60}]\n", "arms.0.tau_d_mnm", ["60", "55.8"]),
    ("population:\n  anatomy:\n    curve_radius_mm: {dist: uniform, low: 0.5, high: 8}\n",
     "population.anatomy.curve_radius_mm", ["0.5", "1.5 .. 100"]),
    ("population:\n  anatomy:\n    working_lenght_mm: {dist: fixed, value: 14}\n",
     "population.anatomy.working_lenght_mm", ["unknown field", "working_length_mm"]),
    ("population:\n  anatomy:\n    material: {dist: choice, values: [dentin]}\n",
     "population.anatomy.material", ["dentin", "resin, acrylic"]),
    ("population:\n  file:\n    size: {dist: uniform, low: 20, high: 30}\n",
     "population.file.size", ["integer"]),
    ("population:\n  anatomy:\n    tilt_deg: {dist: truncnormal, mean: 0, sd: 2}\n",
     "population.anatomy.tilt_deg", ["low", "high"]),
    ("arms: [{name: a}, {name: a}]\n", "arms.1.name", ["unique"]),
    ("arms: [{name: a, fz_max_n: 3}]\n", "arms.0.fz_max_n", ["3", "<= 2"]),
])
def test_bad_input_names_the_field_the_value_and_the_limit(extra, field, words):
    text = BASE.replace("arms: [{name: a, tau_d_mnm: 40}]\n", "")
    if not extra.startswith("arms"):
        text += "arms: [{name: a}]\n"
    with pytest.raises(TrialFileError) as exc:
        parse_trial(text + extra, "spec.yaml")
    message = str(exc.value)
    assert f": {field}: " in message, message
    for w in words:
        assert w in message, message


def test_the_spec_hash_follows_what_the_rows_depend_on():
    a = parse_trial(BASE)
    assert a.spec_hash() == parse_trial(BASE + "description: other words\n").spec_hash()
    assert a.spec_hash() != parse_trial(BASE.replace("seed: 11", "seed: 12")).spec_hash()
    assert a.spec_hash() != parse_trial(BASE.replace("rounds_s: [1]", "rounds_s: [2]")
                                        ).spec_hash()
