"""What every command shares: typed errors turned into a message and exit status 2."""

from __future__ import annotations

import argparse
import sys

from dentibot.errors import DentibotError


def user_errors(func):
    """Typed errors (missing file, not a recording...) -> message on stderr, exit status 2."""

    def wrapper(args: argparse.Namespace) -> int:
        try:
            return func(args)
        except DentibotError as exc:
            print(f"dentibot {args.command}: {exc}", file=sys.stderr)
            return 2

    return wrapper
