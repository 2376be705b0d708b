"""A recording's ``/tf`` messages in CDR: ROS 2's ``tf2_msgs/msg/TFMessage``.

Foxglove's 3D panel builds its frame tree from ``tf2_msgs/msg/TFMessage`` as from its own
``foxglove.FrameTransforms``; so do the ROS 2 tools. In CDR a tick's transforms are 0.2 kB
of numbers, where the JSON text is 0.6 kB that must be printed; and a block of ticks, whose
frame names do not change, is written into copies of a template
(:meth:`TfEncoder.buffer`). The definition below is the ROS 2 one with its dependencies, as
rosbag2 stores it; positions are in metres, rotations unit quaternions (x, y, z, w).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

import numpy as np

from dentibot.telemetry.cdr import CDR_LE, WordBlock

__all__ = ["TF_DEFINITION", "TF_SCHEMA_NAME", "TfEncoder", "tf_encoder"]

TF_SCHEMA_NAME = "tf2_msgs/msg/TFMessage"
_SEP = "=" * 80
TF_DEFINITION = f"""geometry_msgs/TransformStamped[] transforms
{_SEP}
MSG: geometry_msgs/TransformStamped
std_msgs/Header header
string child_frame_id
Transform transform
{_SEP}
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
{_SEP}
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
{_SEP}
MSG: geometry_msgs/Transform
Vector3 translation
Quaternion rotation
{_SEP}
MSG: geometry_msgs/Vector3
float64 x
float64 y
float64 z
{_SEP}
MSG: geometry_msgs/Quaternion
float64 x 0
float64 y 0
float64 z 0
float64 w 1
"""


class TfEncoder:
    """The ``TFMessage`` of one list of (parent, child) frames: each transform's stamp,
    names, translation (3) and rotation (4) in CDR."""

    def __init__(self, names: Sequence[tuple[str, str]]) -> None:
        self.names = tuple(names)
        fmt, pos = ["<4sI"], 4                  # header, then the transforms' count
        self._stamps: list[int] = []              # each transform's sec offset (message)
        self._numbers: list[int] = []             # each transform's first float64 offset
        for parent, child in self.names:
            fmt.append(f"{-pos % 4}x")
            pos += -pos % 4
            self._stamps.append(pos + 4)
            fmt.append("iI")
            pos += 8
            for name in (parent, child):
                data = name.encode()
                fmt.append(f"{-pos % 4}xI{len(data) + 1}s")
                pos += -pos % 4 + 4 + len(data) + 1
            fmt.append(f"{-pos % 8}x7d")
            pos += -pos % 8
            self._numbers.append(pos + 4)
            pos += 56
        self._struct = struct.Struct("".join(fmt))
        self.size = self._struct.size
        #: each transform's names as packed: (length + 1, parent, length + 1, child)
        self._heads = [(len(p) + 1, p, len(c) + 1, c)
                       for p, c in ((a.encode(), b.encode()) for a, b in self.names)]
        self._block = WordBlock(self.encode(0, [(0.0,) * 7] * len(self.names)))
        # each transform's sec among the block's 4-byte words (nanosec the next one)
        self._sec = np.array([(at + 4) // 4 for at in self._stamps], dtype=np.intp)

    def encode(self, log_ns: int, values: Sequence[Sequence[float]]) -> bytes:
        """The message at ``log_ns`` (ns since the epoch), ``values[i]`` the translation and
        rotation (x, y, z, qx, qy, qz, qw) of transform ``i``."""
        sec, nsec = divmod(int(log_ns), 1_000_000_000)
        args: list = [CDR_LE, len(self.names)]
        for names, v in zip(self._heads, values):
            args += (sec, nsec, *names, *v)
        return self._struct.pack(*args)

    def buffer(self, log_ns: np.ndarray) -> np.ndarray:
        """The messages of ``n`` ticks at ``log_ns`` (n int64), their numbers to be written:
        ``n`` rows of float64 words, each holding a message 4 bytes in, so that every
        number of it is one word (transform ``i``'s seven from :meth:`word` ``(i)`` on):
        a :class:`~dentibot.telemetry.cdr.WordBlock` with the stamps written."""
        buf = self._block.buffer(len(log_ns))
        words = buf.view("<u4")
        sec, nsec = np.divmod(np.asarray(log_ns, dtype=np.int64), 1_000_000_000)
        words[:, self._sec] = sec.astype(np.uint32)[:, None]
        words[:, self._sec + 1] = nsec.astype(np.uint32)[:, None]
        return buf

    def word(self, i: int) -> int:
        """The word of :meth:`buffer`'s rows holding transform ``i``'s first number."""
        return self._block.word(self._numbers[i])

    def messages(self, buf: np.ndarray) -> list[bytes]:
        """The messages of a :meth:`buffer`, one per row."""
        return self._block.messages(buf)


_ENCODERS: dict[tuple, TfEncoder] = {}


def tf_encoder(names: Sequence[tuple[str, str]]) -> TfEncoder:
    """The encoder of a frame list, made once (a run has a few)."""
    key = tuple(names)
    enc = _ENCODERS.get(key)
    if enc is None:
        if len(_ENCODERS) > 64:
            _ENCODERS.clear()
        enc = _ENCODERS[key] = TfEncoder(key)
    return enc
