"""What a DentiBot recording holds: the per-tick row, the other channels and their JSON Schemas.

One control tick = one row, a JSON-serialisable dict. The fields are defined once, as data
(:data:`TICK_FIELDS`: name, JSON type, unit, description); the MCAP JSON Schema
(:func:`json_schema`), the row check (:func:`validate_row`) and a row of defaults
(:func:`default_row`) are derived from that table, never written out by hand.

Channels of a recording (one MCAP channel per topic, so the file opens in Foxglove;
``/tick`` in CDR with a ROS 2 definition derived from :data:`TICK_FIELDS`
(:mod:`dentibot.telemetry.cdr`), the others ``json`` with ``jsonschema`` schemas):

==============  ==================================================================
``/run``        once at the start: protocol, seed, rate_hz, devices, dentibot_version,
                the wall-clock start (``start_wall_ns``, ``start_time``)
``/tick``       one row per control tick (:data:`TICK_FIELDS`)
``/events``     ``{t, tick, kind, detail}``: faults, state transitions, notes
``/run/end``    once at the end: ``{status, reason, duration_s}``
==============  ==================================================================

(The 3D topics: ``/tf`` is ROS 2's ``tf2_msgs/msg/TFMessage`` in CDR, ``/scene`` Foxglove's
own schema: :mod:`dentibot.telemetry.foxglove`.)

In CDR an unknown number is NaN and an unknown pose an empty sequence. In the JSON messages
(and the live view's) unknown values are left out, never written as ``null``. Foxglove's and Lichtblick's JSON-schema
parser accepts exactly one ``type`` per property (``"type": ["number", "null"]`` makes the whole
channel unreadable there), so a nullable field is declared with its own type only and is not
``required``; a message leaves the field out when its value is None (unknown, e.g. the phantom
pose on hardware), and :mod:`~dentibot.telemetry.reader` puts None back for every field of the
table that a message lacks (:func:`none_fields`). Rows as the runtime builds them keep their
None values: the recorder drops them while writing.

Units follow docs/architecture.md: mm, deg, N, sensor torques N*m, file torque mNm, time s;
lateness and compute time in microseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from dentibot.errors import ConfigError, DentibotError

__all__ = [
    "END_FIELDS",
    "END_STATUSES",
    "EVENT_FIELDS",
    "RUN_FIELDS",
    "TICK_FIELDS",
    "TOPICS",
    "Field",
    "TelemetryError",
    "default_row",
    "json_schema",
    "none_fields",
    "validate_row",
]


class TelemetryError(DentibotError):
    """A recording cannot be written or read (file missing, not an MCAP file, writer died...).

    ``path`` names the recording, ``detail`` says what went wrong and what to do.
    """

    def __init__(self, path: object, detail: str) -> None:
        self.path = str(path)
        self.detail = detail
        super().__init__(f"telemetry {self.path}: {detail}")

    def __reduce__(self):
        """Pickled with its fields (raised in the recorder process, re-raised here)."""
        return type(self), (self.path, self.detail)


@dataclass(frozen=True)
class Field:
    """One field of a telemetry message.

    ``json_type`` is the JSON Schema type of the value (or of each element when ``length`` is
    set: then the value is an array of exactly ``length`` items; 0: of any length; -1: an
    object whose values have that type, ``keys`` naming the usual ones). ``nullable`` allows
    None (a quantity unknown on this system, e.g. the phantom pose on hardware), which the
    file stores by leaving the field out; ``optional`` fields may be left out of a row
    altogether (simulator-only truths).
    """

    name: str
    json_type: str            # "number" | "integer" | "string" | "boolean"
    unit: str
    description: str
    length: int | None = None
    nullable: bool = False
    optional: bool = False
    keys: tuple[str, ...] = ()


# Element types of the JSON types used here: the Python values a reader gets back.
_PY_TYPES: dict[str, tuple[type, ...]] = {
    "number": (int, float),
    "integer": (int,),
    "string": (str,),
    "boolean": (bool,),
}

# Value of each type in a row of defaults.
_DEFAULTS: dict[str, Any] = {"number": 0.0, "integer": 0, "string": "", "boolean": False}


TICK_FIELDS: tuple[Field, ...] = (
    Field("t", "number", "s", "time since the start of the run"),
    Field("tick", "integer", "", "control tick index, 0-based"),
    Field("step", "string", "", "protocol step name"),
    Field("state", "string", "", "nested state name, e.g. treating.drilling.feeding"),
    Field("q_deg", "number", "deg", "measured joint angles q1..q6", 6),
    Field("qdot_cmd_deg_s", "number", "deg/s", "commanded joint rates", 6),
    Field("tool_pose", "number", "mm, deg",
          "tool (file tip) pose in the base frame: x, y, z mm; alpha, beta, gamma deg "
          "(mobile XYZ Euler angles)", 6),
    Field("phantom_pose", "number", "mm, deg",
          "root phantom pose, same convention as tool_pose (known on the simulator only)",
          6, nullable=True),
    Field("tooth_pose", "number", "mm, deg",
          "tooth (tracker clamp) pose in the base frame from the patient tracker, same "
          "convention as tool_pose; unknown without a tracker or while its strings fail",
          6, nullable=True),
    Field("wrench_s", "number", "N, N*m",
          "external wrench in the sensor frame (offset and gravity removed)", 6),
    Field("wrench_h", "number", "N, N*m",
          "external wrench in {H} at the active reference point", 6),
    Field("f_d", "number", "N, N*m", "desired wrench in {H}", 6),
    Field("fz_star_n", "number", "N", "feed force asked by the feedrate controller (fz*)"),
    Field("fz_n", "number", "N", "insertion force fed to the admittance law, sat(fz*) (eq 5.7)"),
    Field("file_torque_mnm", "number", "mNm", "file torque estimated from the motor current"),
    Field("motor_current_a", "number", "A", "handpiece motor current"),
    Field("motor_rpm", "number", "rpm", "handpiece speed at the file (signed)"),
    Field("depth_mm", "number", "mm", "file tip depth along the canal from the orifice",
          nullable=True),
    Field("true_depth_mm", "number", "mm",
          "true file tip depth along the canal (simulator only; never used by the control; "
          "depth_mm is the estimate)", nullable=True, optional=True),
    Field("working_length_mm", "number", "mm", "working length of the canal", nullable=True),
    Field("completeness", "number", "1", "share of the canal shaped, 0..1 (simulator only)",
          nullable=True),
    Field("patient_moved", "boolean", "", "patient movement detected at this tick"),
    Field("reversals", "integer", "", "file rotation reversals since the start (cumulative)"),
    Field("fractured", "boolean", "", "the file is fractured"),
    Field("events", "string", "", "names of the events detected at this tick", 0),
    Field("lateness_us", "number", "us", "tick start after its deadline"),
    Field("compute_us", "number", "us", "time spent computing the tick"),
    Field("overrun", "boolean", "", "the tick missed its deadline"),
)

EVENT_FIELDS: tuple[Field, ...] = (
    Field("t", "number", "s", "time since the start of the run"),
    Field("tick", "integer", "", "control tick at (or last before) the event"),
    Field("kind", "string", "", "event kind: fault, transition, note, ..."),
    Field("detail", "string", "", "free text: what happened, which value, which limit"),
)

RUN_FIELDS: tuple[Field, ...] = (
    Field("protocol", "string", "", "treatment protocol name"),
    Field("seed", "integer", "", "random seed of the simulated world", nullable=True),
    Field("rate_hz", "number", "Hz", "control rate"),
    Field("devices", "string", "", "device kind per role (arm, ft, handpiece, aux)", -1,
          keys=("arm", "ft", "handpiece", "aux")),
    Field("dentibot_version", "string", "", "version of the software that recorded"),
    Field("start_wall_ns", "integer", "ns",
          "wall-clock time of t = 0, since the Unix epoch (UTC): each message's log time is "
          "this plus its t"),
    Field("start_time", "string", "",
          "the same instant as start_wall_ns, ISO 8601 UTC (exact where a viewer rounds "
          "start_wall_ns to a double)"),
)

END_STATUSES: tuple[str, ...] = ("ok", "fault", "fracture", "aborted")

END_FIELDS: tuple[Field, ...] = (
    Field("status", "string", "", "how the run ended: " + ", ".join(END_STATUSES)),
    Field("reason", "string", "", "why (fault message, operator abort...)"),
    Field("duration_s", "number", "s", "run duration"),
)

# topic -> (schema name, fields, open): an open schema (the run metadata) requires no field
# and allows more (the runtime may add what it knows: operator, tooth, config...).
TOPICS: dict[str, tuple[str, tuple[Field, ...], bool]] = {
    "/run": ("dentibot.Run", RUN_FIELDS, True),
    "/tick": ("dentibot.Tick", TICK_FIELDS, False),
    "/events": ("dentibot.Event", EVENT_FIELDS, False),
    "/run/end": ("dentibot.RunEnd", END_FIELDS, False),
}


def _field_schema(f: Field) -> dict[str, Any]:
    """JSON Schema of one field: always one ``type`` (see the module docstring: a nullable
    field is one that may be absent). An object field lists its usual ``keys`` as properties:
    the viewers' parser walks an object's ``properties`` and fails on an object without."""
    if f.length is None:
        schema: dict[str, Any] = {"type": f.json_type}
    elif f.length == -1:
        schema = {"type": "object",
                  "properties": {k: {"type": f.json_type} for k in f.keys},
                  "additionalProperties": {"type": f.json_type}}
    else:
        schema = {"type": "array", "items": {"type": f.json_type}}
        if f.length > 0:
            schema["minItems"] = schema["maxItems"] = f.length
    desc = f.description + (f" [{f.unit}]" if f.unit else "")
    if f.nullable:
        desc += " (absent when unknown)"
    schema["description"] = desc
    return schema


def _topic(topic: str) -> tuple[str, tuple[Field, ...], bool]:
    try:
        return TOPICS[topic]
    except KeyError:
        raise ConfigError("telemetry.topic", topic, f"one of {list(TOPICS)}") from None


def json_schema(topic: str) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of the messages on ``topic``, derived from its fields.

    Required: the fields that are neither nullable nor optional (an open schema, ``/run``,
    requires none)."""
    title, fields, extra = _topic(topic)
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "type": "object",
        "properties": {f.name: _field_schema(f) for f in fields},
        "required": [] if extra else [f.name for f in fields
                                      if not (f.optional or f.nullable)],
        "additionalProperties": extra,
    }


def none_fields(topic: str) -> dict[str, None]:
    """Every field of ``topic`` set to None: what a reader starts a message from, so that a
    field the file left out (its value was unknown) reads back as None."""
    return dict.fromkeys(f.name for f in _topic(topic)[1])


def _value_ok(value: Any, json_type: str) -> bool:
    if json_type != "boolean" and isinstance(value, bool):
        return False                    # bool is an int in Python, not in JSON
    if not isinstance(value, _PY_TYPES[json_type]):
        return False
    return not (isinstance(value, float) and not math.isfinite(value))


def validate_row(row: dict[str, Any], fields: tuple[Field, ...] = TICK_FIELDS) -> list[str]:
    """Problems of ``row`` against ``fields`` (empty list: the row is valid).

    Each problem names the field, the value found and what was expected. Non-finite floats
    are problems (JSON has no NaN). Lists and tuples are both accepted as arrays. A nullable
    field may be None (as the runtime builds a row) or absent (as the file stores it).
    """
    problems: list[str] = []
    for f in fields:
        if f.name not in row:
            if not (f.optional or f.nullable):
                problems.append(f"{f.name}: missing")
            continue
        value = row[f.name]
        if value is None:
            if not f.nullable:
                problems.append(f"{f.name}: null, expected {f.json_type}")
            continue
        if f.length is None:
            if not _value_ok(value, f.json_type):
                problems.append(f"{f.name} = {value!r}: expected a finite {f.json_type}")
        elif f.length == -1:
            if not isinstance(value, dict) or not all(
                    isinstance(k, str) and _value_ok(v, f.json_type) for k, v in value.items()):
                problems.append(f"{f.name} = {value!r}: expected an object of {f.json_type}")
        elif not isinstance(value, (list, tuple)) or (f.length and len(value) != f.length):
            size = f"{f.length} " if f.length else ""
            problems.append(f"{f.name} = {value!r}: expected an array of {size}{f.json_type}")
        elif not all(_value_ok(v, f.json_type) for v in value):
            problems.append(f"{f.name} = {value!r}: expected finite {f.json_type} items")
    known = {f.name for f in fields}
    problems.extend(f"{name}: unknown field" for name in row if name not in known)
    return problems


def default_row(**values: Any) -> dict[str, Any]:
    """A valid tick row: zeros, empty strings, false, null where nullable; ``values`` override.

    Handy for tests and for the runtime to start each tick's row from.
    """
    row: dict[str, Any] = {}
    for f in TICK_FIELDS:
        if f.optional:
            continue
        if f.nullable:
            row[f.name] = None
        elif f.length is None:
            row[f.name] = _DEFAULTS[f.json_type]
        else:
            row[f.name] = [_DEFAULTS[f.json_type]] * f.length
    unknown = set(values) - {f.name for f in TICK_FIELDS}
    if unknown:
        raise ConfigError("telemetry.row", sorted(unknown),
                          f"fields of TICK_FIELDS: {[f.name for f in TICK_FIELDS]}",
                          "unknown field(s)")
    row.update(values)
    return row
