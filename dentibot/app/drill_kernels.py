"""The built-in simulator's drilling ticks in one compiled call (numba): while a procedure
feeds, turns back or withdraws the file in lock-step time, tick after tick of
``treating.drilling.feeding``, ``treating.drilling.reversing`` or ``treating.retracting``
runs here, each exactly as the control task runs it
(:meth:`~dentibot.runtime.control_task.Runtime.tick`): the simulated devices' readings, the
supervisor's input checks, the estimate, the observers, the estimate's checks, the state's
detection (feeding: the drilling guard, the strategy's decision, feeding's reversal checks;
reversing: the guard, the reversal's end; retracting: its end, the overload), the orientation
loop, the admittance law, the command's checks, the arm's command, then the world's step.

Every law is the kernel the control task and the world call themselves
(:mod:`~dentibot.runtime.supervisor_kernels`, :mod:`~dentibot.control.tick_kernels`,
:mod:`~dentibot.control.admittance_kernels`, :mod:`~dentibot.control.canal_axis_kernels`,
:mod:`~dentibot.states.feeding_kernels`, :mod:`~dentibot.sim.arm_kernels`,
:mod:`~dentibot.sim.world_kernels`); what is here is their order, which is the tick's.

Unlike the kernels it calls, :func:`drill_ticks` is compiled at its first call (a few
seconds once, then loaded from numba's cache): in lock-step time, where no deadline waits.

The first tick in which anything would happen (a finding, an event, a refused command) is
not run: the controller's state arrays are put back as they were before it, and the control
task runs that tick itself. :class:`~dentibot.app.drill_loop.DrillLoop` prepares the arrays
and brings the Python side up to date.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dentibot.app import relay_kernels as rk
from dentibot.control.admittance_kernels import command, lateral_scale
from dentibot.control.canal_axis_kernels import feed_scale
from dentibot.control.canal_axis_kernels import step as axis_step
from dentibot.control.canal_axis_kernels import twist as axis_twist
from dentibot.control.depth import depth_along_xyz
from dentibot.control.kinematics_kernels import tool_euler_deg
from dentibot.control.tick_kernels import sense
from dentibot.runtime import supervisor_kernels as sk
from dentibot.sim.arm_kernels import command_velocity
from dentibot.sim.canal_kernels import red_area
from dentibot.sim.world_kernels import step as world_step
from dentibot.states.feeding_kernels import (
    drilling_guard,
    feeding_checks,
    overloaded,
    retracted,
    reversal_over,
    strategy_decision,
)
from dentibot.telemetry.blocks import COL

#: The states run here (``phase``).
FEEDING, RETRACTING, REVERSING = 0, 1, 2
#: Per-tick figures a study reads after each tick (``out[i]``): the handpiece's torque
#: (mNm, its magnitude), the tip's true depth along the canal (mm), the motor stalled
#: (0/1), the file's position (deg), the file's largest bending strain, the world time (s),
#: the control task's estimate of the file torque (mNm).
OUT_FIELDS = ("torque_abs_mnm", "true_depth_mm", "stalled", "pos_deg", "max_strain", "t",
              "est_torque_mnm")
OUT_TORQUE_ABS, OUT_EST_TORQUE = 0, 6
#: What the last tick's row lacks of its estimate and decision (``last``): the file's axis
#: (3), then the scalars of :data:`LAST_SCALARS` (the decided fz before the orientation
#: loop's scaling).
LAST_AXIS, LAST_SCALAR = 0, 3
LAST_SCALARS = ("force_norm_n", "motor_pos_deg", "fz_n")
LAST_SIZE = LAST_SCALAR + len(LAST_SCALARS)
#: Where each tick's telemetry numbers go in ``rows[i]`` (:data:`dentibot.telemetry.blocks.COL`),
#: written every tick (the last tick's row is also its estimate and commands); the tool's
#: angles and the completeness only when ``truth`` asks for rows
R_Q, R_QDOT, R_TOOL, R_PHANTOM = COL["q_deg"], COL["qdot_cmd_deg_s"], COL["tool_pose"], \
    COL["phantom_xyz"]
R_WS, R_WH, R_FZ, R_FZ_STAR = COL["wrench_s"], COL["wrench_h"], COL["fz_n"], COL["fz_star_n"]
R_TAU, R_CUR, R_RPM, R_DEPTH = COL["file_torque_mnm"], COL["motor_current_a"], \
    COL["motor_rpm"], COL["depth_mm"]
R_TRUE_DEPTH, R_COMPLETENESS = COL["true_depth_mm"], COL["completeness"]


@njit(cache=True)
def _keep(saved, arrays):
    """Copy the controller's state arrays (1-D views) into ``saved`` rows."""
    for i in range(len(arrays)):
        a = arrays[i]
        saved[i, :a.shape[0]] = a


@njit(cache=True)
def _restore(saved, arrays):
    for i in range(len(arrays)):
        a = arrays[i]
        a[:] = saved[i, :a.shape[0]]


@njit(cache=True, nogil=True)
def drill_ticks(n_max, k0, steps0, t0, ts, origins, axis_p, state, saved, world, reads,
                sup, ctl, adm, feed, servo, arm_cmd, truth, relay, out, rows, last, frames_out,
                jh_out):
    """Run up to ``n_max`` ticks of feeding from control tick ``k0``, the world at step
    ``steps0`` (time ``t0``). ``origins[i]``: the canal orifice in {0} at world step
    ``steps0 + i`` (the patient's motion); ``axis_p``: the canal's axis in {0}. ``state``: the
    controller's state arrays as 1-D views (kept before each tick, put back when a tick
    cannot run here). The other tuples hold what each kernel takes (see
    :class:`~dentibot.app.drill_loop.DrillLoop`).

    Returns ``(ticks run, world steps taken, fracture code)``. Run to ``n_max``, the world is
    stepped after every tick but the last (the control task's clock steps it after its work
    between ticks). Stopped before a tick, or by a fracture in a step, the world has been
    stepped after the last tick run too: the next tick is due at once. ``frames_out`` and
    ``jh_out`` get the last tick's chain.

    Each tick's telemetry numbers go into ``rows[i]`` (the columns of
    :data:`~dentibot.telemetry.blocks.COLUMNS` but the compute time; the last tick's row is
    also its estimate and commands, ``last`` what the row lacks of them). ``truth``: whether
    rows are read (then the tool's angles and the completeness are written too), the tool's
    6R_H, and
    what the canal's completeness (eq 6.1) takes: its initial lumen, stained widths, stain
    depth, a work buffer, the initial red area, the index of its lumen's version in the
    canal's state, and the completeness at the first tick. It is computed again only when the
    lumen changed, as :meth:`~dentibot.sim.world.World.completeness` is.

    ``relay``: :func:`~dentibot.app.relay_kernels.wire_args` (or
    :data:`~dentibot.app.relay_kernels.OFF`): each group of ``every`` ticks whose rows are
    written is sent to the recorder's process as the call goes on, with its compute time; a
    group the recorder does not take stops the call before its next tick. The call runs
    without the interpreter lock (``nogil``): the recorder's process is another, and the
    call waits for its room in a system call."""
    (ws, wp, F, dh_w, ast, ap, lims, q, qd, vel_cmd, target, queue_t, queue_v, cst, cp, R, h,
     s_arr, kappa, b0, b1, b2, cout, hs, hpp, hnoise, ss, sp, snoise) = world
    (enc_res, i_origin, i_tip, i_omega, i_pos, i_current, i_torque, i_stalled, i_last0,
     i_status, i_strain, enabled) = reads
    (fresh, bounds, last_force, jump_n, in_out, sp_st, sp_lim, compared, want_rpm, fr_st, fr_ring,
     fr_lim, n_recent, forward_rpm, share, fr_out, tp_st, tp_ring, tip_bound, persist_s,
     disagree, est_lim, file_turning, q_lo_j, q_hi_j, e_out, speed_lim, tip_cap,
     cmd_out) = sup
    (dh, tool, ref_h, g_offset, g_gain, to_h, efficiency, friction_a, depth_o, depth_a) = ctl
    (f_a, f_c, f_v, f_prev, w_prev, half_ts_deg, q_lo, q_hi, sigma, elbow_off, wrist_frame,
     thresholds, lo_rad, hi_rad, vmax_rad_s, margin_rad, lim_ts, file_len, lat_ref) = adm
    (phase, retract_to, retract_fz, rev_start_deg, rev_start_tick, rev_deg, rev_timeout,
     moved_n, depth_max, axial_n, kind, reverse, pd_st, pd_par, blank, rev_th, const_fz, wl,
     spin_up, torque_limit, rise_st, rise_a, rise_ts, min_slope, horizon) = feed
    (has_servo, has_scale, sv_st, sv_par, beam_l, beam_step, beam_0, beam_1, beam_2) = servo
    (dead_time, i_error) = arm_cmd
    (row_on, r_6_h, R0, width0, stain_mm, red_buf, red0, i_version, completeness) = truth
    version = cst[i_version]
    ff0 = np.zeros(6)
    ff = np.empty(6)
    qr = np.empty(6)
    raw = np.empty(6)
    code = 0
    t_w = t0
    # booleans known only at run time: a literal True or False passed on would compile each
    # kernel called with it again, for numba's Literal[bool] type
    yes = n_max > 0
    no = not yes
    last_frames, last_jh = frames_out, jh_out
    ran, stepped = n_max, max(n_max - 1, 0)
    rk.begin(relay)
    for i in range(n_max):
        if not rk.hold(relay):             # a group not taken: stop before the tick
            ran = stepped = i
            break
        _keep(saved, state)
        k = k0 + i
        seq = steps0 + i
        # 1. the simulated devices' readings (the arm's joints at its encoder's resolution)
        for j in range(6):
            qr[j] = np.rint(q[j] / enc_res) * enc_res
            raw[j] = ss[i_last0 + j]
        rpm, pos, cur = hs[i_omega], hs[i_pos], hs[i_current]
        if sk.inputs(fresh, bounds, last_force, k, seq, seq, seq, seq, yes, raw, qr, cur, rpm,
                     pos, int(ss[i_status]), jump_n, in_out):
            _restore(saved, state)
            ran = stepped = i
            break
        # 2. the estimate
        frames, jh, wrench_h, norm, tau, tipax = sense(qr, raw, cur, rpm, dh, tool, ref_h,
                                                       yes, g_offset, g_gain, to_h,
                                                       efficiency, friction_a)
        depth = depth_along_xyz(tipax[3, 0], tipax[3, 1], tipax[3, 2], depth_o[0], depth_o[1],
                                depth_o[2], depth_a[0], depth_a[1], depth_a[2])
        # the observers, then the estimate's checks
        bad = sk.spindle(sp_st, sp_lim, lim_ts, no, compared, want_rpm, rpm, enabled,
                        tau) != 0
        at_speed = forward_rpm > 0.0 and abs(rpm - forward_rpm) < share * forward_rpm
        bad = bad or sk.fracture(fr_st, fr_ring, fr_lim, n_recent, at_speed, tau, depth, yes,
                                 fr_out)
        if not bad:
            v = sk.tip_speed(tp_st, tp_ring, tipax[3, 0], tipax[3, 1], tipax[3, 2], lim_ts,
                             tip_bound)
            bad = v >= 0.0 and tp_st[sk.T_BAD] * lim_ts >= persist_s
        if not bad:
            turning = file_turning and abs(rpm) > 5.0
            bad = sk.estimate_checks(disagree, est_lim, lim_ts, turning, tau, wrench_h[5], yes,
                                     depth_o[0], depth_o[1], depth_o[2], depth_a[0],
                                     depth_a[1], depth_a[2], tipax[3, 0], tipax[3, 1],
                                     tipax[3, 2], wl, qr, q_lo_j, q_hi_j, frames, elbow_off,
                                     wrist_frame, e_out) != 0
        # 3. the state's detection: retracting's end and overload; or the drilling guard,
        # then the reversal's end, or the strategy's decision and feeding's reversal checks
        fz = fz_star = 0.0
        if phase == RETRACTING:
            bad = bad or retracted(yes, depth, retract_to) or overloaded(tau, torque_limit,
                                                                         yes)
        elif not bad:
            bad = drilling_guard(norm, moved_n, yes, depth, depth_max, wrench_h[2],
                                 axial_n) != 0
            if not bad and phase == REVERSING:
                bad = reversal_over(rev_start_deg, pos, rev_deg, rpm, k, rev_start_tick, lim_ts,
                                    rev_timeout) != 0
            elif not bad:
                fz, fz_star, events = strategy_decision(kind, reverse, pd_st, pd_par, blank,
                                                        rev_th, const_fz, wl, tau, depth)
                why, _ = feeding_checks(events, tau, rpm, spin_up, torque_limit, rise_st,
                                        rise_a, rise_ts, min_slope, horizon)
                bad = events != 0 or why != 0
        if bad:
            _restore(saved, state)
            ran = stepped = i
            break
        # 5. the arm's command: the orientation loop, the feed, the admittance law
        ff[:] = ff0
        if has_servo:
            axis_step(sv_st, sv_par, depth, yes, wrench_h, beam_l, beam_step, beam_0, beam_1,
                      beam_2)
            if not axis_twist(sv_st, sv_par, ff):
                ff[:] = ff0
        feed = -retract_fz if phase == RETRACTING else fz     # reversing: 0
        if has_scale and feed > 0.0:
            feed *= feed_scale(sv_st, sv_par)
        twist, _, qdot, _, _, _, _ = command(f_a, f_c, f_v, f_prev, wrench_h, feed, ff, jh,
                                             frames, qr, w_prev, half_ts_deg, q_lo, q_hi,
                                             sigma, elbow_off, wrist_frame, thresholds, lo_rad,
                                             hi_rad, vmax_rad_s, margin_rad, lim_ts,
                                             lateral_scale(depth, file_len, lat_ref))
        if sk.command_checks(qdot, twist, speed_lim, no, speed_lim, tip_cap, cmd_out) != 0 \
                or ast[i_error] != 0.0 or not command_velocity(ast, lims, vel_cmd, queue_t, queue_v,
                                                         qdot, t_w, dead_time):
            _restore(saved, state)
            ran = stepped = i
            break
        # 6. what a study reads after the tick, the telemetry row, the last tick's figures
        o = origins[i]
        true_depth = depth_along_xyz(ws[i_tip], ws[i_tip + 1], ws[i_tip + 2], o[0], o[1], o[2],
                                     axis_p[0], axis_p[1], axis_p[2])
        out[i, 0] = abs(hs[i_torque])
        out[i, 1] = true_depth
        out[i, 2] = hs[i_stalled]
        out[i, 3] = pos
        out[i, 4] = cout[i_strain]
        out[i, 5] = t_w
        out[i, 6] = tau
        r = rows[i]
        for j in range(6):
            r[R_Q + j] = qr[j]
            r[R_QDOT + j] = qdot[j]
            r[R_WS + j] = raw[j]
            r[R_WH + j] = wrench_h[j]
        for j in range(3):
            r[R_TOOL + j] = tipax[3, j]
            r[R_PHANTOM + j] = o[j]
            last[LAST_AXIS + j] = tipax[2, j]
        r[R_FZ] = feed
        r[R_FZ_STAR] = fz_star if phase == FEEDING else feed
        r[R_TAU], r[R_CUR], r[R_RPM], r[R_DEPTH] = tau, cur, rpm, depth
        r[R_TRUE_DEPTH] = true_depth
        if row_on:
            r[R_TOOL + 3], r[R_TOOL + 4], r[R_TOOL + 5] = tool_euler_deg(frames, r_6_h)
            r[R_COMPLETENESS] = completeness
        last[LAST_SCALAR], last[LAST_SCALAR + 1], last[LAST_SCALAR + 2] = norm, pos, fz
        last_frames, last_jh = frames, jh
        rk.publish(relay, i)                  # the rows of a group are written: send them
        if i == n_max - 1:
            break
        # the world's next step (the clock's, between two ticks)
        t_w = (seq + 1) * ts
        for j in range(3):
            ws[i_origin + j] = origins[i + 1, j]
        code = world_step(ws, wp, F, dh_w, ast, ap, lims, q, qd, vel_cmd, target, queue_t,
                          queue_v, cst, cp, R, h, s_arr, kappa, b0, b1, b2, cout, hs, hpp,
                          hnoise, ss, sp, snoise, t_w, ts)
        if code != 0:
            ran = stepped = i + 1
            break
        if row_on and cst[i_version] != version:
            version = cst[i_version]
            completeness = (red0 - red_area(R, R0, width0, stain_mm, red_buf)) / red0
    if ran:
        frames_out[:] = last_frames
        jh_out[:] = last_jh
    rk.end(relay)
    return ran, stepped, code
