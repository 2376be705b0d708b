"""The canal walls' lateral loads on the straight part of a file, compiled (numba).

The model is :meth:`dentibot.sim.canal.Canal.interact`'s (its docstring derives it): the
undeformed file is a straight line from the handpiece's clamp, offset ``e(s)`` from the
canal's centreline (a complex number in the canal's (u, v) plane, linear in depth ``s``); the
file touches the walls at two places at most, the ends of its part in the canal, each with the
wall stiffness of the slices penetrating in its half; the file bends as a tapered cantilever
(:func:`~dentibot.control.filebeam.beam_compliance`) on a tooth held by a support that adds
``support_mm_per_n`` to every pair (``extra_y_mm_per_n`` more along the canal frame's v axis);
the loads solve a two-contact linear complementarity problem by active sets.

This is the only implementation: the world steps it every tick (about 25 us as Python on
this machine, 1-2 us compiled).

Compiled at import, as :mod:`~dentibot.control.kinematics_kernels` explains.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dentibot.control.filebeam import beam_compliance


@njit(cache=True)
def wall_loads(s: np.ndarray, g: np.ndarray, au: float, av: float, eu: float, ev: float,
               s_tip: float, k_slice: float, support: float, extra_y: float,
               length_mm: float, step: float, i0: np.ndarray, i1: np.ndarray,
               i2: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """The walls' loads on the file's straight part in the canal (slices of depths ``s``,
    ``g`` the file's radius minus the lumen's per slice), the file's tip at depth ``s_tip``
    offset ``(eu, ev)`` from the centreline, its axis leaning ``(au, av)`` per mm of depth;
    ``k_slice`` the wall stiffness of one slice (N/mm); the beam's tables as
    :attr:`~dentibot.control.filebeam.FileBeam.integrals` gives them.

    Returns ``(total, fu, fv, mu, mv, contact_from_tip)``: the sum of the loads' magnitudes
    (N, the normal load the wall friction acts with; 0 without contact), the resultant force
    on the file in (u, v) (N), its moment arm sum ``sum -lambda_j n_j a_j`` (N mm, ``a_j``
    the contact's distance from the tip) and the load-weighted contact distance from the tip
    (mm)."""
    n = g.shape[0]
    m = n // 2
    cu = eu - s_tip * au
    cv = ev - s_tip * av
    # the contacts: offset e (re, im), penetration, stiffness, lever from the tip, g there
    e_re = np.zeros(2)
    e_im = np.zeros(2)
    pen = np.zeros(2)
    kk = np.zeros(2)
    lever = np.zeros(2)
    goff = np.zeros(2)
    npt = 0
    for half in range(2):
        lo, hi, j = (0, m, 0) if half == 0 else (m, n, n - 1)
        if hi <= lo:
            continue
        count = 0
        for i in range(lo, hi):
            en = math.hypot(s[i] * au + cu, s[i] * av + cv)
            if min(g[i] + en, en + en) > 0.0:          # far minus near penetration
                count += 1
        xr, xi = s[j] * au + cu, s[j] * av + cv
        en = math.hypot(xr, xi)
        e_re[npt], e_im[npt] = xr, xi
        pen[npt] = min(g[j] + en, en + en)
        kk[npt] = k_slice * max(1, count)
        lever[npt] = s_tip - s[j]
        goff[npt] = g[j]
        npt += 1
    # c(i, j): the beam's compliance plus the support's, symmetric
    comp = np.zeros((2, 2))
    for a in range(npt):
        for b in range(a, npt):
            c = beam_compliance(length_mm, step, i0, i1, i2, lever[a], lever[b]) + support
            comp[a, b] = c
            comp[b, a] = c
    n_re = np.zeros(2)
    n_im = np.zeros(2)
    active = np.zeros(2, np.bool_)
    for a in range(npt):
        r = math.hypot(e_re[a], e_im[a])
        if r > 1e-9:
            n_re[a], n_im[a] = e_re[a] / r, e_im[a] / r
        active[a] = pen[a] > 0.0 and (n_re[a] != 0.0 or n_im[a] != 0.0)
    lam = np.zeros(2)
    for _ in range(4):
        lam[:] = 0.0
        n_act = 0
        first = second = -1
        for a in range(npt):
            if active[a]:
                if n_act == 0:
                    first = a
                else:
                    second = a
                n_act += 1
        if n_act == 1:
            a = first
            caa = comp[a, a] * (n_re[a] * n_re[a] + n_im[a] * n_im[a])
            if extra_y != 0.0:
                caa = caa + extra_y * n_im[a] * n_im[a]
            lam[a] = pen[a] / (1.0 / kk[a] + caa)
        elif n_act == 2:
            a, b = first, second
            cab = comp[a, b] * (n_re[a] * n_re[b] + n_im[a] * n_im[b])
            caa = comp[a, a] * (n_re[a] * n_re[a] + n_im[a] * n_im[a])
            cbb = comp[b, b] * (n_re[b] * n_re[b] + n_im[b] * n_im[b])
            if extra_y != 0.0:
                cab = cab + extra_y * n_im[a] * n_im[b]
                caa = caa + extra_y * n_im[a] * n_im[a]
                cbb = cbb + extra_y * n_im[b] * n_im[b]
            a00, a11 = 1.0 / kk[a] + caa, 1.0 / kk[b] + cbb
            det = a00 * a11 - cab * cab
            lam[a] = (a11 * pen[a] - cab * pen[b]) / det
            lam[b] = (a00 * pen[b] - cab * pen[a]) / det
        # a contact that would pull leaves (the most negative first)
        worst = -1
        for a in range(npt):
            if active[a] and lam[a] < 0.0 and (worst < 0 or lam[a] < lam[worst]):
                worst = a
        if worst >= 0:
            active[worst] = False
            continue
        # a contact the bending presses into the wall joins (the loads of this round's set)
        was = active.copy()
        joined = False
        for a in range(npt):
            if active[a]:
                continue
            w_re = 0.0
            w_im = 0.0
            ys = 0.0
            for b in range(npt):
                if was[b]:
                    c = comp[a, b]
                    w_re += (-lam[b] * n_re[b]) * c
                    w_im += (-lam[b] * n_im[b]) * c
                    ys += -lam[b] * n_im[b]
            if extra_y != 0.0:
                w_im += extra_y * ys
            xr, xi = e_re[a] + w_re, e_im[a] + w_im
            r = math.hypot(xr, xi)
            if r + goff[a] > 0.0 and r > 1e-9:         # bent into the wall
                n_re[a], n_im[a] = xr / r, xi / r
                pen[a] = (e_re[a] * n_re[a] + e_im[a] * n_im[a]) + goff[a]
                active[a] = True
                joined = True
        if not joined:
            break
    total = 0.0
    fu = fv = mu = mv = arm = 0.0
    for a in range(npt):
        total += lam[a]
        fu += -lam[a] * n_re[a]
        fv += -lam[a] * n_im[a]
        mu += (-lam[a] * n_re[a]) * lever[a]
        mv += (-lam[a] * n_im[a]) * lever[a]
        arm += lam[a] * lever[a]
    if total <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    return total, fu, fv, mu, mv, arm / total


def warm_up() -> None:
    """Compile (or load from the cache) :func:`wall_loads` for the argument types the canal
    passes (a simulator serving a real-time controller must not stall). Called once, at
    import."""
    from dentibot.control.filebeam import FileBeam

    step, t0, t1, t2 = FileBeam().integrals
    s = np.arange(4) + 0.5
    wall_loads(s, np.full(4, 0.01), 0.01, 0.0, 0.05, 0.0, 4.0, 5.0, 0.5, 0.0, 25.0, step,
               t0, t1, t2)


warm_up()      # at import: before any device streams or loop runs
