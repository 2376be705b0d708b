"""Smoke test of ``benchmarks/run.py``: every piece at tiny sizes, the JSON's keys, and the
figures that follow from the sizes alone (tick counts, ratios, bytes per minute).

No speed is asserted here (speed belongs in benchmarks/); this only checks that the benchmark
suite runs and reports its figures.
"""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"

TINY = {"tick_n": 200, "world_n": 200, "lockstep_s": 1.0, "recording_rows": 200,
        "realtime_s": 1.0, "sleep_s": 0.5, "floor_s": 0.5, "round_trips": 2,
        "rates": (500.0,),
        "profile_s": 0.5, "population_n": 2, "population_round_s": 1.0,
        "population_workers": 1,
        # no CPU-bound job beside the real-time loop here: the suite's wire tests may be
        # running on the other core, with 40 ms freshness bounds
        "realtime_load": 0}

REQUIRED = ("tick_us_median", "world_step_us_median", "lockstep_speed_factor_recorder",
            "lockstep_recorder_cost", "lateness_us_p99_500hz", "overruns_500hz",
            "population_speed_factor")
BASELINES = ("tick_numpy_dh_us_median", "tick_numpy_dh_ratio", "tick_rtb_us_median",
             "control_rtb_ratio", "tick_rtb_ratio", "jacobian_solve_us_median",
             "jacobian_solve_numpy_dh_us_median", "lockstep_us_per_tick",
             "lockstep_speed_factor", "lockstep_core_speed_factor_rows",
             "lockstep_core_speed_factor_recorder",
             "sleep_lateness_us_p99_500hz", "sleep_overruns_500hz",
             "platform_lateness_us_p99_500hz", "platform_overruns_500hz",
             "witness_overruns_500hz", "witness_stalls_500hz", "recording_ticks_per_s",
             "recording_mb_per_min", "roundtrip_ms_median_arm", "ft_lost_500hz",
             "population_over_single")


def _load_run():
    spec = importlib.util.spec_from_file_location("dentibot_benchmarks_run", BENCH / "run.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod          # dataclasses look their module up
    spec.loader.exec_module(mod)          # puts benchmarks/ on sys.path for its siblings
    return mod


@pytest.fixture(scope="module")
def results():
    path0 = list(sys.path)
    run = _load_run()
    try:
        res = run.collect(run.Sizes(**TINY), profile=True)
        yield run, res, run.flatten(res)
    finally:
        sys.path[:] = path0


@pytest.mark.timeout(90)
def test_json_has_the_expected_keys_and_is_serialisable(results):
    _, _, flat = results
    for key in (*REQUIRED, *BASELINES):
        assert key in flat, key
    for key in REQUIRED:
        assert isinstance(flat[key], (int, float)) and math.isfinite(flat[key]), key
    text = json.dumps(flat)
    assert json.loads(text)["overruns_500hz"] == flat["overruns_500hz"]
    # tick_rtb_ratio's target is judged only with roboticstoolbox installed
    assert set(REQUIRED) <= set(flat["targets_met"]) <= {*REQUIRED, "tick_rtb_ratio"}


def test_ratios_are_baseline_over_ours(results):
    _, res, flat = results
    assert flat["tick_numpy_dh_ratio"] == pytest.approx(
        flat["tick_numpy_dh_us_median"] / flat["tick_us_median"])
    if res["control"]["rtb_version"] is None:
        assert flat["rtb_version"] == "not installed" and flat["control_rtb_ratio"] is None
        assert flat["tick_rtb_ratio"] is None
    else:
        assert flat["control_rtb_ratio"] == pytest.approx(
            flat["tick_rtb_us_median"] / flat["tick_us_median"])
        assert flat["tick_rtb_ratio"] == pytest.approx(     # the whole tick, recorder on
            flat["lockstep_us_per_tick"] / flat["jacobian_solve_rtb_us_median"])
    assert flat["lockstep_recorder_cost"] == pytest.approx(
        1 - flat["lockstep_speed_factor_recorder"] / flat["lockstep_speed_factor"])
    assert res["control"]["full"]["dentibot"]["n"] == TINY["tick_n"]
    assert res["world"]["n"] == TINY["world_n"]


def test_lockstep_counts_follow_from_the_round(results):
    _, res, flat = results
    v = res["lockstep"]["variants"]
    assert set(v) == {"none", "rows", "recorder"}
    for var in v.values():
        # 1 s at the protocol's 500 Hz, unless the round ended early
        assert var["ticks"] == 500 or var["state"] in ("done", "fault")
        assert var["sim_seconds"] == pytest.approx(var["ticks"] * 0.002)
        assert var["speed_factor"] == pytest.approx(var["sim_seconds"] / var["wall_s"])
    rec = v["recorder"]
    assert rec["ticks_written"] == rec["ticks"] and rec["rows_dropped"] == 0
    assert rec["bytes_per_min"] == pytest.approx(rec["file_bytes"] / (rec["ticks"] * 0.002 / 60))
    assert flat["lockstep_core_speed_factor"] == v["none"]["speed_factor"]
    assert flat["lockstep_speed_factor_recorder"] == res["tick"]["speed_factor_recorder"]
    assert res["lockstep"]["profile"]["by_own_time"]


def test_recording_counts_and_size_per_minute(results):
    _, res, flat = results
    for case in res["recording"]["cases"]:
        assert case["ticks_written"] == TINY["recording_rows"] and case["rows_dropped"] == 0
        assert case["mb_per_min_500hz"] == pytest.approx(
            case["file_bytes"] / TINY["recording_rows"] * 500 * 60 / 1e6)
    sizes = {c["compression"]: c["file_bytes"] for c in res["recording"]["cases"]
             if not c["validate"]}
    assert sizes["zstd"] < sizes["none"] and sizes["lz4"] < sizes["none"]
    assert flat["recording_compression"] == "zstd"


def test_realtime_tick_counts_and_lateness_order(results):
    _, res, flat = results
    r = res["realtime"]["rates"]["500"]
    s, sl, fl = r["absolute_deadlines"], r["plain_asyncio_sleep"], r["platform_floor"]
    assert s["ticks"] == round(TINY["realtime_s"] * 500)
    assert sl["ticks"] == round(TINY["sleep_s"] * 500)
    assert fl["ticks"] == round(TINY["floor_s"] * 500)
    assert flat["platform_overruns_500hz"] == fl["overruns"] <= fl["ticks"]
    for stats in (s, sl, fl):
        ex = stats["lateness_us_exact"]
        assert 0.0 <= ex["p50"] <= ex["p99"] <= ex["max"]
        assert sum(stats["histogram_us"].values()) == stats["ticks"]
    assert flat["lateness_us_p99_500hz"] == s["lateness_us_exact"]["p99"]
    assert set(res["realtime"]["round_trips"]) == {"arm", "handpiece", "ft_bias",
                                                   "aux_platform"}
    assert res["load_average_before"] is None or len(res["load_average_before"]) == 3


def test_the_table_prints(results, capsys):
    run, res, flat = results
    run.print_table(res, flat)
    out = capsys.readouterr().out
    for figure in ("control tick", "world step", "lock-step", "500 Hz lateness", "recording",
                   "round trips"):
        assert figure in out


def test_the_real_tick_is_timed_with_and_without_the_recorder_and_broken_down(results):
    _, res, flat = results
    tk = res["tick"]
    assert tk["drill_seconds"] == TINY["lockstep_s"]       # shorter than the protocol's rounds
    for key in ("lockstep_us_per_tick", "lockstep_us_per_tick_no_recorder",
                "lockstep_speed_factor", "lockstep_speed_factor_recorder",
                "lockstep_recorder_ratio"):
        assert isinstance(flat[key], float) and flat[key] > 0.0, key
    assert flat["lockstep_speed_factor_recorder"] == pytest.approx(
        tk["ticks"] * 0.002 / (flat["lockstep_us_per_tick"] * tk["ticks"] / 1e6))
    assert len(tk["recorder_ratios"]) == 3
    for run in tk["runs"]["recorder"] + tk["runs"]["no_recorder"]:
        assert run["status"] == "ok" and run["ticks"] > TINY["lockstep_s"] * 500
    b = flat["lockstep_breakdown"]
    assert set(b) >= {"world_step", "control", "supervisor", "telemetry_row", "sim_truth",
                      "live_summary", "recorder_record", "glue"}
    assert b["world_step"] > 0.0 and b["control"] > 0.0
    # the components and the glue add up to the hooked run's tick
    assert sum(b.values()) == pytest.approx(tk["breakdown_us_per_tick"], rel=1e-6) or \
        b["glue"] == 0.0
