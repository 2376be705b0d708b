"""The Net F/T simulator read by the field's own Python clients, not by our driver:
``pynetft`` (calibration over HTTP, RDT streaming over UDP) and the ``netft`` package
(ATI's raw-counts RDT example as a library). Loopback only, ephemeral ports."""

from __future__ import annotations

import asyncio
import contextlib
from concurrent.futures import ThreadPoolExecutor

import pytest

from dentibot.sim import FTSensorParams, RealTimeStepper, World, WorldConfig
from dentibot.sim.netft_server import NetFTServer

pytestmark = [pytest.mark.wire, pytest.mark.timeout(30)]

CLEAN = {"offset_sigma_n": 0.0, "offset_sigma_nm": 0.0, "noise_n": (0.0, 0.0, 0.0),
         "noise_nm": 0.0, "mass_kg": 0.0}
CPF, CPT = 250_000, 4_000_000              # counts per N and per N*m the box reports
FORCE, TORQUE = (1.25, -2.5, 4.0), (0.125, -0.0625, 0.03125)


async def off_loop(fn):
    """A blocking client call in a thread of its own (joined before returning), off the
    event loop that serves it."""
    with ThreadPoolExecutor(1) as pool:
        return await asyncio.get_running_loop().run_in_executor(pool, fn)


@contextlib.asynccontextmanager
async def box():
    """A massless tool on a clean sensor (it reads exactly the injected load), streamed."""
    world = World(WorldConfig(seed=3, sensor=FTSensorParams(**CLEAN)))
    stop = asyncio.Event()
    stepper = asyncio.create_task(RealTimeStepper(world).run(stop))
    server = NetFTServer(world, port=0, http_port=0, counts_per_force=CPF,
                         counts_per_torque=CPT)
    try:
        await server.start()
        server.inject_offset(FORCE, TORQUE)
        yield server
    finally:
        await server.close()
        stop.set()
        await stepper


async def test_pynetft_reads_calibration_and_wrench_in_si_units():
    pynetft = pytest.importorskip("pynetft")
    async with box() as srv:
        cfg = pynetft.Config(sensor_host="127.0.0.1", rdt_port=srv.port,
                             http_port=srv.http_port, receive_timeout=0.5)

        def read():
            with pynetft.Client(cfg) as client:
                assert client.wait_for_first_sample(5.0)
                sample = client.latest_sample()
                health = client.health()
            return sample, health

        sample, health = await off_loop(read)
    cal = health.sensor_configuration.calibration
    assert (cal.counts_per_force_unit, cal.counts_per_torque_unit) == (CPF, CPT)
    assert cal.force_unit.value == "N" and cal.torque_unit.value == "N-m"
    assert sample.status == 0
    assert sample.force == pytest.approx(FORCE, abs=1 / CPF)
    assert sample.torque == pytest.approx(TORQUE, abs=1 / CPT)
    assert sample.raw_wrench == (round(FORCE[0] * CPF), round(FORCE[1] * CPF),
                                 round(FORCE[2] * CPF), round(TORQUE[0] * CPT),
                                 round(TORQUE[1] * CPT), round(TORQUE[2] * CPT))
    assert health.malformed_count == 0


async def test_the_netft_package_reads_raw_counts():
    NetFT = pytest.importorskip("NetFT")
    async with box() as srv:

        def read():
            sensor = NetFT.Sensor("127.0.0.1")            # talks to the RDT port 49152 ...
            try:
                sensor.sock.connect(("127.0.0.1", srv.port))   # ... here: the ephemeral one
                sensor.sock.settimeout(2.0)
                return sensor.getMeasurement()
            finally:
                sensor.sock.close()

        counts = await off_loop(read)
    assert counts == [round(f * CPF) for f in FORCE] + [round(t * CPT) for t in TORQUE]
