"""The 3D channels: schemas the open-source viewers parse, Foxglove's message definitions, and
transforms checked against poses worked out by hand."""

from __future__ import annotations

import json
import math

import foxglove.messages
import numpy as np
import orjson
import pytest
from foxglove_schema_rules import problems
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from telemetry_helpers import ramp_row

from dentibot.errors import ConfigError
from dentibot.telemetry import McapRecorder, json_schema, read_recording
from dentibot.telemetry.foxglove import (
    FOXGLOVE_TOPICS,
    FRAME_TRANSFORM_SCHEMA,
    FRAME_TRANSFORMS_SCHEMA,
    SCENE_UPDATE_SCHEMA,
    FoxgloveView,
    quat_from_euler_xyz_deg,
    quat_from_matrix,
)

S = math.sqrt(0.5)
START_NS = 1_700_000_000_000_000_000
META = {"protocol": "demo", "seed": 7, "rate_hz": 500,
        "devices": {"arm": "sim", "ft": "sim", "handpiece": "sim", "aux": "sim"}}


# -- the parser's rules ------------------------------------------------------------------------

@pytest.mark.parametrize(("field", "why"), [
    ({"type": ["number", "null"]}, "one string"),          # the old nullable declaration
    ({"type": "null"}, "unsupported type"),
    ({"description": "no type"}, "one string"),
    ({"type": "object", "additionalProperties": {"type": "string"}}, "no properties"),
    ({"type": "array"}, "without an items"),
    ({"type": "array", "items": {"type": "array", "items": {"type": "number"}}}, "item type"),
    ({"type": "string", "contentEncoding": "gzip"}, "contentEncoding"),
    ({"oneOf": [{"title": "A", "const": 0}, {"title": "B", "const": 1}]}, "oneOf"),
])
def test_the_checker_refuses_what_the_viewers_parser_throws_on(field, why):
    schema = {"type": "object", "properties": {"f": field}}
    found = problems(schema)
    assert len(found) == 1 and why in found[0], found
    assert problems({"type": "object", "properties": {
        "a": {"type": "boolean"}, "b": {"type": "string", "contentEncoding": "base64"},
        "c": {"type": "integer"}, "d": {"type": "array", "items": {"type": "number"}},
        "e": {"type": "object", "properties": {"x": {"type": "number"}}},
        "g": {"type": "array", "items": {"type": "object", "properties": {}}}}}) == []
    assert problems({"type": ["object"], "properties": {}})        # the root too


def test_every_schema_the_recorder_writes_parses_in_the_viewers(tmp_path):
    path = tmp_path / "run.mcap"
    with McapRecorder(path, META) as rec:
        for i in range(20):
            rec.record(ramp_row(i))
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    schemas = {c.topic: (c.message_encoding, summary.schemas[c.schema_id])
               for c in summary.channels.values()}
    assert set(schemas) == {"/run", "/tick", "/events", "/run/end", "/tf", "/scene"}
    for topic, (encoding, schema) in schemas.items():
        if schema.encoding == "jsonschema":
            assert encoding == "json"
            assert problems(json.loads(schema.data)) == [], topic
        else:                      # ROS 2: the definition parses in Foxglove's own codec
            assert (schema.encoding, encoding) == ("ros2msg", "cdr"), topic
            assert DecoderFactory().decoder_for(encoding, schema) is not None, topic


# -- Foxglove's message definitions (the SDK's own descriptors) --------------------------------

def _fields(data: bytes) -> list[tuple[int, int, bytes | int]]:
    """A protobuf message's (field number, wire type, value): varints and byte strings."""
    out, i = [], 0

    def varint() -> int:
        nonlocal i
        shift = value = 0
        while True:
            b = data[i]
            i += 1
            value |= (b & 0x7F) << shift
            shift += 7
            if not b & 0x80:
                return value

    while i < len(data):
        key = varint()
        number, wire = key >> 3, key & 7
        if wire == 0:
            out.append((number, wire, varint()))
        elif wire == 2:
            n = varint()
            out.append((number, wire, data[i:i + n]))
            i += n
        elif wire == 1:
            out.append((number, wire, data[i:i + 8]))
            i += 8
        else:
            out.append((number, wire, data[i:i + 4]))
            i += 4
    return out


# FieldDescriptorProto.Type -> JSON schema type; label 3 = repeated
_PROTO_TYPES = {1: "number", 2: "number", 8: "boolean", 9: "string", 10: "object",
                11: "object", 12: "bytes", 14: "enum",
                **dict.fromkeys((3, 4, 5, 6, 7, 13, 15, 16, 17, 18), "integer")}


def _descriptor_messages(message_cls) -> dict[str, dict[str, str]]:
    """'foxglove.X' -> {field: JSON type} from the FileDescriptorSet the SDK ships for
    ``message_cls``; repeated fields are 'array'."""
    schema = message_cls().get_schema()
    assert schema.encoding == "protobuf"
    messages: dict[str, dict[str, str]] = {}
    for _n, _w, file in (f for f in _fields(schema.data) if f[0] == 1):
        parts = _fields(file)
        package = next(v.decode() for n, _w, v in parts if n == 2)
        for _n2, _w2, msg in (p for p in parts if p[0] == 4):
            mparts = _fields(msg)
            name = next(v.decode() for n, _w, v in mparts if n == 1)
            fields = {}
            for _n3, _w3, fd in (p for p in mparts if p[0] == 2):
                fparts = {n: v for n, _w, v in _fields(fd)}
                kind = _PROTO_TYPES[fparts[5]]
                fields[fparts[1].decode()] = "array" if fparts.get(4) == 3 else kind
            messages[f"{package}.{name}"] = fields
    return messages


def _titled(schema: dict, found: dict | None = None) -> dict[str, list[dict]]:
    """Every sub-schema with a 'foxglove.*' title, by title."""
    found = {} if found is None else found
    title = schema.get("title", "")
    if title.startswith("foxglove."):
        found.setdefault(title, []).append(schema)
    for sub in schema.get("properties", {}).values():
        _titled(sub.get("items", sub), found)
    return found


def test_frame_transform_is_foxglove_s_definition():
    """The FrameTransform schema has exactly the fields of Foxglove's FrameTransform, with
    their types; FrameTransforms is a list of them; names are Foxglove's schema names."""
    defs = _descriptor_messages(foxglove.messages.FrameTransforms)
    ft = defs["foxglove.FrameTransform"]
    props = FRAME_TRANSFORM_SCHEMA["properties"]
    assert set(props) == set(ft) == {"timestamp", "parent_frame_id", "child_frame_id",
                                     "translation", "rotation"}
    for name, kind in ft.items():
        assert props[name]["type"] == kind, name
    assert set(props["timestamp"]["properties"]) == {"sec", "nsec"}
    assert set(props["translation"]["properties"]) == set(defs["foxglove.Vector3"])
    assert set(props["rotation"]["properties"]) == set(defs["foxglove.Quaternion"])
    assert defs["foxglove.FrameTransforms"] == {"transforms": "array"}
    assert FRAME_TRANSFORMS_SCHEMA["properties"]["transforms"]["items"] == FRAME_TRANSFORM_SCHEMA
    assert FRAME_TRANSFORMS_SCHEMA["title"] == \
        foxglove.messages.FrameTransforms().get_schema().name
    assert SCENE_UPDATE_SCHEMA["title"] == foxglove.messages.SceneUpdate().get_schema().name


def test_the_scene_schema_uses_foxglove_s_fields_and_types_only():
    defs = _descriptor_messages(foxglove.messages.SceneUpdate)
    titled = _titled(SCENE_UPDATE_SCHEMA)
    assert {"foxglove.SceneUpdate", "foxglove.SceneEntity", "foxglove.ArrowPrimitive",
            "foxglove.CubePrimitive", "foxglove.CylinderPrimitive", "foxglove.Pose",
            "foxglove.Vector3", "foxglove.Quaternion", "foxglove.Color"} <= set(titled)
    for title, schemas in titled.items():
        for schema in schemas:
            for name, sub in schema["properties"].items():
                assert name in defs[title], f"{title}.{name}"
                expected = defs[title][name]
                if sub.get("title") in ("time", "duration"):   # google.protobuf types
                    assert expected == "object"
                else:
                    assert sub["type"] == expected, f"{title}.{name}"


# -- transforms worked out by hand -------------------------------------------------------------

def _by_child(msg: dict) -> dict[str, dict]:
    return {tf["child_frame_id"]: tf for tf in msg["transforms"]}


def _approx(d: dict, expected: tuple[float, ...], keys: str = "xyzw") -> None:
    assert [d[k] for k in keys[:len(expected)]] == pytest.approx(expected, abs=1e-9)


def test_euler_angles_to_quaternions():
    # Ry(90): the half angle is 45 deg about y
    assert quat_from_euler_xyz_deg(0, 90, 0) == pytest.approx((0, S, 0, S))
    # Rx(90) Rz(90): (s,0,0,c)(0,0,s,c) with s = c = sqrt(1/2) is (1/2, -1/2, 1/2, 1/2)
    assert quat_from_euler_xyz_deg(90, 0, 90) == pytest.approx((0.5, -0.5, 0.5, 0.5))
    assert quat_from_euler_xyz_deg(0, 0, 0) == (0.0, 0.0, 0.0, 1.0)
    # a half turn about x: diag(1, -1, -1)
    assert quat_from_matrix([[1, 0, 0], [0, -1, 0], [0, 0, -1]]) == pytest.approx((1, 0, 0, 0))


def _rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
            "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def _matrix_of(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@pytest.mark.parametrize("angles", [(10, 20, 30), (-170, 45, 95), (33, -89, 170), (0, 90, 0)])
def test_quaternions_rotate_as_the_mobile_xyz_matrices(angles):
    a, b, g = angles
    R = _rot("x", a) @ _rot("y", b) @ _rot("z", g)
    q = quat_from_euler_xyz_deg(a, b, g)
    assert math.fsum(v * v for v in q) == pytest.approx(1.0)
    np.testing.assert_allclose(_matrix_of(q), R, atol=1e-12)
    np.testing.assert_allclose(_matrix_of(quat_from_matrix(R)), R, atol=1e-12)


def test_tip_pose_without_tool_geometry_hangs_the_tip_from_the_base():
    row = ramp_row(0, tool_pose=[100.0, 0.0, 200.0, 0.0, 90.0, 0.0], phantom_pose=None)
    msg = FoxgloveView().transforms(row, START_NS + 123)
    tfs = _by_child(msg)
    assert set(tfs) == {"file_tip"}
    tip = tfs["file_tip"]
    assert tip["parent_frame_id"] == "base"
    assert tip["timestamp"] == {"sec": 1_700_000_000, "nsec": 123}
    _approx(tip["translation"], (0.1, 0.0, 0.2))            # mm -> m
    _approx(tip["rotation"], (0.0, S, 0.0, S))


def test_flange_from_the_tip_pose_and_the_tool_geometry():
    """Tip at (100, 0, 200) mm turned by Ry(90); the file tip 90 mm along the flange's z.
    Ry(90) takes z to x, so the flange is 90 mm back along x: (10, 0, 200) mm, same turn."""
    tool = np.eye(4)
    tool[2, 3] = 90.0
    row = ramp_row(0, tool_pose=[100.0, 0.0, 200.0, 0.0, 90.0, 0.0],
                   phantom_pose=[120.0, 5.0, 150.0, 180.0, 0.0, 0.0])
    tfs = _by_child(FoxgloveView(tool_6_h=tool).transforms(row, START_NS))
    assert {(tf["parent_frame_id"], c) for c, tf in tfs.items()} == {
        ("base", "flange"), ("flange", "file_tip"), ("base", "tooth")}
    _approx(tfs["flange"]["translation"], (0.01, 0.0, 0.2))
    _approx(tfs["flange"]["rotation"], (0.0, S, 0.0, S))
    _approx(tfs["file_tip"]["translation"], (0.0, 0.0, 0.09))
    _approx(tfs["file_tip"]["rotation"], (0.0, 0.0, 0.0, 1.0))
    _approx(tfs["tooth"]["translation"], (0.12, 0.005, 0.15))
    _approx(tfs["tooth"]["rotation"], (1.0, 0.0, 0.0, 0.0))     # half turn about x


def test_a_tilted_tool_geometry_composes():
    """Tool frame turned by Rz(90) about the flange's z and 90 mm out: the chain base ->
    flange -> tip gives back the row's tip pose (checked with matrices, not quaternions)."""
    tool = np.eye(4)
    tool[:3, :3] = _rot("z", 90)
    tool[:3, 3] = (5.0, -3.0, 90.0)
    pose = [50.0, -20.0, 180.0, 30.0, -40.0, 75.0]
    tfs = _by_child(FoxgloveView(tool_6_h=tool).transforms(ramp_row(0, tool_pose=pose),
                                                            START_NS))

    def matrix(tf):
        t = np.eye(4)
        r = tf["rotation"]
        t[:3, :3] = _matrix_of((r["x"], r["y"], r["z"], r["w"]))
        t[:3, 3] = [tf["translation"][k] * 1000 for k in "xyz"]
        return t

    expected = np.eye(4)
    expected[:3, :3] = _rot("x", 30) @ _rot("y", -40) @ _rot("z", 75)
    expected[:3, 3] = pose[:3]
    np.testing.assert_allclose(matrix(tfs["flange"]) @ matrix(tfs["file_tip"]), expected,
                               atol=1e-5)


def test_caller_frames_are_added_and_replace_the_view_s_own():
    link = np.eye(4)
    link[:3, 3] = (0.0, 0.0, 135.0)
    flange = np.eye(4)
    flange[:3, 3] = (190.0, 0.0, 308.0)

    def frames(row):
        return [("base", "link1", link), ("base", "flange", flange)]

    tool = np.eye(4)
    tool[2, 3] = 90.0
    tfs = _by_child(FoxgloveView(tool_6_h=tool, frames=frames).transforms(ramp_row(0),
                                                                           START_NS))
    _approx(tfs["link1"]["translation"], (0.0, 0.0, 0.135))
    _approx(tfs["flange"]["translation"], (0.19, 0.0, 0.308))      # the caller's, not ours
    assert tfs["file_tip"]["parent_frame_id"] == "flange"


def test_no_pose_no_transform():
    view = FoxgloveView()
    assert view.transforms({"t": 0.0}, START_NS) is None
    assert view.transforms(ramp_row(0, tool_pose=[0.0, math.nan, 0, 0, 0, 0],
                                    phantom_pose=None), START_NS) is None


def test_the_tracked_tooth_is_a_frame_of_its_own():
    """A tooth 0.1 m ahead on x and turned 90 deg about z (mobile XYZ): translation in m,
    rotation the unit quaternion (0, 0, sin 45, cos 45)."""
    msg = FoxgloveView().transforms(ramp_row(0, phantom_pose=None,
                                             tooth_pose=[100.0, 0.0, 50.0, 0.0, 0.0, 90.0]),
                                    START_NS)
    tf = {t["child_frame_id"]: t for t in msg["transforms"]}
    assert "tooth" not in tf                                  # no simulator truth here
    t = tf["tooth_tracked"]
    assert t["parent_frame_id"] == "base"
    assert t["translation"] == {"x": 0.1, "y": 0.0, "z": 0.05}
    r = t["rotation"]
    assert (r["x"], r["y"]) == (0.0, 0.0)
    assert r["z"] == pytest.approx(math.sqrt(0.5)) and r["w"] == pytest.approx(math.sqrt(0.5))


def test_bad_view_parameters_are_refused():
    with pytest.raises(ConfigError, match="tool_6_h"):
        FoxgloveView(tool_6_h=[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]])
    with pytest.raises(ConfigError, match="scene_hz"):
        FoxgloveView(scene_hz=0)
    with pytest.raises(ConfigError, match="frames"):
        FoxgloveView(frames="links")


# -- the scene ---------------------------------------------------------------------------------

def test_scene_draws_handpiece_file_tooth_and_the_force_arrow():
    """A force of 2 N along -z of {H}: the arrow (Foxglove's points along +x) is turned by
    Ry(90), which takes x to -z, and is 2 N x 10 mm/N = 20 mm long."""
    row = ramp_row(0, wrench_h=[0.0, 0.0, -2.0, 0.0, 0.0, 0.0])
    scene = FoxgloveView().scene(row, START_NS)
    entities = {e["id"]: e for e in scene["entities"]}
    assert set(entities) == {"handpiece", "file", "force", "tooth"}
    assert {e["frame_id"] for k, e in entities.items() if k != "tooth"} == {"file_tip"}
    assert entities["tooth"]["frame_id"] == "tooth"
    assert all(e["frame_locked"] for e in entities.values())
    (arrow,) = entities["force"]["arrows"]
    _approx(arrow["pose"]["orientation"], (0.0, S, 0.0, S))
    assert arrow["shaft_length"] + arrow["head_length"] == pytest.approx(0.020)
    (file_cone,) = entities["file"]["cylinders"]
    assert file_cone["pose"]["position"]["z"] + file_cone["size"]["z"] / 2 == \
        pytest.approx(0.0)                                  # the cone ends at the tip
    assert file_cone["top_scale"] < file_cone["bottom_scale"]
    (handpiece,) = entities["handpiece"]["cylinders"]
    assert handpiece["pose"]["position"]["z"] + handpiece["size"]["z"] / 2 == \
        pytest.approx(-0.025)                               # behind the 25 mm file
    without = FoxgloveView().scene(ramp_row(0, phantom_pose=None,
                                            wrench_h=[0.0] * 6), START_NS)
    ids = {e["id"]: e for e in without["entities"]}
    assert "tooth" not in ids and "arrows" not in ids["force"]


def test_an_arrow_opposite_to_x_is_a_half_turn():
    row = ramp_row(0, wrench_h=[-3.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    force = next(e for e in FoxgloveView().scene(row, START_NS)["entities"]
                 if e["id"] == "force")
    _approx(force["arrows"][0]["pose"]["orientation"], (0.0, 0.0, 1.0, 0.0))


def test_handpiece_reaches_back_to_the_flange():
    tool = np.eye(4)
    tool[2, 3] = 90.0
    hp = next(e for e in FoxgloveView(tool_6_h=tool).scene(ramp_row(0), START_NS)["entities"]
              if e["id"] == "handpiece")["cylinders"][0]
    z, half = hp["pose"]["position"]["z"], hp["size"]["z"] / 2
    assert (z - half, z + half) == pytest.approx((-0.090, -0.025))


# -- in a recording ----------------------------------------------------------------------------

class _JsonDecoders(McapDecoderFactory):
    """JSON messages for the mcap reader's decoded iteration."""

    def decoder_for(self, message_encoding, schema):
        return json.loads if message_encoding == "json" else None


def test_recorded_transforms_follow_the_rows_at_their_log_times(tmp_path):
    path = tmp_path / "run.mcap"
    rows = [ramp_row(i) for i in range(50)]
    with McapRecorder(path, {**META, "start_wall_ns": START_NS}) as rec:
        for row in rows:
            rec.record(row)
    with open(path, "rb") as f:       # /tf in CDR, read by Foxglove's own ROS 2 codec
        msgs = [(c.topic, m.log_time, d) for _s, c, m, d in
                make_reader(f, decoder_factories=[DecoderFactory(), _JsonDecoders()])
                .iter_decoded_messages(topics=["/tf", "/scene"])]
    tfs = [(lt, d) for topic, lt, d in msgs if topic == "/tf"]
    assert [lt for lt, _d in tfs] == [START_NS + round(r["t"] * 1e9) for r in rows]
    for row, (lt, d) in zip(rows, tfs, strict=True):
        tip = next(t for t in d.transforms if t.child_frame_id == "file_tip")
        assert tip.header.frame_id == "base"
        got = tip.transform.translation
        assert (got.x, got.y, got.z) == tuple(v * 0.001 for v in row["tool_pose"][:3])
        sec, nsec = divmod(lt, 1_000_000_000)
        assert (tip.header.stamp.sec, tip.header.stamp.nanosec) == (sec, nsec)
    scenes = [lt for topic, lt, _d in msgs if topic == "/scene"]
    assert scenes == [START_NS + round(i / 500 * 1e9) for i in range(0, 50, 10)]
    assert rec.transforms_written == 50 and rec.scenes_written == 5 and rec.view_errors == 0


def test_a_failing_frames_callable_costs_the_drawing_not_the_recording(tmp_path):
    def frames(row):
        if row["tick"] % 2:
            raise RuntimeError("no kinematics for this one")
        return []

    path = tmp_path / "run.mcap"
    rows = [ramp_row(i) for i in range(40)]
    with McapRecorder(path, META, view=FoxgloveView(frames=frames)) as rec:
        for row in rows:
            rec.record(row)
    assert rec.view_errors == 20 and rec.transforms_written == 20
    assert read_recording(path).rows == rows


def test_without_a_view_only_the_dentibot_topics_are_written(tmp_path):
    path = tmp_path / "run.mcap"
    with McapRecorder(path, META, view=False) as rec:
        rec.record(ramp_row(0))
    with open(path, "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert topics == {"/run", "/tick", "/events", "/run/end"}
    assert set(FOXGLOVE_TOPICS) == {"/tf", "/scene"}
    assert json_schema("/tick")["title"] == "dentibot.Tick"
    with pytest.raises(ConfigError, match="view"):
        McapRecorder(tmp_path / "x.mcap", META, view="3d")


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-2000.0, 2000.0), min_size=6, max_size=6))
def test_tf_numbers_are_the_row_rounded_to_a_nanometre(pose):
    """/tf's JSON writes positions (m) and quaternions to 9 decimals: each reads back as
    Python's round(x, 9) of the exact value."""
    tool = [*pose[:3], *(math.fmod(a, 180.0) for a in pose[3:])]
    msg = FoxgloveView().transforms(ramp_row(0, tool_pose=tool, phantom_pose=None), START_NS)
    tip = msg["transforms"][0]
    want = [round(x * 1e-3, 9) for x in tool[:3]]
    assert [tip["translation"][k] for k in "xyz"] == want
    q = quat_from_euler_xyz_deg(*tool[3:])
    assert [tip["rotation"][k] for k in "xyzw"] == [round(x, 9) for x in q]


@pytest.mark.parametrize("row", [
    {"wrench_h": [0.3, -0.2, 1.5, 0.0, 0.0, 0.0], "phantom_pose": [1, 2, 3, 4, 5, 6]},
    {"wrench_h": [0.0] * 6}, {}, {"wrench_h": [2.0, 1.0, 0.0]},
    {"wrench_h": [-1.0, 0.0, 0.0], "phantom_pose": [0.0, 0.0, 0.0, 90.0, 0.0, 0.0]}])
def test_a_scene_from_its_template_is_the_scene_s_json(row):
    view = FoxgloveView(tool_6_h=np.eye(4).tolist())
    for ns in (0, START_NS, 123_456_789_987_654_321):
        assert view.scene_json(row, ns) == orjson.dumps(view.scene(row, ns))
