"""DentiBot's pytest plugin: simulated procedures for your own (pytest-asyncio) tests.

Installed with DentiBot (entry point ``pytest11``), so in any project that has DentiBot
installed, tests can ask for:

- ``dentibot_sim``: a factory ``dentibot_sim(world=None, config=None, *, calibrated=True)``
  that builds the built-in simulator under a runtime in lock-step time: a
  :class:`~dentibot.app.procedure.Procedure` driven by the test (time passes only while the
  test waits: ``run_for``), with every telemetry row in its ``rows``. Without ``config`` the
  runtime's plan agrees with the world (orifice gap, working length, tool geometry), so depth 0
  is the canal orifice. Commands go through ``command`` (between two ticks, as every
  operator's); the procedures are stopped at the end of the test::

      async def test_drills_to_working_length(dentibot_sim):
          proc = dentibot_sim(WorldConfig(seed=3))
          assert await proc.command("drill") is None
          await proc.run_for(120.0, until=lambda rt: rt.state in ("done", "fault"))
          assert proc.runtime.state == "done"

- ``dentibot_wire``: the four wire simulators (Meca500 TCP, Net F/T UDP, EPOS4 over
  socketcand, aux Modbus TCP) on free ports of 127.0.0.1 in real time, over one simulated
  world; ``dentibot_wire.devices_config()`` is what the drivers connect to
  (:func:`dentibot.io.devices.open_devices`). Stopped at the end of the test.

Worlds are :class:`WorldConfig` (re-exported here); runtime configurations are
:class:`~dentibot.runtime.config.RuntimeConfig`.
"""

from __future__ import annotations

import pytest

from dentibot.app.procedure import Procedure
from dentibot.app.simulated import World, WorldConfig
from dentibot.runtime.config import RuntimeConfig

__all__ = ["Procedure", "WorldConfig", "dentibot_sim", "dentibot_wire", "simulated_procedure"]


def simulated_procedure(world: World | WorldConfig | None = None,
                        config: RuntimeConfig | None = None, *,
                        calibrated: bool = True, tracker=None,
                        hybrid: bool = False) -> Procedure:
    """A simulated procedure in lock-step time, driven by its waits, keeping its rows (what
    ``dentibot_sim`` builds), for helpers outside a fixture; ``tracker``: a simulated patient
    tracker's geometry (``dentibot.sim.tracker_device.TrackerSimParams``), depth then in the
    tooth's frame; ``hybrid``: the tracked tooth's motion fed forward too."""
    return Procedure.simulated(world, config, calibrated=calibrated, keep_rows=True,
                               tracker=tracker, hybrid=hybrid)


@pytest.fixture
async def dentibot_sim():
    """Factory of simulated procedures in lock-step time (see the module docstring)."""
    made: list[Procedure] = []

    def make(world=None, config=None, *, calibrated: bool = True, tracker=None,
             hybrid: bool = False) -> Procedure:
        proc = simulated_procedure(world, config, calibrated=calibrated, tracker=tracker,
                                   hybrid=hybrid)
        made.append(proc)
        return proc

    yield make
    for proc in made:
        await proc.stop()


@pytest.fixture
async def dentibot_wire():
    """The wire simulators on free loopback ports, over one world (seed 0), in real time."""
    from dentibot.app.simulated import serve_wire

    async with serve_wire(WorldConfig(seed=0)) as bot:
        yield bot
