"""Helpers for the telemetry tests: rows and an in-memory stream with controllable I/O."""

from __future__ import annotations

import io
import json
import math
import threading

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from dentibot.telemetry import default_row


def ramp_row(i: int, rate_hz: float = 500.0, **over) -> dict:
    """A valid row for tick ``i`` with values that differ from tick to tick; like the
    runtime's rows it carries the simulator's true depth, unknown (None) on every third tick,
    so that round trips go through both ways of storing a nullable field."""
    t = i / rate_hz
    row = default_row(
        t=t, tick=i, step="approach" if i < 100 else "drilling",
        state="treating.drilling.feeding" if i % 50 < 25 else "treating.drilling.pausing",
        q_deg=[0.5 * i, 1.0, -2.0, 0.25, 90.0, -0.125],
        tool_pose=[190.0, 0.0, 308.0 - 0.01 * i, 0.0, 90.0, 0.0],
        phantom_pose=[200.0, 0.0, 100.0 + 0.001 * i, 0.0, 0.0, 0.0],
        wrench_h=[0.0, 0.0, -1.0 - 0.001 * i, 0.0, 0.0, 0.0],
        file_torque_mnm=0.25 * (i % 160), motor_rpm=300.0, fz_n=1.0, fz_star_n=0.75,
        depth_mm=0.01 * i, true_depth_mm=None if i % 3 == 0 else 0.01 * i + 0.002,
        working_length_mm=20.0, completeness=i / 10000.0,
        reversals=i // 1000, events=["TargetReached"] if i % 1000 == 999 else [],
        lateness_us=float(i % 97), compute_us=120.0, overrun=(i % 1000 == 500))
    row.update(over)
    return row


def real_row(i: int, rate_hz: float = 500.0) -> dict:
    """A row as the runtime builds it while drilling (every field, simulator truths included,
    full-precision floats that change every tick): the size and encoding cost of real rows."""
    t = i / rate_hz
    s, c = math.sin(0.7 * t), math.cos(0.3 * t)
    return {
        "t": t, "tick": i, "step": "4:drill", "state": "treating.drilling.feeding",
        "q_deg": [-1.704 + 1e-3 * s, -9.932, 27.766000000000002 + 1e-4 * c, 1.187, 72.658,
                  -2.071 + 1e-3 * s],
        "qdot_cmd_deg_s": [0.3310737190635941 * s, -0.0736990846575737 * c,
                           0.09363530481767193, -0.20300797735194284 * s,
                           -0.07550897371559703, 0.3911142750132231 * c],
        "tool_pose": [101.27237629281589 + s, 0.15245322048725884 * c,
                      107.43665944582354 - 1e-3 * i, -178.8529042640768, -0.4544986455133137 * s,
                      179.99624089151916],
        "phantom_pose": [101.33305712777273, 1.8030844670175292e-14, 122.53395995108038,
                         -180.0, 3.1805546814635168e-15, 180.0],
        "tooth_pose": None,                # no patient tracker
        "wrench_s": [-0.64 * c, 0.36, 0.66 * s, 0.02025, -0.05775, -0.0495 * c],
        "wrench_h": [0.01927773674531727 * s, -0.0051776619832822135 * c,
                     -0.30859435221158016 - 0.01 * s, -0.0005828249870844632,
                     -0.0009920114470123608 * c, -0.027277150427593346],
        "f_d": [0.0, 0.0, 0.3307929187508018 + 0.01 * c, 0.0, 0.0, 0.0],
        "fz_star_n": 0.3307929187508018 + 0.01 * c, "fz_n": 0.3307929187508018 + 0.01 * c,
        "file_torque_mnm": 27.214425201031847 + 3.0 * s, "motor_current_a": 0.04126655810372048 * c,
        "motor_rpm": 59.999999999999986, "depth_mm": 15.084386766995253 + 1e-5 * i,
        "true_depth_mm": 15.096932049155638 + 1e-5 * i, "working_length_mm": 16.0,
        "completeness": 0.958322647101977 * abs(c), "patient_moved": False,
        "reversals": i // 5000, "fractured": False,
        "events": ["working_length_reached"] if i % 5000 == 4999 else [],
        "lateness_us": 0.0, "compute_us": 73.9110000722576 + s, "overrun": False,
    }


class GatedStream(io.BytesIO):
    """A BytesIO whose writes can be held (``hold()``) until ``release()``, or made to fail.

    ``entered`` is set when a write is waiting at the gate: from then on the writer thread is
    provably stuck in I/O.
    """

    def __init__(self) -> None:
        super().__init__()
        self._open = threading.Event()
        self._open.set()
        self.entered = threading.Event()
        self.fail_with: BaseException | None = None

    def hold(self) -> None:
        self._open.clear()

    def release(self) -> None:
        self._open.set()

    def write(self, data) -> int:
        if not self._open.is_set():
            self.entered.set()
            self._open.wait(10.0)
        if self.fail_with is not None:
            raise self.fail_with
        return super().write(data)


def decoded_messages(path, topics=None) -> list[tuple[str, object]]:
    """A recording's messages as a viewer decodes them: (topic, message), JSON channels by
    ``json.loads``, CDR channels (``/tick``) by Foxglove's own ROS 2 codec (an object with
    the fields as attributes, arrays as sequences)."""
    ros2 = DecoderFactory()
    out = []
    with open(path, "rb") as f:
        reader = make_reader(f)
        schemas = reader.get_summary().schemas
        decoders: dict[int, object] = {}
        for _s, c, m in reader.iter_messages(topics=topics):
            if c.message_encoding == "cdr":
                if c.id not in decoders:
                    decoders[c.id] = ros2.decoder_for("cdr", schemas[c.schema_id])
                out.append((c.topic, decoders[c.id](m.data)))
            else:
                out.append((c.topic, json.loads(m.data)))
    return out
