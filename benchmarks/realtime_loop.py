"""Real-time control loop and device figures against the wire simulators (another process).

    .venv/bin/python benchmarks/realtime_loop.py [--seconds 60] [--rate 500 | --rates 500 1000]
                                                 [--sleep-seconds 10] [--load N] [--json FILE]
                                                 [--witness] [--witness-compute-us US]
                                                 [--cpus N ...] [--sim-cpus N ...]
                                                 [--parts] [--census]

1. Starts ``dentibot sim serve`` in a child process (loopback, free ports), connects the four
   real drivers (Meca500 TCP, Net F/T UDP, EPOS4 via socketcand, Modbus TCP).
2. Device round trips (command -> effect visible in the stream), 20 each: arm MoveJointsVel
   -> joint rate in the monitoring; handpiece velocity -> velocity in the TxPDO; F/T bias ->
   tared record; platform setpoint -> Modbus input registers.
3. For each rate, the runtime's control task for ``--seconds`` with all streams running
   (state idle: every tick reads all four devices, estimates, streams MoveJointsVel, builds its
   telemetry row): lateness p50/p99/max, overruns, skipped deadlines, compute time; exact
   percentiles from every tick's lateness (a sink collects the rows' ``lateness_us``) beside the
   :class:`DeadlineStats` histogram bounds; stream losses (F/T sequence gaps, unanswered
   EPOS4 SYNCs, arm cycles without joints); CPU of both processes.
4. Beside it, the same loop paced by plain ``asyncio.sleep(period)`` (``--sleep-seconds``).
5. The platform's floor (``--floor-seconds``, default ``--seconds``): a bare loop in a process
   of its own, with the same clock and the same raised priority under the same load, that does
   nothing but wake at each deadline (no devices, no other thread, nothing to compute). What it
   misses, the machine missed: on a virtual machine the guest's vCPU is paused now and then by
   the host, and no priority inside the guest can win those milliseconds back. Its lateness
   and overruns (same definition: lateness + compute > period) bound what any loop can
   achieve here; the control loop's figures are read against them.

``--load N`` runs N CPU-bound jobs (busy Python processes at the ordinary priority) for the
whole measurement: the machine as it is when something else runs beside the robot. The control
loop raises its priority where permitted (``realtime_policy``), and so does ``dentibot sim
serve``; ``priority_raised`` says how the system granted it (``fifo``: SCHED_FIFO, for a
loop that waits on the kernel timer; ``nice``; empty: not at all).

``--witness`` runs the bare loop of 5. in a process of its own beside the control loop, in the
same minutes, and counts the control loop's overruns that began within 5 ms of a stall of
it (a wake-up 0.5 ms late or more): ``overruns_shared_with_witness``, the machine's misses
rather than the loop's own (``witness``: its figures, ``stalls``: how many it had).
``--witness-compute-us US`` gives the witness US of pure Python arithmetic to do in every
tick (calibrated at its start: the fastest of 50 timed runs), like the control loop's own
compute but with no device, no other thread and no other work on its event loop. A bare
loop only shows the stalls that take the whole machine away; a loop that computes also
meets the times the machine runs it slower (``slow_ticks``: ticks whose arithmetic took
3 times its calibrated time or more, with ``slow_ticks_top``: the longest, wall and thread
CPU us). Its overruns are what this machine does to any loop with that much compute per
tick.

``--cpus`` keeps the control process to those CPUs while it ticks (``control.cpus``),
``--sim-cpus`` the simulators' process (``dentibot sim serve --cpus``).

``--parts`` times each part of the tick where it runs, and the compiled calls again back to
back (:mod:`tick_parts`): what each part costs in place, and how much more than hot.
``--census`` times every callback the control process's event loop runs while the loop
ticks (:mod:`loop_census`): the tick against the streams' parsing, the drive's cycle and
the I/O polling, per tick. ``overrun_ticks`` (JSON) gives each overrun's lateness and
compute (us): a late start is the loop busy or the machine stalled before the tick, a long
compute the tick itself slowed.

Targets: 500 Hz p99 lateness <= 100 us, zero overruns over 60 s.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import os
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import structlog

sys.path.insert(0, str(Path(__file__).resolve().parent))

import loop_census
from benchutil import fmt, quantiles
from tick_parts import figures, print_figures, timed_parts

from dentibot.app.procedure import Procedure
from dentibot.app.simulated import true_gravity_model
from dentibot.io.devices import loopback_config, open_devices
from dentibot.runtime.actuate import recover_all
from dentibot.runtime.clock import (
    REALTIME_FIFO_PRIORITY,
    Clock,
    DeadlineStats,
    RealTimeClock,
    raised_priority,
    realtime_policy,
)
from dentibot.runtime.config import RuntimeConfig, Thresholds
from dentibot.sim.world import World, WorldConfig

ROOT = Path(__file__).resolve().parents[1]
LOOSE = Thresholds(stale_periods={"arm": 50, "ft": 50, "motor": 50, "aux": 200})
#: a bare loop's wake-up this late is a stall of the machine (a witness's record of it)
STALL_S = 0.0005
#: an overrun that began this close to a stall of the witness is counted as the machine's
SHARED_S = 0.005
#: the witness runs this much longer than the control loop (its start-up, the loop's set-up)
WITNESS_EXTRA_S = 5.0
#: a witness's tick whose arithmetic took this many times its calibrated time ran slowed
SLOW_FACTOR = 3.0


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
    """Median and max (ms) of ``n`` command -> effect round trips per device."""
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


#: Stream counters of the drivers, differenced over each loop: (device, attribute).
STREAM_COUNTERS = (("ft", "received"), ("ft", "lost"), ("arm", "received"), ("arm", "lost"),
                   ("motor", "received"), ("motor", "lost"), ("motor", "overruns"))


def _counters(d) -> dict:
    return {f"{dev}_{attr}": getattr(getattr(d, dev), attr, None)
            for dev, attr in STREAM_COUNTERS}


async def _let_devices_run() -> None:
    """A turn of the event loop for the drivers' cyclic tasks between two pieces of this
    benchmark's own work: the drive's heartbeat consumer (30 ms) takes a longer pause of the
    host's event loop for a dead host. Measured on a loaded machine: the work between two
    loops (figures of the last one, the next one built) ran 16-24 ms in one piece."""
    await asyncio.sleep(0.001)


async def control_loop(d, world: World, clock: Clock, seconds: float,
                       cpus: tuple[int, ...] | None = None) -> dict:
    """The runtime's control task paced by ``clock`` for ``seconds``; its timing figures.
    Devices a previous loop left faulted are brought back first (the operator's reset), so
    that one loop's fault does not become the next one's. ``host_heartbeat_gap_max_ms``:
    the longest pause of the host's heartbeat from here (the work between two loops
    included) to the end of the loop, against the drive's consumer time."""
    d.motor.host_heartbeat_gap_max_s = 0.0
    cause = await recover_all(d.motor, d.arm, d.aux)
    if cause is not None:
        raise RuntimeError(f"the devices did not recover before the loop: {cause}")
    await _let_devices_run()
    late: list[float] = []
    comp: list[float] = []

    overrun_at: list[float] = []
    overrun_ticks: list[list[float]] = []        # (lateness us, compute us) of each

    def sink(row: dict) -> None:
        late.append(row["lateness_us"])
        comp.append(row["compute_us"])
        if row["overrun"]:                 # the tick's deadline, on the monotonic clock
            overrun_at.append(time.monotonic() - (row["lateness_us"] + row["compute_us"]) / 1e6)
            overrun_ticks.append([round(row["lateness_us"]), round(row["compute_us"])])

    proc = Procedure.over(d, RuntimeConfig(period_s=clock.period_s, thresholds=LOOSE,
                                           cpus=cpus),
                          clock=clock, gravity=true_gravity_model(world), sink=sink)
    rt = proc.runtime
    await _let_devices_run()
    c0 = _counters(d)
    cpu0 = time.process_time()
    t0 = time.perf_counter()
    async with proc:
        await proc.run_for(seconds)
    wall = time.perf_counter() - t0
    await _let_devices_run()
    s = rt.stats.as_dict()
    s["effective_rate_hz"] = s["ticks"] / wall
    s["host_heartbeat_gap_max_ms"] = d.motor.host_heartbeat_gap_max_s * 1e3
    s["consumer_ms"] = d.motor.consumer_ms
    s["wall_s"] = wall
    s["control_cpu_percent"] = 100 * (time.process_time() - cpu0) / wall
    s["lateness_us_exact"] = quantiles(late)
    await _let_devices_run()
    s["compute_us_exact"] = quantiles(comp)
    await _let_devices_run()
    c1 = _counters(d)
    s["streams"] = {k: (c1[k] - c0[k]) if c0[k] is not None else None for k in c0}
    s.update(state=rt.state, faults=list(rt.treatment.fault_causes))
    s["overrun_at"] = overrun_at
    s["overrun_ticks"] = overrun_ticks
    return s


def _serve(ports: dict, cpus: tuple[int, ...] | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "dentibot.cli", "sim", "serve", "--meca-port",
         str(ports["meca"]), "--netft-port", str(ports["netft"]), "--netft-http-port",
         str(ports["http"]), "--modbus-port", str(ports["modbus"]), "--can-port",
         str(ports["can"]), "--seed", "1",
         *(["--cpus", *map(str, cpus)] if cpus else [])],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)


def _load_jobs(n: int) -> list[subprocess.Popen]:
    """``n`` CPU-bound jobs at the ordinary priority (a busy loop each)."""
    return [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]


def _arithmetic(n: int) -> float:
    """``n`` steps of pure Python arithmetic: a witness's compute."""
    x = 0.0
    for i in range(n):
        x += i * 0.5
    return x


def _steps_for(work_us: float) -> int:
    """Steps of :func:`_arithmetic` that take ``work_us`` on this machine at its fastest
    (the quickest of 50 timed runs: a loaded machine only slows a run down)."""
    if work_us <= 0:
        return 0
    probe = 10_000
    best = math.inf
    for _ in range(50):
        t0 = time.perf_counter()
        _arithmetic(probe)
        best = min(best, time.perf_counter() - t0)
    return max(1, round(probe * work_us * 1e-6 / best))


async def _bare_loop(rate: float, seconds: float, work_us: float = 0.0) -> dict:
    """A loop that only waits for its deadlines (and does ``work_us`` of arithmetic in each
    tick): :class:`RealTimeClock` at ``rate``, under the control loop's policy, for
    ``seconds``; its :class:`DeadlineStats`, exact lateness quantiles and the ticks its
    arithmetic took :data:`SLOW_FACTOR` times its calibrated time or more."""
    steps = _steps_for(work_us)
    clock = RealTimeClock(1.0 / rate)
    stats = DeadlineStats(clock.period_s)
    late: list[float] = []
    ticks = max(1, round(seconds * rate))
    stalls: list[float] = []                         # when it woke late (monotonic s)
    slow: list[tuple[float, float]] = []             # (wall us, thread CPU us)
    with realtime_policy(clock) as collect:
        clock.start()
        for k in range(ticks):
            lateness = await clock.wait_next()
            t0, c0 = time.perf_counter(), time.thread_time()
            late.append(lateness * 1e6)
            if lateness > STALL_S:
                stalls.append(time.monotonic() - lateness)
            _arithmetic(steps)
            took = time.perf_counter() - t0
            if steps and took >= SLOW_FACTOR * work_us * 1e-6:
                slow.append((took * 1e6, (time.thread_time() - c0) * 1e6))
            stats.add(lateness, took)
            collect(k)                               # in the slack, as the control loop
        stats.skipped = clock.skipped
        granted = _priority_granted(clock)
    s = stats.as_dict()
    s["lateness_us_exact"] = quantiles(late)
    s["priority_raised"] = granted
    s["stalls_at"] = stalls
    s["work_us"] = work_us
    s["slow_ticks"] = len(slow)
    s["slow_ticks_top"] = [[round(w), round(c)] for w, c in sorted(slow)[-5:]]
    return s


def _floor_command(rate: float, seconds: float, work_us: float = 0.0) -> list[str]:
    """This script run as :func:`_bare_loop`'s own process (see ``--floor``)."""
    return [sys.executable, __file__, "--floor", f"{rate!r}", f"{seconds!r}",
            "--floor-work-us", f"{work_us!r}"]


def _floor_figures(stdout: str) -> dict:
    """:func:`_bare_loop`'s figures, the last line its process printed."""
    return json.loads(stdout.strip().splitlines()[-1])


def platform_floor(rate: float, seconds: float) -> dict:
    """:func:`_bare_loop` in a fresh process (so that no thread of this one shares its
    interpreter lock), its figures read back."""
    out = subprocess.run(_floor_command(rate, seconds), cwd=ROOT, capture_output=True,
                         text=True, timeout=seconds + 60, check=True)
    return _floor_figures(out.stdout)


def _witness(rate: float, seconds: float, work_us: float = 0.0) -> subprocess.Popen:
    """:func:`_bare_loop` started in a fresh process now, running ``seconds`` with
    ``work_us`` of arithmetic per tick: a witness of what the machine does to a loop while
    the control loop runs (read with :func:`_attributed`)."""
    return subprocess.Popen(_floor_command(rate, seconds, work_us), cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)


def _attributed(loop: dict, witness: subprocess.Popen) -> dict:
    """The witness's figures, and how many of the loop's overruns began within
    :data:`SHARED_S` of a stall of the witness (the machine's, not the loop's)."""
    out, _ = witness.communicate(timeout=120)
    w = _floor_figures(out)
    stalls = np.array(sorted(w.pop("stalls_at")))
    shared = 0
    for t in loop["overrun_at"]:
        i = np.searchsorted(stalls, t)
        near = stalls[max(i - 1, 0):i + 1]
        shared += bool(near.size and np.abs(near - t).min() <= SHARED_S)
    w["stalls"] = int(stalls.size)
    return {"witness": w, "overruns_shared_with_witness": shared}


def _priority_granted(clock: RealTimeClock) -> str:
    """How the control loop's priority is raised here: "fifo", "nice" or "" (not at all)."""
    with raised_priority(fifo_priority=REALTIME_FIFO_PRIORITY if clock.kernel_timer
                         else None) as how:
        return how


async def main_async(seconds: float = 60.0, rates=(500.0,), sleep_seconds: float = 10.0,
                     round_trip_n: int = 20, load: int = 0,
                     floor_seconds: float | None = None, with_witness: bool = False,
                     witness_work_us: float = 0.0, cpus: tuple[int, ...] | None = None,
                     sim_cpus: tuple[int, ...] | None = None, parts: bool = False,
                     census: bool = False) -> dict:
    ports = {"meca": free_port(), "http": free_port(), "modbus": free_port(),
             "can": free_port(), "netft": free_port(socket.SOCK_DGRAM)}
    serve = _serve(ports, sim_cpus)  # started once, before any timing
    jobs = _load_jobs(load)
    try:
        serve.stdout.readline()                      # the banner: listening
        cfg = loopback_config(meca_port=ports["meca"], netft_port=ports["netft"],
                              netft_http_port=ports["http"], modbus_port=ports["modbus"],
                              can_port=ports["can"])
        world = World(WorldConfig(seed=1))           # the server's world, for its load model
        result: dict = {"seconds": seconds, "sleep_seconds": sleep_seconds, "rates": {},
                        "load_jobs": load, "cpus": cpus, "sim_cpus": sim_cpus,
                        "priority_raised": _priority_granted(RealTimeClock(0.002))}
        async with open_devices(cfg) as d:
            result["round_trips"] = await round_trips(d, round_trip_n)
            for rate in rates:
                r = result["rates"][f"{rate:g}"] = {"rate_hz": rate}
                srv0, t0 = cpu_seconds(serve.pid), time.perf_counter()
                witness = (_witness(rate, seconds + WITNESS_EXTRA_S, witness_work_us)
                           if with_witness else None)
                with timed_parts() if parts else contextlib.nullcontext() as timing, \
                        loop_census.census() if census else contextlib.nullcontext() as seen:
                    r["absolute_deadlines"] = await control_loop(
                        d, world, RealTimeClock(1.0 / rate), seconds, cpus)
                if timing is not None:
                    r["parts"] = figures(timing)
                if seen is not None:
                    r["census"] = loop_census.figures(seen, r["absolute_deadlines"]["ticks"])
                if witness is not None:   # (its end awaited off the loop: the streams go on)
                    r["absolute_deadlines"].update(await asyncio.to_thread(
                        _attributed, r["absolute_deadlines"], witness))
                r["simulator_cpu_percent"] = (100 * (cpu_seconds(serve.pid) - srv0)
                                              / (time.perf_counter() - t0))
            for rate in rates:
                if sleep_seconds > 0:
                    result["rates"][f"{rate:g}"]["plain_asyncio_sleep"] = await control_loop(
                        d, world, SleepClock(1.0 / rate), sleep_seconds)
        floor_s = seconds if floor_seconds is None else floor_seconds
        for rate in rates:                           # the devices closed, the load still on
            if floor_s > 0:
                result["rates"][f"{rate:g}"]["platform_floor"] = await asyncio.to_thread(
                    platform_floor, rate, floor_s)
        return result
    finally:
        for job in jobs:
            job.kill()
            job.wait()
        serve.terminate()
        serve.communicate(timeout=20)


def measure(seconds: float = 60.0, rates=(500.0, 1000.0), sleep_seconds: float = 10.0,
            round_trip_n: int = 20, load: int = 0, floor_seconds: float | None = None,
            with_witness: bool = False, witness_work_us: float = 0.0,
            cpus: tuple[int, ...] | None = None, sim_cpus: tuple[int, ...] | None = None,
            parts: bool = False, census: bool = False) -> dict:
    """Round trips, then each rate with absolute deadlines, then each with plain sleep, then
    each rate's platform floor (``floor_seconds``, default ``seconds``), with ``load``
    CPU-bound jobs running throughout."""
    return asyncio.run(main_async(seconds, rates, sleep_seconds, round_trip_n, load,
                                  floor_seconds, with_witness, witness_work_us, cpus,
                                  sim_cpus, parts, census))


def _cpu_list(cpus) -> str:
    return ",".join(map(str, cpus)) if cpus else "any"


def print_report(r: dict) -> None:
    print(f"{r['load_jobs']} CPU-bound job(s) beside it; control loop priority: "
          f"{r['priority_raised'] or 'NOT raised (not permitted)'}; CPUs: control "
          f"{_cpu_list(r.get('cpus'))}, simulators {_cpu_list(r.get('sim_cpus'))}")
    for rate, res in r["rates"].items():
        for name in ("absolute_deadlines", "plain_asyncio_sleep", "platform_floor"):
            s = res.get(name)
            if s is None:
                continue
            ex = s["lateness_us_exact"]
            if name == "platform_floor":
                print(f"{rate:>5} Hz {name:>19}: ticks {s['ticks']}, lateness p50 "
                      f"{fmt(ex['p50'], '.0f')} us, p99 {fmt(ex['p99'], '.0f')} us, max "
                      f"{fmt(ex['max'], '.0f')} us, overruns {s['overruns']}, skipped "
                      f"{s['skipped']} (a bare loop, priority {s['priority_raised'] or 'not raised'})")
                continue
            st = s["streams"]
            print(f"{rate:>5} Hz {name:>19}: ticks {s['ticks']}, lateness p50 "
                  f"{fmt(ex['p50'], '.0f')} us, p99 {fmt(ex['p99'], '.0f')} us, max "
                  f"{fmt(ex['max'], '.0f')} us (bins: p99 <= "
                  f"{s['lateness_us_p99']:.0f} us), overruns {s['overruns']}, skipped "
                  f"{s['skipped']}, rate {s['effective_rate_hz']:.0f} Hz, compute mean "
                  f"{s['compute_us_mean']:.0f} us, heartbeat gap max "
                  f"{s['host_heartbeat_gap_max_ms']:.1f} ms, F/T lost {st['ft_lost']} of "
                  f"{st['ft_received']}, CPU {s['control_cpu_percent']:.0f} %, "
                  f"state {s['state']}{' ' + '; '.join(s['faults']) if s['faults'] else ''}")
            if "witness" in s:
                w = s["witness"]
                work = (f"with {w['work_us']:g} us of arithmetic per tick (mean compute "
                        f"{w['compute_us_mean']:.0f} us, {w['slow_ticks']} ticks slowed "
                        f">= {SLOW_FACTOR:g}x)" if w.get("work_us") else "bare")
                print(f"{rate:>5} Hz {'witness':>19}: a loop beside it, same minutes, {work}: "
                      f"p99 {fmt(w['lateness_us_exact']['p99'], '.0f')} us, max "
                      f"{fmt(w['lateness_us_exact']['max'], '.0f')} us, overruns "
                      f"{w['overruns']}, {w['stalls']} stalls >= {STALL_S * 1e3:g} ms; "
                      f"{s['overruns_shared_with_witness']} of the loop's {s['overruns']} "
                      f"overruns began in one")
        print(f"{rate:>5} Hz simulator process CPU {res['simulator_cpu_percent']:.0f} %")
        if "parts" in res:
            print(f"{rate:>5} Hz the tick's parts, in place:")
            print_figures(res["parts"], indent="      ")
        if "census" in res:
            print(f"{rate:>5} Hz the event loop's callbacks while it ticks:")
            loop_census.print_figures(res["census"], indent="      ")
    for k, v in r["round_trips"].items():
        print(f"round trip {k:>13}: median {fmt(v['median_ms'], '.2f')} ms, max "
              f"{fmt(v['max_ms'], '.2f')} ms (n={v['n']})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=500.0)
    ap.add_argument("--rates", type=float, nargs="+", help="several rates (overrides --rate)")
    ap.add_argument("--sleep-seconds", type=float, default=None,
                    help="plain asyncio.sleep loop length (default: min(seconds, 10))")
    ap.add_argument("--load", type=int, default=0, help="CPU-bound jobs running beside it")
    ap.add_argument("--floor-seconds", type=float, default=None,
                    help="the bare loop's length (default: --seconds; 0: none)")
    ap.add_argument("--json", help="write the figures to this file")
    ap.add_argument("--witness", action="store_true",
                    help="run the bare loop beside the control loop, in the same minutes, "
                         "and count the overruns that began in one of its stalls")
    ap.add_argument("--witness-compute-us", type=float, default=0.0,
                    help="the witness's pure Python arithmetic per tick, us (default 0: a "
                         "bare loop); give the control loop's compute to see what the "
                         "machine does to a loop with that much")
    ap.add_argument("--cpus", type=int, nargs="+", default=None,
                    help="keep the control process to these CPUs (control.cpus)")
    ap.add_argument("--sim-cpus", type=int, nargs="+", default=None,
                    help="keep the simulators' process to these CPUs (sim serve --cpus)")
    ap.add_argument("--parts", action="store_true",
                    help="time each part of the tick in place, and its compiled calls hot")
    ap.add_argument("--census", action="store_true",
                    help="time every callback of the control process's event loop")
    ap.add_argument("--floor", nargs=2, type=float, metavar=("RATE", "SECONDS"),
                    help=argparse.SUPPRESS)         # the bare loop's own process
    ap.add_argument("--floor-work-us", type=float, default=0.0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.floor:
        print(json.dumps(asyncio.run(_bare_loop(*args.floor, args.floor_work_us))))
        return
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
    # python-can: "Got incomplete message" on each TCP read that splits a frame (under load)
    logging.getLogger("can.interfaces.socketcand").setLevel(logging.ERROR)
    sleep_s = min(args.seconds, 10.0) if args.sleep_seconds is None else args.sleep_seconds
    r = measure(args.seconds, args.rates or [args.rate], sleep_s, load=args.load,
                floor_seconds=args.floor_seconds, with_witness=args.witness or
                args.witness_compute_us > 0, witness_work_us=args.witness_compute_us,
                cpus=tuple(args.cpus) if args.cpus else None,
                sim_cpus=tuple(args.sim_cpus) if args.sim_cpus else None, parts=args.parts,
                census=args.census)
    print_report(r)
    if args.json:
        Path(args.json).write_text(json.dumps(r, indent=2))


if __name__ == "__main__":
    main()
