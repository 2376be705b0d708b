"""Helpers for the simulator tests: drive the file tip kinematically along {H}.

(A module of its own, not the conftest: ``from conftest import`` finds whichever
conftest was imported first when several test folders run together.)"""

from __future__ import annotations

import numpy as np

from dentibot.sim import World


def drive(world: World, v_h_mm_s, seconds: float, every: int = 5, until=None) -> None:
    """Move the file tip at ``v_h`` (mm/s in {H}) for ``seconds`` with MoveJointsVel,
    recomputing the joint rates through the tool Jacobian every ``every`` steps."""
    n = round(seconds / world.ts)
    for k in range(n):
        if k % every == 0:
            world.arm.command_velocity(world.tool_rates(v_h_mm_s), world.t)
        world.step()
        if until is not None and until(world):
            break
    world.arm.stop()


def depth(world: World) -> float:
    """Tip depth along the canal axis (mm), computed here from the public geometry."""
    o, t0 = world.canal_axis_0()
    return float(np.dot(np.subtract(world.tip_0, o), t0))
