"""The main job on the arm fitted to the thesis bench (16 ms of dead time, a 6.3 ms filter,
0.80 of the command realised): deep in the canal the file's short free part is stiff
sideways, and through that delay the lateral admittance rings at 12 Hz until the
patient-moved fault. With the lateral damping raised as the cantilever stiffens
(``control.lateral_free_ref_mm``, LATERAL_FREE_REF_MM) the same job reaches the working
length."""

from __future__ import annotations

from pathlib import Path

import pytest

from dentibot.app.runner import ProtocolRunner
from dentibot.control.admittance import LATERAL_FREE_REF_MM
from dentibot.protocol.loader import parse_protocol

MAIN_JOB = Path(__file__).resolve().parents[2] / "protocols" / "root-canal.yaml"


def _run(extra: str):
    p = parse_protocol(MAIN_JOB.read_text() + extra)
    return ProtocolRunner(p, no_record=True)


@pytest.mark.timeout(300)
async def test_the_main_job_on_the_bench_arm_reaches_the_working_length():
    done = (await _run("simulator: {arm: bench}\n"
                       f"control: {{lateral_free_ref_mm: {LATERAL_FREE_REF_MM}}}\n").run()
            ).summary
    assert done.status == "ok", done.reason
    assert done.depth_reached_mm >= 16.0 and done.completeness > 0.98
    assert done.peak_force_N < 1.5                      # under the patient-moved trigger


@pytest.mark.timeout(300)
async def test_without_the_lateral_schedule_the_bench_arm_rings_to_a_fault():
    done = (await _run("simulator: {arm: bench}\n").run()).summary     # the default: off
    assert done.status == "fault" and "patient-moved" in done.reason
    assert done.depth_reached_mm < 15.0 and done.peak_force_N >= 1.5


@pytest.mark.slow
@pytest.mark.timeout(600)
async def test_the_compiled_ticks_scale_the_lateral_gain_as_the_control_task_does(monkeypatch):
    """The same run, its drilling ticks compiled or the control task's one by one: the same
    summary to the last bit, the schedule in force (the file deeper than 7 mm)."""
    import dentibot.app.drill_loop as dl

    ran = []
    call = dl.DrillLoop.__call__

    async def counted(self, rt):
        n = await call(self, rt)
        ran.append(n)
        return n

    monkeypatch.setattr(dl.DrillLoop, "__call__", counted)
    extra = (f"simulator: {{arm: bench}}\ncontrol: {{lateral_free_ref_mm: "
             f"{LATERAL_FREE_REF_MM}}}\n")
    p = parse_protocol(MAIN_JOB.read_text() + extra)
    fast = (await ProtocolRunner(p, no_record=True, compiled_ticks=True).run()).summary
    compiled = sum(ran)
    slow = (await ProtocolRunner(p, no_record=True, compiled_ticks=False).run()).summary
    assert sum(ran) == compiled and compiled > 10_000
    assert fast == slow
    assert fast.depth_reached_mm > 7.0 + 9.0        # past where the scale starts, and more
