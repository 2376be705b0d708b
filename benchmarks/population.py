"""Population speed: an in-silico trial's procedures per wall second, beside one procedure.

    .venv/bin/python benchmarks/population.py [--n 16] [--round 300] [--workers 2]

A trial of ``--n`` procedures over the default population (one arm: the main job's drill
step, the automated strategy at its tau_d), each a drilling round of ``--round`` simulated
seconds, run as ``dentibot trial`` runs it (:func:`dentibot.trials.runner.run_trial`, batches
of two on ``--workers`` local processes, Parquet files on disk: the feeding and retracting
ticks compiled, many per call, :mod:`dentibot.app.drill_loop`); then the first of those
procedures alone in this process, twice (:func:`~dentibot.trials.runner.run_procedure`, lock-step
time): through the per-procedure runtime tick by tick (``compiled_ticks=False``), and as the
trial runs it.

Figures, simulated seconds per wall second (each procedure's whole simulated time, its
set-up of load calibration and alignment included: ``simulated_s`` of the trial's table):

- ``population_speed_factor``: the trial's, in aggregate (its wall time includes starting the
  worker processes and writing the tables);
- ``single_speed_factor``: the one procedure's through the per-procedure runtime, tick by
  tick; ``single_compiled_speed_factor``: the same procedure as the trial runs it;
- ``population_over_single``: the trial's over the per-procedure runtime's.

Target: 1,000 procedures of a 300 s round in 10 minutes on two cores, 500x real time in
aggregate.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import structlog
from benchutil import fmt

from dentibot.trials.runner import procedures_of, run_procedure, run_trial
from dentibot.trials.spec import parse_trial

SPEC = """\
name: population-benchmark
seed: 11
n: {n}
batch_size: 2
rounds_s: [{round_s}]
arms:
  - {{name: automated}}
"""


def measure(n: int = 16, round_s: float = 300.0, workers: int | None = None) -> dict:
    """Run the trial, then its first procedure alone; the speed factors and their ratio."""
    workers = workers or min(2, os.cpu_count() or 1)
    spec = parse_trial(SPEC.format(n=n, round_s=round_s))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        run = run_trial(spec, Path(tmp) / "trial", workers=workers)
        wall = time.perf_counter() - t0
    rows = run.table.to_pylist()
    sim_s = sum(r["simulated_s"] for r in rows)
    first = procedures_of(spec, 0, [0])[0]
    single = run_procedure(first, compiled_ticks=False)
    compiled = run_procedure(first)
    same = ({k: v for k, v in single.items() if k != "wall_s"}
            == {k: v for k, v in compiled.items() if k != "wall_s"})
    single_factor = single["simulated_s"] / single["wall_s"]
    factor = sim_s / wall
    return {"n": n, "round_s": round_s, "workers": workers, "wall_s": wall,
            "simulated_s": sim_s, "population_speed_factor": factor,
            "procedures_per_s": n / wall, "single_speed_factor": single_factor,
            "single_wall_s": single["wall_s"],
            "single_compiled_speed_factor": compiled["simulated_s"] / compiled["wall_s"],
            "single_same_row": same, "population_over_single": factor / single_factor,
            "engine": "one procedure after another in each worker, its feeding and retracting "
                      "ticks compiled"}


def main() -> None:
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--round", type=float, default=300.0)
    ap.add_argument("--workers", type=int, default=None)
    a = ap.parse_args()
    r = measure(a.n, a.round, a.workers)
    print(f"{r['n']} procedures x {r['round_s']:g} s on {r['workers']} workers: "
          f"{fmt(r['population_speed_factor'])}x real time in aggregate "
          f"({r['procedures_per_s']:.2f} procedures/s); one procedure alone through the "
          f"per-procedure runtime {fmt(r['single_speed_factor'])}x, as the trial runs it "
          f"{fmt(r['single_compiled_speed_factor'])}x (same row: {r['single_same_row']}); "
          f"ratio {r['population_over_single']:.2f} (target 500x in aggregate)")


if __name__ == "__main__":
    main()
