"""The ``dentibot`` command line.

Subcommands arrive with their issues (run, session, sim serve, experiment, report, plot);
for now: the version and the arm's forward kinematics, handy at the bench to check a pose.
"""

from __future__ import annotations

import argparse
import sys

from dentibot import __version__
from dentibot.errors import DentibotError


def _cmd_fk(args: argparse.Namespace) -> int:
    from dentibot.control.kinematics import Meca500, pose_from_matrix

    pose = pose_from_matrix(Meca500().fk(args.joints))
    print("x={:.3f} y={:.3f} z={:.3f} mm  alpha={:.3f} beta={:.3f} gamma={:.3f} deg".format(*pose))
    return 0


def user_errors(func):
    """Typed errors (missing file, not a recording...) -> message on stderr, exit status 2."""

    def wrapper(args: argparse.Namespace) -> int:
        try:
            return func(args)
        except DentibotError as exc:
            print(f"dentibot {args.command}: {exc}", file=sys.stderr)
            return 2

    return wrapper


@user_errors
def _cmd_report(args: argparse.Namespace) -> int:
    from rich.console import Console

    from dentibot.telemetry import summarize_file, summary_json, summary_table

    summary = summarize_file(args.recording)
    if args.json:
        print(summary_json(summary))
    else:
        Console().print(summary_table(summary))
    return 0


@user_errors
def _cmd_plot(args: argparse.Namespace) -> int:
    from dentibot.telemetry.plots import plot_recording

    written = plot_recording(args.recording, args.out)
    for path in written:
        print(f"wrote {path}")
    for name, reason in written.skipped.items():
        print(f"skipped {name}: {reason}")
    return 0


class _Stderr:
    """Whatever ``sys.stderr`` is when a line is logged (not when logging was configured)."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


def _configure_logging(args: argparse.Namespace) -> None:
    import logging

    import structlog

    level = getattr(logging, args.log_level.upper())
    processors = [structlog.processors.add_log_level, structlog.processors.TimeStamper("iso")]
    processors.append(structlog.processors.JSONRenderer() if args.log_json
                      else structlog.dev.ConsoleRenderer(colors=False))
    structlog.configure(processors=processors,
                        wrapper_class=structlog.make_filtering_bound_logger(level),
                        logger_factory=structlog.PrintLoggerFactory(_Stderr()))


def build_parser() -> argparse.ArgumentParser:
    from dentibot import cli_experiment, cli_run, cli_selftest, cli_session, cli_sim

    parser = argparse.ArgumentParser(prog="dentibot", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"dentibot {__version__}")
    parser.add_argument("--log-level", default="warning",
                        choices=["debug", "info", "warning", "error"],
                        help="log level (logs go to stderr)")
    parser.add_argument("--log-json", action="store_true", help="logs as JSON lines")
    sub = parser.add_subparsers(dest="command")
    cli_run.add_parser(sub)
    cli_sim.add_parser(sub)
    cli_experiment.add_parser(sub)
    cli_session.add_parser(sub)
    cli_selftest.add_parser(sub)
    fk = sub.add_parser("fk", help="flange pose of the Meca500 for six joint angles (deg)")
    fk.add_argument("joints", nargs=6, type=float, metavar="Q")
    fk.set_defaults(func=_cmd_fk)
    report = sub.add_parser("report", help="summary of a recorded run (MCAP)")
    report.add_argument("recording", help="run recording, e.g. RUN.mcap")
    report.add_argument("--json", action="store_true", help="JSON instead of a table")
    report.set_defaults(func=_cmd_report)
    plot = sub.add_parser("plot", help="figures of a recorded run (PNG)")
    plot.add_argument("recording", help="run recording, e.g. RUN.mcap")
    plot.add_argument("--out", required=True, help="directory for the PNG files")
    plot.set_defaults(func=_cmd_plot)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    _configure_logging(args)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
