"""The treatment state machine: transitions, refusals with reasons, the latched fault."""

from __future__ import annotations

import pytest

from dentibot.states.modes import MODES
from dentibot.states.treatment import LEAF_STATES, Treatment


def test_every_leaf_state_has_a_mode():
    assert set(MODES) == set(LEAF_STATES)


async def test_drilling_needs_a_load_calibration_and_says_so():
    t = Treatment()
    refusal = await t.fire("drill")
    assert t.state == "idle"
    assert refusal is not None and "calibrat" in refusal.reason and refusal.state == "idle"
    t.gravity_known = True
    assert await t.fire("drill") is None
    assert t.state == "treating.drilling.feeding"


async def test_command_the_state_cannot_take_names_the_states_that_can():
    t = Treatment(gravity_known=True)
    refusal = await t.fire("resume")
    assert refusal.reason == "it needs state treating.paused"
    assert (await t.fire("no_such_command")).reason == "unknown command"


@pytest.mark.parametrize("path, final", [
    (["drill", "reversal_needed", "reversal_finished"], "treating.drilling.feeding"),
    (["drill", "patient_moved"], "treating.patient_moved"),
    (["drill", "reversal_needed", "patient_moved", "patient_released"],
     "treating.drilling.feeding"),
    (["drill", "pause"], "treating.paused"),
    (["drill", "pause", "resume"], "treating.drilling.feeding"),
    (["drill", "working_length_reached", "retracted"], "done"),
    (["drill", "force_limit"], "treating.retracting"),
    (["drag", "align", "drill", "stop"], "idle"),
    (["calibrate_load", "calibration_done"], "idle"),
])
async def test_paths(path, final):
    t = Treatment(gravity_known=True)
    for trigger in path:
        assert await t.fire(trigger) is None, trigger
    assert t.state == final


async def test_passes_repeat_drilling_then_finish():
    t = Treatment(gravity_known=True, passes_left=2)
    await t.fire("drill")
    states = []
    for _ in range(3):
        await t.fire("working_length_reached")
        await t.fire("retracted")
        states.append(t.state)
    assert states == ["treating.drilling.feeding"] * 2 + ["done"]


async def test_fault_is_latched_until_an_allowed_reset():
    t = Treatment(gravity_known=True)
    await t.fire("drill")
    t.estop_active = True
    assert await t.fire("fault", "emergency stop") is None
    assert t.state == "fault"
    # nothing but reset leaves it; more causes accumulate
    for trigger in ("drill", "resume", "patient_released", "calibration_done", "stop"):
        assert (await t.fire(trigger)) is not None
    await t.fire("fault", "stale ft")
    assert t.fault_causes == ["emergency stop", "stale ft"]
    refusal = await t.fire("reset")
    assert t.state == "fault" and "emergency stop released" in refusal.reason
    t.estop_active = False
    assert await t.fire("reset") is None
    assert t.state == "idle" and t.fault_causes == []
