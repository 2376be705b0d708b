"""The public test harness (``dentibot.testing``), used as a user's test would use it: through
the pytest plugin that installing DentiBot registers."""

from __future__ import annotations

import logging

import pytest
import structlog

from dentibot.io.devices import open_devices
from dentibot.testing import WorldConfig

pytestmark = pytest.mark.wire


@pytest.fixture(autouse=True)
def _quiet():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))


def test_the_plugin_is_registered_by_the_installed_package():
    from importlib.metadata import entry_points

    names = {ep.value for ep in entry_points(group="pytest11")}
    assert "dentibot.testing" in names


async def test_default_procedure_measures_depth_from_the_canal_orifice(dentibot_sim):
    """The default world puts the tip 2 mm above the orifice of a 16 mm canal: a default
    procedure must plan with that gap and that length, so that "done" means the true tip
    reached the working length (it reported done at 14 mm when the plan assumed no gap)."""
    proc = dentibot_sim(WorldConfig(seed=3))
    plan = proc.runtime.cfg.plan
    assert plan.orifice_gap_mm == proc.world.config.orifice_gap_mm == 2.0
    assert plan.working_length_mm == 16.0
    rt = proc.runtime
    assert await proc.command("drill") is None
    assert await proc.run_for(200.0, until=lambda r: r.state in ("done", "fault"))
    assert rt.state == "done", rt.treatment.fault_causes
    deepest = max(proc.rows, key=lambda r: r["true_depth_mm"])
    # the canal bottom lies 0.5 mm past the working length (CanalParams.apex_margin_mm)
    assert 15.9 <= deepest["true_depth_mm"] < 16.5
    # the runtime's own depth (kinematics from the orifice) is the true depth
    assert deepest["depth_mm"] == pytest.approx(deepest["true_depth_mm"], abs=0.05)


@pytest.mark.timeout(60)
async def test_wire_simulators_serve_the_real_drivers_on_loopback(dentibot_wire):
    cfg = dentibot_wire.devices_config()
    assert cfg.arm.host == cfg.ft.host == "127.0.0.1"
    async with open_devices(cfg) as d:
        js = await d.arm.read()
        w = await d.ft.read()
    assert len(js.q_deg) == 6
    assert len(w.as_array()) == 6
