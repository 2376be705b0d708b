"""Experiment 1 as the thesis's bench ran it, on the bench-fitted world: the bench's own
500 Hz admittance loop at the file tip (eq 4.23-4.25), commanded with MoveJointsVel, the
insertion force from :func:`~dentibot.sim.bench_physics.fz_des_law`, recorded at the bench's
10 ms. The figures are computed by the experiments (``dentibot experiment alignment
--bench``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dentibot.control.admittance import AdmittanceController, AdmittanceParams
from dentibot.sim.bench_physics import BENCH, LOGGED_MNM_PER_A, BenchPhysics, fz_des_law
from dentibot.sim.canal import CanalParams
from dentibot.sim.world import World


@dataclass
class BenchRecord:
    """A bench run's 100 Hz record (arrays by name), the squares' start and end times (s),
    the Stewart frame (rows: its x, y, z in base axes), the LED's distance behind the tip
    (mm) and the record's period (s)."""

    rec: dict
    starts: list
    ends: list
    stewart: np.ndarray
    led_behind_tip_mm: float
    dt: float


def bench_record(config: str, k: float, b6: float, rotate: bool, *, seed: int = 1,
                 settle_s: float = 4.0, tail_s: float = 6.0,
                 hold_tilt: bool = False, physics: BenchPhysics = BENCH) -> BenchRecord:
    """Run ``config`` (admittance gain ``k``, ``b6`` about the file axis, the file turning
    when ``rotate``) on ``physics``' world (by default
    :data:`~dentibot.sim.bench_physics.BENCH`'s: another set of values to weigh one, as the
    fitting tool does), seated at the working length for ``settle_s`` before the first
    square and ``tail_s`` after the last; ``hold_tilt``: the handpiece's tilt held (b4 = b5
    infinite) instead of the bench's 80 (for comparison: the LED-based and tip-based
    distances are then the same)."""
    bp = physics
    preshaped = CanalParams(initial_apical_mm=CanalParams.target_apical_mm,
                            initial_taper=CanalParams.target_taper)
    seat = preshaped.working_length_mm + preshaped.apex_margin_mm
    cfg = bp.world_config(seed=seed, canal=preshaped, start_s=settle_s,
                          orifice_gap_mm=-seat)
    w = World(cfg)
    path = w.motion
    w.sensor.bias()
    g_tare = w.sensor.true_wrench(w.flange_rotation, (0.0,) * 3, (0.0,) * 3)
    b45 = math.inf if hold_tilt else 80.0
    params = AdmittanceParams(k=k, b=(80, 80, 80, b45, b45, b6),
                              m=(0.08, 0.08, 0.08, b45 / 1000.0, b45 / 1000.0, b6 / 1000.0),
                              name=f"bench_{config}")
    ctl = AdmittanceController(robot=w.kin, params=params, ts=w.ts)
    if rotate:
        w.handpiece.set_velocity(60.0)
    th = math.radians(w.sensor.p.mount_angle_deg)          # {S} turned about the flange z
    c, s = math.cos(th), math.sin(th)
    lever = (w.sensor.p.offset_mm - float(cfg.tool[2, 3])) * 1e-3   # {S} - tip, m
    duration = settle_s + path.duration_s + tail_s
    n = round(duration / w.ts)
    every = 5                                               # the bench logged at 10 ms
    rec: dict[str, list] = {k_: [] for k_ in ("t", "tip", "axis", "root", "fh", "vcmd",
                                              "fz_des", "torque")}
    fz = fz_des_law(config, bp.torque_free_mnm if rotate else 0.0, 0.0)
    for i in range(n):
        w.step()
        last = w.sensor.last
        gw = w.sensor.true_wrench(w.flange_rotation, (0.0,) * 3, (0.0,) * 3)
        e = [last[j] - (gw[j] - g_tare[j]) for j in range(6)]
        f6 = (c * e[0] - s * e[1], s * e[0] + c * e[1], e[2])
        t6 = (c * e[3] - s * e[4], s * e[3] + c * e[4], e[5])
        # moment about the tip: tau + (p_S - p_tip) x f, p_S - p_tip = (0, 0, lever)
        tt = (t6[0] - lever * f6[1], t6[1] + lever * f6[0], t6[2])
        tau_logged = LOGGED_MNM_PER_A * w.handpiece.current_a
        fz = fz_des_law(config, tau_logged, math.sqrt(f6[0] ** 2 + f6[1] ** 2
                                                           + f6[2] ** 2))
        wrench = np.array([f6[0], f6[1], f6[2] + fz, tt[0], tt[1], tt[2]])
        cmd = ctl.step(w.arm.q, wrench)
        w.arm.command_velocity(cmd.qdot_deg_s, w.t)
        if i % every == 0:
            R = w.flange_rotation
            rec["t"].append(w.t)
            rec["tip"].append(w.tip_0)
            rec["axis"].append(w.axis_0)
            rec["root"].append(path.centre_at(w.t))      # where the bench measured it
            rec["fh"].append(f6)
            rec["vcmd"].append(R @ cmd.twist[:3])
            rec["fz_des"].append(fz)
            rec["torque"].append(tau_logged)
    arr = {k_: np.asarray(v) for k_, v in rec.items()}
    starts = [settle_s + s0 for s0 in path.square_starts_s]
    ends = [a + d for a, d in zip(starts, path.durations_s, strict=True)]
    stewart = np.array([path.ex, path.ey, (0.0, 0.0, 1.0)])
    return BenchRecord(arr, starts, ends, stewart, bp.led_behind_tip_mm, w.ts * every)
