"""Real-time control loop and device figures against the wire simulators (another process).

    .venv/bin/python benchmarks/realtime_loop.py [--seconds 60] [--rate 500] [--json FILE]

1. Starts ``dentibot sim serve`` in a child process (loopback, free ports), connects the four
   real drivers (Meca500 TCP, Net F/T UDP, EPOS4 via socketcand, Modbus TCP).
2. Device round trips (command -> effect visible in the stream), 20 each: arm MoveJointsVel
   -> joint rate in the monitoring; handpiece velocity -> velocity in the TxPDO; F/T bias ->
   tared record; platform setpoint -> Modbus input registers.
3. The runtime's control task at ``--rate`` Hz for ``--seconds`` with all streams running
   (state idle: every tick reads all four devices, estimates, streams MoveJointsVel):
   lateness p50/p99/max, overruns, compute time; F/T records lost; CPU of both processes.
4. Beside it, the same loop paced by plain ``asyncio.sleep(period)``.

Targets (issue 5): 500 Hz p99 lateness <= 100 us, zero overruns over 60 s.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import structlog

from dentibot.io.devices import loopback_config, open_devices
from dentibot.runtime.clock import Clock, DeadlineStats, RealTimeClock
from dentibot.runtime.config import RuntimeConfig, Thresholds
from dentibot.runtime.control_task import Devices, Runtime
from dentibot.runtime.harness import true_gravity_model
from dentibot.sim.world import World, WorldConfig

ROOT = Path(__file__).resolve().parents[1]
LOOSE = Thresholds(stale_periods={"arm": 50, "ft": 50, "motor": 50, "aux": 200})


def free_port(kind=socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (Linux /proc), s."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class SleepClock(Clock):
    """The naive pacing: ``asyncio.sleep(period)`` after each tick (relative, drifts)."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.skipped = 0
        self.start()

    def start(self) -> None:
        self._t0 = time.perf_counter()
        self._k = 0

    def now(self) -> float:
        return time.perf_counter() - self._t0

    async def wait_next(self) -> float:
        """Lateness of each wake-up against the time it asked for (the schedule itself also
        drifts by the tick's compute time: see ``effective_rate_hz``)."""
        self._k += 1
        due = time.perf_counter() + self.period_s
        await asyncio.sleep(self.period_s)
        return max(0.0, time.perf_counter() - due)


async def _until(pred, timeout=2.0):
    t0 = time.perf_counter()
    while not await pred():
        if time.perf_counter() - t0 > timeout:
            return None
        await asyncio.sleep(0)
    return time.perf_counter() - t0


async def round_trips(d, n: int = 20) -> dict:
    out = {}

    async def arm_moving():
        return abs((await d.arm.read()).qdot_deg_s[5]) > 0.5

    async def arm_still():
        return abs((await d.arm.read()).qdot_deg_s[5]) < 0.05

    async def motor_fast():
        return (await d.motor.read()).velocity_rpm > 1.0

    async def motor_slow():
        return abs((await d.motor.read()).velocity_rpm) < 0.5

    rts = {"arm": [], "handpiece": [], "ft_bias": [], "aux_platform": []}
    for i in range(n):
        t0 = time.perf_counter()
        await d.arm.move_joints_vel([0, 0, 0, 0, 0, 10.0 if i % 2 == 0 else -10.0])
        dt = await _until(arm_moving)
        if dt is not None:
            rts["arm"].append(time.perf_counter() - t0)
        await d.arm.move_joints_vel([0] * 6)
        await _until(arm_still)
        t0 = time.perf_counter()
        await d.motor.set_velocity(60.0)
        if await _until(motor_fast) is not None:
            rts["handpiece"].append(time.perf_counter() - t0)
        await d.motor.stop()
        await _until(motor_slow)
        seq0 = (await d.ft.read()).seq
        t0 = time.perf_counter()
        await d.ft.bias()

        async def tared(seq0=seq0):
            w = await d.ft.read()
            return w.seq != seq0 and max(map(abs, w.force_n)) < 0.05
        if await _until(tared) is not None:
            rts["ft_bias"].append(time.perf_counter() - t0)
        target = (0.5 * (i % 3), 0.0, 0.0)
        t0 = time.perf_counter()
        await d.aux.set_platform(target)

        async def moved(target=target):
            return abs((await d.aux.read()).platform_mm[0] - target[0]) < 0.02
        if await _until(moved) is not None:
            rts["aux_platform"].append(time.perf_counter() - t0)
    for k, v in rts.items():
        v = sorted(x * 1e3 for x in v)
        out[k] = {"n": len(v), "median_ms": statistics.median(v) if v else None,
                  "max_ms": v[-1] if v else None}
    return out


async def control_loop(d, world: World, clock: Clock, seconds: float) -> dict:
    rt = Runtime(Devices(d.arm, d.ft, d.motor, d.aux), RuntimeConfig(
        period_s=clock.period_s, thresholds=LOOSE), clock, gravity=true_gravity_model(world))
    rt.stats = DeadlineStats(clock.period_s)
    ft_lost0, ft_rx0 = d.ft.lost, d.ft.received
    t0 = time.perf_counter()
    await rt.run(max_ticks=round(seconds / clock.period_s))
    s = rt.stats.as_dict()
    s["effective_rate_hz"] = s["ticks"] / (time.perf_counter() - t0)
    s.update(state=rt.state, faults=rt.treatment.fault_causes,
             ft_received=d.ft.received - ft_rx0, ft_lost=d.ft.lost - ft_lost0,
             arm_lost=getattr(d.arm, "lost", None), motor_lost=getattr(d.motor, "lost", None))
    return s


async def main_async(args) -> dict:
    meca, http, modbus, can = (free_port() for _ in range(4))
    netft = free_port(socket.SOCK_DGRAM)
    serve = subprocess.Popen(  # noqa: ASYNC220 - started once, before any timing
        [sys.executable, "-m", "dentibot.cli", "sim", "serve", "--meca-port", str(meca),
         "--netft-port", str(netft), "--netft-http-port", str(http), "--modbus-port",
         str(modbus), "--can-port", str(can), "--seed", "1"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        serve.stdout.readline()                      # the banner: listening
        cfg = loopback_config(meca_port=meca, netft_port=netft, netft_http_port=http,
                              modbus_port=modbus, can_port=can)
        world = World(WorldConfig(seed=1))           # the server's world, for its load model
        result = {"rate_hz": args.rate, "seconds": args.seconds}
        async with open_devices(cfg) as d:
            result["round_trips"] = await round_trips(d)
            cpu0, srv0, t0 = time.process_time(), cpu_seconds(serve.pid), time.perf_counter()
            result["absolute_deadlines"] = await control_loop(
                d, world, RealTimeClock(1.0 / args.rate), args.seconds)
            wall = time.perf_counter() - t0
            result["cpu_percent"] = {
                "control_process": 100 * (time.process_time() - cpu0) / wall,
                "simulator_process": 100 * (cpu_seconds(serve.pid) - srv0) / wall}
            result["plain_asyncio_sleep"] = await control_loop(
                d, world, SleepClock(1.0 / args.rate), min(args.seconds, 10.0))
        return result
    finally:
        serve.terminate()
        serve.communicate(timeout=20)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=500.0)
    ap.add_argument("--json", help="write the figures to this file")
    args = ap.parse_args()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
    r = asyncio.run(main_async(args))
    for name in ("absolute_deadlines", "plain_asyncio_sleep"):
        s = r[name]
        print(f"{name:>20}: ticks {s['ticks']}, lateness p50 {s['lateness_us_p50']:.0f} us, "
              f"p99 {s['lateness_us_p99']:.0f} us, max {s['lateness_us_max']:.0f} us, "
              f"overruns {s['overruns']}, skipped {s['skipped']}, rate "
              f"{s['effective_rate_hz']:.0f} Hz, compute mean "
              f"{s['compute_us_mean']:.0f} us, F/T lost {s['ft_lost']} of "
              f"{s['ft_received']}, state {s['state']}")
    print("cpu %:", {k: round(v, 1) for k, v in r["cpu_percent"].items()})
    for k, v in r["round_trips"].items():
        print(f"round trip {k:>13}: median {v['median_ms']:.2f} ms, max {v['max_ms']:.2f} ms "
              f"(n={v['n']})")
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=2))


if __name__ == "__main__":
    main()
