#!/usr/bin/env python3
"""The bench-fitted world against the thesis lab's recordings of experiment 1, figure by
figure, as the Markdown tables of docs/sim-to-real.md.

    dentibot experiment alignment --bench --json --seeds N > sim.json
    .venv/bin/python tools/bench_report.py sim.json BENCH_DIR

BENCH_DIR, a copy of the bench recordings' figures, holds exp1_trials.csv. Each
figure's real range is the min..max over the configuration's recorded trials, widened by 20 %
of the median (at least 0.3 mm, 0.2 N, 3 ms or 2 mNm):
dentibot.experiments.alignment.compare_bench.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from dentibot.experiments.alignment import (  # noqa: E402
    BENCH_CONFIGS,
    BENCH_GROUPS,
    compare_bench,
)


def _f(v) -> str:
    return "--" if v is None else f"{v:.2f}"


def report(sim: dict, rows: list[dict]) -> str:
    out = []
    for cfg in BENCH_CONFIGS:
        real = [r for r in rows if r["group"] == BENCH_GROUPS[cfg]]
        cmp = compare_bench(sim["configs"][cfg]["bench_figures"], real)
        n_in = sum(c["inside"] for c in cmp)
        out += [(f"### {cfg}: {n_in} of {len(cmp)} figures inside "
                 f"({round(100 * n_in / len(cmp))}%)"), "",
                "| figure | real min..max | widened by | simulated | inside |",
                "|---|---|---|---|---|"]
        for c in cmp:
            out.append(f"| {c['figure']} | {c['real_min']:.2f}..{c['real_max']:.2f} | "
                       f"{c['widened']:.2f} | {_f(c['sim'])} | "
                       f"{'yes' if c['inside'] else '**no**'} |")
        out.append("")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sim", help="the JSON of dentibot experiment alignment --bench --json")
    ap.add_argument("bench", help="the folder of the bench recordings' figures "
                    "(exp1_trials.csv, exp1_traj_20hz.csv)")
    a = ap.parse_args(argv)
    sim = json.loads(Path(a.sim).read_text())
    with (Path(a.bench) / "exp1_trials.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    print(report(sim, rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
