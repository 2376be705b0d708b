"""``dentibot report RUN.mcap``: the summary of a recorded run (table or ``--json``).

A recording that was not finished by its recorder (the run crashed or is still running, or the
file was rewritten by ``dentibot recover``) is reported as such: its status is ``incomplete``
when it has no ``/run/end``, and a line says what is missing. With ``--json`` the summary
gains a ``recording`` object: ``complete``, ``recovered`` (the recovery record or null) and
``problems``.
"""

from __future__ import annotations

import argparse
import json
import sys

from dentibot.cli.common import user_errors


@user_errors
def cmd_report(args: argparse.Namespace) -> int:
    from rich.console import Console

    from dentibot.telemetry import MessageStream, summary_table
    from dentibot.telemetry.summary import summarize_stream

    stream = MessageStream(args.recording)
    summary = summarize_stream(stream)
    note = incomplete_note(stream, args.recording, summary.status)
    if args.json:
        d = summary.to_dict()
        d["recording"] = {"complete": stream.complete, "recovered": stream.recovered,
                          "problems": stream.problems}
        print(json.dumps(d, indent=2))
        if note:
            print(note, file=sys.stderr)
    else:
        console = Console()
        console.print(summary_table(summary))
        if note:
            console.print(f"[bold red]INCOMPLETE recording[/]: {note}", highlight=False)
    return 0


def incomplete_note(stream, path: str, status: str) -> str:
    """What is missing from a recording not finished by its recorder ('' if finished)."""
    if stream.complete:
        return ""
    if stream.recovered is not None:
        r = stream.recovered
        return (f"recovered by 'dentibot recover' from {r.get('source', '?')} after the "
                f"recording was cut short: {r.get('ticks', '?')} ticks saved, "
                f"the run's end {'was' if r.get('run_end') == 'yes' else 'was not'} recorded")
    what = ("no /run/end: the run did not close its recording (crash, or still running)"
            if status == "incomplete" else "the file was not finished (no summary)")
    return (f"{what}; {'; '.join(stream.problems) or 'no footer'}. "
            f"'dentibot recover {path}' rewrites it into a finished file")


def add_parser(sub) -> None:
    report = sub.add_parser("report", help="summary of a recorded run (MCAP)")
    report.add_argument("recording", help="run recording, e.g. RUN.mcap")
    report.add_argument("--json", action="store_true", help="JSON instead of a table")
    report.set_defaults(func=cmd_report)
