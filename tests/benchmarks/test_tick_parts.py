"""The real-time benchmark's instrument of the tick's parts (``benchmarks/tick_parts.py``):
what it times, the hot replay, and that it leaves the runtime as it found it. No speed is
asserted (speed belongs in benchmarks/)."""

from __future__ import annotations

import pytest

from dentibot.control import tick_kernels
from dentibot.runtime import control_task
from dentibot.runtime import supervisor_kernels as sk
from dentibot.testing import simulated_procedure


@pytest.fixture
def tick_parts(bench_module):
    return bench_module("tick_parts")


async def test_every_tick_is_timed_and_the_runtime_is_given_back(tick_parts):
    originals = (control_task.Runtime.tick, control_task.arm_command, tick_kernels.sense,
                 sk.inputs, sk.estimate_checks)
    proc = simulated_procedure()
    try:
        with tick_parts.timed_parts() as state:
            await proc.run_for(ticks=40)
        figures = tick_parts.figures(state, skip=0)
    finally:
        await proc.stop()
    assert (control_task.Runtime.tick, control_task.arm_command, tick_kernels.sense,
            sk.inputs, sk.estimate_checks) == originals
    assert figures["whole tick"]["n"] == proc.runtime.ticks == 40
    for label in ("devices.read", "supervisor.check_inputs", "estimate", "arm command",
                  "telemetry row", "estimate's compiled call", "input checks' compiled call"):
        assert figures[label]["n"] == 40, label
    for label in ("estimate's compiled call", "input checks' compiled call"):
        f = figures[label]
        assert f["hot_p50_us"] > 0.0
        assert f["in_place_over_hot"] == pytest.approx(f["p50_us"] / f["hot_p50_us"])
    # a part inside another costs less than the tick that holds it
    assert figures["estimate's compiled call"]["mean_us"] < figures["whole tick"]["mean_us"]
