"""Self-alignment's orientation loop, compiled (numba): the steps of
:mod:`dentibot.control.canal_axis` over one state array.

:class:`~dentibot.control.canal_axis.CanalAxisServo` holds the arrays and calls these; they
are the only implementation. The state ``st`` and the parameters ``par`` are float arrays
whose fields :data:`STATE_FIELDS` and :data:`PARAM_FIELDS` name; the file's bending comes
from :func:`~dentibot.control.filebeam.beam_compliance` over the beam's tables (``length``,
``step``, ``i0``, ``i1``, ``i2``: :attr:`FileBeam.integrals`). Units: N, N*m in; mm, rad,
rad/s inside and out.

Compiled at import, as :mod:`~dentibot.control.kinematics_kernels` explains.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dentibot.control.filebeam import beam_compliance

#: The loop's state: the tare out of the canal (fx, fy N; mx, my N*m) and whether it was
#: taken; the low-passed loads in the canal (fx, fy N; the moment arms z x M, N*mm) and
#: whether they are building up; the chord's tilt from the tool axis (x, y in {H}, rad).
STATE_FIELDS = ("tare_fx", "tare_fy", "tare_mx", "tare_my", "tared", "load_fx", "load_fy",
                "arm_x", "arm_y", "loaded", "tilt_x", "tilt_y")
#: The parameters as the kernels take them: the tare's and the loads' filter coefficients
#: (per period), the rate bound (rad/s), the hold and stop angles (rad), the gain (1/s) and
#: the least readable depth (mm).
PARAM_FIELDS = ("a_tare", "a_load", "max_rate", "hold", "stop", "gain", "min_depth")

S_TARE, S_TARED, S_LOAD, S_LOADED, S_TILT = 0, 4, 5, 9, 10
P_A_TARE, P_A_LOAD, P_MAX_RATE, P_HOLD, P_STOP, P_GAIN, P_MIN_DEPTH = range(7)


@njit(cache=True)
def chord_tilt(depth_mm: float, fx: float, fy: float, arm_x: float, arm_y: float,
               length: float, step: float, i0: np.ndarray, i1: np.ndarray, i2: np.ndarray,
               out: np.ndarray) -> None:
    """Steps 2-3 of the loop: the tilt (rad, x and y in {H}) of the chord of the file's part
    in a canal ``depth_mm`` deep under the lateral force (fx, fy) and the loads' moment arms
    (z x M about the tip), written to ``out``. The orifice load is ``P_o = arm / d``, the tip
    load ``P_t = F - P_o``, and the chord turns by ``(w_t - w_o) / d`` with
    ``w_i = sum_j c(i, j) P_j``."""
    d = depth_mm
    c00 = beam_compliance(length, step, i0, i1, i2, 0.0, 0.0)
    c0d = beam_compliance(length, step, i0, i1, i2, 0.0, d)
    cdd = beam_compliance(length, step, i0, i1, i2, d, d)
    for i in range(2):
        p_o = (arm_x if i == 0 else arm_y) / d
        p_t = (fx if i == 0 else fy) - p_o
        out[i] = ((c00 - c0d) * p_t + (c0d - cdd) * p_o) / d


@njit(cache=True)
def step(st: np.ndarray, par: np.ndarray, depth_mm: float, known: bool, wrench_h: np.ndarray,
         length: float, beam_step: float, i0: np.ndarray, i1: np.ndarray,
         i2: np.ndarray) -> None:
    """One period with the depth (``known``: else unknown) and the wrench at the tip in {H}:
    out of the canal the tare follows the lateral force and moment (the first reading at
    once); in it, deeper than the least readable depth, the loads low-passed from zero and
    the chord's tilt from them."""
    w0, w1, w2, w3 = wrench_h[0], wrench_h[1], wrench_h[3], wrench_h[4]
    if not known or depth_mm < 0.0:
        a = par[P_A_TARE] if st[S_TARED] != 0.0 else 1.0
        st[S_TARE] += a * (w0 - st[S_TARE])
        st[S_TARE + 1] += a * (w1 - st[S_TARE + 1])
        st[S_TARE + 2] += a * (w2 - st[S_TARE + 2])
        st[S_TARE + 3] += a * (w3 - st[S_TARE + 3])
        st[S_TARED] = 1.0
        st[S_LOADED] = 0.0
        st[S_TILT] = st[S_TILT + 1] = 0.0
        return
    if depth_mm < par[P_MIN_DEPTH]:
        st[S_LOADED] = 0.0
        st[S_TILT] = st[S_TILT + 1] = 0.0
        return
    if st[S_LOADED] == 0.0:                 # they build up from zero in the canal
        st[S_LOAD] = st[S_LOAD + 1] = st[S_LOAD + 2] = st[S_LOAD + 3] = 0.0
        st[S_LOADED] = 1.0
    fx, fy = w0 - st[S_TARE], w1 - st[S_TARE + 1]
    mx, my = (w2 - st[S_TARE + 2]) * 1e3, (w3 - st[S_TARE + 3]) * 1e3
    a = par[P_A_LOAD]
    st[S_LOAD] += a * (fx - st[S_LOAD])
    st[S_LOAD + 1] += a * (fy - st[S_LOAD + 1])
    st[S_LOAD + 2] += a * (-my - st[S_LOAD + 2])     # z x M: the loads' moment arms
    st[S_LOAD + 3] += a * (mx - st[S_LOAD + 3])
    chord_tilt(depth_mm, st[S_LOAD], st[S_LOAD + 1], st[S_LOAD + 2], st[S_LOAD + 3], length,
               beam_step, i0, i1, i2, st[S_TILT:S_TILT + 2])


@njit(cache=True)
def twist(st: np.ndarray, par: np.ndarray, out: np.ndarray) -> bool:
    """Step 4: the rotation rate about the tip that turns the tool axis towards the chord,
    ``gain`` times the tilt, bounded, written to ``out`` as [0, 0, 0, wx, wy, 0] (rad/s,
    {H}); False (and ``out`` untouched) while there is nothing to turn."""
    tx, ty = st[S_TILT], st[S_TILT + 1]
    if tx == 0.0 and ty == 0.0:
        return False
    k = par[P_GAIN]
    wx, wy = -k * ty, k * tx               # z x (tx, ty, 1): turn z towards the chord
    n = math.hypot(wx, wy)
    if n > par[P_MAX_RATE]:
        wx, wy = wx * par[P_MAX_RATE] / n, wy * par[P_MAX_RATE] / n
    out[0] = out[1] = out[2] = out[5] = 0.0
    out[3], out[4] = wx, wy
    return True


@njit(cache=True)
def angle_rad(st: np.ndarray) -> float:
    """The misalignment (rad) between the tool axis and the chord."""
    return math.atan(math.hypot(st[S_TILT], st[S_TILT + 1]))


@njit(cache=True)
def feed_scale(st: np.ndarray, par: np.ndarray) -> float:
    """The factor (0..1) on the insertion force: 1 below the hold angle of misalignment, 0
    from the stop angle, linear in between."""
    a = angle_rad(st)
    if a <= par[P_HOLD]:
        return 1.0
    return max(0.0, (par[P_STOP] - a) / (par[P_STOP] - par[P_HOLD]))


def warm_up() -> None:
    """Compile (or load from the cache) the kernels for the argument types the servo passes.
    Called once, at import."""
    from dentibot.control.filebeam import FileBeam

    st, par = np.zeros(len(STATE_FIELDS)), np.full(len(PARAM_FIELDS), 0.1)
    beam_step, i0, i1, i2 = FileBeam().integrals
    w = np.zeros(6)
    step(st, par, -1.0, True, w, 25.0, beam_step, i0, i1, i2)
    step(st, par, 3.0, True, w, 25.0, beam_step, i0, i1, i2)
    chord_tilt(3.0, 0.1, 0.0, 0.0, 0.0, 25.0, beam_step, i0, i1, i2, np.zeros(2))
    twist(st, par, w)
    feed_scale(st, par)
    angle_rad(st)


warm_up()      # at import: before any device streams or loop runs
