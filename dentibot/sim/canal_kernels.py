"""The canal's step, compiled (numba): the file's contact with the walls, the resistances,
the drag, cutting and screw-in of :class:`~dentibot.sim.canal.Canal`, on arrays.

These kernels are the only implementation of the canal's laws (their physics is explained
in :mod:`dentibot.sim.canal`, whose methods call them). A canal is three kinds of arrays:

- its lumen per slice: ``R`` (radius, mm, cut by the file), ``h`` (``-(taper/2) s - R``
  for the file in use: the file's radius minus the lumen's is ``h + (d_tip + taper s_tip)/2``),
  ``s`` (slice centres, mm) and ``kappa`` (centreline curvature, 1/mm);
- its state ``st`` (:data:`STATE_FIELDS`): filtered feed and slip, the last depth, debris,
  the flush reference, whether the tip entered, the last lateral offset, the window of
  slices the file engages and the torques on the flutes this step;
- its parameters ``cp`` (:data:`PARAM_FIELDS`, from :class:`~dentibot.sim.canal.CanalParams`
  and the file): constants, never written here.

Each kernel works on one canal; a population of canals calls them in a loop inside compiled
code. The outcome of :func:`interact` is the array ``out`` (:data:`OUT_FIELDS`), the
fields of :class:`~dentibot.sim.canal.Interaction`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dentibot.control.filebeam import WORKING_PART_MM
from dentibot.sim.canal_walls import wall_loads

#: The canal's state, one float each (flags are 0.0 / 1.0).
STATE_FIELDS = (
    "feed",          # filtered feed rate (mm/s)
    "last_depth",    # tip depth last step (mm; -1: none)
    "slip",          # filtered axial slip rate (mm/s, + deeper)
    "flush_ref",     # deepest point since the debris was last flushed (mm)
    "debris",        # debris in the canal (mm^3)
    "entered",       # the tip is in the canal
    "has_last_e",    # the lateral offset of last step is known
    "last_eu", "last_ev",   # lateral offset of the tip last step (mm)
    "tau_cut",       # cutting torque of the last interaction (mNm)
    "tau_edges",     # torque on the flutes' edges: cutting + rubbing (mNm)
    "win_i0", "win_i1",     # slices the file engaged last step
    "win_c",         # the file's radius at the tip's depth last step, (d_tip + taper s)/2
    "turning",       # the file turns (set each step): a still file sticks
    "version",       # changes of the lumen R
)
#: The canal's and the file's constants.
PARAM_FIELDS = (
    "slice_mm", "n", "n_straight", "curved", "bottom_mm", "drag",
    "t0x", "t0y", "t0z", "ux", "uy", "uz", "vx", "vy", "vz",
    "feed_filter_s", "drag_filter_s", "withdraw_deadband_mm", "withdraw_mm",
    "access_margin_mm", "bottom_n_mm", "torque_mnm_per_mm2", "torque_mnm_s_per_mm3",
    "torque_mnm_per_mm3", "friction_mu", "rub_mnm_per_mm", "rub_clearance_mm",
    "axial_n_per_mm2", "axial_n_per_mm3", "axial_n_s_per_mm3", "bottom_torque_mnm_per_n",
    "drag_n_s_per_mm", "drag_coulomb_n", "drag_static_factor", "drag_v0_mm_s",
    "drag_depth_mm", "drag_still_coulomb_n", "drag_lat_n_s_per_mm", "support_mm_per_n",
    "support_extra_y_mm_per_n",
    "wall_n_mm_per_mm", "c_rev_per_rev", "c_fwd_per_rev", "cutting_energy_mj_mm3",
    "screw_n_per_mnm", "reverse_factor",
    # the file
    "file_tip_mm", "file_taper", "file_length_mm", "beam_step_mm",
)
#: What the canal does to the file this step (phantom frame {P}, N, mm, mNm).
OUT_FIELDS = ("depth_mm", "f_lat_x", "f_lat_y", "f_lat_z", "contact_from_tip_mm",
              "m_lat_x", "m_lat_y", "m_lat_z", "f_axial_n", "resist_mnm", "engagement_mm2",
              "max_strain")


def _index(names) -> dict[str, int]:
    return {name: i for i, name in enumerate(names)}


S = _index(STATE_FIELDS)
P = _index(PARAM_FIELDS)
O = _index(OUT_FIELDS)

# the indices as compiled constants
(_FEED, _LAST, _SLIP, _FLUSH, _DEBRIS, _ENTERED, _HAS_E, _EU, _EV, _TAU_CUT, _TAU_EDGES,
 _WIN0, _WIN1, _WINC, _TURNING, _VERSION) = range(len(STATE_FIELDS))
(_DS, _N, _NSTRAIGHT, _CURVED, _BOTTOM, _DRAG,
 _T0X, _T0Y, _T0Z, _UX, _UY, _UZ, _VX, _VY, _VZ,
 _FEED_TAU, _DRAG_TAU, _DEADBAND, _WITHDRAW, _ACCESS, _BOTTOM_K, _K_A, _K_V, _K_DEB, _MU,
 _RUB, _RUB_CLEAR, _AX_A, _AX_DEB, _AX_V, _BOTTOM_TQ, _DRAG_B, _DRAG_C, _DRAG_STATIC,
 _DRAG_V0, _DRAG_DEPTH, _DRAG_STILL_C, _DRAG_LAT, _SUPPORT, _SUPPORT_Y, _WALL_K, _C_REV,
 _C_FWD, _U_S, _SCREW, _REVERSE, _F_TIP, _F_TAPER, _F_LENGTH, _B_STEP) = range(len(PARAM_FIELDS))
#: The outcome's indices (the world's kernel reads them too).
(OUT_DEPTH, OUT_FX, OUT_FY, OUT_FZ, OUT_CONTACT, OUT_MX, OUT_MY, OUT_MZ, OUT_AXIAL,
 OUT_RESIST, OUT_ENGAGE, OUT_STRAIN) = range(len(OUT_FIELDS))

#: Indices other kernels use (compiled constants).
P_DRAG, P_REVERSE, S_TURNING = _DRAG, _REVERSE, _TURNING


@njit(cache=True)
def interact(st: np.ndarray, cp: np.ndarray, R: np.ndarray, h: np.ndarray, s: np.ndarray,
             kappa: np.ndarray, b0: np.ndarray, b1: np.ndarray, b2: np.ndarray,
             tx: float, ty: float, tz: float, ax: float, ay: float, az: float, dt: float,
             out: np.ndarray) -> None:
    """Geometry and resistances for the file's tip at ``(tx, ty, tz)`` (mm) along the unit
    axis ``(ax, ay, az)`` (from the handpiece into the tooth), both in {P}; ``dt`` (s) the
    period. ``b0, b1, b2``: the file beam's tables
    (:attr:`~dentibot.control.filebeam.FileBeam.integrals`). Writes ``out`` and ``st``."""
    for i in range(out.shape[0]):
        out[i] = 0.0
    s_tip = tx * cp[_T0X] + ty * cp[_T0Y] + tz * cp[_T0Z]
    out[OUT_DEPTH] = s_tip
    st[_WIN0] = 0.0
    st[_WIN1] = 0.0
    last = st[_LAST]
    raw = (s_tip - last) / dt if last > -1.0 else 0.0
    st[_FEED] += (raw - st[_FEED]) * (dt / (cp[_FEED_TAU] + dt))
    feed = st[_FEED]
    st[_LAST] = s_tip
    st[_TAU_CUT] = 0.0
    st[_TAU_EDGES] = 0.0
    drag = cp[_DRAG] != 0.0
    if drag:
        u = raw if s_tip <= cp[_BOTTOM] else 0.0
        st[_SLIP] += (u - st[_SLIP]) * (dt / (cp[_DRAG_TAU] + dt))
    if s_tip <= 0.0:
        st[_DEBRIS] = 0.0
        st[_ENTERED] = 0.0
        st[_FLUSH] = 0.0
        st[_HAS_E] = 0.0
        return
    if s_tip > st[_FLUSH]:
        st[_FLUSH] = s_tip
    else:
        back = st[_FLUSH] - s_tip - cp[_DEADBAND]
        if back > 0.0:
            st[_DEBRIS] *= math.exp(-back / cp[_WITHDRAW])
            st[_FLUSH] = s_tip + cp[_DEADBAND]
    ux, uy, uz = cp[_UX], cp[_UY], cp[_UZ]
    vx, vy, vz = cp[_VX], cp[_VY], cp[_VZ]
    eu = tx * ux + ty * uy + tz * uz
    ev = tx * vx + ty * vy + tz * vz
    ds = cp[_DS]
    n = int(cp[_N])
    i_tip = min(int(s_tip / ds), n)
    r_tip = R[max(i_tip - 1, 0)]
    if st[_ENTERED] == 0.0:
        if math.hypot(eu, ev) > r_tip + cp[_ACCESS]:
            out[OUT_DEPTH] = -1.0   # on the chamber floor, not in the canal
            out[OUT_AXIAL] = cp[_BOTTOM_K] * s_tip
            return
        # once in the canal the tip stays there: a large offset bends the file instead
        st[_ENTERED] = 1.0
    at = max(ax * cp[_T0X] + ay * cp[_T0Y] + az * cp[_T0Z], 0.2)
    au = (ax * ux + ay * uy + az * uz) / at
    av = (ax * vx + ay * vy + az * vz) / at
    i0 = max(int((s_tip - WORKING_PART_MM) / ds), 0)
    c = (cp[_F_TIP] + cp[_F_TAPER] * s_tip) / 2.0
    g = h[i0:i_tip] + c                       # r_f - R per slice
    area = 0.0
    touching = 0
    for i in range(g.shape[0]):
        if g[i] > 0.0:
            area += g[i]
        if g[i] > -cp[_RUB_CLEAR]:
            touching += 1
    area *= ds
    out[OUT_ENGAGE] = area
    i1 = min(i_tip, int(cp[_NSTRAIGHT]))
    nsum = 0.0
    if i1 > i0:
        # the walls' lateral loads on the straight part (see Canal.interact)
        sup = cp[_SUPPORT]
        total, fu, fv, mu, mv, d = wall_loads(
            s[i0:i1], g[: i1 - i0], au, av, eu, ev, s_tip, cp[_WALL_K] * ds, sup,
            cp[_SUPPORT_Y], cp[_F_LENGTH], cp[_B_STEP], b0, b1, b2)
        if total > 0.0:
            out[OUT_FX] = fu * ux + fv * vx
            out[OUT_FY] = fu * uy + fv * vy
            out[OUT_FZ] = fu * uz + fv * vz
            out[OUT_MX] = mu * ux + mv * vx
            out[OUT_MY] = mu * uy + mv * vy
            out[OUT_MZ] = mu * uz + mv * vz
            out[OUT_CONTACT] = d
            nsum = total
    deb = st[_DEBRIS]
    fin = max(feed, 0.0)
    tau_cut = (cp[_K_A] + cp[_K_V] * fin) * area
    st[_TAU_CUT] = tau_cut
    st[_TAU_EDGES] = tau_cut
    # the file's diameter at the contact (FileBeam.diameter_mm)
    x = min(max(out[OUT_CONTACT], 0.0), WORKING_PART_MM)
    diameter = cp[_F_TIP] + cp[_F_TAPER] * x
    resist = tau_cut + cp[_K_DEB] * deb + cp[_MU] * nsum * diameter / 2.0
    if cp[_RUB] != 0.0:
        rub = cp[_RUB] * ds * touching
        resist += rub
        st[_TAU_EDGES] += rub
    fa = (cp[_AX_A] * area + cp[_AX_DEB] * deb) * feed / (abs(feed) + 0.05)
    fa += cp[_AX_V] * feed * area
    if s_tip > cp[_BOTTOM]:
        f_bottom = cp[_BOTTOM_K] * (s_tip - cp[_BOTTOM])
        fa += f_bottom
        resist += cp[_BOTTOM_TQ] * f_bottom
    out[OUT_RESIST] = resist
    if drag:
        fa += _drag_forces(st, cp, out, eu, ev, dt, s_tip)
    out[OUT_AXIAL] = fa
    if cp[_CURVED] != 0.0:
        strain = 0.0
        for i in range(i0, i_tip):   # r_f / rho = d / (2 rho)
            e = kappa[i] * (g[i - i0] + R[i])
            if e > strain or i == i0:
                strain = e
        out[OUT_STRAIN] = strain
    st[_WIN0] = i0
    st[_WIN1] = i_tip
    st[_WINC] = c


@njit(cache=True)
def axial_drag_n(u: float, turning: bool, inside_mm: float, b: float, coulomb: float,
                 v0: float, static: float, still_coulomb: float, depth_mm: float) -> float:
    """The walls' axial drag (N, + pushes the file out) on a file slipping at ``u`` (mm/s,
    + deeper) with ``inside_mm`` of it in the canal: ``b u + coulomb tanh(u / v0)``, both
    ``static`` times harder and ``still_coulomb tanh(u / v0)`` more for a file that does not
    turn, in proportion to ``inside_mm / depth_mm`` when ``depth_mm`` > 0 (the
    :class:`~dentibot.sim.canal.CanalParams` drag fields). The canal's kernel and the bench's
    reduced axial model (:func:`~dentibot.sim.bench_physics.axial_chase`) both take it."""
    still = 1.0 if turning else static
    c = coulomb * still + (0.0 if turning else still_coulomb)
    fa = b * u * still + c * math.tanh(u / v0)
    if depth_mm > 0.0:
        fa *= inside_mm / depth_mm
    return fa


@njit(cache=True)
def _drag_forces(st: np.ndarray, cp: np.ndarray, out: np.ndarray, eu: float, ev: float,
                 dt: float, s_tip: float) -> float:
    """Canal drag: adds the lateral damping to the lateral loads in ``out`` and returns the
    axial drag (:func:`axial_drag_n` with the file ``s_tip`` deep)."""
    fa = axial_drag_n(st[_SLIP], st[_TURNING] != 0.0, s_tip, cp[_DRAG_B], cp[_DRAG_C],
                      cp[_DRAG_V0], cp[_DRAG_STATIC], cp[_DRAG_STILL_C], cp[_DRAG_DEPTH])
    had, last_u, last_v = st[_HAS_E], st[_EU], st[_EV]
    st[_HAS_E], st[_EU], st[_EV] = 1.0, eu, ev
    if cp[_DRAG_LAT] != 0.0 and had != 0.0 and (
            out[OUT_FX] != 0.0 or out[OUT_FY] != 0.0 or out[OUT_FZ] != 0.0):
        c = cp[_DRAG_LAT] / dt
        du, dv = (eu - last_u) * c, (ev - last_v) * c
        d = out[OUT_CONTACT]     # the damping acts at the contact
        for k in range(3):
            dl = du * cp[_UX + k] + dv * cp[_VX + k]
            out[OUT_FX + k] -= dl
            out[OUT_MX + k] -= d * dl
    return fa


@njit(cache=True)
def cut(st: np.ndarray, cp: np.ndarray, R: np.ndarray, h: np.ndarray,
        revolutions: float) -> float:
    """Apply ``revolutions`` of file rotation (signed, + cutting) after :func:`interact`;
    returns the removed volume (mm^3). See :meth:`dentibot.sim.canal.Canal.cut`."""
    if revolutions < 0.0:
        if st[_DEBRIS] != 0.0:
            st[_DEBRIS] *= math.exp(cp[_C_REV] * revolutions)
        return 0.0
    if revolutions == 0.0 or st[_LAST] <= 0.0:
        return 0.0
    i0, i1 = int(st[_WIN0]), int(st[_WIN1])
    if i1 <= i0:
        return 0.0
    c = st[_WINC]
    overlap = np.maximum(h[i0:i1] + c, 0.0)
    # volume per unit of overlap fraction: 2 pi ds sum(R_i overlap_i) (thin annuli)
    full = 2.0 * math.pi * cp[_DS] * np.dot(R[i0:i1], overlap)
    if full <= 0.0:
        return 0.0
    want = st[_TAU_CUT] * 2.0 * math.pi * revolutions / cp[_U_S]
    q = min(want / full, 1.0)
    for i in range(i0, i1):
        dr = q * overlap[i - i0]
        R[i] += dr
        h[i] -= dr
    st[_VERSION] += 1.0
    dv = q * full
    st[_DEBRIS] = st[_DEBRIS] * math.exp(-cp[_C_FWD] * revolutions) + dv
    return dv


@njit(cache=True)
def screw_in_n(st: np.ndarray, cp: np.ndarray, revolutions: float) -> float:
    """Axial pull (N, into the canal) of the engaged flutes for this step's rotation; see
    :meth:`dentibot.sim.canal.Canal.screw_in_n`."""
    if revolutions == 0.0 or st[_TAU_EDGES] == 0.0:
        return 0.0
    pull = cp[_SCREW] * st[_TAU_EDGES]
    return pull if revolutions > 0.0 else -cp[_REVERSE] * pull


@njit(cache=True)
def red_area(R: np.ndarray, R0: np.ndarray, width0: np.ndarray, stain_mm: float,
             out: np.ndarray) -> float:
    """The red area a photograph across the stained canal shows, per slice into ``out``
    (mm^2): the slice's stained width ``width0`` (zero beyond the working length) scaled by
    the stain the file has not cut away, ``clip(1 - (R - R0) / stain, 0, 1)``; returns their
    sum (see :meth:`dentibot.sim.canal.Canal.completeness`, eq 6.1)."""
    total = 0.0
    for i in range(R.shape[0]):
        left = min(max(1.0 - (R[i] - R0[i]) / stain_mm, 0.0), 1.0)
        out[i] = width0[i] * left
        total += out[i]
    return total


def warm_up() -> None:
    """Compile (or load from the cache) the kernels for the argument types the canal passes
    (a simulator serving a real-time controller must not stall). Called once, at import."""
    from dentibot.control.filebeam import FileBeam

    step, b0, b1, b2 = FileBeam().integrals
    n = 8
    s = (np.arange(n) + 0.5) * 0.25
    R = np.full(n, 0.1)
    h = -0.03 * s - R
    cp = np.zeros(len(PARAM_FIELDS))
    cp[_DS], cp[_N], cp[_NSTRAIGHT], cp[_CURVED], cp[_DRAG] = 0.25, n, n, 1.0, 1.0
    cp[_T0Z], cp[_UX], cp[_VY] = 1.0, 1.0, 1.0
    cp[_FEED_TAU] = cp[_DRAG_TAU] = cp[_WITHDRAW] = cp[_DRAG_V0] = cp[_U_S] = 1.0
    cp[_F_TIP], cp[_F_TAPER], cp[_F_LENGTH], cp[_B_STEP] = 0.25, 0.06, 25.0, step
    st = np.zeros(len(STATE_FIELDS))
    st[_LAST] = -1.0
    out = np.zeros(len(OUT_FIELDS))
    interact(st, cp, R, h, s, np.zeros(n), b0, b1, b2, 0.0, 0.0, 1.5, 0.0, 0.0, 1.0, 0.002,
             out)
    cut(st, cp, R, h, 0.1)
    screw_in_n(st, cp, 0.1)
    red_area(R, R.copy(), s, 0.02, np.empty(n))


warm_up()      # at import: before any device streams or loop runs
