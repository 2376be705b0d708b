"""What a tick looks like in Foxglove's 3D panel: frame transforms and a scene.

A telemetry row carries the file-tip pose (``tool_pose``), the phantom pose when it is known
(``phantom_pose``) and the wrench in the tool frame (``wrench_h``). :class:`FoxgloveView` turns
one row into two of Foxglove's well-known message types, so that a recording (and the live
view) shows the handpiece, the file, the tooth and the force in 3D without any layout or
plug-in:

``/tf`` (every tick: ``tf2_msgs/msg/TFMessage`` in CDR in a recording,
:meth:`FoxgloveView.transforms_cdr`; ``foxglove.FrameTransforms`` in JSON in the live view,
:meth:`FoxgloveView.transforms_json`)
    The tree ``base`` -> ``flange`` -> ``file_tip``, ``base`` -> ``tooth`` (the simulator's
    phantom) and ``base`` -> ``tooth_tracked`` (the patient tracker's). One message per
    tick holds all of the tick's transforms: one MCAP record instead of one per frame, which
    is what the writer pays for (see docs/recordings.md).
    Without the tool geometry (``tool_6_h``) the flange cannot be placed from the row alone
    and the tree is ``base`` -> ``file_tip``.
``/scene`` (``foxglove.SceneUpdate``, decimated to ``scene_hz`` of procedure time)
    The handpiece (a cylinder behind the file), the file (a cone ending at the tip), the tooth
    (a box around the canal, at the phantom pose) and the force on the file (an arrow from the
    tip, ``force_scale_mm_per_n`` long per newton). Entities are locked to their frames, so
    they follow ``/tf`` at the full rate between two scene updates.

Conventions. Foxglove's 3D panel works in metres (its grid, its camera, its default sizes):
positions are converted from the row's millimetres. Poses in the rows are mobile XYZ Euler
angles (``R = Rx(alpha) Ry(beta) Rz(gamma)``, docs/architecture.md); Foxglove wants unit
quaternions ``(x, y, z, w)``. The file axis is the z axis of the tool frame {H}, pointing out of
the handpiece; the canal runs along +z of the phantom frame from the orifice.

Schemas. The JSON schemas are Foxglove's published ones (``foxglove.FrameTransform`` verbatim,
inside ``foxglove.FrameTransforms``); ``foxglove.SceneUpdate`` is the published schema cut down
to the parts written here (entities with arrows, cubes and cylinders; no deletions), because
its enumerations are declared with ``oneOf`` and no ``type``, which the open-source viewers'
JSON-schema parser rejects. Messages written against the cut-down schema are valid
``foxglove.SceneUpdate`` messages: Foxglove fills absent primitive lists with empty ones.

More frames. The Meca500's forward kinematics belongs to :mod:`dentibot.control`, which the
telemetry layer does not import. A caller that wants more frames (the links, or a flange pose
from the joint angles) passes ``frames``: a callable that takes a row and returns
``(parent, child, T)`` triples, ``T`` a 4x4 homogeneous transform in millimetres; a triple for a
child frame the view already places replaces the view's own transform of that frame. The
callable runs in the thread that encodes the messages (the recorder's writer), so it must
not touch state the control task changes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np
import orjson

from dentibot.errors import ConfigError
from dentibot.telemetry.quaternion_kernels import (
    fill_tool_frames,
    flange_of_tip,
    qconj,
    qrotate,
)
from dentibot.telemetry.quaternion_kernels import quat_from_euler_xyz_deg as _quat_euler
from dentibot.telemetry.tf_cdr import TfEncoder, tf_encoder

__all__ = [
    "FOXGLOVE_TOPICS",
    "FRAME_TRANSFORMS_SCHEMA",
    "FRAME_TRANSFORM_SCHEMA",
    "SCENE_TOPIC",
    "SCENE_UPDATE_SCHEMA",
    "TF_TOPIC",
    "FoxgloveView",
    "FramesFn",
    "quat_from_euler_xyz_deg",
    "quat_from_matrix",
    "stamp",
]

TF_TOPIC = "/tf"
SCENE_TOPIC = "/scene"

BASE, FLANGE, FILE_TIP, TOOTH = "base", "flange", "file_tip", "tooth"
#: the tooth as the patient tracker measures it (``tooth_pose``), beside the simulator's truth
TRACKED_TOOTH = "tooth_tracked"

#: A caller's extra frames: row -> (parent frame, child frame, 4x4 transform in mm).
FramesFn = Callable[[dict[str, Any]], Iterable[tuple[str, str, Any]]]

_MM = 0.001                     # metres per millimetre
_PROBE_NS = 123_456_789_987_654_321   # the stamp a scene template is made with


# -- schemas (Foxglove's published JSON schemas, built from their common parts) -----------------

def _time(description: str) -> dict[str, Any]:
    return {"type": "object", "title": "time",
            "properties": {"sec": {"type": "integer", "minimum": 0},
                           "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
            "description": description}


def _duration(description: str) -> dict[str, Any]:
    return {"type": "object", "title": "duration",
            "properties": {"sec": {"type": "integer"},
                           "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
            "description": description}


def _numbers(title: str, description: str, names: dict[str, str]) -> dict[str, Any]:
    return {"title": title, "description": description, "type": "object",
            "properties": {k: {"type": "number", "description": d} for k, d in names.items()},
            "required": list(names)}


def _vector3(description: str) -> dict[str, Any]:
    return _numbers("foxglove.Vector3", description, {
        "x": "x coordinate length", "y": "y coordinate length", "z": "z coordinate length"})


def _quaternion(description: str) -> dict[str, Any]:
    return _numbers("foxglove.Quaternion", description, {
        "x": "x value", "y": "y value", "z": "z value", "w": "w value"})


def _color(description: str) -> dict[str, Any]:
    return _numbers("foxglove.Color", description, {
        "r": "Red value between 0 and 1", "g": "Green value between 0 and 1",
        "b": "Blue value between 0 and 1", "a": "Alpha value between 0 and 1"})


def _pose(description: str) -> dict[str, Any]:
    return {"title": "foxglove.Pose", "description": description, "type": "object",
            "properties": {
                "position": _vector3("Point denoting position in 3D space"),
                "orientation": _quaternion("Quaternion denoting orientation in 3D space")},
            "required": ["position", "orientation"]}


def _array(items: dict[str, Any], description: str) -> dict[str, Any]:
    return {"type": "array", "items": items, "description": description}


_FRAME_TRANSFORM_DESCRIPTION = (
    "A transform between two reference frames in 3D space. The transform defines the position "
    "and orientation of a child frame within a parent frame. Foxglove applies the translation "
    "first and then the rotation.")


def _frame_transform() -> dict[str, Any]:
    return {
        "title": "foxglove.FrameTransform",
        "description": _FRAME_TRANSFORM_DESCRIPTION,
        "type": "object",
        "properties": {
            "timestamp": _time("Timestamp of transform"),
            "parent_frame_id": {"type": "string", "description": "Name of the parent frame"},
            "child_frame_id": {"type": "string", "description": "Name of the child frame"},
            "translation": _vector3(
                "Translation component of the transform, representing the position of the "
                "child frame's origin in the parent frame."),
            "rotation": _quaternion(
                "Rotation component of the transform, representing the orientation of the "
                "child frame in the parent frame"),
        },
        "required": ["timestamp", "parent_frame_id", "child_frame_id", "translation",
                     "rotation"],
    }


#: Foxglove's ``foxglove.FrameTransform`` JSON schema.
FRAME_TRANSFORM_SCHEMA: dict[str, Any] = _frame_transform()

#: Foxglove's ``foxglove.FrameTransforms`` JSON schema: the ``/tf`` channel.
FRAME_TRANSFORMS_SCHEMA: dict[str, Any] = {
    "title": "foxglove.FrameTransforms",
    "description": "An array of FrameTransform messages",
    "type": "object",
    "properties": {"transforms": _array(_frame_transform(), "Array of transforms")},
    "required": ["transforms"],
}

_ARROW = {
    "title": "foxglove.ArrowPrimitive", "description": "A primitive representing an arrow",
    "type": "object",
    "properties": {
        "pose": _pose("Position of the arrow's tail and orientation of the arrow. Identity "
                      "orientation means the arrow points in the +x direction."),
        "shaft_length": {"type": "number", "description": "Length of the arrow shaft"},
        "shaft_diameter": {"type": "number", "description": "Diameter of the arrow shaft"},
        "head_length": {"type": "number", "description": "Length of the arrow head"},
        "head_diameter": {"type": "number", "description": "Diameter of the arrow head"},
        "color": _color("Color of the arrow"),
    },
    "required": ["pose", "shaft_length", "shaft_diameter", "head_length", "head_diameter",
                 "color"],
}

_CUBE = {
    "title": "foxglove.CubePrimitive",
    "description": "A primitive representing a cube or rectangular prism",
    "type": "object",
    "properties": {
        "pose": _pose("Position of the center of the cube and orientation of the cube"),
        "size": _vector3("Size of the cube along each axis"),
        "color": _color("Color of the cube"),
    },
    "required": ["pose", "size", "color"],
}

_CYLINDER = {
    "title": "foxglove.CylinderPrimitive",
    "description": "A primitive representing a cylinder, elliptic cylinder, or truncated cone",
    "type": "object",
    "properties": {
        "pose": _pose("Position of the center of the cylinder and orientation of the cylinder. "
                      "The flat face(s) are perpendicular to the z-axis."),
        "size": _vector3("Size of the cylinder's bounding box"),
        "bottom_scale": {"type": "number", "description":
                         "0-1, ratio of the diameter of the cylinder's bottom face (min z) to "
                         "the bottom of the bounding box"},
        "top_scale": {"type": "number", "description":
                      "0-1, ratio of the diameter of the cylinder's top face (max z) to the "
                      "top of the bounding box"},
        "color": _color("Color of the cylinder"),
    },
    "required": ["pose", "size", "bottom_scale", "top_scale", "color"],
}

#: ``foxglove.SceneUpdate``: Foxglove's published schema, cut down to what the view writes.
SCENE_UPDATE_SCHEMA: dict[str, Any] = {
    "title": "foxglove.SceneUpdate",
    "description": "An update to the entities displayed in a 3D scene",
    "type": "object",
    "properties": {
        "entities": _array({
            "title": "foxglove.SceneEntity",
            "description": "A visual element in a 3D scene. An entity may be composed of "
                           "multiple primitives which all share the same frame of reference.",
            "type": "object",
            "properties": {
                "timestamp": _time("Timestamp of the entity"),
                "frame_id": {"type": "string", "description": "Frame of reference"},
                "id": {"type": "string", "description":
                       "Identifier for the entity. A entity will replace any prior entity on "
                       "the same topic with the same `id`."},
                "lifetime": _duration(
                    "Length of time (relative to `timestamp`) after which the entity should be "
                    "automatically removed. Zero value indicates the entity should remain "
                    "visible until it is replaced or deleted."),
                "frame_locked": {"type": "boolean", "description":
                                 "Whether the entity should keep its location in the fixed "
                                 "frame (false) or follow the frame specified in `frame_id` "
                                 "as it moves relative to the fixed frame (true)"},
                "arrows": _array(_ARROW, "Arrow primitives"),
                "cubes": _array(_CUBE, "Cube primitives"),
                "cylinders": _array(_CYLINDER, "Cylinder primitives"),
            },
            "required": ["timestamp", "frame_id", "id", "lifetime", "frame_locked"],
        }, "Scene entities to add or replace"),
    },
    "required": ["entities"],
}

#: topic -> JSON schema (its ``title`` is the schema name) of the 3D channels.
FOXGLOVE_TOPICS: dict[str, dict[str, Any]] = {
    TF_TOPIC: FRAME_TRANSFORMS_SCHEMA,
    SCENE_TOPIC: SCENE_UPDATE_SCHEMA,
}


# -- rotations -------------------------------------------------------------------------------

Quat = tuple[float, float, float, float]          # (x, y, z, w), unit
Vec = tuple[float, float, float]


def quat_from_euler_xyz_deg(alpha: float, beta: float, gamma: float) -> Quat:
    """Unit quaternion (x, y, z, w) of ``R = Rx(alpha) Ry(beta) Rz(gamma)`` (mobile XYZ Euler
    angles in degrees, the convention of the rows' poses)
    (:func:`~dentibot.telemetry.quaternion_kernels.quat_from_euler_xyz_deg`)."""
    return _quat_euler(float(alpha), float(beta), float(gamma))


def quat_from_matrix(m: Any) -> Quat:
    """Unit quaternion (x, y, z, w) of the rotation part of ``m`` (3x3 or 4x4, row-major
    nested sequences or numpy), by the largest-component method (stable for every rotation,
    including half turns)."""
    r00, r01, r02 = (float(v) for v in m[0][:3])
    r10, r11, r12 = (float(v) for v in m[1][:3])
    r20, r21, r22 = (float(v) for v in m[2][:3])
    tr = r00 + r11 + r22
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = ((r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s, 0.25 * s)
    elif r00 > r11 and r00 > r22:
        s = math.sqrt(1.0 + r00 - r11 - r22) * 2.0
        q = (0.25 * s, (r01 + r10) / s, (r02 + r20) / s, (r21 - r12) / s)
    elif r11 > r22:
        s = math.sqrt(1.0 + r11 - r00 - r22) * 2.0
        q = ((r01 + r10) / s, 0.25 * s, (r12 + r21) / s, (r02 - r20) / s)
    else:
        s = math.sqrt(1.0 + r22 - r00 - r11) * 2.0
        q = ((r02 + r20) / s, (r12 + r21) / s, 0.25 * s, (r10 - r01) / s)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if q[3] < 0.0:                                 # one of the two: w >= 0
        n = -n
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


def _arrow_quat(d: Vec) -> Quat:
    """The rotation taking +x (Foxglove's arrow direction) onto the unit vector ``d``."""
    w = 1.0 + d[0]
    if w < 1e-9:                                   # d = -x: half turn about z
        return (0.0, 0.0, 1.0, 0.0)
    qx, qy, qz = 0.0, -d[2], d[1]                  # x cross d
    n = math.sqrt(w * w + qy * qy + qz * qz)
    return (qx / n, qy / n, qz / n, w / n)


# -- message parts -----------------------------------------------------------------------------

def stamp(ns: int) -> dict[str, int]:
    """Foxglove ``time`` of ``ns`` nanoseconds since the epoch."""
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


#: one ``foxglove.FrameTransform`` in JSON: its stamp, then parent and child (quoted),
#: translation (m) and rotation, to 1e-9
_TF_STAMP = '{"timestamp":{"sec":%d,"nsec":%d},'
_TF_JSON = ('"parent_frame_id":%s,"child_frame_id":%s,'
            '"translation":{"x":%.9f,"y":%.9f,"z":%.9f},'
            '"rotation":{"x":%.9f,"y":%.9f,"z":%.9f,"w":%.9f}}')
_QUOTED: dict[str, str] = {}


def _quoted(name: str) -> str:
    """``name`` as a JSON string (frame names are few: kept once quoted)."""
    text = _QUOTED.get(name)
    if text is None:
        text = orjson.dumps(name).decode()
        if len(_QUOTED) < 256:
            _QUOTED[name] = text
    return text


def _v(p: Vec) -> dict[str, float]:
    return {"x": p[0], "y": p[1], "z": p[2]}


def _q(q: Quat) -> dict[str, float]:
    return {"x": q[0], "y": q[1], "z": q[2], "w": q[3]}


def _pose6(value: Any) -> Sequence[float] | None:
    """A row's pose (six finite numbers), or None (unknown, or not a pose). The sum tells
    both at once: it fails on a non-number and is NaN or infinite if any item is."""
    if not isinstance(value, (list, tuple)) or len(value) != 6:
        return None
    try:
        total = sum(value)
        if total - total != 0.0:
            return None
    except TypeError:
        return None
    return value


def _rgba(r: float, g: float, b: float, a: float = 1.0) -> dict[str, float]:
    return {"r": r, "g": g, "b": b, "a": a}


_IDENTITY = {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}
_ZERO_DURATION = {"sec": 0, "nsec": 0}
_HANDPIECE_COLOR = _rgba(0.55, 0.58, 0.62)
_FILE_COLOR = _rgba(0.85, 0.7, 0.25)
_TOOTH_COLOR = _rgba(0.95, 0.93, 0.85, 0.45)
_FORCE_COLOR = _rgba(0.9, 0.15, 0.1)


def _positive(name: str, value: float) -> float:
    if not (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value) and value > 0):
        raise ConfigError(f"foxglove.{name}", value, "a finite number > 0")
    return float(value)


class FoxgloveView:
    """Turns telemetry rows into ``/tf`` and ``/scene`` messages (see the module docstring).

    Its configuration is fixed once built, so one view can serve the recorder and the live
    view at once; the decimation of the scene is the sink's (:meth:`scene_due`).

    Parameters (defaults in brackets; lengths in mm):

    - ``tool_6_h`` [None]: the flange -> file-tip transform 6T_H (4x4, mm), as calibrated
      (``runtime.tool.tool_matrix``). With it the tree has the flange; without it, the tip
      hangs from the base directly.
    - ``frames`` [None]: the caller's extra frames (:data:`FramesFn`).
    - ``scene_hz`` [50]: scene updates per second of procedure time.
    - ``file_length_mm`` [25], ``file_diameter_mm`` [1.2]: the file's cone (its tip a quarter
      of its base).
    - ``handpiece_diameter_mm`` [12], ``handpiece_length_mm`` [None: from the file's base back
      to the flange when ``tool_6_h`` is given, else 60].
    - ``tooth_size_mm`` [(10, 10, 26)], ``crown_mm`` [6]: the tooth's box, ``crown_mm`` of it
      above the orifice, the rest along the canal.
    - ``force_scale_mm_per_n`` [10]: arrow length per newton of ``wrench_h``'s force.
    """

    def __init__(self, *, tool_6_h: Any = None, frames: FramesFn | None = None,
                 scene_hz: float = 50.0, file_length_mm: float = 25.0,
                 file_diameter_mm: float = 1.2, handpiece_diameter_mm: float = 12.0,
                 handpiece_length_mm: float | None = None,
                 tooth_size_mm: Sequence[float] = (10.0, 10.0, 26.0), crown_mm: float = 6.0,
                 force_scale_mm_per_n: float = 10.0) -> None:
        self.scene_period_s = 1.0 / _positive("scene_hz", scene_hz)
        self.frames = frames
        # (Euler angles, quaternion) of the last phantom pose: a cache, not state (a stale
        # entry is recomputed; the pair is stored in one assignment, safe across threads)
        self._tooth_q: tuple[list, Quat] | None = None
        # per child frame, its last transform and that transform's JSON (without the stamp):
        # a cache as well (frames that do not move are not written out again)
        self._tf_texts: dict[str, tuple[tuple, str]] = {}
        self._scene_texts: dict[tuple[bool, bool], bytes] = {}
        if frames is not None and not callable(frames):
            raise ConfigError("foxglove.frames", frames, "a callable row -> (parent, child, T)")
        self._tool: tuple[Quat, Vec] | None = None
        if tool_6_h is not None:
            self._tool = self._transform(tool_6_h, "tool_6_h")
        file_len = _positive("file_length_mm", file_length_mm)
        if handpiece_length_mm is None:
            behind = 60.0
            if self._tool is not None:            # flange origin in {H}: -R^T p (on -z)
                q, p = self._tool
                behind = qrotate(qconj(q), p)[2] - file_len
            handpiece_length_mm = behind if behind > 1.0 else 60.0
        hp_len = _positive("handpiece_length_mm", handpiece_length_mm)
        hp_d = _positive("handpiece_diameter_mm", handpiece_diameter_mm)
        file_d = _positive("file_diameter_mm", file_diameter_mm)
        size = tuple(_positive("tooth_size_mm", float(v)) for v in tooth_size_mm)
        if len(size) != 3:
            raise ConfigError("foxglove.tooth_size_mm", tooth_size_mm, "three lengths (mm)")
        crown = float(crown_mm)
        if not 0.0 <= crown <= size[2]:
            raise ConfigError("foxglove.crown_mm", crown_mm, f"0..{size[2]} mm (the box height)")
        self.force_scale_m_per_n = _positive("force_scale_mm_per_n", force_scale_mm_per_n) * _MM
        # the constant primitives, in metres, in their frames
        self._handpiece = {
            "pose": {"position": _v((0.0, 0.0, -(file_len + hp_len / 2) * _MM)),
                     "orientation": _IDENTITY},
            "size": _v((hp_d * _MM, hp_d * _MM, hp_len * _MM)),
            "bottom_scale": 1.0, "top_scale": 1.0, "color": _HANDPIECE_COLOR}
        self._file = {
            "pose": {"position": _v((0.0, 0.0, -file_len / 2 * _MM)), "orientation": _IDENTITY},
            "size": _v((file_d * _MM, file_d * _MM, file_len * _MM)),
            "bottom_scale": 1.0, "top_scale": 0.25, "color": _FILE_COLOR}
        self._tooth = {
            "pose": {"position": _v((0.0, 0.0, (size[2] / 2 - crown) * _MM)),
                     "orientation": _IDENTITY},
            "size": _v(tuple(v * _MM for v in size)), "color": _TOOTH_COLOR}

    @staticmethod
    def _transform(m: Any, what: str) -> tuple[Quat, Vec]:
        """(rotation, translation in mm) of a 4x4 homogeneous transform."""
        try:
            rows = [[float(v) for v in m[i][:4]] for i in range(4)]
        except (TypeError, ValueError, IndexError) as exc:
            raise ConfigError(f"foxglove.{what}", m, "a 4x4 homogeneous transform (mm)",
                              str(exc)) from None
        if not all(math.isfinite(v) for r in rows for v in r) or rows[3] != [0, 0, 0, 1]:
            raise ConfigError(f"foxglove.{what}", m, "a finite 4x4 transform, last row 0 0 0 1")
        return quat_from_matrix(rows), (rows[0][3], rows[1][3], rows[2][3])

    # -- /tf ------------------------------------------------------------------------------

    def transforms(self, row: dict[str, Any], log_ns: int) -> dict[str, Any] | None:
        """The ``foxglove.FrameTransforms`` message of ``row`` at ``log_ns`` (what
        :meth:`transforms_json` writes, read back), or None when the row places no frame."""
        data = self.transforms_json(row, log_ns)
        return None if data is None else orjson.loads(data)

    def transforms_json(self, row: dict[str, Any], log_ns: int) -> bytes | None:
        """The ``foxglove.FrameTransforms`` message of ``row`` at ``log_ns`` as JSON, or None
        when the row places no frame (no valid tool pose, no phantom pose, no extra frames).
        Positions and quaternion components are written to 1 nm and 1e-9 (far below what the
        arm or the row can tell): full-precision noise digits do not compress, and the
        rounding halves what ``/tf`` adds to the file."""
        frames = self._frames(row)
        if not frames:
            return None
        sec, nsec = divmod(int(log_ns), 1_000_000_000)
        stamped = _TF_STAMP % (sec, nsec)
        texts = self._tf_texts
        parts = []
        for parent, child, p, q in frames:
            key = (parent, *p, *q)
            last = texts.get(child)
            if last is not None and last[0] == key:     # a frame that did not move
                text = last[1]
            else:
                text = _TF_JSON % (_quoted(parent), _quoted(child), p[0] * _MM, p[1] * _MM,
                                   p[2] * _MM, q[0], q[1], q[2], q[3])
                if child in texts or len(texts) < 64:
                    texts[child] = (key, text)          # one atomic store
            parts.append(stamped + text)
        return ('{"transforms":[' + ",".join(parts) + "]}").encode()

    def transforms_cdr(self, row: dict[str, Any], log_ns: int) -> bytes | None:
        """The ``tf2_msgs/msg/TFMessage`` (CDR) of ``row`` at ``log_ns``: the frames of
        :meth:`transforms_json`, in full precision; None when the row places no frame."""
        frames = self._frames(row)
        if not frames:
            return None
        return tf_encoder(tuple((parent, child) for parent, child, _p, _q in frames)).encode(
            log_ns, [(p[0] * _MM, p[1] * _MM, p[2] * _MM, *q) for _a, _b, p, q in frames])

    def block_transforms_cdr(self, tool: Any, phantom_xyz: Any,
                             phantom_euler: Sequence[float], log_ns: Any) -> list[bytes] | None:
        """:meth:`transforms_cdr` of ``n`` rows at once, bit for bit: their tool poses
        (n x 6), the phantom's positions (n x 3) and its one orientation. None if a row's
        frames would not be the others' (a pose with a non-finite number) or the caller adds
        frames of its own: then each row goes through :meth:`transforms_cdr`."""
        words = self.block_transforms_words(tool, phantom_xyz, phantom_euler, log_ns)
        return None if words is None else words[1].messages(words[0])

    def block_transforms_words(self, tool: Any, phantom_xyz: Any,
                               phantom_euler: Sequence[float],
                               log_ns: Any) -> tuple[np.ndarray, TfEncoder] | None:
        """:meth:`block_transforms_cdr`'s messages as the rows of a float64 buffer, with
        their encoder (its ``size``; ``messages`` cuts them out): each message 4 bytes into
        its row."""
        tool = np.asarray(tool, dtype=float)
        phantom_xyz = np.asarray(phantom_xyz, dtype=float)
        if self.frames is not None or not (np.isfinite(tool).all()
                                           and np.isfinite(phantom_xyz).all()
                                           and all(map(math.isfinite, phantom_euler))):
            return None
        if self._tool is None:
            names = [(BASE, FILE_TIP), (BASE, TOOTH)]
            q_6h, p_6h = (0.0, 0.0, 0.0, 1.0), (0.0, 0.0, 0.0)
        else:
            names = [(BASE, FLANGE), (FLANGE, FILE_TIP), (BASE, TOOTH)]
            q_6h, p_6h = self._tool
        enc = tf_encoder(names)
        buf = enc.buffer(log_ns)
        fill_tool_frames(buf, np.ascontiguousarray(tool), q_6h, p_6h,
                            self._tool is not None, enc.word(0))
        if self._tool is not None:                 # the tip in the flange: the geometry
            buf[:, enc.word(1):enc.word(1) + 7] = (p_6h[0] * _MM, p_6h[1] * _MM,
                                                   p_6h[2] * _MM, *q_6h)
        tooth = enc.word(len(names) - 1)
        buf[:, tooth:tooth + 3] = phantom_xyz * _MM
        buf[:, tooth + 3:tooth + 7] = quat_from_euler_xyz_deg(*phantom_euler)
        return buf, enc

    def _frames(self, row: dict[str, Any]) -> list[tuple[str, str, Sequence[float], Quat]]:
        """The frames ``row`` places: (parent, child, position in mm, rotation)."""
        out: dict[str, tuple[str, str, Sequence[float], Quat]] = {}      # by child frame
        tip = _pose6(row.get("tool_pose"))
        if tip is not None:
            q_0h = quat_from_euler_xyz_deg(tip[3], tip[4], tip[5])
            p_0h = (float(tip[0]), float(tip[1]), float(tip[2]))
            if self._tool is None:
                out[FILE_TIP] = (BASE, FILE_TIP, p_0h, q_0h)
            else:
                q_6h, p_6h = self._tool               # 0T_6 = 0T_H (6T_H)^-1
                p_06, q_06 = flange_of_tip(p_0h, q_0h, q_6h, p_6h)
                out[FLANGE] = (BASE, FLANGE, p_06, q_06)
                out[FILE_TIP] = (FLANGE, FILE_TIP, p_6h, q_6h)
        tooth = _pose6(row.get("phantom_pose"))
        if tooth is not None:
            cached = self._tooth_q                # the phantom rarely moves: reuse its rotation
            if cached is not None and cached[0] == tooth[3:]:
                q_tooth = cached[1]
            else:
                q_tooth = quat_from_euler_xyz_deg(tooth[3], tooth[4], tooth[5])
                self._tooth_q = (list(tooth[3:]), q_tooth)     # one atomic store
            out[TOOTH] = (BASE, TOOTH, tooth[:3], q_tooth)
        tracked = _pose6(row.get("tooth_pose"))
        if tracked is not None:
            out[TRACKED_TOOTH] = (BASE, TRACKED_TOOTH, tracked[:3],
                                  quat_from_euler_xyz_deg(*tracked[3:]))
        if self.frames is not None:
            for parent, child, m in self.frames(row):
                q, p = self._transform(m, "frames")
                out[str(child)] = (str(parent), str(child), p, q)
        return list(out.values())

    # -- /scene ---------------------------------------------------------------------------

    def scene_due(self, t: Any, last_t: float | None) -> bool:
        """Whether a row at procedure time ``t`` gets a scene, the last one having been at
        ``last_t`` (None: none yet). Time going backwards (a new run) restarts the count."""
        if not isinstance(t, (int, float)) or isinstance(t, bool) or not math.isfinite(t):
            return False
        return last_t is None or t < last_t or t - last_t >= self.scene_period_s - 1e-9

    def scene_json(self, row: dict[str, Any], log_ns: int) -> bytes:
        """:meth:`scene` as JSON, byte for byte ``orjson.dumps(scene(row, log_ns))``, from a
        template of the constant entities (one per kind of scene: with or without a force
        arrow, a tooth) with the stamps and the arrow put in."""
        arrows = self._force(row.get("wrench_h"))
        key = (bool(arrows), _pose6(row.get("phantom_pose")) is not None)
        template = self._scene_texts.get(key)
        if template is None:
            probe = {"wrench_h": [1.0, 0.0, 0.0]} if key[0] else {}
            if key[1]:
                probe["phantom_pose"] = [0.0] * 6
            text = orjson.dumps(self.scene(probe, _PROBE_NS))
            if key[0]:
                arrow = orjson.dumps(self._force(probe["wrench_h"]))
                if text.count(arrow) != 1:               # cannot tell it apart: no template
                    return orjson.dumps(self.scene(row, log_ns))
                text = text.replace(arrow, b"\0arrows\0")
            ts = orjson.dumps(stamp(_PROBE_NS))          # a stamp nothing else reads as
            template = self._scene_texts[key] = text.replace(b"%", b"%%").replace(
                ts, b"%(ts)b").replace(b"\0arrows\0", b"%(arrows)b")
        sec, nsec = divmod(int(log_ns), 1_000_000_000)
        return template % {b"ts": b'{"sec":%d,"nsec":%d}' % (sec, nsec),
                           b"arrows": orjson.dumps(arrows)}

    def scene(self, row: dict[str, Any], log_ns: int) -> dict[str, Any]:
        """The ``foxglove.SceneUpdate`` message of ``row`` at ``log_ns``: handpiece, file,
        force arrow (frame ``file_tip``), and the tooth when the phantom pose is known."""
        ts = stamp(log_ns)
        entities = [
            self._entity(ts, FILE_TIP, "handpiece", cylinders=[self._handpiece]),
            self._entity(ts, FILE_TIP, "file", cylinders=[self._file]),
            self._entity(ts, FILE_TIP, "force", arrows=self._force(row.get("wrench_h"))),
        ]
        if _pose6(row.get("phantom_pose")) is not None:
            entities.append(self._entity(ts, TOOTH, "tooth", cubes=[self._tooth]))
        return {"entities": entities}

    @staticmethod
    def _entity(ts: dict[str, int], frame: str, ident: str, **primitives: list) -> dict:
        """A scene entity; empty primitive lists are left out (Foxglove reads them as empty)."""
        entity: dict[str, Any] = {"timestamp": ts, "frame_id": frame, "id": ident,
                                  "lifetime": _ZERO_DURATION, "frame_locked": True}
        entity.update((kind, items) for kind, items in primitives.items() if items)
        return entity

    def _force(self, wrench: Any) -> list[dict[str, Any]]:
        """The arrow of the force part of ``wrench`` (N, in {H}) from the tip; none when the
        force is unknown or below 1 mN (no direction to draw)."""
        if not isinstance(wrench, (list, tuple)) or len(wrench) < 3:
            return []
        try:
            f = (float(wrench[0]), float(wrench[1]), float(wrench[2]))
        except (TypeError, ValueError):
            return []
        n = math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])
        if not (math.isfinite(n) and n >= 1e-3):
            return []
        length = n * self.force_scale_m_per_n
        head = min(0.3 * length, 4.0 * _MM)
        return [{"pose": {"position": _v((0.0, 0.0, 0.0)),
                          "orientation": _q(_arrow_quat((f[0] / n, f[1] / n, f[2] / n)))},
                 "shaft_length": length - head, "shaft_diameter": 0.8 * _MM,
                 "head_length": head, "head_diameter": 2.4 * _MM, "color": _FORCE_COLOR}]


def as_view(view: FoxgloveView | bool | None, field: str) -> FoxgloveView | None:
    """A ``view`` argument of the recorder or the live view: True -> the default view (file tip
    from the base only), False/None -> none, else a :class:`FoxgloveView`."""
    if view is True:
        return FoxgloveView()
    if view is False or view is None:
        return None
    if not isinstance(view, FoxgloveView):
        raise ConfigError(field, view, "a FoxgloveView, True or False")
    return view
