"""``dentibot run PROTOCOL.yaml``: the protocol runner with a live progress display.

A progress bar per step with the live key figures (state, depth / working length, file torque
against its limit, force), then the result table (or ``--json``). Exit status: 0 ok,
3 fault, 4 fracture, 130 aborted (Ctrl-C), 143 terminated (SIGTERM; stopped as safely as
Ctrl-C), 2 bad input (nothing started).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from dentibot.cli.common import user_errors
from dentibot.cli.devices_option import add_devices_options, devices_from_args
from dentibot.protocol.loader import load_protocol
from dentibot.app.runner import EXIT_CODES, ProtocolRunner, step_duration_s
from dentibot.telemetry import summary_table


def _figures_text(f: dict) -> str:
    depth = f["depth_mm"]
    depth_s = "--" if depth is None else f"{depth:5.2f}"
    comp = f.get("completeness")
    comp_s = "" if comp is None else f"  shaped {100 * comp:4.1f}%"
    return (f"{f['state']:<28} depth {depth_s}/{f['working_length_mm']:.1f} mm  "
            f"torque {f['file_torque_mnm']:5.1f}/{f['torque_limit_mnm']:.0f} mNm  "
            f"force {f['force_n']:4.2f} N{comp_s}")


def cmd_run(args: argparse.Namespace) -> int:
    return user_errors(_run)(args)


def _run(args: argparse.Namespace) -> int:
    protocol = load_protocol(args.protocol)          # bad input: raises before anything runs
    devices = devices_from_args(args, "run")
    out = sys.stderr if args.json else sys.stdout
    console = Console(file=out)
    progress = Progress(TextColumn("{task.description:<16}"), BarColumn(bar_width=24),
                        TimeElapsedColumn(), TextColumn("{task.fields[figures]}"),
                        console=console, transient=False, disable=args.quiet)
    tasks: dict[str, tuple] = {}        # step -> (progress task id, step start time)

    def on_progress(f: dict) -> None:
        step = f["step"]
        if step not in tasks:
            for task, _ in tasks.values():  # the previous step is over
                progress.update(task, total=1, completed=1)
            total = step_duration_s(protocol, step)
            tasks[step] = (progress.add_task(step, total=total, figures=""), f["t"])
        task, t0 = tasks[step]
        progress.update(task, completed=f["t"] - t0, figures=_figures_text(f))

    runner = ProtocolRunner(protocol, recording=None if args.out is None else args.out,
                            progress=on_progress, no_record=args.no_record,
                            devices=devices, overwrite=args.force, live=args.live,
                            resume_arm=args.resume_arm)
    try:
        with progress:
            result = asyncio.run(runner.run(handle_sigint=True))
    except KeyboardInterrupt:
        summary = runner.summary
        console.print("[bold red]aborted[/]: file stopped, withdrawn, arm stopped")
        if summary is not None:
            _print_summary(summary, runner, args, console)
        return EXIT_CODES["aborted"]
    _print_summary(result.summary, runner, args, console)
    return result.exit_code


def _print_summary(summary, runner, args, console) -> None:
    if args.json:
        out = summary.to_dict()
        out["recording"] = None if runner.path is None else str(runner.path)
        print(json.dumps(out, indent=2))
    else:
        console.print(summary_table(summary))
        if runner.path is not None:
            console.print(f"recording: {runner.path}  (dentibot report {runner.path})")


def add_parser(sub) -> None:
    run = sub.add_parser("run", help="run a treatment protocol (YAML) end to end")
    run.add_argument("protocol", help="protocol file, e.g. protocols/root-canal.yaml")
    run.add_argument("--json", action="store_true",
                     help="print the result as one JSON object (progress goes to stderr)")
    run.add_argument("--out", help="recording file (MCAP); default from the protocol")
    run.add_argument("--no-record", action="store_true", help="do not write a recording")
    run.add_argument("--live", type=int, nargs="?", const=8765, default=None, metavar="PORT",
                     help="serve the run live to Foxglove on ws://127.0.0.1:PORT (default "
                          "8765)")
    run.add_argument("--force", action="store_true",
                     help="replace the recording file if it exists (refused otherwise)")
    add_devices_options(run)
    run.add_argument("--resume-arm", action="store_true",
                     help="with devices: resume an arm found paused (a run that did not park "
                          "it, an expired connection watchdog) once the workspace is clear; "
                          "an arm in error is still refused")
    run.add_argument("--quiet", action="store_true", help="no progress display")
    run.set_defaults(func=cmd_run)
