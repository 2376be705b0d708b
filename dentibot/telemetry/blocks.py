"""Telemetry rows one at a time (:func:`tick_row`) and many at once (:class:`TickBlock`).

A control tick's row (:data:`~dentibot.telemetry.schema.TICK_FIELDS`) is a dict built by
:func:`tick_row`, the one place that lays it out. The built-in simulator's drilling ticks,
run many per compiled call in lock-step time, write their rows' numbers into the columns of
one array instead (:data:`COLUMNS`); a :class:`TickBlock` carries that array with what its
ticks share (step, state, working length, reversals, the phantom's orientation) and gives the
same dicts, through :func:`tick_row`, to readers that take rows one at a time. Readers that
take blocks (the recorder, the run's summary) take the array itself: handing over a block of
ticks costs about as much as handing over one row.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from dentibot.telemetry.cdr import BlockEncoder
from dentibot.telemetry.schema import TICK_FIELDS

__all__ = ["COL", "COLUMNS", "WIDTH", "TickBlock", "tick_row"]


def tick_row(t: float, tick: int, step: str, state: str, q_deg: list, qdot_deg_s: list,
             tool_pose: list, phantom_pose: list | None, tooth_pose: list | None,
             wrench_s: list, wrench_h: list, fz_n: float, fz_star_n: float,
             file_torque_mnm: float, motor_current_a: float, motor_rpm: float,
             depth_mm: float | None, true_depth_mm: float | None, working_length_mm: float,
             completeness: float | None, patient_moved: bool, reversals: int,
             fractured: bool, events: list, lateness_us: float, compute_us: float,
             overrun: bool) -> dict[str, Any]:
    """One tick's telemetry row (the fields and their order: ``TICK_FIELDS``); ``f_d`` is
    ``(0, 0, fz_n, 0, 0, 0)``."""
    return {
        "t": t, "tick": tick, "step": step, "state": state, "q_deg": q_deg,
        "qdot_cmd_deg_s": qdot_deg_s, "tool_pose": tool_pose, "phantom_pose": phantom_pose,
        "tooth_pose": tooth_pose, "wrench_s": wrench_s, "wrench_h": wrench_h,
        "f_d": [0.0, 0.0, fz_n, 0.0, 0.0, 0.0], "fz_star_n": fz_star_n, "fz_n": fz_n,
        "file_torque_mnm": file_torque_mnm, "motor_current_a": motor_current_a,
        "motor_rpm": motor_rpm, "depth_mm": depth_mm, "true_depth_mm": true_depth_mm,
        "working_length_mm": working_length_mm, "completeness": completeness,
        "patient_moved": patient_moved, "reversals": reversals, "fractured": fractured,
        "events": events, "lateness_us": lateness_us, "compute_us": compute_us,
        "overrun": overrun,
    }


#: A block's columns per tick: (name, width). ``tool_pose`` is the tip (mm) and the tool's
#: mobile XYZ Euler angles (deg); ``phantom_xyz`` the phantom's origin in {0} (mm).
COLUMNS: tuple[tuple[str, int], ...] = (
    ("q_deg", 6), ("qdot_cmd_deg_s", 6), ("tool_pose", 6), ("phantom_xyz", 3),
    ("wrench_s", 6), ("wrench_h", 6), ("fz_n", 1), ("fz_star_n", 1), ("file_torque_mnm", 1),
    ("motor_current_a", 1), ("motor_rpm", 1), ("depth_mm", 1), ("true_depth_mm", 1),
    ("completeness", 1), ("compute_us", 1),
)
#: each column's first index in a block's row
COL: dict[str, int] = {}
_WIDTHS = dict(COLUMNS)
WIDTH = 0
for _name, _width in COLUMNS:
    COL[_name], WIDTH = WIDTH, WIDTH + _width
del _name, _width

_Q, _QD, _TOOL, _PH = COL["q_deg"], COL["qdot_cmd_deg_s"], COL["tool_pose"], COL["phantom_xyz"]
_WS, _WH = COL["wrench_s"], COL["wrench_h"]
_FZ, _STAR, _TAU, _CUR, _RPM, _DEPTH, _TRUE, _DONE, _US = (COL[name] for name in (
    "fz_n", "fz_star_n", "file_torque_mnm", "motor_current_a", "motor_rpm", "depth_mm",
    "true_depth_mm", "completeness", "compute_us"))
#: a row's fields that a block's columns fill whole (the rest: t, tick, phantom_pose's
#: position, f_d's fz, and what the block's rows share)
_FILLED = ("q_deg", "qdot_cmd_deg_s", "tool_pose", "wrench_s", "wrench_h", "fz_star_n",
           "fz_n", "file_torque_mnm", "motor_current_a", "motor_rpm", "depth_mm",
           "true_depth_mm", "completeness", "compute_us")


class _TickTemplate:
    """A block's ``/tick`` template and where its columns go: ``buf[:, slots] =
    cols[:, cols]``."""

    __slots__ = ("cols", "enc", "slots", "t", "tick")

    def __init__(self, row: dict[str, Any]) -> None:
        self.enc = enc = BlockEncoder(TICK_FIELDS, row)
        pairs = [(enc.slot("phantom_pose", i), COL["phantom_xyz"] + i) for i in range(3)]
        pairs.append((enc.slot("f_d", 2), COL["fz_n"]))
        for name in _FILLED:
            pairs += [(enc.slot(name, i), COL[name] + i) for i in range(_WIDTHS[name])]
        self.slots = np.array([s for s, _ in pairs], dtype=np.intp)
        self.cols = np.array([c for _, c in pairs], dtype=np.intp)
        self.t, self.tick = enc.slot("t"), enc.slot("tick")


#: /tick message templates by what a block's rows share (a few per run)
_TEMPLATES: dict[tuple, _TickTemplate] = {}

#: A block's wire form (:meth:`TickBlock.packed`): this tag, then the header (first tick,
#: ticks, columns, period, working length, reversals, the phantom's three angles, the
#: step's and the state's UTF-8 lengths), the two names, and the columns' float64 values,
#: little-endian. A pickle starts with 0x80, never with the tag.
WIRE_TAG = b"B"
_WIRE_HEAD = struct.Struct("<qIIddq3dHH")
#: where the first tick (int64) and the number of ticks (uint32) lie in the wire form
WIRE_K0_AT, WIRE_N_AT = len(WIRE_TAG), len(WIRE_TAG) + 8


@dataclass(slots=True)
class TickBlock:
    """The rows of ticks ``k0``, ``k0 + 1``, ... of one state of a lock-step run on the built-in
    simulator, with no event among them: ``cols[i]`` holds tick ``k0 + i``'s numbers
    (:data:`COLUMNS`), the rest is what they share."""

    cols: np.ndarray
    k0: int
    ts: float
    step: str
    state: str
    working_length_mm: float
    reversals: int
    #: the phantom's orientation (mobile XYZ Euler, deg) beside ``phantom_xyz``
    phantom_euler: tuple[float, float, float]

    def __len__(self) -> int:
        return self.cols.shape[0]

    @property
    def ticks(self) -> range:
        return range(self.k0, self.k0 + self.cols.shape[0])

    def rows(self, start: int = 0, stop: int | None = None) -> list[dict[str, Any]]:
        """Rows ``start`` to ``stop`` as dicts, each as the control task builds it."""
        out = []
        k, ts, step, state = self.k0 + start, self.ts, self.step, self.state
        wl, rev, euler = self.working_length_mm, self.reversals, list(self.phantom_euler)
        for r in self.cols[start:stop].tolist():
            out.append(tick_row(
                k * ts, k, step, state, r[_Q:_Q + 6], r[_QD:_QD + 6], r[_TOOL:_TOOL + 6],
                [*r[_PH:_PH + 3], *euler], None, r[_WS:_WS + 6], r[_WH:_WH + 6], r[_FZ],
                r[_STAR], r[_TAU], r[_CUR], r[_RPM], r[_DEPTH], r[_TRUE], wl, r[_DONE],
                False, rev, False, [], 0.0, r[_US], False))
            k += 1
        return out

    def scene_row(self, i: int) -> dict[str, Any]:
        """Row ``i``'s fields a 3D scene is drawn from (``t``, ``tick``, ``wrench_h``,
        ``phantom_pose``), as :meth:`rows` gives them, without the others."""
        k, r = self.k0 + i, self.cols[i]
        return {"t": k * self.ts, "tick": k, "wrench_h": r[_WH:_WH + 6].tolist(),
                "phantom_pose": [*r[_PH:_PH + 3].tolist(), *self.phantom_euler]}

    def tick_cdr(self, start: int = 0, stop: int | None = None) -> list[bytes]:
        """The ``/tick`` messages (CDR) of rows ``start`` to ``stop``: the bytes of
        ``Codec(TICK_FIELDS).encode(row)`` for each row of :meth:`rows`, written by copying
        the block's columns into a template of the rows' shared values."""
        if len(self.cols[start:stop]) == 0:
            return []
        buf, enc = self.tick_words(start, stop)
        return enc.messages(buf)

    def tick_words(self, start: int = 0, stop: int | None = None) -> tuple[np.ndarray, Any]:
        """:meth:`tick_cdr`'s messages as the rows of a float64 buffer, with their
        :class:`~dentibot.telemetry.cdr.BlockEncoder` (its ``size``, and ``messages`` to cut
        them out): each message 4 bytes into its row."""
        cols = self.cols[start:stop]
        n = cols.shape[0]
        key = (self.step, self.state, self.working_length_mm, self.reversals,
               self.phantom_euler)
        tpl = _TEMPLATES.get(key)
        if tpl is None:
            if len(_TEMPLATES) > 64:
                _TEMPLATES.clear()
            tpl = _TEMPLATES[key] = _TickTemplate(self.rows(start, start + 1)[0])
        ticks = np.arange(self.k0 + start, self.k0 + start + n, dtype=np.int64)
        buf = tpl.enc.buffer(n)
        buf[:, tpl.slots] = cols[:, tpl.cols]
        buf[:, tpl.t] = ticks * self.ts                  # t = k ts, as the rows compute it
        buf.view(np.int64)[:, tpl.tick] = ticks
        return buf, tpl.enc

    def packed(self) -> list:
        """The block's wire form: a list of buffers to write one after the other (no copy
        of the columns), read back by :meth:`unpack`; about 1 us against 20-50 us for a
        pickle of the block."""
        step, state = self.step.encode(), self.state.encode()
        cols = np.ascontiguousarray(self.cols, dtype="<f8")
        head = WIRE_TAG + _WIRE_HEAD.pack(
            self.k0, cols.shape[0], cols.shape[1], self.ts, self.working_length_mm,
            self.reversals, *self.phantom_euler, len(step), len(state)) + step + state
        return [head, memoryview(cols).cast("B")]

    @classmethod
    def unpack(cls, data: bytes | bytearray | memoryview) -> TickBlock:
        """The block of :meth:`packed`'s buffers, joined (its columns a copy, writable)."""
        if bytes(data[:1]) != WIRE_TAG:
            raise ValueError("not a packed tick block")
        (k0, n, width, ts, wl, rev, e0, e1, e2, n_step, n_state) = _WIRE_HEAD.unpack_from(
            data, 1)
        at = 1 + _WIRE_HEAD.size
        step = bytes(data[at:at + n_step]).decode()
        state = bytes(data[at + n_step:at + n_step + n_state]).decode()
        at += n_step + n_state
        if len(data) - at != 8 * n * width:
            raise ValueError(f"a packed tick block of {n} x {width} values has "
                             f"{len(data) - at} bytes of them")
        cols = np.frombuffer(data, dtype="<f8", count=n * width, offset=at).reshape(n, width)
        return cls(cols.astype(np.float64), k0, ts, step, state, wl, rev, (e0, e1, e2))

    def part(self, start: int, stop: int) -> TickBlock:
        """Ticks ``start`` to ``stop`` of the block, as a block."""
        return TickBlock(self.cols[start:stop], self.k0 + start, self.ts, self.step, self.state,
                         self.working_length_mm, self.reversals, self.phantom_euler)

    def row(self, i: int) -> dict[str, Any]:
        """Row ``i`` (negative: from the end) as a dict."""
        i = range(len(self))[i]
        return self.rows(i, i + 1)[0]
