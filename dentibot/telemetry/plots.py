"""Figures of a recording, after the thesis's experiment figures (fig 6.7-6.16).

:func:`plot_recording` writes one PNG per figure of :data:`FIGURES` into ``out_dir`` and skips
the figures whose data the recording lacks (the phantom pose is known on the simulator only,
for example); the returned list carries the reasons in ``.skipped``.

Figures (file names ``<recording stem>-<name>.png``):

- ``position_vs_root``: handpiece (file tip) and root (phantom) displacement per axis
  x, y, z (mm, from their first sample), and the distance between them (mm).
- ``force_vs_velocity``: measured force along the file axis (z of ``wrench_h``) against the
  velocity along the file axis (mm/s; the tool position differentiated, projected on the
  tool z axis), one colour per phase (the state's first two levels).
- ``force_vs_position``: the same force against the depth in the canal (mm), or against the
  position along the initial file axis when the depth is unknown, coloured the same way.

The three figures above leave out the load calibration's rows: its moves through the
workspace span tens of millimetres and would flatten the few millimetres of the treatment.
- ``torque_feed``: file torque with the file's strength (62 mNm), the limit in force (the
  runtime's, metadata ``torque_limit_mnm``) and the ``tau_d`` line (metadata ``tau_d_mnm``)
  over time; feed force ``fz_n`` and its set point ``fz_star_n``.
- ``state_timeline``: coloured bands per protocol step and per state over time.

Matplotlib is used through :class:`matplotlib.figure.Figure` with the Agg canvas only
(no pyplot, no global backend, no display).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import structlog
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from dentibot.telemetry.reader import Recording, read_recording

__all__ = ["FIGURES", "FILE_STRENGTH_MNM", "PlotSet", "plot_recording"]

log = structlog.get_logger("dentibot.telemetry")

# Torsional strength of the NiTi file (mNm): the same value as
# dentibot.control.feedrate.FILE_STRENGTH_MNM (telemetry does not import control);
# the metadata key "file_strength_mnm" overrides it.
FILE_STRENGTH_MNM = 62.0

_DPI = 100
_LABEL_PT = 7
_AXES = ("x", "y", "z")


class PlotSet(list):
    """The PNG paths written (a list of Path), with ``skipped``: figure name -> reason."""

    def __init__(self, paths=(), skipped: dict[str, str] | None = None) -> None:
        super().__init__(paths)
        self.skipped: dict[str, str] = dict(skipped or {})


def _t(rec: Recording) -> np.ndarray:
    return rec.column("t")


def _treatment(rec: Recording) -> np.ndarray:
    """Rows outside the load calibration (state ``calibrating...``), as a boolean mask."""
    return np.array([not str(s).startswith("calibrating") for s in rec.column("state")],
                    dtype=bool)


def _phase(rec: Recording) -> np.ndarray:
    """The state's first two levels per row (``treating.drilling.feeding`` ->
    ``treating.drilling``): the phases the force figures are coloured by."""
    return np.array([".".join(str(s).split(".")[:2]) for s in rec.column("state")])


def _scatter_by_phase(ax, x: np.ndarray, y: np.ndarray, phase: np.ndarray) -> None:
    """One colour and legend entry per phase, in order of first appearance."""
    seen = list(dict.fromkeys(phase.tolist()))
    for i, name in enumerate(seen):
        sel = phase == name
        ax.plot(x[sel], y[sel], ".", markersize=2, color=f"C{i % 10}", label=name or "(none)")
    if seen:
        ax.legend(loc="best", markerscale=4, fontsize=8)


def _valid_rows(a: np.ndarray) -> np.ndarray:
    """Rows of ``a`` (n,) or (n, k) without nan."""
    return np.isfinite(a) if a.ndim == 1 else np.isfinite(a).all(axis=1)


def _rot_mobile_xyz(pose_deg: np.ndarray) -> np.ndarray:
    """Rotation matrices (n, 3, 3) from mobile XYZ Euler angles (deg): Rx(a) Ry(b) Rz(g)."""
    a, b, g = np.radians(pose_deg[:, 3]), np.radians(pose_deg[:, 4]), np.radians(pose_deg[:, 5])
    ca, sa, cb, sb, cg, sg = np.cos(a), np.sin(a), np.cos(b), np.sin(b), np.cos(g), np.sin(g)
    r = np.empty((len(a), 3, 3))
    r[:, 0, 0] = cb * cg
    r[:, 0, 1] = -cb * sg
    r[:, 0, 2] = sb
    r[:, 1, 0] = ca * sg + sa * sb * cg
    r[:, 1, 1] = ca * cg - sa * sb * sg
    r[:, 1, 2] = -sa * cb
    r[:, 2, 0] = sa * sg - ca * sb * cg
    r[:, 2, 1] = sa * cg + ca * sb * sg
    r[:, 2, 2] = ca * cb
    return r


_FORCE_LABEL = "force along the file axis, wrench_h fz (N)"


def _axial_force(rec: Recording) -> np.ndarray:
    """Measured force along the file axis: z of the external wrench in {H} (N)."""
    return rec.column("wrench_h")[:, 2]


def _insertion_rows(rec: Recording) -> np.ndarray:
    """The rows :func:`_insertion` uses: treatment rows with a tool pose and a time."""
    return _valid_rows(rec.column("tool_pose")) & np.isfinite(_t(rec)) & _treatment(rec)


def _insertion(rec: Recording) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """(t, position along the initial file axis mm, velocity along the file axis mm/s) over
    :func:`_insertion_rows`, or the reason it cannot be computed."""
    ok = _insertion_rows(rec)
    t, pose = _t(rec)[ok], rec.column("tool_pose")[ok]
    if len(t) < 3 or not np.all(np.diff(t) > 0):
        return "fewer than 3 tool poses with increasing t"
    z_axis = _rot_mobile_xyz(pose)[:, :, 2]
    p = pose[:, :3]
    v = np.gradient(p, t, axis=0)
    return t, (p - p[0]) @ z_axis[0], np.einsum("ij,ij->i", v, z_axis)


def _fig_position_vs_root(rec: Recording, fig: Figure) -> str | None:
    t, tool, root = _t(rec), rec.column("tool_pose"), rec.column("phantom_pose")
    ok = _valid_rows(tool) & _valid_rows(root) & np.isfinite(t) & _treatment(rec)
    if ok.sum() < 2:
        return "no phantom pose in the recording (known on the simulator only)"
    t, tool, root = t[ok], tool[ok, :3], root[ok, :3]
    axes = fig.subplots(4, 1, sharex=True)
    for i, ax in enumerate(axes[:3]):
        ax.plot(t, tool[:, i] - tool[0, i], label="handpiece (file tip)")
        ax.plot(t, root[:, i] - root[0, i], "--", label="root (phantom)")
        ax.set_ylabel(f"{_AXES[i]} displacement (mm)")
    axes[0].legend(loc="best")
    axes[3].plot(t, np.linalg.norm(tool - root, axis=1), color="k")
    axes[3].set_ylabel("distance (mm)")
    axes[3].set_xlabel("t (s)")
    fig.suptitle("Handpiece vs root position")
    return None


def _fig_force_vs_velocity(rec: Recording, fig: Figure) -> str | None:
    ins = _insertion(rec)
    if isinstance(ins, str):
        return ins
    _t_ins, _pos, vel = ins
    rows = _insertion_rows(rec)
    fz, phase = _axial_force(rec)[rows], _phase(rec)[rows]
    ok = np.isfinite(fz)
    if ok.sum() < 2:
        return "no measured wrench (wrench_h) in the recording"
    ax = fig.subplots()
    _scatter_by_phase(ax, vel[ok], fz[ok], phase[ok])
    ax.set_xlabel("velocity along the file axis (mm/s)")
    ax.set_ylabel(_FORCE_LABEL)
    ax.grid(True)
    fig.suptitle("Force vs velocity (insertion axis)")
    return None


def _fig_force_vs_position(rec: Recording, fig: Figure) -> str | None:
    fz, depth, phase = _axial_force(rec), rec.column("depth_mm"), _phase(rec)
    ok = np.isfinite(fz) & np.isfinite(depth) & _treatment(rec)
    if ok.sum() >= 2:
        x, fz, phase, label = depth[ok], fz[ok], phase[ok], "depth in the canal (mm)"
    else:
        ins = _insertion(rec)
        if isinstance(ins, str):
            return f"no depth and {ins}"
        rows = _insertion_rows(rec)
        fz, phase = fz[rows], phase[rows]
        ok = np.isfinite(fz)
        if ok.sum() < 2:
            return "no measured wrench (wrench_h) in the recording"
        x, fz, phase = ins[1][ok], fz[ok], phase[ok]
        label = "position along the initial file axis (mm)"
    ax = fig.subplots()
    _scatter_by_phase(ax, x, fz, phase)
    ax.set_xlabel(label)
    ax.set_ylabel(_FORCE_LABEL)
    ax.grid(True)
    fig.suptitle("Force vs position")
    return None


def _fig_torque_feed(rec: Recording, fig: Figure) -> str | None:
    t, tau = _t(rec), rec.column("file_torque_mnm")
    ok = np.isfinite(t) & np.isfinite(tau)
    if ok.sum() < 2:
        return "no file torque in the recording"
    # older recordings named the strength "file_torque_limit_mnm"
    strength = rec.metadata.get("file_strength_mnm",
                                rec.metadata.get("file_torque_limit_mnm", FILE_STRENGTH_MNM))
    enforced = rec.metadata.get("torque_limit_mnm")
    tau_d = rec.metadata.get("tau_d_mnm")
    ax_tau, ax_f = fig.subplots(2, 1, sharex=True)
    ax_tau.plot(t[ok], tau[ok], label="file torque")
    ax_tau.axhline(strength, color="r", linestyle="--",
                   label=f"file strength {strength:g} mNm")
    if isinstance(enforced, (int, float)):      # recordings from before it was recorded: none
        ax_tau.axhline(enforced, color="orange", linestyle="--",
                       label=f"limit in force {enforced:g} mNm")
    if isinstance(tau_d, (int, float)):
        ax_tau.axhline(tau_d, color="g", linestyle=":", label=f"tau_d {tau_d:g} mNm")
    ax_tau.set_ylabel("torque (mNm)")
    ax_tau.legend(loc="best")
    for name, style, label in (("fz_n", "-", "fz = sat(fz*), fed to the admittance"),
                               ("fz_star_n", "--", "fz* (feedrate PD output)")):
        y = rec.column(name)
        good = np.isfinite(t) & np.isfinite(y)
        if good.any():
            ax_f.plot(t[good], y[good], style, label=label)
    ax_f.set_ylabel("feed force (N)")
    ax_f.set_xlabel("t (s)")
    ax_f.legend(loc="best")
    fig.suptitle("File torque and feed")
    return None


def _segments(t: np.ndarray, labels: np.ndarray) -> list[tuple[str, float, float]]:
    """(label, start, end) runs of equal consecutive labels."""
    out: list[tuple[str, float, float]] = []
    start = 0
    for i in range(1, len(labels) + 1):
        if i == len(labels) or labels[i] != labels[start]:
            end = t[i] if i < len(labels) else t[-1] + (t[-1] - t[0]) / max(len(t) - 1, 1)
            out.append((str(labels[start]), float(t[start]), float(end)))
            start = i
    return out


def _fig_state_timeline(rec: Recording, fig: Figure) -> str | None:
    t = _t(rec)
    ok = np.isfinite(t)
    if ok.sum() < 1:
        return "no rows in the recording"
    ax = fig.subplots()
    t = t[ok]
    span = float(t[-1] - t[0]) or 1.0
    # the axes' width in points (the legend takes about a quarter of the figure)
    width_pt = 0.7 * fig.get_figwidth() * 72.0
    legend: dict[str, dict[str, str]] = {}
    for y, name in ((1, "step"), (0, "state")):
        colours = legend[name] = {}           # label -> colour, in order of first appearance
        for label, start, end in _segments(t, rec.column(name)[ok]):
            colour = colours.setdefault(label, f"C{len(colours) % 10}")
            ax.broken_barh([(start, end - start)], (y - 0.4, 0.8), facecolors=colour)
            text = label or "(none)"
            # written inside its band only where it fits: a character of a 7 pt font is at
            # most 0.6 em wide, plus one em of margin; the legend names every band anyway
            if (end - start) / span * width_pt > (len(text) + 1) * _LABEL_PT * 0.6:
                ax.text((start + end) / 2, y, text, ha="center", va="center",
                        fontsize=_LABEL_PT, clip_on=True)
    handles = [Patch(facecolor=c, label=f"{name}: {label or '(none)'}")
               for name, colours in legend.items() for label, c in colours.items()]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7,
              frameon=False)
    ax.set_yticks([0, 1], ["state", "step"])
    ax.set_xlabel("t (s)")
    fig.suptitle("Protocol steps and states")
    return None


# name -> (figure size in inches, drawing function returning None or the reason to skip)
FIGURES: dict[str, tuple[tuple[float, float], Callable[[Recording, Figure], str | None]]] = {
    "position_vs_root": ((8, 9), _fig_position_vs_root),
    "force_vs_velocity": ((7, 5), _fig_force_vs_velocity),
    "force_vs_position": ((7, 5), _fig_force_vs_position),
    "torque_feed": ((9, 6), _fig_torque_feed),
    "state_timeline": ((12, 3.5), _fig_state_timeline),
}


def plot_recording(path: str | os.PathLike[str] | Recording,
                   out_dir: str | os.PathLike[str]) -> PlotSet:
    """Write the figures of a recording (path or :class:`Recording`) as PNGs in ``out_dir``
    (created if needed). Returns the paths written; ``.skipped`` names the figures not drawn
    and why. Raises TelemetryError if the recording cannot be read."""
    rec = path if isinstance(path, Recording) else read_recording(path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = PlotSet()
    if not rec.rows:
        result.skipped = {name: "no /tick rows in the recording" for name in FIGURES}
        return result
    for name, (size, draw) in FIGURES.items():
        fig = Figure(figsize=size)
        FigureCanvasAgg(fig)
        reason = draw(rec, fig)
        if reason is not None:
            result.skipped[name] = reason
            log.info("telemetry.plot_skipped", figure=name, reason=reason)
            continue
        fig.tight_layout()
        target = out / f"{rec.path.stem}-{name}.png"
        fig.savefig(target, dpi=_DPI)
        result.append(target)
    return result
