"""The ``dentibot`` command line.

Subcommands arrive with their issues (run, session, sim serve, experiment, report, plot);
for now: the version and the arm's forward kinematics, handy at the bench to check a pose.
"""

from __future__ import annotations

import argparse
import sys

from dentibot import __version__


def _cmd_fk(args: argparse.Namespace) -> int:
    from dentibot.control.kinematics import Meca500, pose_from_matrix

    pose = pose_from_matrix(Meca500().fk(args.joints))
    print("x={:.3f} y={:.3f} z={:.3f} mm  alpha={:.3f} beta={:.3f} gamma={:.3f} deg".format(*pose))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dentibot", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"dentibot {__version__}")
    sub = parser.add_subparsers(dest="command")
    fk = sub.add_parser("fk", help="flange pose of the Meca500 for six joint angles (deg)")
    fk.add_argument("joints", nargs=6, type=float, metavar="Q")
    fk.set_defaults(func=_cmd_fk)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not hasattr(args, "func"):
        parser.print_help()
        return 2
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
