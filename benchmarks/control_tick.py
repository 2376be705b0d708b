"""Control-tick compute time: the full computation against a plain-numpy DH baseline.

    .venv/bin/python benchmarks/control_tick.py [--n 20000]

Prints the median and p99 of one full control computation (wrench compensation + {S}->{H}
change + admittance step + tool Jacobian + joint rates + limits) and, in the same run, of a
plain numpy implementation that rebuilds six 4x4 DH matrices per call, with their ratio.
Target (issue 2): <= 50 us median on the project's 2-core machines.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from dentibot.control.admittance import SELF_ALIGNMENT, AdmittanceController
from dentibot.control.kinematics import MECA500_DH, Meca500, matrix_from_pose
from dentibot.control.tick import ControlComputation
from dentibot.control.wrench import GravityModel, WrenchTransform


def baseline_numpy_dh(q_deg, tool, wrench, gravity_gain, offset, w_matrix, filt_state):
    """The same computation the straightforward way: six 4x4 DH matrices, numpy throughout."""
    t = np.eye(4)
    origins, axes = [], []
    for (alpha, a, off, d), q in zip(MECA500_DH, q_deg):
        al, th = np.radians(alpha), np.radians(q + off)
        ca, sa, ct, st = np.cos(al), np.sin(al), np.cos(th), np.sin(th)
        ti = np.array([[ct, -st, 0, a], [sa * st * 0 + ca * st, ca * ct, -sa, -sa * d],
                       [sa * st, sa * ct, ca, ca * d], [0, 0, 0, 1.0]])
        t = t @ ti
        origins.append(t[:3, 3].copy())
        axes.append(t[:3, 2].copy())
    th_ = t @ tool
    ext = wrench - offset - gravity_gain @ t[2, :3]
    wh = w_matrix @ ext
    v = 0.5 * filt_state + wh / 160.0
    j = np.zeros((6, 6))
    for i in range(6):
        j[:3, i] = np.cross(axes[i], th_[:3, 3] - origins[i])
        j[3:, i] = axes[i]
    r = th_[:3, :3].T
    jh = np.vstack([r @ j[:3], r @ j[3:]])
    qdot = np.linalg.solve(jh, v)
    vmax = np.radians([150, 150, 180, 300, 300, 500])
    scale = min(1.0, float(np.min(vmax / np.maximum(np.abs(qdot), 1e-12))))
    return np.asarray(q_deg) + np.degrees(qdot * scale * 0.002)


def timeit_us(fn, n):
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter_ns()
        fn()
        out[i] = (time.perf_counter_ns() - t0) / 1000.0
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000)
    args = ap.parse_args()
    tool = matrix_from_pose([1.0, -0.5, 95.0, 0, 0, 0])
    robot = Meca500(tool=tool)
    gravity = GravityModel(f0_n=[0.3, -0.2, 1.1], tau0_nm=[0.01, -0.02, 0.005], weight_n=1.363,
                           centroid_mm=[2.0, -1.5, 45.0], mount_angle_deg=3.0)
    to_h = WrenchTransform.for_tool(np.eye(3), [1.0, -0.5, 95.0], mount_angle_deg=3.0)
    comp = ControlComputation(gravity, to_h, AdmittanceController(robot, SELF_ALIGNMENT))
    q = [0.0, 10.0, 20.0, 0.0, 30.0, 0.0]
    raw = np.array([0.5, -0.1, 1.4, 0.02, 0.01, 0.003])
    f_d = np.array([0, 0, 0.5, 0, 0, 0])
    ours = timeit_us(lambda: comp.step(q, raw, f_d), args.n)
    state = np.zeros(6)
    base = timeit_us(lambda: baseline_numpy_dh(q, tool, raw, gravity._gain, gravity._offset,
                                                to_h.matrix, state), args.n)
    med_o, med_b = np.median(ours), np.median(base)
    print(f"{'computation':<44}{'median us':>10}{'p99 us':>10}")
    print(f"{'dentibot control tick (closed form)':<44}{med_o:>10.1f}{np.percentile(ours, 99):>10.1f}")
    print(f"{'plain numpy DH baseline':<44}{med_b:>10.1f}{np.percentile(base, 99):>10.1f}")
    print(f"speed-up over baseline: {med_b / med_o:.2f}x; target <= 50 us median: "
          f"{'met' if med_o <= 50.0 else 'NOT met'}")
    assert math.isfinite(med_o)


if __name__ == "__main__":
    main()
