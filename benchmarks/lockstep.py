"""Lock-step speed: a treatment round with the controller and the world together.

    .venv/bin/python benchmarks/lockstep.py [--seconds 300] [--profile 20]

The main job's set-up (``protocols/root-canal.yaml``: world, runtime configuration, alignment)
on a :class:`~dentibot.app.procedure.Procedure`, then one drilling round driven as
``dentibot run`` drives it (automated strategy, passes until the round's time is up) for
``--seconds`` of simulated time, three ways:

- ``none``: no telemetry sink (the runtime builds no rows): controller + world only;
- ``rows``: the telemetry row built every tick and discarded;
- ``recorder``: every row and event to the recorder ``dentibot run`` uses (``open_recorder``:
  the MCAP recorder in its own process, ``validate=False``); the wall time includes closing
  the file (the writer draining what it was handed).

The speed factor is simulated seconds per wall second; the world's share is timed around
``World.step``. ``--profile S`` adds a cProfile breakdown of an ``S``-second round (no sink).
Target: >= 50x real time (40 us per 2 ms tick).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import cProfile
import logging
import pstats
import sys
import tempfile
import time
from pathlib import Path

import structlog

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchutil import fmt

from dentibot.app.procedure import Procedure
from dentibot.app.runner import runtime_config, world_config
from dentibot.app.simulated import World
from dentibot.app.steps import StepExecutor, drill_setup
from dentibot.protocol.loader import load_protocol
from dentibot.telemetry.recorder_process import open_recorder

ROOT = Path(__file__).resolve().parents[1]
PROTOCOL = ROOT / "protocols" / "root-canal.yaml"
VARIANTS = ("none", "rows", "recorder")


def _discard(row: dict) -> None:
    """A sink that drops the row (the cost of building it, nothing else)."""


class _TimedStep:
    """``World.step`` with its accumulated wall time."""

    def __init__(self, step) -> None:
        self._step = step
        self.ns = 0
        self.calls = 0

    def __call__(self) -> None:
        t0 = time.perf_counter_ns()
        self._step()
        self.ns += time.perf_counter_ns() - t0
        self.calls += 1


class _Sink:
    """The procedure's row sink, switched on for the drilling round only."""

    def __init__(self) -> None:
        self.to = None

    def __call__(self, row: dict) -> None:
        if self.to is not None:
            self.to(row)


@contextlib.asynccontextmanager
async def drilling(protocol, sink=None):
    """The main job's procedure, aligned as the protocol gives it and drilling (passes until
    stopped) with the protocol's drill spec, as ``dentibot run`` does it; ``sink`` gets the rows
    from then on. Yields ``(procedure, timed world step)``."""
    world = World(world_config(protocol))
    timed = _TimedStep(world.step)
    world.step = timed               # the lock-step clock takes ``world.step`` at construction
    switch = _Sink()
    proc = Procedure.simulated(world, runtime_config(protocol), sink=switch)
    steps = {s.kind: s.spec for s in protocol.steps}
    async with proc:
        ex = StepExecutor(proc)
        await ex.align(steps["align"])
        await proc.call(lambda: drill_setup(proc.runtime, steps["drill"]))
        await ex.start_drilling(passes=10**6)
        if proc.runtime.state == "fault":
            raise RuntimeError("drill refused: " + "; ".join(proc.runtime.treatment.fault_causes))
        switch.to = sink
        yield proc, timed


def run_variant(variant: str, seconds: float, protocol=None, out_dir: Path | None = None,
                profile: bool = False) -> dict:
    """One drilling round of ``seconds`` simulated seconds with telemetry ``variant``."""
    protocol = protocol or load_protocol(PROTOCOL)
    rec = None
    sink = None
    if variant == "rows":
        sink = _discard
    elif variant == "recorder":
        path = (out_dir or Path(tempfile.gettempdir())) / "dentibot-bench-lockstep.mcap"
        rec = open_recorder(path, {"protocol": protocol.name, "seed": protocol.seed,
                                   "rate_hz": protocol.control.rate_hz},
                            overwrite=True, validate=False)
        sink = rec.record
    elif variant != "none":
        raise ValueError(f"variant must be one of {VARIANTS}")
    prof = cProfile.Profile() if profile else None

    async def go() -> dict:
        async with drilling(protocol, sink) as (proc, timed):
            rt = proc.runtime
            ticks0, step_ns0 = rt.ticks, timed.ns
            if prof is not None:
                prof.enable()
            t0 = time.perf_counter()
            await proc.run_for(seconds, until=lambda r: r.state in ("done", "fault"))
            wall_run = time.perf_counter() - t0
            if prof is not None:
                prof.disable()
            return {"rt": rt, "world": proc.world, "ticks": rt.ticks - ticks0,
                    "world_ns": timed.ns - step_ns0, "wall_run": wall_run}

    r = asyncio.run(go())
    rt, world, ticks, wall_run = r["rt"], r["world"], r["ticks"], r["wall_run"]
    t_close = time.perf_counter()
    out = {}
    if rec is not None:
        rec.close("ok")
        size = rec.path.stat().st_size
        out.update(file_bytes=size, bytes_per_min=size / (ticks * rt.ts / 60.0),
                   queue_depth_max=rec.queue_depth_max, ticks_written=rec.ticks_written,
                   events_written=rec.events_written, rows_dropped=rec.rows_dropped)
        rec.path.unlink()
    wall = wall_run + (time.perf_counter() - t_close)
    sim_s = ticks * rt.ts
    out.update(variant=variant, sim_seconds=sim_s, ticks=ticks, wall_s=wall,
               close_s=wall - wall_run, speed_factor=sim_s / wall, us_per_tick=1e6 * wall / ticks,
               world_us_per_tick=r["world_ns"] / 1e3 / ticks,
               state=rt.state, reversals=rt.ctx.reversals,
               completeness=world.completeness(), fractured=world.fractured is not None)
    if prof is not None:
        out["profile"] = _profile_table(prof, ticks)
    return out


def _profile_table(prof: cProfile.Profile, ticks: int, top: int = 20) -> dict:
    """The ``top`` functions by own time and by cumulative time, in us per tick."""
    st = pstats.Stats(prof)
    total = st.total_tt
    rows = []
    package = str(ROOT / "dentibot")
    for (file, line, name), (_cc, nc, tt, ct, _callers) in st.stats.items():
        where = f"{Path(file).name}:{line}" if line else file
        rows.append({"function": f"{where}({name})", "calls_per_tick": nc / ticks,
                     "own_us_per_tick": 1e6 * tt / ticks, "cum_us_per_tick": 1e6 * ct / ticks,
                     "own_pct": 100 * tt / total if total else 0.0,
                     "dentibot": file.startswith(package)})
    by_own = sorted(rows, key=lambda r: -r["own_us_per_tick"])[:top]
    # cumulative: DentiBot's own functions only (the asyncio frames above them say nothing)
    by_cum = sorted((r for r in rows if r["dentibot"]),
                    key=lambda r: -r["cum_us_per_tick"])[:top]
    return {"total_us_per_tick_profiled": 1e6 * total / ticks, "by_own_time": by_own,
            "by_cumulative_time": by_cum}


def measure(seconds: float = 300.0, variants=VARIANTS, profile_seconds: float | None = None,
            out_dir: Path | None = None) -> dict:
    protocol = load_protocol(PROTOCOL)
    res = {"protocol": protocol.name, "round_s": seconds,
           "variants": {v: run_variant(v, seconds, protocol, out_dir) for v in variants}}
    if profile_seconds:
        res["profile"] = run_variant("none", profile_seconds, protocol, profile=True)["profile"]
    return res


def print_report(r: dict) -> None:
    print(f"lock-step round ({r['protocol']}, drilling, {r['round_s']:.0f} s simulated):")
    for v in r["variants"].values():
        extra = ""
        if v["variant"] == "recorder":
            extra = (f", file {v['bytes_per_min'] / 1e6:.2f} MB/min, queue max "
                     f"{v['queue_depth_max']}, close {v['close_s']:.2f} s")
        print(f"  {v['variant']:>8}: {v['speed_factor']:6.1f}x real time, "
              f"{v['us_per_tick']:6.1f} us/tick (world {v['world_us_per_tick']:.1f}), "
              f"{v['ticks']} ticks, {v['wall_s']:.1f} s wall, end {v['state']}, "
              f"reversals {v['reversals']}, completeness {fmt(v['completeness'], '.3f')}{extra}")
    prof = r.get("profile")
    if prof:
        print(f"  profile (cProfile, no sink; {prof['total_us_per_tick_profiled']:.0f} us/tick "
              "under the profiler):")
        print(f"    {'own us/tick':>11} {'cum us/tick':>11} {'calls/tick':>10}  function")
        for row in prof["by_own_time"]:
            print(f"    {row['own_us_per_tick']:11.2f} {row['cum_us_per_tick']:11.2f} "
                  f"{row['calls_per_tick']:10.2f}  {row['function']}")
        print("    by cumulative time (dentibot functions):")
        for row in prof["by_cumulative_time"]:
            print(f"    {row['own_us_per_tick']:11.2f} {row['cum_us_per_tick']:11.2f} "
                  f"{row['calls_per_tick']:10.2f}  {row['function']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=300.0, help="simulated round length")
    ap.add_argument("--profile", type=float, default=None, metavar="S",
                    help="also profile an S-second round")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    args = ap.parse_args()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
    print_report(measure(args.seconds, args.variants, args.profile))


if __name__ == "__main__":
    main()
