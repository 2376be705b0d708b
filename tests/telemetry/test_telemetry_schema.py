"""The tick row schema: one table of fields, the JSON Schema and the row check derived from it."""

from __future__ import annotations

import json
import math

import pytest

from dentibot.errors import ConfigError
from dentibot.telemetry import (
    TICK_FIELDS,
    TOPICS,
    default_row,
    json_schema,
    validate_row,
)
from dentibot.telemetry.schema import none_fields

# The fields the telemetry spec asks for, in its order, with their array sizes.
SPEC_FIELDS = {
    "t": None, "tick": None, "step": None, "state": None, "q_deg": 6, "qdot_cmd_deg_s": 6,
    "tool_pose": 6, "phantom_pose": 6, "tooth_pose": 6, "wrench_s": 6, "wrench_h": 6, "f_d": 6,
    "fz_star_n": None, "fz_n": None, "file_torque_mnm": None, "motor_current_a": None,
    "motor_rpm": None, "depth_mm": None, "true_depth_mm": None, "working_length_mm": None,
    "completeness": None,
    "patient_moved": None, "reversals": None, "fractured": None, "events": 0,
    "lateness_us": None, "compute_us": None, "overrun": None,
}
NULLABLE = {"phantom_pose", "tooth_pose", "depth_mm", "working_length_mm", "completeness", "true_depth_mm"}
# Not in the spec's list: the simulator's true depth, which the runtime adds (optional).
OPTIONAL = {"true_depth_mm"}


def test_fields_are_the_specified_ones_with_units_and_descriptions():
    assert [f.name for f in TICK_FIELDS] == list(SPEC_FIELDS)
    for f in TICK_FIELDS:
        assert f.length == SPEC_FIELDS[f.name], f.name
        assert f.nullable == (f.name in NULLABLE), f.name
        assert f.optional == (f.name in OPTIONAL), f.name
        assert f.description
    units = {f.name: f.unit for f in TICK_FIELDS}
    assert units["t"] == "s" and units["file_torque_mnm"] == "mNm"
    assert units["lateness_us"] == "us" and units["q_deg"] == "deg"


def test_json_schema_is_derived_from_the_field_table():
    schema = json_schema("/tick")
    json.dumps(schema)                                    # serialisable as is
    assert schema["type"] == "object" and schema["additionalProperties"] is False
    assert list(schema["properties"]) == list(SPEC_FIELDS)
    # a nullable field is left out of a message when unknown: not required, one type only
    # (Foxglove's JSON-schema parser takes a single "type" per property)
    assert schema["required"] == [f for f in SPEC_FIELDS if f not in OPTIONAL | NULLABLE]
    q = schema["properties"]["q_deg"]
    assert q["type"] == "array" and q["items"] == {"type": "number"}
    assert q["minItems"] == q["maxItems"] == 6
    assert schema["properties"]["phantom_pose"]["type"] == "array"
    assert schema["properties"]["depth_mm"]["type"] == "number"
    assert "absent when unknown" in schema["properties"]["depth_mm"]["description"]
    assert schema["properties"]["tick"]["type"] == "integer"
    assert schema["properties"]["overrun"]["type"] == "boolean"
    events = schema["properties"]["events"]
    assert events["type"] == "array" and "minItems" not in events
    assert "[mNm]" in schema["properties"]["file_torque_mnm"]["description"]


def test_every_topic_has_a_schema():
    assert set(TOPICS) == {"/run", "/tick", "/events", "/run/end"}
    end = json_schema("/run/end")
    assert set(end["required"]) == {"status", "reason", "duration_s"}
    assert set(json_schema("/events")["required"]) == {"t", "tick", "kind", "detail"}
    assert json_schema("/run")["additionalProperties"] is True
    with pytest.raises(ConfigError, match="/nope"):
        json_schema("/nope")


def test_default_row_is_valid_and_round_trips_through_json():
    row = default_row(t=0.5, tick=250, step="glide_path")
    assert validate_row(row) == []
    assert json.loads(json.dumps(row)) == row
    with pytest.raises(ConfigError, match="speed"):
        default_row(speed=3)


@pytest.mark.parametrize(("change", "problem"), [
    ({"q_deg": [0.0] * 5}, "q_deg"),
    ({"tick": 1.5}, "tick"),
    ({"tick": True}, "tick"),                 # bool is not an integer in JSON
    ({"fz_n": math.nan}, "fz_n"),
    ({"wrench_h": [0.0, 0.0, math.inf, 0.0, 0.0, 0.0]}, "wrench_h"),
    ({"step": None}, "step"),
    ({"fractured": 0}, "fractured"),
    ({"events": "TargetReached"}, "events"),
    ({"extra": 1}, "extra: unknown"),
])
def test_validate_row_names_the_field(change, problem):
    row = default_row()
    row.update(change)
    problems = validate_row(row)
    assert len(problems) == 1 and problems[0].startswith(problem), problems


def test_validate_row_reports_a_missing_field():
    row = default_row()
    del row["lateness_us"]
    assert validate_row(row) == ["lateness_us: missing"]


def test_a_nullable_field_may_be_absent_a_required_one_may_not():
    """As the file stores a row: the unknown values left out."""
    row = default_row()
    for name in NULLABLE:
        row.pop(name, None)
    assert validate_row(row) == []
    del row["fz_n"]
    assert validate_row(row) == ["fz_n: missing"]


def test_run_schema_records_the_wall_clock_start_and_lists_the_device_roles():
    run = json_schema("/run")["properties"]
    assert run["start_wall_ns"]["type"] == "integer"
    assert run["start_time"]["type"] == "string"
    assert run["seed"]["type"] == "integer"                # nullable: absent when unknown
    devices = run["devices"]
    assert devices["type"] == "object"
    assert set(devices["properties"]) == {"arm", "ft", "handpiece", "aux"}


def test_none_fields_is_every_field_of_the_topic():
    assert none_fields("/tick") == dict.fromkeys(SPEC_FIELDS)
    assert none_fields("/run/end") == {"status": None, "reason": None, "duration_s": None}


def test_tuples_and_nulls_where_allowed_are_valid():
    row = default_row(q_deg=(1, 2, 3, 4, 5, 6), phantom_pose=None, depth_mm=3.5)
    assert validate_row(row) == []
    assert "true_depth_mm" not in row                       # optional: may be absent...
    assert validate_row({**row, "true_depth_mm": 2.5}) == []    # ...or present
