"""The runtime over open devices: the drivers of real hardware or of the wire simulators
(``dentibot sim serve``), in real time."""

from __future__ import annotations

from collections.abc import Callable

from dentibot.control.wrench import GravityModel
from dentibot.runtime.clock import Clock, RealTimeClock
from dentibot.runtime.config import RuntimeConfig
from dentibot.runtime.control_task import Devices, Runtime


def hardware_runtime(devices, config: RuntimeConfig, *, clock: Clock | None = None,
                     gravity: GravityModel | None = None,
                     sink: Callable[[dict], None] | None = None) -> Runtime:
    """A runtime over ``devices`` (anything with ``arm``, ``ft``, ``motor`` and ``aux``, e.g.
    what :func:`dentibot.io.devices.open_devices` yields); ``clock`` defaults to real time at
    the configured period. Without ``gravity`` a load calibration must come first."""
    return Runtime(Devices(devices.arm, devices.ft, devices.motor, devices.aux), config,
                   clock or RealTimeClock(config.period_s), gravity=gravity, sink=sink)
