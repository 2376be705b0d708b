"""``dentibot plot RUN.mcap --out DIR``: figures of a recorded run (PNG, thesis fig 6.7-6.16
style)."""

from __future__ import annotations

import argparse
import json

from dentibot.cli.common import user_errors


@user_errors
def cmd_plot(args: argparse.Namespace) -> int:
    from dentibot.telemetry.plots import plot_recording

    written = plot_recording(args.recording, args.out)
    if args.json:
        print(json.dumps({"written": [str(p) for p in written], "skipped": written.skipped},
                         indent=2))
        return 0
    for path in written:
        print(f"wrote {path}")
    for name, reason in written.skipped.items():
        print(f"skipped {name}: {reason}")
    return 0


def add_parser(sub) -> None:
    plot = sub.add_parser("plot", help="figures of a recorded run (PNG)")
    plot.add_argument("recording", help="run recording, e.g. RUN.mcap")
    plot.add_argument("--out", required=True, help="directory for the PNG files")
    plot.add_argument("--json", action="store_true",
                      help="print the files written and the figures skipped (with why) as JSON")
    plot.set_defaults(func=cmd_plot)
