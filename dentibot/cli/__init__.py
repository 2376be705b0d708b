"""The ``dentibot`` command line: one module per command, each with its
``add_parser(sub)``; this module builds the parser, configures logging and dispatches."""

from __future__ import annotations

import argparse

from dentibot import __version__


def _configure_logging(args: argparse.Namespace) -> None:
    from dentibot.logs import configure_logging

    configure_logging(args.log_level, json=args.log_json)


def build_parser() -> argparse.ArgumentParser:
    from dentibot.cli import experiment, fk, plot, recover, report, run, selftest, session, sim
    from dentibot.cli import tracker, trial

    parser = argparse.ArgumentParser(prog="dentibot", description="The dentibot command line.")
    parser.add_argument("--version", action="version", version=f"dentibot {__version__}")
    _logging_options(parser, top=True)
    sub = parser.add_subparsers(dest="command")
    for command in (run, sim, experiment, session, selftest, fk, report, recover, plot, trial,
                    tracker):
        command.add_parser(sub)
    _logging_options_everywhere(parser)
    return parser


def _logging_options(parser: argparse.ArgumentParser, top: bool = False) -> None:
    """``--log-level`` and ``--log-json``; below the top level they default to nothing, so
    the value given before the command stands unless the command's own is given."""
    parser.add_argument("--log-level", default="warning" if top else argparse.SUPPRESS,
                        choices=["debug", "info", "warning", "error"],
                        help="log level (logs go to stderr)")
    parser.add_argument("--log-json", action="store_true",
                        default=False if top else argparse.SUPPRESS, help="logs as JSON lines")


def _logging_options_everywhere(parser: argparse.ArgumentParser) -> None:
    """The logging options after any command or subcommand too (``dentibot run X --log-level
    info`` as well as ``dentibot --log-level info run X``)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                _logging_options(sub)
                _logging_options_everywhere(sub)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    _configure_logging(args)
    return args.func(args)
