"""The main job on the world fitted to the thesis bench (``world: bench``): an arm with 16 ms
of dead time, a 6.3 ms filter and 0.80 of the command realised, a canal whose walls drag the
file.

Two loops ring through that delay unless the controller is made for it. Sideways: deep in the
canal the file's short free part is stiff, and the lateral admittance rings at 12 Hz until the
patient-moved fault, unless the lateral damping rises as the cantilever stiffens
(``control.lateral_free_ref_mm``, LATERAL_FREE_REF_MM). Along the file: the walls' drag read
at once and answered by Table 4.3's admittance (a 1 ms lag) is a velocity loop of gain about
1 that runs away at about 19 Hz, unless the admittance lags along the file
(``control.axial_lag_ms``, AXIAL_LAG_S). With both (that world's defaults) the job reaches the
working length."""

from __future__ import annotations

from pathlib import Path

import pytest

from dentibot.app.runner import ProtocolRunner
from dentibot.protocol.loader import parse_protocol

MAIN_JOB = Path(__file__).resolve().parents[2] / "protocols" / "root-canal.yaml"


def _run(extra: str):
    p = parse_protocol(MAIN_JOB.read_text() + "world: bench\n" + extra)
    return ProtocolRunner(p, no_record=True)


@pytest.mark.timeout(300)
async def test_the_main_job_on_the_bench_world_reaches_the_working_length():
    done = (await _run("").run()).summary
    assert done.status == "ok", done.reason
    assert done.depth_reached_mm >= 16.0 and done.completeness > 0.98
    assert done.patient_moved_episodes == 0


@pytest.mark.timeout(300)
async def test_without_the_lateral_schedule_the_bench_arm_rings_to_a_fault():
    # the lateral loop alone: the drag-free canal
    done = (await _run("simulator: {canal_drag: none}\n"
                       "control: {lateral_free_ref_mm: 0}\n").run()).summary
    assert done.status == "fault" and "patient-moved" in done.reason
    assert done.depth_reached_mm < 15.0 and done.peak_force_N >= 1.5


@pytest.mark.timeout(300)
async def test_with_table_4_3s_lag_along_the_file_the_dragging_canal_runs_away():
    done = (await _run("control: {axial_lag_ms: null}\n").run()).summary
    assert done.status == "fault"
    assert done.depth_reached_mm < 13.0 and done.peak_force_N >= 1.5


@pytest.mark.slow
@pytest.mark.timeout(600)
async def test_the_compiled_ticks_scale_the_lateral_gain_as_the_control_task_does(monkeypatch):
    """The main job, its drilling ticks compiled or the control task's one by one: the same
    summary to the last bit, the lateral schedule in force (the file deeper than 7 mm) and
    the lag along the file."""
    import dentibot.app.drill_loop as dl

    ran = []
    call = dl.DrillLoop.__call__

    async def counted(self, rt):
        n = await call(self, rt)
        ran.append(n)
        return n

    monkeypatch.setattr(dl.DrillLoop, "__call__", counted)
    p = parse_protocol(MAIN_JOB.read_text() + "world: bench\n")
    fast = (await ProtocolRunner(p, no_record=True, compiled_ticks=True).run()).summary
    compiled = sum(ran)
    slow = (await ProtocolRunner(p, no_record=True, compiled_ticks=False).run()).summary
    assert sum(ran) == compiled and compiled > 10_000
    assert fast == slow
    assert fast.depth_reached_mm > 7.0 + 9.0        # past where the scale starts, and more
