"""Controller-level smoke test: the same small motion against the in-process simulated devices
(lock-step) and against the wire simulators through the real drivers (real time, loopback)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import structlog

from dentibot.app.procedure import Procedure
from dentibot.app.simulated import serve_wire, tool_geometry_of, true_gravity_model
from dentibot.io.devices import open_devices
from dentibot.runtime.config import RuntimeConfig, Thresholds
from dentibot.sim.world import World, WorldConfig

pytestmark = pytest.mark.wire

HAND_N = (1.0, 0.0, 0.0)
SECONDS = 0.6
# Loopback on a shared 2-core machine: tolerate a few late samples before calling a stream stale
LOOSE = Thresholds(stale_periods={"arm": 25, "ft": 25, "motor": 50, "aux": 100})
LOOSE_FT_MS = 50.0          # the F/T driver's own bound as loose as the 25 periods above


def _loose_liveness(cfg):
    """The drive's heartbeat consumer and the aux I/O's host watchdog at 250 ms and 1 s: the
    host and the simulated devices share this process, so a stall of it (a collection on a
    loaded machine) is a stall of the host, which the product's 30 and 200 ms rightly treat
    as a lost host; this test is about the motion (the liveness tests hold those times)."""
    return cfg.model_copy(update={
        "handpiece": cfg.handpiece.model_copy(update={"consumer_ms": 250}),
        "aux": cfg.aux.model_copy(update={"watchdog_ms": 1000})})


@pytest.fixture(autouse=True)
def _quiet():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))


async def _drag(proc: Procedure, world: World) -> tuple[np.ndarray, float]:
    """Drag mode, a 1 N hand push for SECONDS of ticks; returns the tip displacement (mm,
    {0}) and how long the world felt the push (s of its own time: in real time, ticks that
    start late or are skipped make it longer than the ticks' SECONDS)."""
    async with proc:
        assert await proc.command("drag") is None
        await proc.run_for(ticks=5)
        start = np.array(world.tip_0)
        world.hand_force_0 = HAND_N
        t_on = world.t
        await proc.run_for(ticks=round(SECONDS / 0.002))
        world.hand_force_0 = (0.0, 0.0, 0.0)
        pushed_s = world.t - t_on
        await proc.command("stop")
        await proc.run_for(ticks=5)
    return np.array(world.tip_0) - start, pushed_s


@pytest.mark.timeout(60)
async def test_same_motion_in_process_and_over_the_wire():
    h = Procedure.simulated(WorldConfig(seed=21), RuntimeConfig(thresholds=LOOSE))
    local, local_s = await _drag(h, h.world)
    # Table 4.3 dragging: k/b = 18.75 mm/s per N at the grip, for the ticks' SECONDS exactly
    assert local_s == pytest.approx(SECONDS, abs=0.002)
    assert local[0] == pytest.approx(18.75 * SECONDS, rel=0.05)

    world = World(WorldConfig(seed=21))
    async with serve_wire(world) as bot, \
            open_devices(_loose_liveness(bot.devices_config(ft_stale_after_ms=LOOSE_FT_MS))
                         ) as d:
        proc = Procedure.over(d, RuntimeConfig(tool=tool_geometry_of(world), thresholds=LOOSE),
                              gravity=true_gravity_model(world))
        # the looser liveness times reached the devices
        assert bot.modbus.watchdog_ms == 1000 and bot.epos.consumer[1] == 0.25
        wire, wire_s = await _drag(proc, world)
        assert proc.runtime.state == "idle", proc.runtime.treatment.fault_causes
        assert d.ft.lost == 0
    # the same drag speed: the arm keeps the last joint velocities it was sent until the next
    # command, so over the wire the tip moves for as long as the world felt the push, which a
    # busy machine stretches (late and skipped ticks); within the servo lag and the wire's
    # start and stop jitter
    assert SECONDS - 0.01 <= wire_s < 2 * SECONDS, wire_s
    np.testing.assert_allclose(wire, local * (wire_s / local_s), atol=0.08 * abs(local[0]))


async def test_a_real_time_run_ends_its_file_summary_and_rows_at_the_same_tick(tmp_path,
                                                                              monkeypatch):
    """Over the wire the control task ticks on while the recording is finished (off the
    loop, made to take 0.3 s here): the ticks after the end reach neither the file nor the
    summary, and the control task does not die on a closed recorder. The file's rows are
    the summary's ticks, numbered without a gap."""
    import time

    import dentibot.app.runner as runner_mod
    from dentibot.app.runner import ProtocolRunner
    from dentibot.app.selftest_wire import CHILD_STALE_PERIODS as N
    from dentibot.protocol.loader import parse_protocol
    from dentibot.telemetry.reader import read_recording

    real_open = runner_mod.open_recorder

    def slow_closing(*args, **kwargs):
        rec = real_open(*args, **kwargs)
        real_close = rec.close

        def close(*a, **k):
            time.sleep(0.3)                       # 150 periods the control task goes on
            return real_close(*a, **k)

        rec.close = close
        return rec

    monkeypatch.setattr(runner_mod, "open_recorder", slow_closing)
    # seconds of calibration on a shared machine: the wire self-test's stale bounds (its
    # controller's protocol), this test being about the run's end, not about staleness
    protocol = parse_protocol(
        f"name: t\nlimits: {{stale_periods: {{arm: {N}, ft: {N}, motor: {N}, aux: 200}}}}\n"
        "steps:\n  - calibrate_load: {}\n  - drag: {duration_s: 0.2}\n")
    path = tmp_path / "run.mcap"
    async with serve_wire(World(WorldConfig(seed=3))) as bot:
        cfg = _loose_liveness(bot.devices_config(ft_stale_after_ms=N * 2.0))
        runner = ProtocolRunner(protocol, devices=cfg, recording=path)
        res = await runner.run()
    assert res.summary.status == "ok", res.summary.reason
    assert runner.procedure.error is None
    rec = read_recording(path)
    ticks = [r["tick"] for r in rec.rows]
    assert rec.complete and ticks == list(range(ticks[0], ticks[0] + len(ticks)))
    assert res.summary.ticks == len(ticks)
