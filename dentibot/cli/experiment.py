"""``dentibot experiment alignment|preclinical``: the thesis's chapter-6 experiments on the
built-in simulator, in lock-step simulated time, with the thesis's numbers alongside.

- ``alignment [--config A|B|C|all] [--tracking force|hybrid]``: experiment 1 (Table 6.4,
  fig 6.7-6.16), by force alone as in the thesis or with the patient tracker and hybrid
  control;
- ``patient-jerk [--mm --mm-s --deg]``: the patient jerks (and turns) while the file works at
  the working length, with and without the patient tracker;
- ``preclinical [--strategy automated|feedrate|reversal|none|all] [--material M]``:
  experiment 2 (Table 6.5) and its ablations.

``--seeds N --workers W`` runs N seeded patients / phantom sets in W local processes and
reports medians and worst cases. ``--json`` prints one JSON object (progress goes to stderr).
Figures (PNG) go to ``--out`` (default runs/experiments/<experiment>).
Exit status: 0 every claim of the thesis shown (an ablation claims none), 1 a claim not
shown (the table says which), 2 bad input, 130 aborted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable

import numpy as np
from rich.console import Console
from rich.table import Table

from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.cli.common import user_errors
from dentibot.errors import ConfigError
from dentibot.experiments import alignment as al
from dentibot.experiments import patient_jerk as pj
from dentibot.experiments import preclinical as pc
from dentibot.experiments import results as res
from dentibot.app import batch
from dentibot.app.batch import default_workers
from dentibot.protocol.schema import MATERIAL_NAMES


def _f(x, fmt="{:.2f}", none="--") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return fmt.format(x)


def _console() -> Console:
    """stdout; a pipe or file gets wide lines rather than rich's 80 columns."""
    return Console() if sys.stdout.isatty() else Console(width=160)


def _progress(args: argparse.Namespace) -> Callable[[str], None] | None:
    """The progress lines on stderr, unless ``--quiet``."""
    if args.quiet:
        return None
    console = Console(file=sys.stderr)
    return lambda text: console.print(text, soft_wrap=True, highlight=False)


def _checks_table(checks) -> Table:
    t = Table(title="The thesis's claims, checked on these runs", show_lines=False)
    t.add_column("claim")
    t.add_column("shown", justify="center")
    t.add_column("figures")
    for c in checks:
        t.add_row(c.claim, "[green]yes[/]" if c.passed else "[red]no[/]", c.detail)
    return t


# ---------------------------------------------------------------------------- alignment
def _alignment_tables(runs: dict[str, list[al.AlignmentRun]]) -> list[Table]:
    single = all(len(rs) == 1 for rs in runs.values())
    tables = []
    if single:
        t = Table(title="Experiment 1: relative distance handpiece-root (mm, base axes, from "
                        "the square's start) and detachments along the insertion axis")
        for col in ("config", "speed mm/s", "max |x|", "max |y|", "max |z|", "rms x / y / z",
                    "peak out", "law", "detach.", "recovery s"):
            t.add_column(col, justify="right")
        for cfg, (r,) in sorted(runs.items()):
            for s in r.speeds:
                rec = [d.recovery_s for d in s.detachments]
                t.add_row(cfg, f"{s.speed_mm_s:g}", *(_f(s.max_rel_mm[a]) for a in "xyz"),
                          " / ".join(_f(s.rms_rel_mm[a]) for a in "xyz"), _f(s.max_out_mm),
                          _f(s.expected_ripple_mm), str(len(s.detachments)),
                          ", ".join(_f(x, none="not yet") for x in rec) or "--")
            rec = [d.recovery_s for d in r.detachments]
            t.add_row(f"[bold]{cfg}[/]", "all", *(_f(r.max_rel_mm[a]) for a in "xyz"),
                      " / ".join(_f(r.rms_rel_mm[a]) for a in "xyz"), _f(r.max_out_mm), "",
                      str(len(r.detachments)),
                      _f(max((x for x in rec if x is not None), default=None)),
                      end_section=True)
        tables.append(t)
        return tables
    t = Table(title="Experiment 1 over a population: median / worst (mm, s)")
    for col in ("config", "n (not ok)", "max |x|", "max |y|", "max |z|", "speed mm/s",
                "peak out", "law", "detach.", "recovery s", "not recovered"):
        t.add_column(col, justify="right")
    for cfg, rs in sorted(runs.items()):
        p = al.population_summary(rs)
        if "speeds" not in p:
            t.add_row(cfg, str(p["n"]), "every run ended before the square", end_section=True)
            continue
        mr = p["max_rel_mm"]
        head = [cfg, f"{p['n']} ({p['not_ok']})",
                *(f"{_f(mr[a]['median'])} / {_f(mr[a]['worst'])}"
                                    for a in "xyz")]
        for k, s in enumerate(p["speeds"]):
            row = head if k == 0 else [""] * len(head)
            t.add_row(*row, f"{s['speed_mm_s']:g}",
                      f"{_f(s['max_out_mm']['median'])} / {_f(s['max_out_mm']['worst'])}",
                      _f(al.expected_ripple_mm(cfg, s["speed_mm_s"])),
                      f"{_f(s['detachments']['median'], '{:g}')} / "
                      f"{_f(s['detachments']['worst'], '{:g}')}",
                      f"{_f(s['recovery_s']['median'])} / {_f(s['recovery_s']['worst'])}",
                      str(s["not_recovered"]), end_section=k == len(p["speeds"]) - 1)
    tables.append(t)
    return tables


def _abort() -> int:
    print("aborted", file=sys.stderr)
    return 130


def cmd_alignment(args: argparse.Namespace) -> int:
    if getattr(args, "bench", False):
        return _cmd_bench(args)
    try:
        result = res.alignment_experiment(
            config=args.config, speeds=args.speeds, seeds=args.seeds, seed=args.seed,
            workers=args.workers, out=args.out, no_figures=args.no_figures,
            tracking=args.tracking, progress=_progress(args))
    except KeyboardInterrupt:
        return _abort()
    if args.json:
        print(json.dumps(result.to_dict(), indent=1))
    else:
        con = _console()
        for t in _alignment_tables(result.by_config):
            con.print(t)
        if args.tracking == "hybrid":
            con.print("tracking: hybrid (the patient tracker's tooth motion fed forward to the "
                      "arm, the force law correcting the rest); max across the canal: "
                      + ", ".join(f"{r.spec.config}/{r.spec.seed} "
                                  f"{_f(r.max_lateral_mm, '{:.3f}')} mm" for r in result.runs))
        con.print(f"detachment: the tip more than {al.DETACH_START_MM} mm out of its seated "
                  f"position along the file axis, until back within {al.DETACH_END_MM} mm; "
                  "recovery counted from the peak. law: what the admittance law predicts "
                  "(15 mm x (1 - k fz_max / (b3 v))). Thesis: X, Y within about 3 mm; config C "
                  "about 5 mm at 6 mm/s, back within about 5 s.")
        for r in result.runs:
            if r.status != "ok":
                con.print(f"[red]config {r.spec.config} seed {r.spec.seed}: {r.status}[/] "
                          f"{r.reason}")
        con.print(_checks_table(result.checks))
        for p in result.figures:
            con.print(f"wrote {p}")
        con.print(f"{len(result.runs)} runs of {result.runs[0].spec.duration_s:.0f} s "
                  f"simulated in {result.wall_s:.1f} s ({args.workers} workers)")
    return 0 if result.passed else 1


def _cmd_bench(args: argparse.Namespace) -> int:
    config = args.config if args.config in (*al.BENCH_CONFIGS, "all") else "all"
    try:
        result = res.bench_alignment_experiment(config=config, seeds=args.seeds,
                                                seed=args.seed, workers=args.workers,
                                                progress=_progress(args))
    except KeyboardInterrupt:
        return _abort()
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    t = Table(title="Experiment 1 on the bench-fitted world (median over seeds)")
    cfgs = list(result["configs"])
    t.add_column("figure")
    for c in cfgs:
        t.add_column(c, justify="right")
    for name in al.BENCH_FIGURES:
        t.add_row(name, *(_f(result["configs"][c]["bench_figures"].get(name), "{:.2f}")
                          for c in cfgs))
    _console().print(t)
    return 0


# ---------------------------------------------------------------------------- patient jerk
@user_errors
def cmd_patient_jerk(args: argparse.Namespace) -> int:
    try:
        result = res.patient_jerk_experiment(mm=args.mm, mm_s=args.mm_s, deg=args.deg,
                                             seed=args.seed, workers=args.workers,
                                             progress=_progress(args))
    except KeyboardInterrupt:
        return _abort()
    if args.json:
        print(json.dumps(result.to_dict(), indent=1))
        return 0 if result.passed else 1
    turn = (f", turning {args.deg:g} deg about the jaw's hinge ({pj.HINGE_MM:g} mm beyond "
            "the orifice along the canal)") if args.deg else ""
    t = Table(title=f"The tooth steps {args.mm:g} mm towards the robot along the canal at "
                    f"{args.mm_s:g} mm/s{turn} while the file works at the working length")
    for col in ("mode", "overshoot mm", "past WL s", "depth error mm", "axis error deg",
                "peak axis error deg", "fractures", "peak mNm", "state after the watch"):
        t.add_column(col, justify="right")
    for m, r in result.runs.items():
        t.add_row(m, f"{r.overshoot_mm:.2f}", f"{r.past_wl_s:.2f}",
                  _f(r.depth_error_mm, "{:.2f}"), _f(r.axis_error_deg, "{:.2f}"),
                  _f(r.peak_axis_error_deg, "{:.2f}"), str(r.fractures),
                  f"{r.peak_torque_mNm:.1f}", r.final_state
                  + (f" ({r.fault_cause})" if r.fault_cause else ""))
    con = _console()
    con.print(t)
    con.print("force: depth in the robot's base frame (the thesis); tracked: depth in the "
              "tooth's frame from the patient tracker; hybrid: that, and the tooth's motion "
              "(translation and turn) fed forward to the arm. overshoot: the deepest true tip "
              "depth past the working length; past WL: time more than 0.2 mm past it; depth "
              "error: true minus measured, 0.5 s after the jerk; axis error: the angle "
              "between the file and the canal, 0.5 s after the jerk (peak: the largest "
              "during the watch with the tip in the canal); -- where the run had stopped by "
              "then (see the state).")
    con.print(_checks_table(result.checks))
    return 0 if result.passed else 1


# ---------------------------------------------------------------------------- preclinical
def _preclinical_tables(runs: list[pc.PhantomRun]) -> list[Table]:
    members = sorted({r.spec.phantom.member for r in runs})
    strategy = runs[0].spec.strategy
    if len(members) == 1:
        t = Table(title=f"Experiment 2 (Table 6.5), strategy {strategy}: two rounds of "
                        f"{' s + '.join(f'{d:g}' for d in runs[0].spec.rounds_s)} s")
        for col in ("phantom", "canal", "WL mm", "tau_d", "red mm2 before > after",
                    "compl. %", "thesis %", "shaped %", "fracture", "peak mNm", "rev. (limit)", "passes",
                    "1st WL s", "stalled s", "fatigue"):
            t.add_column(col, justify="right")
        for r in runs:
            p = r.spec.phantom
            th = pc.THESIS_TABLE_6_5[p.name]
            frac = f"[red]{r.fracture_cause}[/]" if r.fracture else "no"
            t.add_row(p.name, p.describe(), f"{p.working_length_mm:.1f}", f"{p.tau_d_mnm:g}",
                      f"{_f(r.red_before_mm2, '{:.2f}')} > {_f(r.red_after_mm2, '{:.3f}')}",
                      f"{100 * r.completeness:.2f}", f"{100 * th[2]:.2f}",
                      f"{100 * r.shaping:.1f}", frac,
                      _f(r.peak_torque_mnm, "{:.1f}"), f"{r.reversals} ({r.limit_reversals})",
                      str(r.passes), _f(r.t_first_wl_s, "{:.0f}", "never"),
                      _f(r.stalled_s, "{:.0f}"), _f(r.fatigue_damage, "{:.2f}"))
        means = pc.group_means(runs)
        for tau, m in means.items():
            th = pc.THESIS_MEANS.get(tau)
            t.add_row(f"mean {tau:g}", "", "", "", "", f"{100 * m:.2f}",
                      "" if th is None else f"{100 * th:.2f}", "", "", "", "", "", "", "", "")
        return [t]
    p = pc.population_summary(runs)
    t = Table(title=f"Experiment 2 over {p['members']} phantom sets, strategy {strategy}: "
                    "median / worst")
    for col in ("phantom", "canal", "tau_d", "completeness", "thesis", "fractures",
                "peak torque mNm", "reversals", "stalled s", "never at WL"):
        t.add_column(col, justify="right")
    for e in p["phantoms"]:
        c, q = e["completeness"], e["peak_torque_mnm"]
        t.add_row(e["name"], e["canal"], f"{e['tau_d']:g}",
                  f"{_f(100 * c['median'])} / {_f(100 * c['worst'])} %",
                  f"{100 * pc.THESIS_TABLE_6_5[e['name']][2]:.2f} %",
                  f"{e['fractures']} of {e['n']}", f"{_f(q['median'], '{:.1f}')} / "
                  f"{_f(q['worst'], '{:.1f}')}",
                  f"{_f(e['reversals']['median'], '{:g}')} / "
                  f"{_f(e['reversals']['worst'], '{:g}')} "
                  f"({_f(e['limit_reversals']['worst'], '{:g}')})",
                  f"{_f(e['stalled_s']['median'], '{:.0f}')} / "
                  f"{_f(e['stalled_s']['worst'], '{:.0f}')}", str(e["never_reached_wl"]))
    for tau, d in p["tau_d_groups"].items():
        th = pc.THESIS_MEANS.get(tau)
        t.add_row(f"all tau_d {tau:g}", "", "", f"{_f(100 * d['median'])} / "
                  f"{_f(100 * d['worst'])} %", "" if th is None else f"{100 * th:.2f} % (mean)",
                  "", "", "", "", "")
    return [t]


def _numbers(text: str, check: Callable[[tuple[float, ...]], tuple[float, ...]],
             what: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: {what} separated by commas") from None
    try:
        return check(vals)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: {exc.limit}") from None


def _torque_limit(text: str) -> float:
    v = _numbers(text, lambda vals: tuple(res.torque_limit_of(x) for x in vals), "mNm")
    if len(v) != 1:
        raise argparse.ArgumentTypeError(f"{text!r}: one number of mNm")
    return v[0]


def _rounds(text: str) -> tuple[float, ...]:
    return _numbers(text, res.rounds_of, "seconds")


def _speeds(text: str) -> tuple[float, ...]:
    return _numbers(text, res.speeds_of, "mm/s")


def cmd_preclinical(args: argparse.Namespace) -> int:
    try:
        result = res.preclinical_experiment(
            strategy=args.strategy, material=args.material, torque_limit=args.torque_limit,
            phantom=args.phantom, rounds=args.rounds, seeds=args.seeds, seed=args.seed,
            workers=args.workers, out=args.out, no_figures=args.no_figures,
            progress=_progress(args))
    except ConfigError as exc:
        print(f"dentibot experiment preclinical: {exc.field} {exc.value!r}: {exc.limit}",
              file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return _abort()
    if args.json:
        print(json.dumps(result.to_dict(), indent=1))
        return 0 if result.passed else 1
    by = result.by_strategy
    con = _console()
    for rs in by.values():
        for t in _preclinical_tables(rs):
            con.print(t)
    if len(by) > 1:
        con.print(_strategy_table(by))
    con.print("canal: tilt deg, or curve angle deg / radius mm @ start depth mm. red: the "
              "red-stained canal as a photograph across it shows it (Table 6.5 counts its "
              "pixels, so compare completeness). shaped: how much of the volume between "
              "the initial lumen and the target #25/.06 shape was cut. "
              f"stalled: feeding without gaining {batch.STALL_GAIN_MM} mm of new depth in "
              f"{batch.STALL_WINDOW_S:g} s before first reaching the working length. fatigue: "
              "Miner sum (1 = fatigue fracture). reversals (limit): all reversals (those the "
              "runtime's hard torque limit forced, whatever the strategy). Phantom "
              f"material: {args.material}. Hard torque limit: "
              + ", ".join(f"{st} {_limit_text(rs[0].spec)}"
                          for st, rs in by.items()) + ".")
    if args.strategy not in ("automated", "all"):
        con.print("An ablation's figures mean most beside the automated algorithm's: "
                  "--strategy all runs the four strategies on the same phantoms.")
    for r in result.runs:
        if r.status not in ("ok", "fracture"):
            con.print(f"[red]{r.spec.strategy}: phantom {r.name} seed "
                      f"{r.spec.phantom.member}: {r.status}[/] {r.reason}")
    if result.checks:
        con.print(_checks_table(result.checks))
    for p in result.figures:
        con.print(f"wrote {p}")
    con.print(f"{len(result.runs)} runs of {sum(args.rounds):g} s simulated in "
              f"{result.wall_s:.1f} s ({args.workers} workers)")
    return 0 if result.passed else 1


def _limit_text(spec: pc.PreclinicalSpec) -> str:
    limit = pc.torque_limit_of(spec)
    if limit >= FILE_STRENGTH_MNM:
        return f"{limit:g} mNm (at the strength: off in effect)"
    return f"{limit:.1f} mNm ({100 * limit / FILE_STRENGTH_MNM:.0f} % of the strength)"


def _strategy_table(by: dict[str, list[pc.PhantomRun]]) -> Table:
    """The strategies side by side on the same phantoms: what each protection buys."""
    t = Table(title="What each protection buys (same phantoms, same rounds)")
    for col in ("strategy", "fractures", "mean compl. % tau_d 40", "tau_d 50",
                "peak mNm", "reversals (median)", "stalled s (median)", "never at WL"):
        t.add_column(col, justify="right")
    for st, rs in by.items():
        means = pc.group_means(rs)
        t.add_row(st, f"{sum(r.fracture for r in rs)} of {len(rs)}",
                  _f(100 * means[40.0] if 40.0 in means else None),
                  _f(100 * means[50.0] if 50.0 in means else None),
                  f"{max(r.peak_torque_mnm for r in rs):.1f}",
                  f"{float(np.median([r.reversals for r in rs])):g}",
                  f"{float(np.median([r.stalled_s for r in rs])):.0f}",
                  str(sum(r.t_first_wl_s is None for r in rs)))
    return t


# ---------------------------------------------------------------------------- parser
def _positive(text: str) -> int:
    n = int(text)
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text}: must be >= 1")
    return n


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seeds", type=_positive, default=1, metavar="N",
                   help="population: N seeded random patients/phantoms (default 1: the "
                        "thesis's set-up)")
    p.add_argument("--seed", type=int, default=1, help="first seed (default 1)")
    p.add_argument("--workers", type=_positive, default=default_workers(), metavar="W",
                   help="parallel local processes (default: the CPU count)")
    p.add_argument("--json", action="store_true", help="print the results as one JSON object")
    p.add_argument("--out", help="directory for the figures (default runs/experiments/...)")
    p.add_argument("--no-figures", action="store_true", help="write no figures")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")


def add_parser(sub) -> None:
    exp = sub.add_parser("experiment", help="the thesis's chapter-6 experiments on the "
                         "simulator (lock-step time)", description=__doc__.split("\n\n")[0])
    esub = exp.add_subparsers(dest="experiment", required=True)
    a = esub.add_parser("alignment", help="experiment 1: force-guided alignment while the "
                        "phantom rides the Stewart-platform square (Table 6.4)")
    a.add_argument("--config", choices=[*al.CONFIGS, "all"], default="all",
                   help="Table 6.4 configuration (default all)")
    a.add_argument("--speeds", type=_speeds, default=al.SPEEDS_MM_S, metavar="V,V",
                   help="platform speeds of the squares in mm/s (default 3,4,5,6)")
    a.add_argument("--tracking", choices=al.TRACKING, default="force",
                   help="force: the file follows the patient by the admittance law alone (the "
                        "thesis, default); hybrid: with the patient tracker, the tooth's motion "
                        "fed forward to the arm")
    a.add_argument("--bench", action="store_true",
                   help="run A, B, C and C_K250 as the thesis's bench ran them on the "
                        "bench-fitted world and print the recordings' figures")
    _common(a)
    a.set_defaults(func=cmd_alignment)
    j = esub.add_parser("patient-jerk", help="the tooth jerks towards the robot along the "
                        "canal while the file works at the working length: depth in the "
                        "robot's frame against depth in the tooth's frame (patient tracker)")
    j.add_argument("--mm", type=float, default=3.0, help="the jerk's travel (mm, default 3)")
    j.add_argument("--mm-s", type=float, default=20.0,
                   help="the jerk's speed (mm/s, default 20)")
    j.add_argument("--deg", type=float, default=0.0,
                   help="the patient also turns by this much (deg, default 0) in step with "
                        "the jerk, about the jaw's hinge")
    j.add_argument("--seed", type=int, default=1, help="the simulated world's seed (default 1)")
    j.add_argument("--workers", type=_positive, default=min(3, default_workers()),
                   metavar="W", help="parallel local processes (default: up to 3, one per mode)")
    j.add_argument("--json", action="store_true", help="print the results as one JSON object")
    j.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    j.set_defaults(func=cmd_patient_jerk)
    p = esub.add_parser("preclinical", help="experiment 2: six phantoms A-F, two rounds of "
                        "300 s and 200 s (Table 6.5)")
    p.add_argument("--strategy", choices=[*pc.STRATEGIES, "all"], default="automated",
                   help="drilling strategy: automated (thesis 5.4), or an ablation: feedrate "
                        "(no reversal), reversal (no feedrate control), none (neither); all: "
                        "the four side by side (four times the runs)")
    p.add_argument("--material", choices=list(MATERIAL_NAMES), default=pc.MATERIAL,
                   help=f"phantom material (default {pc.MATERIAL}, the thesis's phantoms)")
    p.add_argument("--torque-limit", type=_torque_limit, default=None, metavar="MNM",
                   help="the runtime's hard file-torque limit (default: 90 %% of the "
                        "strength for automated, the strength itself for the ablations)")
    p.add_argument("--phantom", default="all", help="phantoms to run, e.g. AD (default all)")
    p.add_argument("--rounds", type=_rounds, default=pc.ROUNDS_S, metavar="S,S",
                   help="round durations in s (default 300,200)")
    _common(p)
    p.set_defaults(func=cmd_preclinical)
