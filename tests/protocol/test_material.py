"""The phantom material in protocol files: a name or a name with constants changed."""

from __future__ import annotations

import pytest

from dentibot.protocol.loader import ProtocolFileError, load_protocol
from dentibot.app.runner import world_config
from dentibot.protocol.schema import MATERIAL_NAMES, MaterialSpec
from dentibot.sim.canal import MATERIAL_FIELDS, MATERIALS, CanalParams

HEAD = "name: m\nsteps:\n  - calibrate_load: {}\n"


def _load(tmp_path, phantom: str):
    f = tmp_path / "p.yaml"
    f.write_text(HEAD + phantom)
    return load_protocol(f)


def test_default_is_resin(tmp_path):
    canal = world_config(_load(tmp_path, "")).canal
    assert canal.cutting_energy_mj_mm3 == CanalParams().cutting_energy_mj_mm3
    assert canal.rub_mnm_per_mm == 0.0


def test_a_named_material_sets_its_constants(tmp_path):
    canal = world_config(_load(tmp_path, "phantom: {material: acrylic}\n")).canal
    for name, value in MATERIALS["acrylic"].items():
        assert getattr(canal, name) == value


def test_constants_can_be_changed_on_top_of_a_material(tmp_path):
    p = _load(tmp_path, "phantom:\n  material: {name: acrylic, rub_mnm_per_mm: 0.7}\n")
    canal = world_config(p).canal
    assert canal.rub_mnm_per_mm == 0.7
    assert canal.cutting_energy_mj_mm3 == MATERIALS["acrylic"]["cutting_energy_mj_mm3"]


@pytest.mark.parametrize("phantom, words", [
    ("phantom: {material: granite}\n", ["phantom.material", "granite", "resin", "acrylic"]),
    ("phantom:\n  material: {name: acrylic, rub_mnm_per_mm: 50}\n",
     ["rub_mnm_per_mm", "50", "10"]),
    ("phantom:\n  material: {name: acrylic, hardness: 3}\n", ["hardness"]),
])
def test_bad_materials_are_named_with_their_limits(tmp_path, phantom, words):
    with pytest.raises(ProtocolFileError) as e:
        _load(tmp_path, phantom)
    text = str(e.value)
    for w in words:
        assert w in text, text


def test_the_schema_offers_exactly_the_simulators_materials_and_constants():
    assert set(MaterialSpec.model_fields) - {"name"} == set(MATERIAL_FIELDS)
    assert set(MATERIAL_NAMES) == set(MATERIALS)
    for name in MATERIALS:
        assert MaterialSpec.model_validate(name).name == name
