"""The world's step after the arm, compiled (numba): the file in the canal, the handpiece
against that load, cutting, fatigue and fracture, the wrench the sensor reads.

:meth:`dentibot.sim.world.World.step` moves the arm and the patient, then calls
:func:`contact_step` once; it is the only implementation of what the step does from there
(the order and the frames are in :mod:`dentibot.sim.world`). The world's own state is the
array ``ws`` (:data:`STATE_FIELDS`), its constants ``wp`` (:data:`PARAM_FIELDS`); the canal,
the handpiece and the sensor bring theirs (:mod:`~dentibot.sim.canal_kernels`,
:mod:`~dentibot.sim.handpiece_kernels`, :mod:`~dentibot.sim.ftsensor_kernels`), and the
flange's pose is the array ``F`` (shape (4, 3): the rotation 0R_6's columns, then its origin,
mm) of the kinematics kernels.
"""

from __future__ import annotations

import numpy as np
from numba import njit

import dentibot.sim.arm_kernels as arm
import dentibot.sim.canal_kernels as canal
import dentibot.sim.ftsensor_kernels as sensor
import dentibot.sim.handpiece_kernels as handpiece
from dentibot.control.kinematics_kernels import dh_frames

#: The world's state.
STATE_FIELDS = (
    "tip_x", "tip_y", "tip_z",          # the file's tip in {0} (mm)
    "axis_x", "axis_y", "axis_z",       # the file's axis in {0}, towards the tip
    "origin_x", "origin_y", "origin_z",  # the phantom's origin {P} in {0} now (mm)
    # 0R_P now, row by row
    "rp00", "rp01", "rp02", "rp10", "rp11", "rp12", "rp20", "rp21", "rp22",
    "contact_x", "contact_y", "contact_z",   # the canal's net force on the file, {0} (N)
    "ext_tau_x", "ext_tau_y", "ext_tau_z",   # the external torque about {S}'s origin, {0}
    "hand_x", "hand_y", "hand_z",            # the operator's hand on the handpiece, {0} (N)
    "grip_x", "grip_y", "grip_z",            # where it holds it, in the flange frame (mm)
    "fractured",        # the file is broken
    "fatigue_damage",   # Miner's sum of the bending cycles
    "fracture_torque",  # |torque| when it broke (mNm)
    "fracture_depth",   # the tip's depth along the canal when it broke (mm)
)
#: The world's constants.
PARAM_FIELDS = ("tool_px", "tool_py", "tool_pz", "tool_zx", "tool_zy", "tool_zz",
                "fatigue_c", "fatigue_b", "torsional_strength_mnm")

S = {name: i for i, name in enumerate(STATE_FIELDS)}
P = {name: i for i, name in enumerate(PARAM_FIELDS)}

#: :func:`contact_step`'s outcome: nothing broke, or the cause of a fracture.
FRACTURE_CAUSES = ("", "torsion", "fatigue")

_TIP, _AXIS, _ORIGIN, _RP, _CONTACT, _EXT_TAU, _HAND, _GRIP = 0, 3, 6, 9, 18, 21, 24, 27
_FRACTURED, _FATIGUE, _FR_TORQUE, _FR_DEPTH = 30, 31, 32, 33
_TOOL_P, _TOOL_Z, _FAT_C, _FAT_B, _STRENGTH = 0, 3, 6, 7, 8



@njit(cache=True)
def pose(ws: np.ndarray, wp: np.ndarray, F: np.ndarray) -> None:
    """The file's tip and axis in {0} from the flange's pose ``F`` and the tool."""
    a0, a1, a2 = wp[_TOOL_P], wp[_TOOL_P + 1], wp[_TOOL_P + 2]
    b0, b1, b2 = wp[_TOOL_Z], wp[_TOOL_Z + 1], wp[_TOOL_Z + 2]
    for i in range(3):
        ws[_TIP + i] = F[3, i] + F[0, i] * a0 + F[1, i] * a1 + F[2, i] * a2
        ws[_AXIS + i] = F[0, i] * b0 + F[1, i] * b1 + F[2, i] * b2


@njit(cache=True)
def update_pose(ws: np.ndarray, wp: np.ndarray, F: np.ndarray, dh: np.ndarray,
                q: np.ndarray) -> None:
    """The flange's pose ``F`` at the joints ``q`` (deg; the link table ``dh``:
    :mod:`~dentibot.control.kinematics_kernels`), then the file's tip and axis."""
    F[:, :] = dh_frames(dh, q)[5]
    pose(ws, wp, F)


@njit(cache=True)
def clear_interaction(out: np.ndarray) -> None:
    """No contact: the canal's outcome as a file outside it (depth -1)."""
    for i in range(out.shape[0]):
        out[i] = 0.0
    out[canal.OUT_DEPTH] = -1.0


@njit(cache=True)
def step(ws: np.ndarray, wp: np.ndarray, F: np.ndarray, dh: np.ndarray,
         ast: np.ndarray, ap: np.ndarray, lims: np.ndarray, q: np.ndarray, qd: np.ndarray,
         vel_cmd: np.ndarray, target: np.ndarray, queue_t: np.ndarray, queue_v: np.ndarray,
         cst: np.ndarray, ccp: np.ndarray, cR: np.ndarray, ch: np.ndarray,
         cs: np.ndarray, ckappa: np.ndarray, b0: np.ndarray, b1: np.ndarray,
         b2: np.ndarray, cout: np.ndarray,
         hs: np.ndarray, hp: np.ndarray, hnoise: np.ndarray,
         ss: np.ndarray, sp: np.ndarray, snoise: np.ndarray, t: float, ts: float) -> int:
    """One period of the world after the patient's motion (``ws``'s phantom origin and
    rotation are this step's): the arm's servo (:func:`dentibot.sim.arm_kernels.step`), the
    flange's pose when it moved (the link table ``dh``: :mod:`~dentibot.control.kinematics_kernels`),
    then :func:`contact_step`. Returns what :func:`contact_step` returns."""
    arm.step(ast, ap, lims, q, qd, vel_cmd, target, queue_t, queue_v, t, ts)
    if ast[arm.S_MOVING] != 0.0:
        update_pose(ws, wp, F, dh, q)
    return contact_step(ws, wp, F, cst, ccp, cR, ch, cs, ckappa, b0, b1, b2, cout, hs, hp,
                        hnoise, ss, sp, snoise, ts)


@njit(cache=True)
def contact_step(ws: np.ndarray, wp: np.ndarray, F: np.ndarray,
                 cst: np.ndarray, ccp: np.ndarray, cR: np.ndarray, ch: np.ndarray,
                 cs: np.ndarray, ckappa: np.ndarray, b0: np.ndarray, b1: np.ndarray,
                 b2: np.ndarray, cout: np.ndarray,
                 hs: np.ndarray, hp: np.ndarray, hnoise: np.ndarray,
                 ss: np.ndarray, sp: np.ndarray, snoise: np.ndarray, ts: float) -> int:
    """One period of the file in the canal with the arm and the patient already moved
    (``ws``'s tip, axis, phantom origin and rotation are this step's). Returns the index in
    :data:`FRACTURE_CAUSES` of a fracture this step (0: none)."""
    code = 0
    if ws[_FRACTURED] == 0.0:
        d0 = ws[_TIP] - ws[_ORIGIN]
        d1 = ws[_TIP + 1] - ws[_ORIGIN + 1]
        d2 = ws[_TIP + 2] - ws[_ORIGIN + 2]
        ax0, ax1, ax2 = ws[_AXIS], ws[_AXIS + 1], ws[_AXIS + 2]
        tip_p = np.empty(3)
        axis_p = np.empty(3)
        for j in range(3):     # into {P}: 0R_P^T v
            tip_p[j] = ws[_RP + j] * d0 + ws[_RP + 3 + j] * d1 + ws[_RP + 6 + j] * d2
            axis_p[j] = ws[_RP + j] * ax0 + ws[_RP + 3 + j] * ax1 + ws[_RP + 6 + j] * ax2
        if ccp[canal.P_DRAG] != 0.0:
            cst[canal.S_TURNING] = 1.0 if hs[handpiece.S_OMEGA] != 0.0 else 0.0
        canal.interact(cst, ccp, cR, ch, cs, ckappa, b0, b1, b2, tip_p[0], tip_p[1],
                       tip_p[2], axis_p[0], axis_p[1], axis_p[2], ts, cout)
        resist = cout[canal.OUT_RESIST]
        dpos = handpiece.step(hs, hp, hnoise, ts, resist, resist * ccp[canal.P_REVERSE])
        rev = dpos / 360.0
        if cout[canal.OUT_ENGAGE] > 0.0 or rev < 0.0:
            canal.cut(cst, ccp, cR, ch, rev)
            cout[canal.OUT_AXIAL] -= canal.screw_in_n(cst, ccp, rev)
        strain = cout[canal.OUT_STRAIN]
        if strain > 0.0 and rev != 0.0:   # Miner's rule, a Coffin-Manson strain-life
            ws[_FATIGUE] += abs(rev) / (wp[_FAT_C] / strain) ** (1.0 / wp[_FAT_B])
        torque = abs(hs[handpiece.S_TORQUE])
        if torque > wp[_STRENGTH]:
            code = 1
        elif ws[_FATIGUE] >= 1.0:
            code = 2
        if code:
            ws[_FRACTURED] = 1.0
            ws[_FR_TORQUE] = torque
            ws[_FR_DEPTH] = cout[canal.OUT_DEPTH]
            clear_interaction(cout)
    else:
        handpiece.step(hs, hp, hnoise, ts, 0.0, 0.0)
    sense(ws, sp, F, cout, hs[handpiece.S_TORQUE], ss, snoise)
    return code


@njit(cache=True)
def sense(ws: np.ndarray, sp: np.ndarray, F: np.ndarray, cout: np.ndarray, torque_mnm: float,
          ss: np.ndarray, snoise: np.ndarray) -> None:
    """The sensor's reading of the canal's loads on the file (``cout``), the motor's torque
    ``torque_mnm`` reacting on the handpiece and the operator's hand."""
    d = sp[sensor.P_OFFSET_MM]
    # the sensor's origin in {0}: p06 + 0R_6 z d
    o0, o1, o2 = F[3, 0] + F[2, 0] * d, F[3, 1] + F[2, 1] * d, F[3, 2] + F[2, 2] * d
    fa = cout[canal.OUT_AXIAL]
    loaded = fa != 0.0 or cout[canal.OUT_RESIST] != 0.0
    for k in range(3):
        loaded = loaded or cout[canal.OUT_FX + k] != 0.0 or cout[canal.OUT_MX + k] != 0.0
    f0 = f1 = f2 = t0 = t1 = t2 = 0.0
    if ws[_FRACTURED] == 0.0 and loaded:
        rp = ws[_RP:_RP + 9]
        fp0, fp1, fp2 = cout[canal.OUT_FX], cout[canal.OUT_FX + 1], cout[canal.OUT_FX + 2]
        gp0, gp1, gp2 = cout[canal.OUT_MX], cout[canal.OUT_MX + 1], cout[canal.OUT_MX + 2]
        fl0 = rp[0] * fp0 + rp[1] * fp1 + rp[2] * fp2
        fl1 = rp[3] * fp0 + rp[4] * fp1 + rp[5] * fp2
        fl2 = rp[6] * fp0 + rp[7] * fp1 + rp[8] * fp2
        # the lateral loads' moment arms about the tip (mm -> m for torques)
        gl0 = (rp[0] * gp0 + rp[1] * gp1 + rp[2] * gp2) * 1e-3
        gl1 = (rp[3] * gp0 + rp[4] * gp1 + rp[5] * gp2) * 1e-3
        gl2 = (rp[6] * gp0 + rp[7] * gp1 + rp[8] * gp2) * 1e-3
        a0, a1, a2 = ws[_AXIS], ws[_AXIS + 1], ws[_AXIS + 2]
        # lateral loads along the file (their moment about the tip is -axis x m_lat), axial
        # force at the tip
        r0 = (ws[_TIP] - o0) * 1e-3
        r1 = (ws[_TIP + 1] - o1) * 1e-3
        r2 = (ws[_TIP + 2] - o2) * 1e-3
        f0, f1, f2 = fl0 + -fa * a0, fl1 + -fa * a1, fl2 + -fa * a2
        # the canal's torque on the file: opposes the motor's, about the file's axis
        tq = -torque_mnm * 1e-3
        t0 = r1 * f2 - r2 * f1 - (a1 * gl2 - a2 * gl1) + tq * a0
        t1 = r2 * f0 - r0 * f2 - (a2 * gl0 - a0 * gl2) + tq * a1
        t2 = r0 * f1 - r1 * f0 - (a0 * gl1 - a1 * gl0) + tq * a2
    ws[_CONTACT], ws[_CONTACT + 1], ws[_CONTACT + 2] = f0, f1, f2
    h0, h1, h2 = ws[_HAND], ws[_HAND + 1], ws[_HAND + 2]
    if h0 != 0.0 or h1 != 0.0 or h2 != 0.0:
        # the operator's hand at the grip (flange frame), its moment about the sensor
        g0, g1, g2 = ws[_GRIP], ws[_GRIP + 1], ws[_GRIP + 2]
        q0 = ((F[3, 0] + F[0, 0] * g0 + F[1, 0] * g1 + F[2, 0] * g2) - o0) * 1e-3
        q1 = ((F[3, 1] + F[0, 1] * g0 + F[1, 1] * g1 + F[2, 1] * g2) - o1) * 1e-3
        q2 = ((F[3, 2] + F[0, 2] * g0 + F[1, 2] * g1 + F[2, 2] * g2) - o2) * 1e-3
        f0, f1, f2 = f0 + h0, f1 + h1, f2 + h2
        t0, t1, t2 = (t0 + q1 * h2 - q2 * h1, t1 + q2 * h0 - q0 * h2,
                      t2 + q0 * h1 - q1 * h0)
    ws[_EXT_TAU], ws[_EXT_TAU + 1], ws[_EXT_TAU + 2] = t0, t1, t2
    sensor.sample(ss, sp, snoise, F, f0, f1, f2, t0, t1, t2)


def warm_up() -> None:
    """Compile (or load from the cache) the kernels for the argument types the world passes
    (a simulator serving a real-time controller must not stall). Called once, at import."""
    from dentibot.control.kinematics import Meca500
    from dentibot.sim.arm import SimArmModel
    from dentibot.sim.canal import Canal
    from dentibot.sim.ftsensor import FTSensorModel, FTSensorParams
    from dentibot.sim.handpiece import HandpieceModel, HandpieceParams
    from dentibot.sim.nitifile import NiTiFile

    c = Canal()
    c._prepare(NiTiFile())
    rng = np.random.default_rng(0)
    h = HandpieceModel(HandpieceParams(), rng)
    s = FTSensorModel(FTSensorParams(), rng)
    a = SimArmModel(Meca500(), (0.0, -10.0, 20.0, 0.0, 80.0, 0.0))
    ws = np.zeros(len(STATE_FIELDS))
    wp = np.ones(len(PARAM_FIELDS))
    F = np.zeros((4, 3))
    update_pose(ws, wp, F, a.kin._dh_arr, a._q)
    b0, b1, b2 = c._beam
    step(ws, wp, F, a.kin._dh_arr, a.ast, a.ap, a.lims, a._q, a._qd, a._vel_cmd, a._target,
         a._queue_t, a._queue_v, c.st, c.cp, c.R, c._h, c.s, c.kappa, b0, b1, b2, c._out,
         h.hs, h.hp, h.noise, s.ss, s.sp, s.noise, 0.002, 0.002)
    sense(ws, s.sp, F, c._out, 0.0, s.ss, s.noise)
    clear_interaction(np.zeros(len(canal.OUT_FIELDS)))


warm_up()      # at import: before any device streams or loop runs
