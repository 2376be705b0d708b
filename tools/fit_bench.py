#!/usr/bin/env python3
"""Re-derive the bench-fitted world's physics (dentibot.sim.bench_physics) from the thesis
lab's recordings of experiment 1.

    .venv/bin/python tools/fit_bench.py BENCH_DIR

BENCH_DIR, a copy of the bench recordings' figures, holds exp1_trials.csv and
exp1_traj_20hz.csv. Prints every fitted value with its residual; BenchPhysics holds these
values (rounded as printed).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

N_KNOTS = 24


def load(bench: Path):
    trials = pd.read_csv(bench / "exp1_trials.csv")
    traj = pd.read_csv(bench / "exp1_traj_20hz.csv")
    return trials, traj


def fit_arm(traj: pd.DataFrame) -> dict:
    """Command -> motion along Stewart z: v_tip(t) = g * lag_tau(vcmd(t - d)), least squares
    on the 20 Hz means (the model is run at 1 ms on the zero-order-held command and averaged
    over each 50 ms sample like the logs)."""
    rows = []
    for _, g in traj.groupby("source_file"):
        g = g[g.square > 0]
        t = g.t_s.to_numpy()
        vt = np.gradient(g.tip_z_mm.to_numpy(), t)
        rows.append((t, g.vcmd_z_mm_s.to_numpy(), vt))

    def model(p, t, vc):
        gain, d, tau = p
        dt = 0.001
        tt = np.arange(t[0] - 0.05, t[-1] + 0.05, dt)
        idx = np.clip(np.searchsorted(t, tt - d / 1000.0) , 0, len(vc) - 1)
        u = vc[idx]
        a = 1.0 - math.exp(-dt / max(tau / 1000.0, 1e-4))
        y = np.empty_like(u)
        acc = 0.0
        for i, x in enumerate(u):
            acc += (x - acc) * a
            y[i] = acc
        return gain * np.interp(t, tt, y)

    def res(p):
        return np.concatenate([model(p, t, vc) - vt for t, vc, vt in rows])

    fit = least_squares(res, [0.8, 16.0, 6.0], bounds=([0.3, 0.0, 0.5], [1.5, 60.0, 40.0]),
                        diff_step=[1e-3, 0.05, 0.05])
    r = res(fit.x)
    return {"gain": fit.x[0], "delay_ms": fit.x[1], "tau_ms": fit.x[2],
            "rms_mm_s": float(np.sqrt(np.mean(r ** 2))), "n": len(r)}


def fit_platform(trials: pd.DataFrame, traj: pd.DataFrame) -> dict:
    """The loop's shape: piecewise-linear periodic curve of the square's time phase,
    least squares over the 12 recorded squares (positions from the platform at rest before
    the first square); the per-square durations and pauses: medians over all trials."""
    phis, pts = [], []
    for _, g in traj.groupby("source_file"):
        rest = g[g.square == 0].iloc[:30]
        p0 = rest[["platform_x_mm", "platform_y_mm", "platform_z_mm"]].mean().to_numpy()
        for sq in (1, 2, 3, 4):
            h = g[g.square == sq]
            t = h.t_s.to_numpy()
            phis.append((t - t[0]) / (t[-1] - t[0] + 0.05))
            pts.append(h[["platform_x_mm", "platform_y_mm", "platform_z_mm"]].to_numpy() - p0)
    phi = np.concatenate(phis) % 1.0
    xyz = np.concatenate(pts)
    n = N_KNOTS
    u = phi * n
    i = np.floor(u).astype(int) % n
    f = u - np.floor(u)
    A = np.zeros((len(phi), n))
    A[np.arange(len(phi)), i] += 1.0 - f
    A[np.arange(len(phi)), (i + 1) % n] += f
    knots, *_ = np.linalg.lstsq(A, xyz, rcond=None)
    knots -= knots[0]                                   # the loop starts at rest
    r = A @ knots - xyz
    # the squares' own wander: each square's deviation from the loop, smoothed over 1/12 of
    # the loop (what is faster is the motion capture's noise), rms per square, median
    wander, fast, first = [], [], 0
    for p in pts:
        d = -r[first:first + len(p)]
        first += len(p)
        w = max(len(d) // 12, 1)
        sm = np.column_stack([np.convolve(d[:, k] - d[:, k].mean(), np.ones(w) / w, "same")
                              for k in range(3)])
        wander.append(sm.std(0))
        fast.append((d - d.mean(0) - sm).std(0))
    durs = [float(trials[f"sq{k}_dur_s"].median()) for k in (1, 2, 3, 4)]
    pauses = [float(trials[f"pause{k}_s"].median()) for k in (1, 2, 3)] \
        if "pause1_s" in trials else None
    if pauses is None or any(not math.isfinite(p) for p in pauses):
        pauses = [float((trials[f"sq{k + 1}_t0_s"] - trials[f"sq{k}_t0_s"]
                         - trials[f"sq{k}_dur_s"]).median()) for k in (1, 2, 3)]
    return {"knots": knots, "rms_mm": np.sqrt((r ** 2).mean(0)), "durations_s": durs,
            "wander_mm": np.median(wander, axis=0), "fast_mm": np.median(fast, axis=0),
            "pauses_s": pauses,
            "v_eff": [float(trials[f"sq{k}_v_eff_mm_s"].median()) for k in (1, 2, 3, 4)]}


def fit_torque(trials: pd.DataFrame, traj: pd.DataFrame) -> dict:
    """Logged file torque (eq 5.4, Km GR I): free-running level (median over B, at rest
    and moving), motor-off level (A), the wander (std of B), and the torque per N of the
    tip pressed onto the canal bottom: least squares of torque - free level on the
    compressive contact force in B, where the turning file stays seated at the bottom and is
    pressed with 1 N and more (up to about 3 N while the root rises onto it). C's peaks come
    when the file re-enters the canal after detaching: the flutes' engagement with the walls
    (the canal model's cutting torque), not the bottom."""
    b = traj[traj.config == "B"]
    a = traj[traj.config == "A"].file_torque_mNm
    free = float(b.file_torque_mNm.median())
    press = np.maximum(-b.contact_h_Fz_N.to_numpy(), 0.0)
    y = b.file_torque_mNm.to_numpy() - free
    x = press - press.mean()
    k = float(np.dot(x, y - y.mean()) / np.dot(x, x))
    r = y - y.mean() - k * x
    return {"free_mnm": free, "off_mnm": float(a.median()),
            "wander_mnm": float(b.file_torque_mNm.std()), "press_mnm_per_n": k,
            "press_p99_n": float(np.percentile(press, 99)),
            "press_rms_mnm": float(np.sqrt(np.mean(r ** 2)))}


def holder_slopes(traj: pd.DataFrame) -> dict:
    """The tip's offset from the platform against the admittance input force, per platform
    axis (least-squares slope, mm per N, during the squares): the lateral compliance the
    file meets, holder and tracking together. The simulated bench is compared on the same
    slopes (its holder's compliances are swept against them)."""
    out = {}
    for cfg, g in traj[traj.square > 0].groupby("config"):
        sl = []
        for ax in "xy":
            x = g[f"force_in_{ax}_N"].to_numpy()
            y = g[f"rel_tip_{ax}_mm"].to_numpy()
            x, y = x - x.mean(), y - y.mean()
            sl.append(float(np.dot(x, y) / np.dot(x, x)))
        out[cfg] = sl
    return out


def platform_turn(traj: pd.DataFrame, led_mm: float = 44.0) -> dict:
    """The platform's turn as it travels (during the squares, per configuration): the
    tip's offset from the platform's measured centre on its travel and the admittance input
    force together (least squares: y on x travel and x on z travel, mm per mm), the LED's
    offset from the tip on the travel (the handpiece turned with the canal). A roll about
    x_S of r rad per mm of x travel about a centre h above the canal's bottom moves the tip
    h r across and the LED, ``led_mm`` up the file, -led_mm r: h = led_mm * tip / -LED,
    r = tip / h (medians over the configurations)."""
    out = {}
    for cfg, g in traj[traj.square > 0].groupby("config"):
        p = g[[f"platform_{a}_mm" for a in "xyz"]].to_numpy()
        f = g[[f"force_in_{a}_N" for a in "xyz"]].to_numpy()
        x = np.column_stack([p, f, np.ones(len(g))])
        ty, *_ = np.linalg.lstsq(x, g.rel_tip_y_mm.to_numpy(), rcond=None)
        tx, *_ = np.linalg.lstsq(x, g.rel_tip_x_mm.to_numpy(), rcond=None)
        xp = np.column_stack([p, np.ones(len(g))])
        ly, *_ = np.linalg.lstsq(xp, (g.robot_led_y_mm - g.tip_y_mm).to_numpy(), rcond=None)
        lx, *_ = np.linalg.lstsq(xp, (g.robot_led_x_mm - g.tip_x_mm).to_numpy(), rcond=None)
        out[cfg] = {"tip_y_per_x": ty[0], "tip_x_per_z": tx[2], "led_y_per_x": ly[0],
                    "led_x_per_z": lx[2]}
    tip = float(np.median([v["tip_y_per_x"] for v in out.values()]))
    led = float(np.median([v["led_y_per_x"] for v in out.values()]))
    h = led_mm * tip / -led
    return {"per_config": out, "centre_above_tip_mm": h, "roll_rad_per_mm": tip / h}


def fit_noise(traj: pd.DataFrame) -> dict:
    """F/T noise: std of the contact force in {H} at rest before the first square, x and y
    (20 Hz means of 5 samples: times sqrt(5) for the 100 Hz samples)."""
    g = traj[(traj.square == 0) & (traj.t_s < 1.0)]
    sd = [float(g.groupby("source_file")[c].std().median()) * math.sqrt(5.0)
          for c in ("contact_h_Fx_N", "contact_h_Fy_N")]
    return {"noise_n": sd}


def lowpass_from_chatter(f_hz: float, dead_ms: float, tau_ms: float) -> float:
    """The reading's low-pass time constant (ms) that turns the seated file's axial loop by
    -180 deg at ``f_hz``, the frequency it chatters at: the admittance's integration (-90
    deg), the arm's dead time and lag, and the low-pass make up the half turn."""
    w = 2 * math.pi * f_hz
    rest = math.pi / 2 - w * dead_ms / 1000 - math.atan(w * tau_ms / 1000)
    return 1000 * math.tan(rest) / w


def loop_gain(f_hz: float, gain: float, tau_ms: float, lowpass_ms: float, bottom_n_mm: float,
              k_over_b: float = 6.25) -> float:
    """The seated loop's gain at ``f_hz`` (about 1 where it chatters undamped)."""
    w = 2 * math.pi * f_hz
    return (k_over_b * gain * bottom_n_mm / w / math.hypot(1, w * tau_ms / 1000)
            / math.hypot(1, w * lowpass_ms / 1000))


def fit_axial(traj: pd.DataFrame, arm: dict, lowpass_ms: float,
              held_bottoms_n_mm: tuple = ()) -> dict:
    """Canal drag and bottom stiffness: least squares of the reduced axial model
    (dentibot.sim.bench_physics.axial_chase) on the tip-root distance along z and the
    contact force of the three recorded trials, given the platform's recorded z, the fitted
    arm and the reading's low-pass ``lowpass_ms`` ("filtered"); also with an unfiltered
    reading ("unfiltered"), and with the bottom held at each of ``held_bottoms_n_mm``, the
    drag fitted alone (keyed by that bottom)."""
    from dentibot.sim.bench_physics import axial_chase

    runs = []
    for _, g in traj.groupby("source_file"):
        cfg = g.config.iloc[0]
        t = g.t_s.to_numpy()
        runs.append((cfg, t, g.platform_z_mm.to_numpy(),
                     g.rel_tip_z_mm.to_numpy() - g.rel_tip_z_mm.to_numpy()[:40].mean(),
                     g.contact_h_Fz_N.to_numpy()))

    def res(p, lp):
        out = []
        for cfg, t, pz, rel, fz in runs:
            sim = axial_chase(t, pz, cfg, arm_gain=arm["gain"], dead_ms=arm["delay_ms"],
                              tau_ms=arm["tau_ms"], drag_n_s_per_mm=p[0], still_factor=1.0,
                              still_coulomb_n=p[1], coulomb_n=p[2], bottom_n_mm=p[3],
                              lowpass_ms=lp)
            out.append(sim["gap_mm"] - rel)
            out.append(0.5 * (sim["fz_h_n"] - fz))
        return np.concatenate(out)

    start, lo, hi = [0.1, 0.3, 0.3, 3.0], [0.0, 0.0, 0.0, 0.3], [2.0, 5.0, 3.0, 30.0]

    def fit(lp, held=None):
        """Drag, a still file's friction, Coulomb and bottom (or the first three, the bottom
        held)."""
        n = 4 if held is None else 3

        def whole(x):
            return [*x, held] if held is not None else list(x)
        x = least_squares(lambda x: res(whole(x), lp), start[:n], bounds=(lo[:n], hi[:n]),
                          diff_step=[0.05] * n).x
        p = whole(x)
        return {"drag_n_s_per_mm": p[0], "still_coulomb_n": p[1], "coulomb_n": p[2],
                "bottom_n_mm": p[3], "lowpass_ms": lp,
                "rms": float(np.sqrt(np.mean(res(p, lp) ** 2)))}

    return {"filtered": fit(lowpass_ms), "unfiltered": fit(0.0),
            **{bottom: fit(lowpass_ms, bottom) for bottom in held_bottoms_n_mm}}


def _drag_line(v: dict) -> str:
    """One fit of :func:`fit_axial`'s drag, as printed."""
    return (f"drag {v['drag_n_s_per_mm']:.3f} N per mm/s off the seat (a still file held by "
            f"{v['still_coulomb_n']:.2f} N more), Coulomb {v['coulomb_n']:.3f} N")


def chatter_rms(config: str, bottom_n_mm: float, seed: int = 1) -> float:
    """``Fz_chatter_rms_N`` of ``config``'s run of experiment 1 on the bench-fitted world
    with its bottom at ``bottom_n_mm`` (the experiment's own figure, the same definition as
    the recordings')."""
    from dataclasses import replace

    from dentibot.experiments.alignment import BenchSpec, run_bench
    from dentibot.sim.bench_physics import BENCH

    fig = run_bench(BenchSpec(config, seed), physics=replace(BENCH, bottom_n_mm=bottom_n_mm))
    return fig["Fz_chatter_rms_N"]


#: The bottom stiffnesses (N/mm) :func:`bottom_from_chatter` runs the world at.
CHATTER_GRID_N_MM = tuple(float(k) for k in range(7, 15))


def bottom_from_chatter(trials: pd.DataFrame, grid=CHATTER_GRID_N_MM) -> dict:
    """The seated file's chatter (file bottomed out at 1 N, A and B) grows with the bottom's
    stiffness, which sets the seated loop's gain: least squares, in logs, of the simulated
    ``Fz_chatter_rms_N`` of A and B (seed 1) on the recorded medians, over ``grid`` (N/mm),
    refined by a parabola through the best point and its neighbours."""
    real = {c: float(trials[trials.group == f"{c}_K500_fz1.0"].Fz_chatter_rms_N.median())
            for c in ("A", "B")}
    grid = np.asarray(grid, dtype=float)
    sims = {c: [chatter_rms(c, float(k)) for k in grid] for c in real}
    cost = np.array([sum(math.log(sims[c][i] / real[c]) ** 2 for c in real)
                     for i in range(len(grid))])
    i = int(np.clip(np.argmin(cost), 1, len(grid) - 2))
    a, b, c = cost[i - 1:i + 2]
    h = float(grid[1] - grid[0])
    shift = 0.5 * h * (a - c) / (a - 2 * b + c) if a - 2 * b + c > 0 else 0.0
    return {"bottom_n_mm": float(grid[i] + shift), "real": real,
            "grid": [float(k) for k in grid], "sim": sims, "cost": cost.tolist()}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("bench", help="the folder of the bench recordings' figures "
                    "(exp1_trials.csv, exp1_traj_20hz.csv)")
    ap.add_argument("--skip-axial", action="store_true", help="skip the slow axial fit")
    ap.add_argument("--chatter", action="store_true",
                    help="also weigh the bottom by the seated file's chatter (runs experiment 1 "
                         "on the fitted world 16 times, about a minute), and re-fit the drag "
                         "with that bottom held (another two minutes)")
    ap.add_argument("--bottom", type=float, metavar="N_MM",
                    help="also re-fit the drag with the bottom held at N_MM N/mm")
    a = ap.parse_args(argv)
    trials, traj = load(Path(a.bench))
    arm = fit_arm(traj)
    print(f"arm (vcmd_z -> tip vz): gain {arm['gain']:.3f}, dead time {arm['delay_ms']:.1f} ms,"
          f" lag {arm['tau_ms']:.1f} ms (rms residual {arm['rms_mm_s']:.2f} mm/s, "
          f"n {arm['n']})")
    print(f"  100 Hz fits in the table (median): gain "
          f"{trials.realised_gain_vmeas_over_vcmd.median():.3f}, dead time "
          f"{trials.fit_delay_ms_z.median():.1f} ms, lag {trials.fit_tau_ms_z.median():.1f} ms")
    pl = fit_platform(trials, traj)
    print("platform loop knots (x, y, z mm at phase i/%d):" % N_KNOTS)
    print("  " + ", ".join(f"({x:.1f}, {y:.1f}, {z:.1f})" for x, y, z in pl["knots"]))
    print(f"  residual rms x/y/z {pl['rms_mm'][0]:.2f}/{pl['rms_mm'][1]:.2f}/"
          f"{pl['rms_mm'][2]:.2f} mm; durations {[round(d, 2) for d in pl['durations_s']]} s;"
          f" pauses {[round(p, 2) for p in pl['pauses_s']]} s; v_eff "
          f"{[round(v, 2) for v in pl['v_eff']]} mm/s")
    print(f"  wander per square (smoothed over 1/12 loop, rms, median) x/y/z "
          f"{pl['wander_mm'][0]:.2f}/{pl['wander_mm'][1]:.2f}/{pl['wander_mm'][2]:.2f} mm; "
          f"faster {pl['fast_mm'][0]:.2f}/{pl['fast_mm'][1]:.2f}/{pl['fast_mm'][2]:.2f} mm")
    tq = fit_torque(trials, traj)
    print(f"torque reading: free running {tq['free_mnm']:.2f} mNm, motor off "
          f"{tq['off_mnm']:.2f} mNm, wander std {tq['wander_mnm']:.2f} mNm, pressed "
          f"{tq['press_mnm_per_n']:.2f} mNm/N in B, pressed up to {tq['press_p99_n']:.1f} N "
          f"(p99; rms residual {tq['press_rms_mnm']:.2f} mNm)")
    hs = holder_slopes(traj)
    print("tip offset per N of admittance input, during squares (x, y mm/N): "
          + "; ".join(f"{c} {x:.2f}, {y:.2f}" for c, (x, y) in sorted(hs.items())))
    pt = platform_turn(traj)
    print("platform turn (mm per mm of travel): " + "; ".join(
        f"{c} tip y/x {v['tip_y_per_x']:.3f}, LED y/x {v['led_y_per_x']:.3f}, tip x/z "
        f"{v['tip_x_per_z']:.3f}, LED x/z {v['led_x_per_z']:.3f}"
        for c, v in sorted(pt["per_config"].items())))
    print(f"  roll about x_S {pt['roll_rad_per_mm']:.4f} rad per mm of x, about a centre "
          f"{pt['centre_above_tip_mm']:.1f} mm above the canal's bottom")
    nz = fit_noise(traj)
    print(f"F/T noise at 100 Hz: Fx {nz['noise_n'][0]:.3f} N, Fy {nz['noise_n'][1]:.3f} N")
    if not a.skip_axial:
        arm_t = {"gain": trials.realised_gain_vmeas_over_vcmd.median(),
                 "delay_ms": trials.fit_delay_ms_z.median(),
                 "tau_ms": trials.fit_tau_ms_z.median()}
        chat = trials[trials.group.isin(["A_K500_fz1.0", "B_K500_fz1.0"])].Fz_chatter_peak_hz
        f_hz = float(chat.median())
        lp = lowpass_from_chatter(f_hz, arm_t["delay_ms"], arm_t["tau_ms"])
        print(f"the reading's low-pass: {lp:.0f} ms turns the seated loop by -180 deg at the "
              f"recorded chatter, {f_hz:.2f} Hz (median peak of A and B at 1 N, "
              f"{chat.min():.2f}-{chat.max():.2f})")
        held = [] if a.bottom is None else [a.bottom]
        if a.chatter:
            ch = bottom_from_chatter(trials)
            held.insert(0, round(ch["bottom_n_mm"], 1))
        ax = fit_axial(traj, arm_t, lp, tuple(held))
        for name in ("filtered", "unfiltered"):
            v = ax[name]
            print(f"canal axial, {name} reading: {_drag_line(v)}, bottom "
                  f"{v['bottom_n_mm']:.2f} N/mm (rms residual {v['rms']:.3f})")
        g = loop_gain(f_hz, arm_t["gain"], arm_t["tau_ms"], lp, ax["filtered"]["bottom_n_mm"])
        print(f"  the seated loop's gain at {f_hz:.2f} Hz: {g:.2f} (1: it chatters undamped)")
        if a.chatter:
            print(f"the bottom from the seated file's chatter: {ch['bottom_n_mm']:.2f} N/mm "
                  f"(recorded Fz_chatter_rms A {ch['real']['A']:.3f}, B {ch['real']['B']:.3f}"
                  " N; simulated A/B, N, with the bottom at " + ", ".join(
                      f"{k:g} N/mm: {sa:.3f}/{sb:.3f}" for k, sa, sb in
                      zip(ch["grid"], ch["sim"]["A"], ch["sim"]["B"], strict=True)) + ")")
        for bottom in held:
            v = ax[bottom]
            print(f"canal axial, the bottom held at {bottom:g} N/mm: {_drag_line(v)} (rms "
                  f"residual {v['rms']:.3f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
