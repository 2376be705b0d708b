"""``dentibot report RUN.mcap``: the summary of a recorded run (table or ``--json``)."""

from __future__ import annotations

import argparse

from dentibot.cli.common import user_errors


@user_errors
def cmd_report(args: argparse.Namespace) -> int:
    from rich.console import Console

    from dentibot.telemetry import summarize_file, summary_json, summary_table

    summary = summarize_file(args.recording)
    if args.json:
        print(summary_json(summary))
    else:
        Console().print(summary_table(summary))
    return 0


def add_parser(sub) -> None:
    report = sub.add_parser("report", help="summary of a recorded run (MCAP)")
    report.add_argument("recording", help="run recording, e.g. RUN.mcap")
    report.add_argument("--json", action="store_true", help="JSON instead of a table")
    report.set_defaults(func=cmd_report)
