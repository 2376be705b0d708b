"""The ``dentibot`` command line: one module per command, each with its
``add_parser(sub)``; this module builds the parser, configures logging and dispatches."""

from __future__ import annotations

import argparse
import sys

from dentibot import __version__


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
    from dentibot.cli import experiment, fk, plot, recover, report, run, selftest, session, sim

    parser = argparse.ArgumentParser(prog="dentibot", description="The dentibot command line.")
    parser.add_argument("--version", action="version", version=f"dentibot {__version__}")
    parser.add_argument("--log-level", default="warning",
                        choices=["debug", "info", "warning", "error"],
                        help="log level (logs go to stderr)")
    parser.add_argument("--log-json", action="store_true", help="logs as JSON lines")
    sub = parser.add_subparsers(dest="command")
    for command in (run, sim, experiment, session, selftest, fk, report, recover, plot):
        command.add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    _configure_logging(args)
    return args.func(args)
