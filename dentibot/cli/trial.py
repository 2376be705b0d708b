"""``dentibot trial SPEC.yaml``: an in-silico trial on the built-in simulator (lock-step time):
each arm's settings over a population of canals, files and patients; fracture, completeness,
time to the working length and over-instrumentation per arm and curvature class, with 95 %
intervals, and the canals a file lasts.

``--out DIR`` (default runs/trials/<name>) holds the batches as they finish
(``batches/*.parquet``), then ``procedures.parquet`` (one row per procedure), ``summary.json``
and the figures (PNG). A rerun with the same spec and ``--out`` skips the batches already
there (after Ctrl-C). ``--workers N`` local processes, or ``--ray ADDRESS`` a Ray cluster.
``--json`` prints the summary. Progress (bar and ETA) goes to stderr.
Exit status: 0 done, 2 bad input, 130 interrupted (the finished batches are kept).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from dentibot.app.batch import quiet_logs
from dentibot.cli.common import user_errors
from dentibot.trials import report
from dentibot.trials.runner import PROCEDURES, run_trial
from dentibot.trials.spec import load_trial

#: Where a trial's outputs go unless told.
TRIALS_DIR = Path("runs/trials")


def _f(x, fmt="{:.2f}") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "--"
    return fmt.format(x)


def _pct(rate, ci) -> str:
    if rate is None:
        return "--"
    return f"{100 * rate:.0f} % ({100 * ci[0]:.0f}-{100 * ci[1]:.0f})"


def _table(summary: dict) -> Table:
    t = Table(title=f"Trial {summary['trial']}: {summary['procedures']} procedures, drilling "
                    f"{' + '.join(f'{d:g}' for d in summary['rounds_s'])} s "
                    "(rates with Wilson 95 % intervals)")
    for col in ("arm", "class", "n", "fracture", "reached WL", "time to WL s", "completeness",
                "over-instr.", "peak mNm", "canals/file"):
        t.add_column(col, justify="right")
    for a in summary["arms"]:
        life = a["file_life"]
        groups = [("all", a), *a["by_curvature"].items()]
        for k, (cls, e) in enumerate(groups):
            tw = e["t_wl_s"]
            t.add_row(a["name"] if k == 0 else "", cls, str(e["n"]),
                      _pct(e["fracture_rate"], e["fracture_rate_ci"]),
                      _pct(e["reached_wl_rate"], e["reached_wl_rate_ci"]),
                      f"{_f(tw['median'], '{:.0f}')} ({_f(tw['q25'], '{:.0f}')}-"
                      f"{_f(tw['q75'], '{:.0f}')})",
                      f"{_f(e['completeness_median'], '{:.3f}')} "
                      f"({_f(e['completeness_iqr'][0], '{:.3f}')}-"
                      f"{_f(e['completeness_iqr'][1], '{:.3f}')})",
                      _pct(e["over_instrumentation_rate"], e["over_instrumentation_rate_ci"]),
                      _f(e["peak_torque_mnm"]["max"], "{:.1f}"),
                      (f"{_f(life['median'], '{:g}')} ({_f(life['q25'], '{:g}')}-"
                       f"{_f(life['q75'], '{:g}')})") if k == 0 else "",
                      end_section=k == len(groups) - 1)
    return t


@user_errors
def cmd_trial(args: argparse.Namespace) -> int:
    spec = load_trial(args.spec)
    out = Path(args.out) if args.out else TRIALS_DIR / spec.name
    if getattr(args, "log_level", "warning") not in ("debug", "info"):
        quiet_logs(logging.CRITICAL)   # else every procedure warns, and logs each fault
    err = Console(file=sys.stderr)
    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(),
                        MofNCompleteColumn(), TimeElapsedColumn(), TextColumn("ETA"),
                        TimeRemainingColumn(), console=err, disable=args.quiet)
    task = None

    def start(total: int, kept: int) -> None:
        nonlocal task
        if kept and not args.quiet:
            err.print(f"{kept} of {total} procedures already in {out}: kept")
        task = progress.add_task(spec.name, total=total, completed=kept)

    def advance(batch) -> None:
        progress.advance(task, len(batch.procedures))

    try:
        with progress:
            run = run_trial(spec, out, workers=args.workers, ray_address=args.ray,
                            start=start, advance=advance)
    except KeyboardInterrupt:
        print(f"interrupted: the finished batches are in {out}; the same command goes on "
              "from there", file=sys.stderr)
        return 130
    summary = report.summarize(run.table, spec)
    summary["wall_s"] = run.wall_s
    summary["batches"] = {"ran": run.ran, "kept": run.kept}
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    figs = [] if args.no_figures else report.figures(run.table, spec, summary, out)
    if args.json:
        print(json.dumps(summary, indent=1))
        return 0
    con = Console() if sys.stdout.isatty() else Console(width=170)
    con.print(_table(summary))
    con.print("class: Schneider's curvature classes (straight <= 5 deg, moderate <= 20 deg, "
              "severe above). reached WL: the runtime's first arrival at the working length; "
              "time from the start of drilling. over-instr.: the true tip more than 0.2 mm past "
              "the working length. canals/file: median (quartiles) of the canals a file "
              "prepares before fatigue (Miner's rule) or a fracture ends it.")
    con.print(f"wrote {out / PROCEDURES}, {out / 'summary.json'}"
              + "".join(f", {p}" for p in figs))
    con.print(f"{run.ran} batches run, {run.kept} kept, in {run.wall_s:.1f} s")
    return 0


def _positive(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"{text}: must be >= 1")
    return n


def add_parser(sub) -> None:
    p = sub.add_parser("trial", help="an in-silico trial: settings over a population of "
                       "canals (simulator, lock-step time)", description=__doc__.split("\n\n")[0])
    p.add_argument("spec", help="the trial file (YAML)")
    p.add_argument("--out", help="output directory (default runs/trials/<name>)")
    p.add_argument("--workers", type=_positive, default=1, metavar="N",
                   help="parallel local processes (default 1)")
    p.add_argument("--ray", metavar="ADDRESS", default=None,
                   help="run the batches on a Ray cluster (e.g. auto, ray://host:10001); "
                        "needs ray installed")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--no-figures", action="store_true", help="write no figures")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_trial)
