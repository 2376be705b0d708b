"""Control-tick compute time: the full computation beside a plain-numpy DH baseline and, when
roboticstoolbox-python is installed, its C-accelerated kinematics.

    .venv/bin/python benchmarks/control_tick.py [--n 20000]

Prints the median and p99 of one full control computation (wrench compensation + {S}->{H}
change + admittance step + tool Jacobian + joint rates + limits) and, in the same run:

- a plain numpy implementation that rebuilds six 4x4 DH matrices per call;
- the same plain-numpy computation with its kinematics (forward chain and tool Jacobian in {H})
  from roboticstoolbox-python's C extension (``ETS.eval`` + ``ETS.jacobe``) ("not installed"
  when the optional ``bench`` extra is absent);
- the Jacobian + 6x6 solve alone, for each of the three kinematics,

with the ratios (baseline median / ours). The three Jacobians are checked equal first, so the
comparison is between implementations of the same maths.
Target: <= 50 us median on the project's 2-core machines.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from benchutil import dist_us, fmt, timeit_us

from dentibot.control.admittance import SELF_ALIGNMENT, AdmittanceController
from dentibot.control.kinematics import (
    MECA500_DH,
    MECA500_JOINT_SPEED_LIMITS_DEG_S,
    Meca500,
    matrix_from_pose,
)
from dentibot.control.tick import ControlComputation
from dentibot.control.wrench import GravityModel, WrenchTransform

VMAX_RAD_S = np.radians(MECA500_JOINT_SPEED_LIMITS_DEG_S)
Q_DEG = [0.0, 10.0, 20.0, 0.0, 30.0, 0.0]
TOOL_POSE = [1.0, -0.5, 95.0, 0, 0, 0]


def numpy_dh_tool_jacobian(q_deg, tool):
    """0T_6 and the tool Jacobian in {H} the straightforward way: six 4x4 DH matrices."""
    t = np.eye(4)
    origins, axes = [], []
    for (alpha, a, off, d), q in zip(MECA500_DH, q_deg):
        al, th = np.radians(alpha), np.radians(q + off)
        ca, sa, ct, st = np.cos(al), np.sin(al), np.cos(th), np.sin(th)
        ti = np.array([[ct, -st, 0, a], [ca * st, ca * ct, -sa, -sa * d],
                       [sa * st, sa * ct, ca, ca * d], [0, 0, 0, 1.0]])
        t = t @ ti
        origins.append(t[:3, 3].copy())
        axes.append(t[:3, 2].copy())
    th_ = t @ tool
    j = np.zeros((6, 6))
    for i in range(6):
        j[:3, i] = np.cross(axes[i], th_[:3, 3] - origins[i])
        j[3:, i] = axes[i]
    r = th_[:3, :3].T
    return t, np.vstack([r @ j[:3], r @ j[3:]])


def _rest_of_tick(q_deg, r_0_6, jh, wrench, gravity_gain, offset, w_matrix, filt_state):
    """Compensation, {H} change, first-order admittance, solve, speed scaling, integration."""
    ext = wrench - offset - gravity_gain @ r_0_6[2, :3]
    wh = w_matrix @ ext
    v = 0.5 * filt_state + wh / 160.0
    qdot = np.linalg.solve(jh, v)
    scale = min(1.0, float(np.min(VMAX_RAD_S / np.maximum(np.abs(qdot), 1e-12))))
    return np.asarray(q_deg) + np.degrees(qdot * scale * 0.002)


def baseline_numpy_dh(q_deg, tool, wrench, gravity_gain, offset, w_matrix, filt_state):
    """The same computation the straightforward way: six 4x4 DH matrices, numpy throughout."""
    t, jh = numpy_dh_tool_jacobian(q_deg, tool)
    return _rest_of_tick(q_deg, t, jh, wrench, gravity_gain, offset, w_matrix, filt_state)


def rtb_model(tool):
    """roboticstoolbox-python's ETS of the Meca500 (Table 3.1, modified DH) with ``tool``, or
    None when the package is not installed."""
    try:
        from roboticstoolbox import DHRobot, RevoluteMDH
        from spatialmath import SE3
    except ImportError:
        return None
    links = [RevoluteMDH(alpha=math.radians(al), a=a, offset=math.radians(off), d=d)
             for al, a, off, d in MECA500_DH]
    return DHRobot(links, tool=SE3(np.asarray(tool), check=False)).ets()


def rtb_version() -> str | None:
    try:
        from importlib.metadata import version
        return version("roboticstoolbox-python")
    except Exception:  # noqa: BLE001 - not installed
        return None


def baseline_rtb(ets, tool_r_t, q_deg, wrench, gravity_gain, offset, w_matrix, filt_state):
    """The plain-numpy computation with roboticstoolbox's C forward chain and Jacobian."""
    q = np.radians(q_deg)
    r_0_6 = ets.eval(q)[:3, :3] @ tool_r_t
    jh = ets.jacobe(q)
    return _rest_of_tick(q_deg, r_0_6, jh, wrench, gravity_gain, offset, w_matrix, filt_state)


def measure(n: int = 20000) -> dict:
    """Per-call times of the three implementations (full tick, and Jacobian + solve)."""
    tool = matrix_from_pose(TOOL_POSE)
    robot = Meca500(tool=tool)
    gravity = GravityModel(f0_n=[0.3, -0.2, 1.1], tau0_nm=[0.01, -0.02, 0.005], weight_n=1.363,
                           centroid_mm=[2.0, -1.5, 45.0], mount_angle_deg=3.0)
    to_h = WrenchTransform.for_tool(np.eye(3), TOOL_POSE[:3], mount_angle_deg=3.0)
    comp = ControlComputation(gravity, to_h, AdmittanceController(robot, SELF_ALIGNMENT))
    q = list(Q_DEG)
    raw = np.array([0.5, -0.1, 1.4, 0.02, 0.01, 0.003])
    f_d = np.array([0, 0, 0.5, 0, 0, 0])
    state = np.zeros(6)
    v = np.array([0.1, -0.2, 0.5, 0.01, 0.0, 0.02])
    args = (raw, gravity._gain, gravity._offset, to_h.matrix, state)

    ets = rtb_model(tool)
    j_ours = robot.tool_jacobian(q)
    j_np = numpy_dh_tool_jacobian(q, tool)[1]
    if not np.allclose(j_ours, j_np, atol=1e-9):
        raise AssertionError("numpy DH baseline Jacobian differs from dentibot's")
    if ets is not None and not np.allclose(j_ours, ets.jacobe(np.radians(q)), atol=1e-9):
        raise AssertionError("roboticstoolbox Jacobian differs from dentibot's")

    out = {"n": n, "rtb_version": rtb_version()}
    full = {
        "dentibot": lambda: comp.step(q, raw, f_d[2]),
        "numpy_dh": lambda: baseline_numpy_dh(q, tool, *args),
    }
    jac = {
        "dentibot": lambda: np.linalg.solve(robot.tool_jacobian(q), v),
        "numpy_dh": lambda: np.linalg.solve(numpy_dh_tool_jacobian(q, tool)[1], v),
    }
    if ets is not None:
        tool_r_t = np.ascontiguousarray(tool[:3, :3].T)
        full["rtb"] = lambda: baseline_rtb(ets, tool_r_t, q, *args)
        jac["rtb"] = lambda: np.linalg.solve(ets.jacobe(np.radians(q)), v)
    for key, group in (("full", full), ("jacobian_solve", jac)):
        res = {name: dist_us(timeit_us(fn, n)) for name, fn in group.items()}
        res.setdefault("rtb", None)
        ours = res["dentibot"]["median_us"]
        for name in ("numpy_dh", "rtb"):
            res[f"ratio_{name}"] = (res[name]["median_us"] / ours) if res[name] else None
        out[key] = res
    return out


def print_report(r: dict) -> None:
    rtb = f"roboticstoolbox {r['rtb_version']}" if r["rtb_version"] else "not installed"
    print(f"{'computation':<66}{'median us':>10}{'p99 us':>10}{'x ours':>8}")
    for key, title in (("full", "full control tick"), ("jacobian_solve", "Jacobian + 6x6 solve")):
        res = r[key]
        for name, label in (("dentibot", "dentibot (closed form, compiled kernels)"),
                            ("numpy_dh", "plain numpy DH (six 4x4 matrices)"),
                            ("rtb", f"numpy + C kinematics ({rtb})")):
            d = res[name]
            ratio = 1.0 if name == "dentibot" else res[f"ratio_{name}"]
            print(f"{title + ': ' + label:<66}{fmt(d and d['median_us']):>10}"
                  f"{fmt(d and d['p99_us']):>10}{fmt(ratio, '.2f'):>8}")
    med = r["full"]["dentibot"]["median_us"]
    print(f"target <= 50 us median: {'met' if med <= 50.0 else 'NOT met'} ({med:.1f} us)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=20000)
    print_report(measure(ap.parse_args().n))


if __name__ == "__main__":
    main()
