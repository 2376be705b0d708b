"""Self-alignment that aligns: in tilted canals the handpiece turns until the file's axis
follows the canal (the simulator's truth: the tool axis against the canal's axis)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sim_runs import GAP_MM, harness

from dentibot.runtime.config import TreatmentPlan
from dentibot.sim.canal import CanalParams


async def _angles_at(tilt_deg: float, depths_mm, plan=None) -> dict[float, float]:
    """Drill from 2 mm above the orifice of a canal tilted by ``tilt_deg``; the angle (deg)
    between the tool axis and the canal's axis when the tip first passes each depth."""
    h, rows = harness(seed=1, canal=CanalParams(tilt_deg=tilt_deg), plan=plan)
    w = h.world
    _, canal_axis = w.canal_axis_0()
    left = sorted(depths_mm)
    out: dict[float, float] = {}

    def until(r) -> bool:
        d = r.last_row["true_depth_mm"] if r.last_row else -1.0
        while left and d >= left[0]:
            c = abs(float(np.dot(w.axis_0, canal_axis)))
            out[left.pop(0)] = math.degrees(math.acos(min(1.0, c)))
        return not left or r.state in ("done", "fault")

    assert await h.command("drill") is None
    await h.run_for(ticks=20_000, until=until)
    assert not left, f"stopped at {rows[-1]['true_depth_mm']:.2f} mm in {h.runtime.state}"
    return out


@pytest.mark.parametrize("tilt", [10.0, 20.0])
async def test_the_file_axis_follows_a_tilted_canal_within_2_deg_after_3_mm(tilt):
    angles = await _angles_at(tilt, (0.0, 3.0, 6.0))
    assert angles[0.0] == pytest.approx(tilt, abs=0.1)     # entering at the full tilt
    assert angles[3.0] <= 2.0
    assert angles[6.0] <= 1.5


async def test_the_admittance_alone_turns_the_handpiece_far_slower():
    """The thesis's self-alignment (Table 4.3, b4 = b5 = 80) without the orientation loop: the
    couple on the flexible file is a few N*mm, under 1 deg/s of rotation, and the file goes
    3 mm deep still bent through most of the tilt."""
    angles = await _angles_at(10.0, (3.0,), TreatmentPlan(orifice_gap_mm=GAP_MM,
                                                          axis_servo=None))
    assert angles[3.0] > 5.0
