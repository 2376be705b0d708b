"""Recording throughput: how fast the MCAP recorder writes real telemetry rows, and how big
the file grows per minute at 500 Hz.

    .venv/bin/python benchmarks/recording_speed.py [--rows 15000]

Rows are real: ``--rows`` consecutive ticks of the main job's drilling round on the built-in
simulator (the lock-step set-up of ``lockstep.py``), with the simulator's truth fields. They
are then handed to a fresh :class:`~dentibot.telemetry.recorder.McapRecorder` as fast as the
caller can (``record()`` each, then ``close()``), for each compression and with and without
schema validation. Figures: the writer's throughput (ticks written per wall second, from the
first ``record()`` to the end of ``close()``), the caller's cost per ``record()`` call, and
the file size per tick scaled to a minute at 500 Hz (events excluded: a handful per minute).
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import structlog

sys.path.insert(0, str(Path(__file__).resolve().parent))

import lockstep
from benchutil import dist_us

from dentibot.protocol.loader import load_protocol
from dentibot.telemetry.recorder import McapRecorder

#: (compression, validate): the protocol runner's setting first.
CASES = (("zstd", False), ("zstd", True), ("lz4", False), ("none", False))
RATE_HZ = 500.0


def real_rows(n: int) -> list[dict]:
    """``n`` consecutive telemetry rows of the main job's drilling round (lock-step)."""
    protocol = load_protocol(lockstep.PROTOCOL)
    rows: list[dict] = []

    async def go() -> None:
        async with lockstep.drilling(protocol, sink=rows.append) as (proc, _):
            await proc.run_for(ticks=n)

    asyncio.run(go())
    return rows[:n]


def write_rows(rows: list[dict], path: Path, compression: str = "zstd",
               validate: bool = False) -> dict:
    """Hand ``rows`` to a recorder as fast as possible; throughput, call cost, file size."""
    calls = np.empty(len(rows))
    clock = time.perf_counter_ns
    t0 = time.perf_counter()
    rec = McapRecorder(path, {"protocol": "bench", "rate_hz": RATE_HZ}, overwrite=True,
                       compression=compression, validate=validate)
    record = rec.record
    for i, row in enumerate(rows):
        c0 = clock()
        record(row)
        calls[i] = clock() - c0
    t_fed = time.perf_counter()
    rec.close("ok")
    wall = time.perf_counter() - t0
    size = path.stat().st_size
    path.unlink()
    n = len(rows)
    return {"compression": compression, "validate": validate, "rows": n,
            "ticks_written": rec.ticks_written, "rows_dropped": rec.rows_dropped,
            "ticks_per_s": rec.ticks_written / wall, "wall_s": wall,
            "feed_s": t_fed - t0, "queue_depth_max": rec.queue_depth_max,
            "record_call_us": dist_us(calls / 1000.0), "file_bytes": size,
            "bytes_per_tick": size / n, "mb_per_min_500hz": size / n * RATE_HZ * 60 / 1e6,
            "realtime_headroom_500hz": rec.ticks_written / wall / RATE_HZ}


def measure(rows_n: int = 15000, cases=CASES, out_dir: Path | None = None) -> dict:
    rows = real_rows(rows_n)
    path = (out_dir or Path(tempfile.gettempdir())) / "dentibot-bench-recording.mcap"
    results = [write_rows(rows, path, c, v) for c, v in cases]
    return {"rows": len(rows), "row_keys": sorted(rows[0]), "cases": results}


def print_report(r: dict) -> None:
    print(f"recording ({r['rows']} real rows, {len(r['row_keys'])} fields each):")
    for c in r["cases"]:
        print(f"  {c['compression']:>4}{' +validate' if c['validate'] else '':<10}: "
              f"{c['ticks_per_s']:8.0f} ticks/s ({c['realtime_headroom_500hz']:.1f}x 500 Hz), "
              f"record() median {c['record_call_us']['median_us']:.1f} us, "
              f"{c['bytes_per_tick']:.0f} B/tick = {c['mb_per_min_500hz']:.2f} MB/min at 500 Hz")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=15000)
    args = ap.parse_args()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
    print_report(measure(args.rows))


if __name__ == "__main__":
    main()
