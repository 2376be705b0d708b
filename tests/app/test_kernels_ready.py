"""The compiled kernels are ready once their modules are imported: a procedure (drilling in a
canal, with self-alignment and the limiter) compiles nothing more while it runs, so a live
control loop never stalls on a compilation at its first tick."""

from __future__ import annotations

import logging

import structlog

from dentibot.app.procedure import Procedure
from dentibot.control import filebeam, joint_rate_kernels, kinematics_kernels
from dentibot.sim import canal_walls
from dentibot.sim.world import WorldConfig


def _signatures() -> dict[str, int]:
    out = {}
    for mod in (kinematics_kernels, joint_rate_kernels, filebeam, canal_walls):
        for name, obj in vars(mod).items():
            if hasattr(obj, "signatures") and obj.__module__ == mod.__name__:
                out[f"{mod.__name__}.{name}"] = len(obj.signatures)
    return out


async def test_a_procedure_compiles_nothing_after_import():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.CRITICAL))
    before = _signatures()
    # every public kernel has its signature from the import on
    assert {k for k, n in before.items() if n == 0 and not k.split(".")[-1].startswith("_")} \
        == set(), before
    proc = Procedure.simulated(WorldConfig(seed=1), keep_rows=True)
    async with proc:
        assert await proc.command("drill") is None
        await proc.run_for(ticks=60_000, until=lambda r: r.last_row is not None
                           and r.last_row["true_depth_mm"] > 3.0)
        assert proc.runtime.state.startswith("treating.drilling")
    assert max(r["true_depth_mm"] for r in proc.rows) > 3.0     # the file in the canal
    assert _signatures() == before
