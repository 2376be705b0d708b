"""``dentibot fk Q1..Q6``: the Meca500's flange pose for six joint angles (deg), handy at the
bench to check a pose."""

from __future__ import annotations

import argparse
import json


def cmd_fk(args: argparse.Namespace) -> int:
    from dentibot.control.kinematics import Meca500, pose_from_matrix

    pose = pose_from_matrix(Meca500().fk(args.joints))
    if args.json:
        keys = ("x_mm", "y_mm", "z_mm", "alpha_deg", "beta_deg", "gamma_deg")
        print(json.dumps({"joints_deg": list(args.joints),
                          "flange_pose": {k: float(v) for k, v in zip(keys, pose)}}))
        return 0
    print("x={:.3f} y={:.3f} z={:.3f} mm  alpha={:.3f} beta={:.3f} gamma={:.3f} deg".format(*pose))
    return 0


def add_parser(sub) -> None:
    fk = sub.add_parser("fk", help="flange pose of the Meca500 for six joint angles (deg)")
    fk.add_argument("joints", nargs=6, type=float, metavar="Q")
    fk.add_argument("--json", action="store_true",
                    help="print the pose as one JSON object (mm, deg; mobile XYZ Euler angles)")
    fk.set_defaults(func=cmd_fk)
