"""DentiBot's speed figures, measured the same way every time and compared side by side.

    .venv/bin/python benchmarks/run.py [--quick] [--json FILE] [--profile] [--only SECTION ...]

Sections (all by default, in this order; the real-time one last so that nothing of this
process is running beside it):

- ``control``: one control computation (median, p99) beside a plain-numpy DH baseline and
  roboticstoolbox-python's C kinematics ("not installed" without the ``bench`` extra), with
  the ratios; the Jacobian + 6x6 solve alone for the three (``control_tick.py``);
- ``world``: one ``World.step`` in contact and cutting (``world_step.py``);
- ``lockstep``: a 300 s drilling round (30 s with --quick) of the main job with controller and
  world together, without telemetry, with rows built, with the MCAP recorder: simulated
  seconds per wall second (``lockstep.py``); ``--profile`` adds a cProfile breakdown;
- ``tick``: the real lock-step tick, as ``dentibot run`` runs the main job (the protocol
  runner with the live summary and the MCAP recorder): its drill step timed whole with the
  recorder and without it (interleaved, repeated), and broken down by component
  (``real_tick.py``). The drill step drills the protocol's rounds, or one round of the
  lock-step round's length when that is shorter (--quick);
- ``population``: an in-silico trial's procedures on the machine's cores (two at most) as
  ``dentibot trial`` runs them, beside one of them alone, in simulated seconds per wall second
  (``population.py``);
- ``recording``: MCAP recorder throughput on real rows, file size per minute at 500 Hz
  (``recording_speed.py``);
- ``realtime``: the control task at 500 Hz and 1 kHz for 60 s each (10 s with --quick)
  against ``dentibot sim serve`` in another process, with one CPU-bound job running beside
  them, and the same loop paced by plain ``asyncio.sleep``; device round trips; stream losses
  (``realtime_loop.py``).

The machine's load average is recorded before and after: the figures are only comparable
between runs on a quiet machine, but ratios inside one run are always comparable.

Key figures of ``--json`` (all measured in the same run):

- ``lockstep_us_per_tick``, ``lockstep_speed_factor_recorder``: the whole lock-step tick as
  ``dentibot run`` runs the main job's drill step, recorder on (the default);
  ``lockstep_speed_factor``: the same without the recorder; ``lockstep_recorder_cost``:
  1 - on / off; ``lockstep_breakdown``: us per tick by component (``tick`` section);
- ``tick_rtb_ratio``: that whole tick over one C-accelerated Jacobian + 6x6 solve
  (roboticstoolbox's ``jacobe``, ``jacobian_solve_rtb_us_median``; None without the ``bench``
  extra); ``control_rtb_ratio``: the same chain on those C kinematics over our control
  computation (above 1: ours is faster); ``tick_us_median``: our control computation;
- ``lockstep_core_*``: the controller and the world alone, without the runner (``lockstep``);
- ``population_speed_factor``: the trial's simulated procedure-seconds per wall second, in
  aggregate; ``population_over_single``: its ratio to one procedure alone, same run;
  ``population_procedures_per_s``;
- ``lateness_us_p99_500hz``, ``sleep_lateness_us_p99_500hz``, ``overruns_500hz``: 500 Hz on
  the wire with ``realtime_load_jobs`` CPU-bound jobs beside it, with absolute deadlines and
  with plain ``asyncio.sleep``; ``realtime_priority_raised``: how the loop's priority was
  raised (``fifo``, ``nice`` or empty); ``platform_lateness_us_p99_500hz``,
  ``platform_overruns_500hz``: the platform's floor, a bare loop with the same clock and
  priority under the same load that only waits for its deadlines (in its own process): what
  the machine itself misses, which no control loop on it can do better than;
  ``witness_overruns_500hz``, ``witness_stalls_500hz``, ``witness_work_us``: a loop of its
  own beside the control loop in the same minutes, with ``witness_work_us`` of arithmetic per
  tick (``realtime_loop.py --witness-compute-us``), its overruns and its wake-ups 0.5 ms late
  or more: on a shared machine the minutes differ, and the witness says whether these were
  quiet ones (``overruns_shared_with_witness_500hz``: the loop's overruns that began in one
  of its stalls).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as _dt
import json
import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import structlog

sys.path.insert(0, str(Path(__file__).resolve().parent))

import control_tick
import lockstep
import population
import real_tick
import realtime_loop
import recording_speed
import world_step
from benchutil import fmt, load_average, machine

SECTIONS = ("control", "world", "lockstep", "tick", "population", "recording", "realtime")

#: The speed targets: (JSON key, comparison, bound).
TARGETS = {
    "tick_us_median": ("<=", 50.0),
    "world_step_us_median": ("<=", 30.0),
    "lockstep_speed_factor_recorder": (">=", 50.0),
    "tick_rtb_ratio": ("<=", 5.0),
    "lockstep_recorder_cost": ("<=", 0.20),
    "population_speed_factor": (">=", 500.0),
    "lateness_us_p99_500hz": ("<=", 100.0),
    "overruns_500hz": ("<=", 0),
}


@dataclass(frozen=True)
class Sizes:
    """How much of each benchmark to run."""

    tick_n: int = 20000
    world_n: int = 20000
    lockstep_s: float = 300.0
    recording_rows: int = 15000
    realtime_s: float = 60.0
    sleep_s: float = 10.0
    floor_s: float | None = None    # the bare loop's length (None: realtime_s)
    round_trips: int = 20
    rates: tuple[float, ...] = (500.0, 1000.0)
    realtime_load: int = 1          # CPU-bound jobs beside the real-time loop
    witness_work_us: float = 80.0   # the witness's arithmetic per tick (0: a bare witness)
    profile_s: float = 20.0
    tick_repeats: int = 3
    population_n: int = 64
    population_round_s: float = 300.0
    population_workers: int | None = None     # None: the machine's cores, two at most


FULL = Sizes()
QUICK = Sizes(tick_n=3000, world_n=3000, lockstep_s=30.0, recording_rows=3000,
              realtime_s=10.0, sleep_s=5.0, round_trips=5, profile_s=5.0,
              population_n=4, population_round_s=60.0)


def collect(sizes: Sizes = FULL, sections=SECTIONS, profile: bool = False,
            progress=None) -> dict:
    """Run the ``sections`` at ``sizes``; the nested results of each, plus the machine."""
    say = progress or (lambda msg: None)
    res: dict = {"sizes": dataclasses.asdict(sizes), "machine": machine(),
                 "load_average_before": load_average(),
                 "started": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}
    t0 = time.perf_counter()
    if "control" in sections:
        say(f"control tick ({sizes.tick_n} calls each)")
        res["control"] = control_tick.measure(sizes.tick_n)
    if "world" in sections:
        say(f"world step ({sizes.world_n} steps)")
        res["world"] = world_step.measure(sizes.world_n)
    if "lockstep" in sections:
        say(f"lock-step round ({sizes.lockstep_s:g} s simulated, 3 ways"
            f"{', then profiled' if profile else ''})")
        res["lockstep"] = lockstep.measure(sizes.lockstep_s,
                                           profile_seconds=sizes.profile_s if profile else None)
    if "tick" in sections:
        rounds = real_tick.drill_rounds_s()
        tick_s = None if sizes.lockstep_s >= rounds else sizes.lockstep_s
        say(f"real tick (the main job's drill step, {rounds if tick_s is None else tick_s:g} s "
            f"simulated, recorder on and off x{sizes.tick_repeats}, then broken down)")
        res["tick"] = real_tick.measure(tick_s, sizes.tick_repeats)
    if "population" in sections:
        say(f"population ({sizes.population_n} procedures x {sizes.population_round_s:g} s "
            "drilling, as dentibot trial runs them, then one alone)")
        res["population"] = population.measure(sizes.population_n, sizes.population_round_s,
                                               sizes.population_workers)
    if "recording" in sections:
        say(f"recording ({sizes.recording_rows} real rows)")
        res["recording"] = recording_speed.measure(sizes.recording_rows)
    if "realtime" in sections:
        say(f"real time ({', '.join(f'{r:g}' for r in sizes.rates)} Hz, {sizes.realtime_s:g} s "
            f"each, plain sleep {sizes.sleep_s:g} s each, wire simulators in another process, "
            f"{sizes.realtime_load} CPU-bound job(s) beside them)")
        res["realtime"] = realtime_loop.measure(sizes.realtime_s, sizes.rates, sizes.sleep_s,
                                                sizes.round_trips, load=sizes.realtime_load,
                                                floor_seconds=sizes.floor_s,
                                                with_witness=True,
                                                witness_work_us=sizes.witness_work_us)
    res["elapsed_s"] = time.perf_counter() - t0
    res["load_average_after"] = load_average()
    return res


def _hz(rate: str) -> str:
    return f"{float(rate):g}hz"


def flatten(res: dict) -> dict:
    """The key figures under flat names (the JSON's top level); ``details`` holds ``res``."""
    out: dict = {k: res[k] for k in ("started", "elapsed_s", "load_average_before",
                                     "load_average_after", "machine") if k in res}
    if "control" in res:
        c = res["control"]
        out["rtb_version"] = c["rtb_version"] or "not installed"
        for key, prefix in (("full", "tick"), ("jacobian_solve", "jacobian_solve")):
            g = c[key]
            out[f"{prefix}_us_median"] = g["dentibot"]["median_us"]
            out[f"{prefix}_us_p99"] = g["dentibot"]["p99_us"]
            for base in ("numpy_dh", "rtb"):
                d = g[base]
                out[f"{prefix}_{base}_us_median"] = d["median_us"] if d else None
                out[f"{prefix}_{base}_us_p99"] = d["p99_us"] if d else None
                out[f"{prefix}_{base}_ratio"] = g[f"ratio_{base}"]
        # the control computation against the same chain on roboticstoolbox's C kinematics
        # ("tick_rtb_ratio" is the whole lock-step tick's, below)
        out["control_rtb_ratio"] = out.pop("tick_rtb_ratio")
    if "world" in res:
        out["world_step_us_median"] = res["world"]["median_us"]
        out["world_step_us_p99"] = res["world"]["p99_us"]
    if "lockstep" in res:                    # the controller and the world alone
        ls = res["lockstep"]
        v = ls["variants"]
        out["lockstep_core_round_s"] = ls["round_s"]
        if "none" in v:
            out["lockstep_core_speed_factor"] = v["none"]["speed_factor"]
            out["lockstep_core_us_per_tick"] = v["none"]["us_per_tick"]
            out["lockstep_core_world_us_per_tick"] = v["none"]["world_us_per_tick"]
        if "rows" in v:
            out["lockstep_core_speed_factor_rows"] = v["rows"]["speed_factor"]
        if "recorder" in v:
            out["lockstep_core_speed_factor_recorder"] = v["recorder"]["speed_factor"]
            out["lockstep_recording_mb_per_min"] = v["recorder"]["bytes_per_min"] / 1e6
    if "tick" in res:                        # the whole tick, as dentibot run runs it
        tk = res["tick"]
        out["lockstep_us_per_tick"] = tk["us_per_tick_recorder"]
        out["lockstep_us_per_tick_no_recorder"] = tk["us_per_tick"]
        out["lockstep_speed_factor"] = tk["speed_factor"]
        out["lockstep_speed_factor_recorder"] = tk["speed_factor_recorder"]
        out["lockstep_recorder_ratio"] = tk["recorder_ratio"]
        out["lockstep_recorder_cost"] = 1.0 - tk["speed_factor_recorder"] / tk["speed_factor"]
        out["lockstep_writer_cpu_us_per_tick"] = tk["writer_cpu_us_per_tick"]
        out["lockstep_breakdown"] = tk.get("breakdown")
        rtb = out.get("jacobian_solve_rtb_us_median")
        out["tick_rtb_ratio"] = None if not rtb else out["lockstep_us_per_tick"] / rtb
    if "population" in res:
        pp = res["population"]
        for k in ("population_speed_factor", "population_over_single", "procedures_per_s",
                  "single_speed_factor", "single_compiled_speed_factor", "single_same_row"):
            out[k if k.startswith("population") else f"population_{k}"] = pp[k]
    if "recording" in res:
        first = res["recording"]["cases"][0]          # the protocol runner's setting
        out["recording_ticks_per_s"] = first["ticks_per_s"]
        out["recording_mb_per_min"] = first["mb_per_min_500hz"]
        out["recording_record_call_us_median"] = first["record_call_us"]["median_us"]
        out["recording_compression"] = first["compression"]
    if "realtime" in res:
        rt = res["realtime"]
        out["realtime_load_jobs"] = rt["load_jobs"]
        out["realtime_priority_raised"] = rt["priority_raised"]
        for rate, r in rt["rates"].items():
            hz = _hz(rate)
            floor = r.get("platform_floor")
            if floor is not None:
                out[f"platform_lateness_us_p99_{hz}"] = floor["lateness_us_exact"]["p99"]
                out[f"platform_lateness_us_max_{hz}"] = floor["lateness_us_exact"]["max"]
                out[f"platform_overruns_{hz}"] = floor["overruns"]
            witness = r["absolute_deadlines"].get("witness")
            if witness is not None:
                out["witness_work_us"] = witness["work_us"]
                out[f"witness_overruns_{hz}"] = witness["overruns"]
                out[f"witness_stalls_{hz}"] = witness["stalls"]
                out[f"overruns_shared_with_witness_{hz}"] = \
                    r["absolute_deadlines"]["overruns_shared_with_witness"]
            for prefix, name in (("", "absolute_deadlines"), ("sleep_", "plain_asyncio_sleep")):
                s = r.get(name)
                if s is None:
                    continue
                ex = s["lateness_us_exact"]
                out[f"{prefix}lateness_us_p50_{hz}"] = ex["p50"]
                out[f"{prefix}lateness_us_p99_{hz}"] = ex["p99"]
                out[f"{prefix}lateness_us_max_{hz}"] = ex["max"]
                out[f"{prefix}lateness_us_p99_bin_{hz}"] = s["lateness_us_p99"]
                out[f"{prefix}overruns_{hz}"] = s["overruns"]
                out[f"{prefix}skipped_{hz}"] = s["skipped"]
                out[f"{prefix}ticks_{hz}"] = s["ticks"]
                out[f"{prefix}effective_rate_hz_{hz}"] = s["effective_rate_hz"]
                out[f"{prefix}compute_us_mean_{hz}"] = s["compute_us_mean"]
                if not prefix:
                    out[f"state_{hz}"] = s["state"]
                    out[f"faults_{hz}"] = s["faults"]
                    for k, val in s["streams"].items():
                        out[f"{k}_{hz}"] = val
        for dev, v in rt["round_trips"].items():
            out[f"roundtrip_ms_median_{dev}"] = v["median_ms"]
    out["targets_met"] = {k: _met(out[k], *TARGETS[k]) for k in TARGETS if out.get(k) is not None}
    out["details"] = res
    return out


def _met(x, op: str, bound) -> bool:
    return x <= bound if op == "<=" else x >= bound


def _verdict(flat: dict, key: str) -> str:
    met = flat["targets_met"].get(key)
    return "" if met is None else ("met" if met else "NOT met")


def print_table(res: dict, flat: dict) -> None:
    """One line per figure: target, measured, what ran beside it, verdict."""
    m = res["machine"]
    rows: list[tuple[str, str, str, str, str]] = []
    if "control" in res:
        c = res["control"]
        rtb = "rtb" if c["rtb_version"] else "rtb not installed"
        for key, title, tkey in (("full", "control tick", "tick_us_median"),
                                 ("jacobian_solve", "  Jacobian + 6x6 solve", None)):
            g = c[key]
            d = g["dentibot"]
            beside = [(f"numpy DH {g['numpy_dh']['median_us']:.1f} us "
                      f"(x{g['ratio_numpy_dh']:.2f})")]
            if g["rtb"]:
                beside.append(f"{rtb} C kinematics {g['rtb']['median_us']:.1f} us "
                              f"(x{g['ratio_rtb']:.2f})")
            else:
                beside.append(rtb)
            rows.append((title + ", median (p99)", "<= 50 us" if tkey else "",
                         f"{d['median_us']:.1f} us ({d['p99_us']:.1f})", "; ".join(beside),
                         _verdict(flat, tkey) if tkey else ""))
    if "world" in res:
        w = res["world"]
        rows.append(("world step, median (p99)", "<= 30 us",
                     f"{w['median_us']:.1f} us ({w['p99_us']:.1f})", "",
                     _verdict(flat, "world_step_us_median")))
    if "lockstep" in res:
        ls = res["lockstep"]
        for name, v in ls["variants"].items():
            label = {"none": f"lock-step {ls['round_s']:g} s round, controller + world",
                     "rows": "  + telemetry rows built", "recorder": "  + MCAP recorder"}[name]
            extra = (f", {v['bytes_per_min'] / 1e6:.1f} MB/min" if name == "recorder" else
                     f", world {v['world_us_per_tick']:.0f}" if name == "none" else "")
            rows.append((label, "", f"{v['speed_factor']:.1f}x real time",
                         f"{v['us_per_tick']:.0f} us/tick{extra}", ""))
    if "tick" in res:
        tk = res["tick"]
        what = ("protocol's rounds" if tk["drill_seconds"] is None
                else f"{tk['drill_seconds']:g} s round")
        rows.append((f"whole lock-step tick, main job's drill step ({what}), as dentibot run "
                     f"runs it (recorder on)", ">= 50x",
                     f"{tk['speed_factor_recorder']:.1f}x real time",
                     (f"{tk['us_per_tick_recorder']:.0f} us/tick with the recorder, "
                      f"{tk['us_per_tick']:.0f} without (x{tk['recorder_ratio']:.2f}); "
                      f"the recorder's process {fmt(tk['writer_cpu_us_per_tick'], '.0f')} us "
                      f"CPU/tick"), _verdict(flat, "lockstep_speed_factor_recorder")))
        rows.append(("  recorder cost (1 - speed on / speed off)", "<= 0.20",
                     f"{flat['lockstep_recorder_cost']:.2f}", "",
                     _verdict(flat, "lockstep_recorder_cost")))
        if flat.get("tick_rtb_ratio") is not None:
            rows.append(("  whole tick / one C Jacobian + solve (roboticstoolbox)", "<= 5",
                         f"{flat['tick_rtb_ratio']:.1f}",
                         f"rtb jacobe + solve {flat['jacobian_solve_rtb_us_median']:.1f} us",
                         _verdict(flat, "tick_rtb_ratio")))
        b = tk.get("breakdown")
        if b:
            top = sorted(b.items(), key=lambda kv: -kv[1])
            rows.append(("  by component, us/tick", "", f"{tk['breakdown_us_per_tick']:.0f} hooked",
                         ", ".join(f"{k} {v:.0f}" for k, v in top if v >= 0.5), ""))
    if "population" in res:
        pp = res["population"]
        rows.append((f"population: {pp['n']} procedures x {pp['round_s']:g} s drilling on "
                     f"{pp['workers']} workers, in aggregate", ">= 500x",
                     f"{pp['population_speed_factor']:.1f}x real time",
                     (f"{pp['procedures_per_s']:.2f} procedures/s; one alone through the "
                      f"per-procedure runtime {pp['single_speed_factor']:.1f}x "
                      f"(x{pp['population_over_single']:.2f}), as the trial runs it "
                      f"{pp['single_compiled_speed_factor']:.1f}x (same row: "
                      f"{pp['single_same_row']}); {pp['engine']}"),
                     _verdict(flat, "population_speed_factor")))
    if "recording" in res:
        for cse in res["recording"]["cases"]:
            rows.append(((f"recording ({cse['compression']}"
                         f"{', validated' if cse['validate'] else ''})"), "",
                         f"{cse['ticks_per_s']:.0f} ticks/s",
                         (f"{cse['mb_per_min_500hz']:.1f} MB/min at 500 Hz, record() "
                         f"{cse['record_call_us']['median_us']:.1f} us"), ""))
    if "realtime" in res:
        rt = res["realtime"]
        for rate, r in rt["rates"].items():
            s = r["absolute_deadlines"]
            ex = s["lateness_us_exact"]
            sl = r.get("plain_asyncio_sleep")
            beside = ""
            if sl is not None:
                e2 = sl["lateness_us_exact"]
                beside = (f"plain asyncio.sleep: {fmt(e2['p50'], '.0f')}/{fmt(e2['p99'], '.0f')}/"
                          f"{fmt(e2['max'], '.0f')} us, {sl['overruns']} overruns, "
                          f"{sl['effective_rate_hz']:.0f} Hz")
            is500 = float(rate) == 500.0
            rows.append((f"{float(rate):g} Hz lateness p50/p99/max, {rt['seconds']:g} s, "
                         f"{rt['load_jobs']} CPU job(s) beside, priority "
                         f"{rt['priority_raised'] or 'not raised'}",
                         "p99 <= 100 us, 0 overruns" if is500 else "",
                         (f"{fmt(ex['p50'], '.0f')}/{fmt(ex['p99'], '.0f')}/"
                          f"{fmt(ex['max'], '.0f')} us, "
                         f"{s['overruns']} overruns, {s['skipped']} skipped"), beside,
                         ("met" if all(flat["targets_met"].get(k, False) for k in
                                       ("lateness_us_p99_500hz", "overruns_500hz"))
                          else "NOT met") if is500 else ""))
            w = s.get("witness")
            if w is not None:
                rows.append(((f"  witness at {float(rate):g} Hz: a loop beside it, same "
                              f"minutes, {w['work_us']:g} us of arithmetic per tick"), "",
                             f"{w['overruns']} overruns, {w['stalls']} stalls >= 0.5 ms",
                             (f"{s['overruns_shared_with_witness']} of the loop's overruns "
                              "began in one"), ""))
            fl = r.get("platform_floor")
            if fl is not None:
                e3 = fl["lateness_us_exact"]
                rows.append((f"  platform floor at {float(rate):g} Hz: a bare loop, same "
                             f"clock, priority and load", "",
                             (f"{fmt(e3['p50'], '.0f')}/{fmt(e3['p99'], '.0f')}/"
                              f"{fmt(e3['max'], '.0f')} us, {fl['overruns']} overruns"),
                             "what the machine itself misses", ""))
            if s["state"] == "fault":
                rows.append((f"  {float(rate):g} Hz loop ended in fault", "", "fault",
                             "; ".join(s["faults"])[:160], ""))
            st = s["streams"]
            rows.append((f"  streams during {float(rate):g} Hz", "",
                         f"F/T lost {st['ft_lost']} of {st['ft_received']}",
                         (f"EPOS4 SYNCs unanswered {st['motor_lost']} of "
                          f"{st['motor_received']} (own SYNC cycles late "
                          f"{st['motor_overruns']}), arm cycles {st['arm_received']} "
                          f"({st['arm_lost']} without joints); compute mean "
                          f"{s['compute_us_mean']:.0f} us; host heartbeat gap max "
                          f"{s['host_heartbeat_gap_max_ms']:.1f} ms (the drive's consumer "
                          f"{s['consumer_ms']} ms)"), ""))
        rts = rt["round_trips"]
        rows.append(("device round trips, median", "",
                     ", ".join(f"{k} {fmt(v['median_ms'], '.1f')}" for k, v in rts.items())
                     + " ms", "loopback, wire simulators in another process", ""))
    head = ("figure", "target", "measured", "beside it (same run)", "")
    widths = [max(len(r[i]) for r in [*rows, head]) for i in range(5)]
    order = (0, 1, 4, 2, 3)                  # the verdict next to the target
    rows = [tuple(r[i] for i in order) for r in rows]
    head = tuple(head[i] for i in order)
    widths = [widths[i] for i in order]
    print(f"DentiBot benchmarks - {m['cpu']}, {m['cores']} cores, Python {m['python']}, "
          f"numpy {m['numpy']}")
    print(f"load average before {res['load_average_before']}, after "
          f"{res['load_average_after']}; {res['elapsed_s']:.0f} s; (xN) = baseline median / "
          "ours, same run")
    line = "  ".join(f"{h:<{w}}" for h, w in zip(head, widths))
    print(line)
    print("-" * len(line))
    for r in rows:
        print("  ".join(f"{x:<{w}}" for x, w in zip(r, widths)).rstrip())
    prof = res.get("lockstep", {}).get("profile")
    if prof:
        print()
        lockstep.print_report({**res["lockstep"], "variants": {}})


def quiet_logs() -> None:
    """Errors only: a benchmark's output is its table (faults still show)."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
    # python-can: "Got incomplete message" on each TCP read that splits a frame (under load)
    logging.getLogger("can.interfaces.socketcand").setLevel(logging.ERROR)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help="smaller sizes: 30 s lock-step round, 10 s real-time loops")
    ap.add_argument("--json", metavar="FILE", help="write the figures to FILE")
    ap.add_argument("--profile", action="store_true",
                    help="add a cProfile breakdown of a lock-step round")
    ap.add_argument("--only", nargs="+", choices=SECTIONS, default=list(SECTIONS),
                    help="run only these sections")
    args = ap.parse_args(argv)
    quiet_logs()
    sizes = QUICK if args.quick else FULL
    res = collect(sizes, args.only, args.profile,
                  progress=lambda msg: print(f"... {msg}", file=sys.stderr, flush=True))
    flat = flatten(res)
    flat["command"] = " ".join(["benchmarks/run.py", *(argv if argv is not None
                                                       else sys.argv[1:])])
    print_table(res, flat)
    if args.json:
        Path(args.json).write_text(json.dumps(flat, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
