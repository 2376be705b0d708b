"""``dentibot fk Q1..Q6``: the Meca500's flange pose for six joint angles (deg), handy at the
bench to check a pose."""

from __future__ import annotations

import argparse


def cmd_fk(args: argparse.Namespace) -> int:
    from dentibot.control.kinematics import Meca500, pose_from_matrix

    pose = pose_from_matrix(Meca500().fk(args.joints))
    print("x={:.3f} y={:.3f} z={:.3f} mm  alpha={:.3f} beta={:.3f} gamma={:.3f} deg".format(*pose))
    return 0


def add_parser(sub) -> None:
    fk = sub.add_parser("fk", help="flange pose of the Meca500 for six joint angles (deg)")
    fk.add_argument("joints", nargs=6, type=float, metavar="Q")
    fk.set_defaults(func=cmd_fk)
