"""Every device stops on its own when the controller dies or freezes.

The wire simulators (:class:`~dentibot.sim.serve.VirtualDentiBot`) run in this process over one
World; the controller runs in a child process (``dentibot run PROTOCOL --devices FILE``, the
product's own command, or a small driver script). The child is killed (SIGKILL) or frozen
(SIGSTOP) while the file turns at 60 rpm, and the handpiece speed is sampled here, at every
World step, in the simulator's process: how long the file turns after the signal.

Bounds are derived from the configured times and the simulated physics, never from what a
run printed:

- the drive's heartbeat consumer expires at most ``consumer_ms`` after the host's last beat,
  which came before the signal;
- its fault reaction ramps the speed down at the quick-stop deceleration the driver wrote:
  60 rpm / (rpm/s) seconds;
- the World's handpiece follows through its first-order speed loop: from at most 60 rpm to
  below 1 rpm takes at most ``tau ln 60`` after the ramp ended (41 ms for tau = 10 ms);
- scheduling on a shared, loaded machine: the World's 2 ms step, the 1 ms ramp update, the
  stepper's 1 ms sleep and the simulator loop's own latency (up to about 12 ms: heartbeat
  gaps of 17 ms at a 5 ms period were measured at the node): :data:`SCHEDULING_S`.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
import os
import signal
import sys
import time
from pathlib import Path

import pytest
import structlog

from dentibot.io.canopen_protocol import HEARTBEAT_ERROR_CODE, State
from dentibot.io.devices import devices_yaml
from dentibot.io.epos4 import DEFAULT_CONSUMER_MS, DEFAULT_QUICK_STOP_FILE_RPM_S
from dentibot.sim.serve import ServePorts, VirtualDentiBot
from dentibot.sim.world import WorldConfig

ROOT = Path(__file__).resolve().parents[2]
RPM = 60.0                       # thesis 5.3: the drilling speed
STOPPED_RPM = 1.0                # "the file stops": below 1 rpm
SCHEDULING_S = 0.015
#: The requirement: a dead or frozen host's file is still within 100 ms.
REQUIRED_S = 0.100

PROTOCOL = f"""name: liveness
seed: 1
limits: {{stale_periods: {{arm: 50, ft: 50, motor: 50, aux: 200}}}}
steps:
  - calibrate_load: {{}}
  - drill: {{rpm: {RPM:g}, rounds: [{{duration_s: 60}}]}}
"""

pytestmark = pytest.mark.timeout(60)


@pytest.fixture(autouse=True)
def _quiet():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))


def settle_s(world) -> float:
    """The World's speed loop from RPM to below STOPPED_RPM: tau ln(RPM / STOPPED_RPM)."""
    return world.config.handpiece.tau_s * math.log(RPM / STOPPED_RPM)


def heartbeat_bound_s(world) -> float:
    """The drive's own supervision: consumer time + quick-stop ramp + speed loop + slack."""
    return (DEFAULT_CONSUMER_MS / 1000.0 + RPM / DEFAULT_QUICK_STOP_FILE_RPM_S
            + settle_s(world) + SCHEDULING_S)


class SpeedLog:
    """(monotonic time, file speed rpm) at every World step, recorded in this process. A
    step run late by a stalled loop is stamped late: the measured time can only grow."""

    def __init__(self, world) -> None:
        self.world = world
        self.samples: list[tuple[float, float]] = []
        self._step = world.step
        world.step = self._record            # the stepper calls world.step()

    def _record(self) -> None:
        self._step()
        self.samples.append((time.monotonic(), self.world.handpiece.omega_rpm))

    def turning_since(self) -> float | None:
        """Since when the file has turned steadily at RPM (None if it does not now)."""
        since = None
        for t, rpm in reversed(self.samples):
            if abs(rpm - RPM) > 0.5:
                break
            since = t
        return since

    def stopped_after(self, t0: float) -> float | None:
        """Seconds from ``t0`` to the first step after it with the file below STOPPED_RPM."""
        return next((t - t0 for t, rpm in self.samples if t > t0 and abs(rpm) < STOPPED_RPM),
                    None)

    def restore(self) -> None:
        self.world.step = self._step


@contextlib.asynccontextmanager
async def simulators(tmp_path: Path):
    """The wire simulators on free loopback ports, their device file, a speed log; the
    garbage collector off meanwhile (a full collection of pytest's heap stalls the loop)."""
    ports = ServePorts(meca_port=0, netft_port=0, netft_http_port=0, modbus_port=0,
                       can_port=0)
    gc_was = gc.isenabled()
    gc.disable()
    try:
        async with VirtualDentiBot(WorldConfig(seed=1), ports) as bot:
            devices = tmp_path / "devices.yaml"
            devices.write_text(devices_yaml(bot.devices_config()), encoding="utf-8")
            log = SpeedLog(bot.world)
            try:
                yield bot, devices, log
            finally:
                log.restore()
    finally:
        if gc_was:
            gc.enable()


#: The controller child runs at a lower priority than the simulators: simulated devices stand
#: for hardware, which never stalls; on a loaded 2-core machine a simulator starved by the
#: child's start-up lets the F/T stream go stale (the driver's 20 ms limit) and the run ends
#: before it drills.
CHILD_NICE = 3


async def start_child(args: list[str], tmp_path: Path) -> tuple[asyncio.subprocess.Process,
                                                               Path]:
    err = tmp_path / "child-stderr.txt"
    with err.open("wb") as f:
        proc = await asyncio.create_subprocess_exec(
            "nice", "-n", str(CHILD_NICE), sys.executable, *args, cwd=ROOT,
            stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.DEVNULL, stderr=f)
    return proc, err


class EndedEarly(AssertionError):
    """The controller ended before the file turned."""


async def until_turning(proc, log: SpeedLog, err: Path, timeout_s: float = 40.0,
                        steady_s: float = 0.3) -> None:
    """Wait until the file has turned at RPM for ``steady_s`` (the child is mid-drilling)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.returncode is not None:
            raise EndedEarly(f"the controller ended ({proc.returncode}) before the file "
                             f"turned: {err.read_text()[-3000:]}")
        since = log.turning_since()
        if since is not None and time.monotonic() - since >= steady_s:
            return
        await asyncio.sleep(0.01)
    raise AssertionError(f"the file never turned steadily at {RPM} rpm: "
                         f"{err.read_text()[-3000:]}")


async def signal_and_measure(proc, sig: int, log: SpeedLog, watch_s: float = 0.5) -> float:
    t_sig = time.monotonic()
    os.kill(proc.pid, sig)
    await asyncio.sleep(watch_s)
    stopped = log.stopped_after(t_sig)
    assert stopped is not None, f"the file still turns {watch_s} s after signal {sig}"
    return stopped


async def end_child(proc) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(proc.pid, signal.SIGCONT)
        os.kill(proc.pid, signal.SIGKILL)
    await proc.wait()


#: Attempts at reaching the drilling state, and no new one after START_BUDGET_S. On a loaded
#: 2-core machine the controller's F/T driver (20 ms freshness) occasionally finds the
#: loopback stream late during the load calibration and the run ends with that fault before
#: it drills (a start-up takes about 8 s); the measurement itself is never repeated: the first
#: attempt that drilled is the one measured.
ATTEMPTS = 3
START_BUDGET_S = 12.0


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSTOP], ids=["kill-9", "sigstop"])
async def test_the_drive_stops_the_file_when_the_controller_dies_or_freezes(tmp_path, sig):
    protocol = tmp_path / "drill.yaml"
    protocol.write_text(PROTOCOL, encoding="utf-8")
    t0 = time.monotonic()
    for attempt in range(1, ATTEMPTS + 1):
        async with simulators(tmp_path) as (bot, devices, log):
            proc, err = await start_child(
                ["-m", "dentibot.cli", "run", str(protocol), "--devices", str(devices),
                 "--quiet", "--json", "--out", str(tmp_path / f"run{attempt}.mcap")],
                tmp_path)
            try:
                try:
                    await until_turning(proc, log, err)
                except EndedEarly:
                    if attempt == ATTEMPTS or time.monotonic() - t0 > START_BUDGET_S:
                        raise
                    continue
                node = bot.epos
                assert node.consumer == (127, DEFAULT_CONSUMER_MS / 1000)   # set by connect
                stopped = await signal_and_measure(proc, sig, log)
                bound = heartbeat_bound_s(bot.world)
                print(f"\nsignal {sig.name}: the file turned {stopped * 1e3:.1f} ms "
                      f"(bound {bound * 1e3:.1f} ms)")
                assert stopped <= bound <= REQUIRED_S
                # it was the drive's own heartbeat supervision, not the aux watchdog (200 ms)
                assert node.heartbeat_errors == 1 and node.error_code == HEARTBEAT_ERROR_CODE
                assert node.state is State.FAULT
                # the arm is at rest too (its velocity timeout, 50 ms at most)
                assert max(abs(v) for v in bot.world.arm.qdot) < 1e-3
                return
            finally:
                await end_child(proc)


AUX_CHILD = """
import asyncio, logging, sys
import structlog
structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
from dentibot.io.aux_modbus import AuxModbusDriver
from dentibot.io.epos4 import Epos4Driver

async def main(modbus_port, can_port, watchdog_ms):
    aux = AuxModbusDriver("127.0.0.1", modbus_port, watchdog_ms=watchdog_ms)
    motor = Epos4Driver(interface="socketcand", port=can_port, channel="vcan0",
                        consumer_ms=0, stale_after_s=0.5, answer_timeout_s=0.5)
    await aux.connect()
    await motor.connect()
    await motor.set_velocity(60.0)
    while True:                               # a control loop: read both every tick
        await aux.read()
        if motor.received:
            await motor.read()
        await asyncio.sleep(0.002)

asyncio.run(main(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])))
"""


async def test_the_aux_watchdog_cuts_the_handpiece_even_without_the_drives_heartbeat(tmp_path):
    """The drive's heartbeat consumer is off (``consumer_ms=0``): the aux I/O's host watchdog
    opens the drive's STO when the controller dies, in ``dentibot sim serve``'s wiring."""
    watchdog_ms = 100
    async with simulators(tmp_path) as (bot, _devices, log):
        p = bot.ports
        proc, err = await start_child(["-c", AUX_CHILD, str(p["modbus_port"]),
                                       str(p["can_port"]), str(watchdog_ms)], tmp_path)
        try:
            await until_turning(proc, log, err, timeout_s=20.0)
            assert bot.epos.consumer is None and bot.modbus.watchdog_ms == watchdog_ms
            stopped = await signal_and_measure(proc, signal.SIGKILL, log)
            # the last feed came before the kill: expiry within the watchdog time, found by
            # the PLC's 10 ms scan; STO takes the power stage at once (no ramp), then the
            # speed loop
            bound = watchdog_ms / 1000 + 0.010 + settle_s(bot.world) + SCHEDULING_S
            print(f"\naux watchdog: the file turned {stopped * 1e3:.1f} ms "
                  f"(bound {bound * 1e3:.1f} ms)")
            assert stopped <= bound
            assert bot.modbus.host_lost and bot.epos.error_code == 0x8A88   # STO error
            assert bot.epos.heartbeat_errors == 0
        finally:
            await end_child(proc)
