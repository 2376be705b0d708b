"""DentiBot's pytest plugin: simulated procedures for your own (pytest-asyncio) tests.

Installed with DentiBot (entry point ``pytest11``), so in any project that has DentiBot
installed, tests can ask for:

- ``dentibot_sim``: a factory ``dentibot_sim(world=None, config=None, *, calibrated=True)``
  that builds the built-in simulator under a runtime in lock-step time
  (:class:`~dentibot.app.simulated.SimHarness`). Every telemetry row goes to the returned
  :class:`SimProcedure`'s ``rows``. Without ``config`` the runtime's plan agrees with the
  world (orifice gap, working length, tool geometry), so depth 0 is the canal orifice::

      async def test_drills_to_working_length(dentibot_sim):
          proc = dentibot_sim(WorldConfig(seed=3))
          assert await proc.runtime.command("drill") is None
          await proc.run_until(lambda rt: rt.state in ("done", "fault"), seconds=120)
          assert proc.runtime.state == "done"

- ``dentibot_wire``: the four wire simulators (Meca500 TCP, Net F/T UDP, EPOS4 over
  socketcand, aux Modbus TCP) on free ports of 127.0.0.1 in real time, over one simulated
  world; ``dentibot_wire.devices_config()`` is what the drivers connect to
  (:func:`dentibot.io.devices.open_devices`). Stopped at the end of the test.

Worlds are :class:`WorldConfig` (re-exported here); runtime configurations are
:class:`~dentibot.runtime.config.RuntimeConfig`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import pytest

from dentibot.app.simulated import SimHarness, World, WorldConfig
from dentibot.runtime.config import RuntimeConfig

__all__ = ["SimProcedure", "WorldConfig", "dentibot_sim", "dentibot_wire", "simulated_procedure"]


@dataclass
class SimProcedure:
    """A simulated procedure ready to run: ``harness`` (world, devices, clock, runtime) and the
    telemetry ``rows`` it produced so far."""

    harness: SimHarness
    rows: list[dict] = field(default_factory=list)

    @property
    def runtime(self):
        return self.harness.runtime

    @property
    def world(self) -> World:
        return self.harness.world

    async def run_for(self, seconds: float) -> None:
        """Run ``seconds`` of simulated time (lock step: as fast as the machine allows)."""
        rt = self.runtime
        await rt.run(max_ticks=max(1, round(seconds / rt.ts)))

    async def run_until(self, until: Callable, seconds: float) -> bool:
        """Run until ``until(runtime)`` holds, at most ``seconds`` of simulated time; returns
        whether it held."""
        rt = self.runtime
        await rt.run(until=until, max_ticks=max(1, round(seconds / rt.ts)))
        return bool(until(rt))


def simulated_procedure(world: World | WorldConfig | None = None,
                        config: RuntimeConfig | None = None, *,
                        calibrated: bool = True) -> SimProcedure:
    """A simulated procedure in lock-step time (what ``dentibot_sim`` builds), for helpers
    outside a fixture."""
    rows: list[dict] = []
    return SimProcedure(SimHarness(world, config, calibrated=calibrated, sink=rows.append), rows)


@pytest.fixture
def dentibot_sim():
    """Factory of simulated procedures in lock-step time (see the module docstring)."""

    return simulated_procedure


@pytest.fixture
async def dentibot_wire():
    """The wire simulators on free loopback ports, over one world (seed 0), in real time."""
    from dentibot.app.simulated import serve_wire

    async with serve_wire(WorldConfig(seed=0)) as bot:
        yield bot
