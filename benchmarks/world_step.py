"""Median / p99 time of one World.step with the file in contact and cutting.

Run: ``.venv/bin/python benchmarks/world_step.py [--n 20000]`` (target: median <= 30 us).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchutil import dist_us

from dentibot.sim.bench import world_step_times_us


def measure(n: int = 20000) -> dict:
    """``World.step`` times (us) while the file feeds 8 mm deep, cutting, in lateral contact."""
    return dist_us(world_step_times_us(n))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000)
    d = measure(ap.parse_args().n)
    print(f"World.step (contact + cutting), n={d['n']}: median {d['median_us']:.1f} us, "
          f"p99 {d['p99_us']:.1f} us, max {d['max_us']:.1f} us; target <= 30 us median: "
          f"{'met' if d['median_us'] <= 30.0 else 'NOT met'}")


if __name__ == "__main__":
    main()
