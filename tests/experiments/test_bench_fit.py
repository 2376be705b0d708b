"""The bench-fitted world against the thesis lab's recordings of experiment 1.

Reads the recordings' per-trial figures from ../shared/bench (relative to the repository);
skips when they are absent."""

import csv
from pathlib import Path

import pytest

from dentibot.experiments.alignment import (
    BENCH_CONFIGS,
    BENCH_GROUPS,
    BenchSpec,
    compare_bench,
    run_bench,
)

BENCH_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "bench"
TRIALS = BENCH_DIR / "exp1_trials.csv"


def _rows(config):
    if not TRIALS.exists():
        pytest.skip("bench recordings absent")
    with TRIALS.open() as fh:
        return [r for r in csv.DictReader(fh) if r["group"] == BENCH_GROUPS[config]]


def test_compare_definitions():
    rows = _rows("A")
    sim = {k: float(rows[0][k]) for k in ("Fh_z_mean_N", "torque_median_mNm")}
    cmp = {c["figure"]: c for c in compare_bench(sim, rows)}
    assert cmp["Fh_z_mean_N"]["inside"] and cmp["torque_median_mNm"]["inside"]
    assert cmp["rel_x_maxabs_mm"]["sim"] is None and not cmp["rel_x_maxabs_mm"]["inside"]


#: Share of the applicable figures inside the widened real range that the fitted world
#: reaches today (A 100 %, B 85 %, C 95 %, C_K250 78 %, seed 1): a floor against regressions.
REACHED = {"A": 0.96, "B": 0.83, "C": 0.93, "C_K250": 0.75}


@pytest.fixture(scope="module")
def bench_runs(worker_runs):
    """The four configurations' bench runs, two at a time in worker processes (each run is
    independent and as long as the others)."""
    if not TRIALS.exists():
        pytest.skip("bench recordings absent")
    return worker_runs({c: (run_bench, BenchSpec(c)) for c in BENCH_CONFIGS})


_SHARES: dict = {}


def _share(config, runs):
    if config not in _SHARES:
        cmp = compare_bench(runs[config].result(timeout=600), _rows(config))
        inside = sum(c["inside"] for c in cmp)
        _SHARES[config] = inside / len(cmp), [c["figure"] for c in cmp if not c["inside"]]
    return _SHARES[config]


@pytest.mark.slow
@pytest.mark.parametrize("config", BENCH_CONFIGS)
def test_bench_figures_keep_todays_share_within_the_real_range(config, bench_runs):
    share, out = _share(config, bench_runs)
    assert share >= REACHED[config], f"{share:.0%} inside; out: {out}"


_NOT_YET = pytest.mark.xfail(strict=True, reason="the fitted world is not there yet: B's "
                             "and C_K250's files leave their seat too far in square 4, "
                             "C_K250's in square 3 too")


@pytest.mark.slow
@pytest.mark.parametrize("config", [c if c in ("A", "C") else pytest.param(c, marks=_NOT_YET)
                                    for c in BENCH_CONFIGS])
def test_bench_figures_within_real_range(config, bench_runs):
    share, out = _share(config, bench_runs)
    assert share >= 0.9, f"{share:.0%} inside; out: {out}"
