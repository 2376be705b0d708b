"""Helpers for the telemetry tests: rows and an in-memory stream with controllable I/O."""

from __future__ import annotations

import io
import threading

from dentibot.telemetry import default_row


def ramp_row(i: int, rate_hz: float = 500.0, **over) -> dict:
    """A valid row for tick ``i`` with values that differ from tick to tick."""
    t = i / rate_hz
    row = default_row(
        t=t, tick=i, step="approach" if i < 100 else "drilling",
        state="treating.drilling.feeding" if i % 50 < 25 else "treating.drilling.pausing",
        q_deg=[0.5 * i, 1.0, -2.0, 0.25, 90.0, -0.125],
        tool_pose=[190.0, 0.0, 308.0 - 0.01 * i, 0.0, 90.0, 0.0],
        phantom_pose=[200.0, 0.0, 100.0 + 0.001 * i, 0.0, 0.0, 0.0],
        wrench_h=[0.0, 0.0, -1.0 - 0.001 * i, 0.0, 0.0, 0.0],
        file_torque_mnm=0.25 * (i % 160), motor_rpm=300.0, fz_n=1.0, fz_star_n=0.75,
        depth_mm=0.01 * i, working_length_mm=20.0, completeness=i / 10000.0,
        reversals=i // 1000, events=["TargetReached"] if i % 1000 == 999 else [],
        lateness_us=float(i % 97), compute_us=120.0, overrun=(i % 1000 == 500))
    row.update(over)
    return row


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
