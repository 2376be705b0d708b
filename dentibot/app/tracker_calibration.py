"""The patient tracker's anchors identified on the set-up: the arm moves the handpiece (and the
mount anchors with it) through a set of poses while the clamp is held still, and
:func:`dentibot.control.strings.calibrate_anchors` finds the anchors that explain the string
lengths measured there.

Procedure (:func:`calibrate_tracker`, the protocol step ``calibrate_tracker``): the file is
out of the canal and the patient's clamp is held still (the operator confirms by starting the
step). For each pose of :func:`pose_set` the arm moves there (MoveJoints), waits until the
joints are within ``tol_deg`` of the target, settles ``settle_s`` and then, for ``average_s``,
averages the six lengths of the tracker's reads (the very samples the runtime reads every
tick) and the measured joints. Back at the start pose, the anchors are identified.

Pose set (:func:`pose_set`), in the tool frame {H} (origin at the file tip, z along the file
towards the tooth): the start pose; turns of ``rotation_deg`` about +x, -x, +y, -y and the
four diagonals (x +- y)/sqrt(2) of {H}, all about the file tip, which stays where it is;
a lift of ``translation_mm`` along -z; and the four sideways moves of ``translation_mm``
along +-x, +-y, each with the same lift. Fourteen poses. The rotations are what separate a
mount anchor from a tooth anchor (with a single orientation only ``R b_i - a_i`` is seen, and
with translations only the Jacobian is singular); the translations turn the strings' directions
without turning the clamp, and lower the condition number. With the default 10 deg and
5 mm and the simulator's geometry (a 40 mm ring of mount anchors, a 15 mm ring on the clamp,
strings 62-71 mm long over the set), each string's Jacobian has a condition number of 289,
and an anchor coordinate's standard deviation is at most 37 times that of an averaged length
(8 deg and 4 mm: 450 and 56 times; 5 deg and 3 mm: 1149 and 140 times: the smaller the
moves, the worse).
Nothing moves towards the tooth: the file tip stays put or moves away from it, and a move
is at most ``translation_mm`` sideways.

The arm: the state machine has no state for this calibration. From ``idle`` (or ``done``) the
routine sets the runtime's arm mode to a script, between two ticks, for its duration: the
control task then sends its joint targets (MoveJoints) instead of holding, exactly as in
``calibrating.load``, while the supervisor keeps checking every tick. Any state change (a fault,
an emergency stop) gives the new state's mode back and ends the routine, as does an abort
(Ctrl-C of a protocol run); at its end,
or on an error, the hold comes back (and on an error the arm is told to stop first).

The tooth's pose: the clamp is static in the base frame and the mount moves with the flange,
so at pose k ``MT_T(k) = (0T_6(k) 6T_M)^-1 0T_T`` with ``0T_T`` unknown but constant. It is
not identified with the anchors: a rigid displacement of the clamp's frame and the opposite
displacement of all six tooth anchors give the same lengths, so ``0T_T`` and the ``b_i``
together have six undetermined directions, and some frame must be chosen anyway. The runtime
needs none in particular: it registers the depth reference in {T} when the file goes in and
maps it back every tick, so any frame rigid with the clamp will do. The frame is fixed at the
first pose, then placed to fit the drawing:

1. ``MT_T(k) = (0T_6(k) 6T_M)^-1 0T_6(0) 6T_M S`` with ``S`` the nominal anchors' own
   solution of the first pose's lengths (:func:`~dentibot.control.strings.forward`): only the
   arm's relative motions enter, and the mount anchors are absolute in {M} (an error of
   ``6T_M`` is taken up by them, consistently with the runtime, which uses the same ``6T_M``);
2. the identified tooth anchors are then moved by the rigid transform ``G`` that best fits
   them to the nominal ones (Kabsch, least squares), and the poses with them
   (``MT_T(k) G^-1``): the tooth anchors' change from nominal is then only the part that is not
   a displacement of the whole clamp, and the lengths are unchanged.

Standard deviations: ``sqrt(diag(s^2 (J^T J)^-1))`` per string (as ``calibrate_anchors``),
with ``s`` the string's residual ``sqrt(SSR / (N - k))`` (N poses, k = 6 or 7 parameters),
and no less than the averaged reading's quantisation ``step / sqrt(12 n)``: the residual
carries the arm's pose errors too, which the encoders' noise alone would not.

Report (:class:`TrackerCalibration`): per string the mount and tooth anchors' change from
nominal (mm), their standard deviations, the rms residual (mm), the condition number of the
string's Jacobian and pass or fail against :class:`CalibrationBounds`; and the anchors in the
device file's format (:meth:`TrackerCalibration.anchors_yaml`,
:meth:`TrackerCalibration.tracker_config`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dentibot.control.strings import (
    AnchorCalibration,
    StringGeometry,
    calibrate_anchors,
    calibration_condition,
    forward,
    lengths,
)
from dentibot.errors import ConfigError, DentibotError
from dentibot.states.modes import MODES, Mode

#: States from which the calibration may start (the arm holds still, no force control).
START_STATES = ("idle", "done")
#: The arm mode while the routine moves it: a script (MoveJoints), as the load calibration's.
_SCRIPT = Mode("script")


class TrackerCalibrationError(DentibotError):
    """The tracker calibration could not measure (the arm did not reach a pose, the clamp
    moved during a hold, a fault or an abort stopped it)."""


@dataclass(frozen=True)
class CalibrationBounds:
    """Pass/fail of one string (mm). ``max_change_mm``: an anchor that moved further from the
    drawing is a wrong hook-up or a wrong drawing, not a tolerance; ``max_std_mm``: the
    anchors must be determined to this; ``max_rms_mm``: a larger residual means the model does
    not fit (a caught or slack wire, a clamp that moved, a wrong length offset)."""

    max_change_mm: float = 5.0
    max_std_mm: float = 0.2
    max_rms_mm: float = 0.02


@dataclass(frozen=True)
class TrackerCalibrationParams:
    """The pose set (deg, mm; :func:`pose_set`), the holds (s) and the checks.

    ``tol_deg``: joints this close to the target are there; ``timeout_s``: per move;
    ``max_spread_mm``: a string whose length moves more than this during a hold means the
    clamp or the mount moved; ``min_margin_mm``: no pose may bring a string (as the nominal
    anchors predict it) closer than this to its slack minimum or range end;
    ``max_joint_step_deg``: the joint motion of a pose from the start (a pose set that needs
    more is near a singularity)."""

    rotation_deg: float = 10.0
    translation_mm: float = 5.0
    tol_deg: float = 0.01
    settle_s: float = 0.2
    average_s: float = 0.1
    timeout_s: float = 5.0
    max_spread_mm: float = 0.05
    min_margin_mm: float = 5.0
    max_joint_step_deg: float = 45.0
    fit_offsets: bool = False
    bounds: CalibrationBounds = CalibrationBounds()

    def __post_init__(self) -> None:
        if not 2.0 <= self.rotation_deg <= 15.0:
            raise ConfigError("tracker_calibration.rotation_deg", self.rotation_deg,
                              "2 .. 15 deg (turns about the file tip)")
        if not 1.0 <= self.translation_mm <= 10.0:
            raise ConfigError("tracker_calibration.translation_mm", self.translation_mm,
                              "1 .. 10 mm (moves of the handpiece)")


def pose_set(rotation_deg: float = 10.0, translation_mm: float = 5.0
             ) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """The calibration's moves ``(rotation vector deg, translation mm)`` of the tool frame {H}
    from the start pose, about the file tip and in {H} axes (see the module docstring):
    ``0T_H(k) = 0T_H(0) D_k`` with ``D_k = [exp([r_k]x), t_k]``."""
    a, d = float(rotation_deg), float(translation_mm)
    h = a / np.sqrt(2.0)
    rot = [(a, 0, 0), (-a, 0, 0), (0, a, 0), (0, -a, 0), (h, h, 0), (-h, h, 0), (h, -h, 0),
           (-h, -h, 0)]
    move = [(0, 0, -d), (d, 0, -d), (-d, 0, -d), (0, d, -d), (0, -d, -d)]
    out = [(np.zeros(3), np.zeros(3))]
    out += [(np.array(r, float), np.zeros(3)) for r in rot]
    out += [(np.zeros(3), np.array(t, float)) for t in move]
    return tuple(out)


def move_matrix(rotvec_deg, translation_mm) -> np.ndarray:
    """``D = [exp([r]x), t]`` (4x4) of a move of :func:`pose_set`."""
    d = np.eye(4)
    d[:3, :3] = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    d[:3, 3] = translation_mm
    return d


def joint_target(kin, q_start_deg, flange_target: np.ndarray, *, iterations: int = 50,
                 tol_mm: float = 1e-9) -> np.ndarray:
    """Joints (deg) that put the flange at ``flange_target`` (0T_6, 4x4), by Newton steps on
    the flange's geometric Jacobian (``kin.jacobian``: linear mm/rad, angular rad/rad) from
    ``q_start_deg``, the nearby branch. Raises TrackerCalibrationError if it does not
    converge (a target out of reach or at a singularity)."""
    q = np.array(q_start_deg, dtype=float)
    for _ in range(iterations):
        t = kin.fk(q)
        e = np.concatenate([flange_target[:3, 3] - t[:3, 3], Rotation.from_matrix(
            flange_target[:3, :3] @ t[:3, :3].T).as_rotvec()])
        if np.linalg.norm(e[:3]) < tol_mm and np.linalg.norm(e[3:]) < tol_mm * 1e-3:
            return q
        q = q + np.degrees(np.linalg.lstsq(kin.jacobian(q), e, rcond=None)[0])
    raise TrackerCalibrationError(
        f"no joint solution for a calibration pose near {np.round(q_start_deg, 2).tolist()} "
        f"deg (position error {np.linalg.norm(e[:3]):.3g} mm)")


@dataclass(frozen=True)
class StringReport:
    """One string's result (mm): the anchors' change from nominal and their standard
    deviations (x, y, z), the rms residual, the condition number of its Jacobian, pass/fail
    and why it failed."""

    string: int
    mount_change_mm: np.ndarray
    tooth_change_mm: np.ndarray
    mount_std_mm: np.ndarray
    tooth_std_mm: np.ndarray
    offset_mm: float
    rms_mm: float
    condition: float
    ok: bool
    why: str = ""


def _fmt(v) -> str:
    return "[" + ", ".join(f"{x:.3f}" for x in np.asarray(v, float)) + "]"


@dataclass(frozen=True, eq=False)
class TrackerCalibration:
    """Result of :func:`identify` / :func:`calibrate_tracker`.

    Attributes:
        nominal: the anchors before (the device file's).
        calibration: :func:`~dentibot.control.strings.calibrate_anchors`'s result in the
            final tooth frame (its ``geometry`` is the identified anchors).
        strings: one :class:`StringReport` per string.
        poses: ``MT_T`` at each pose (N, 4, 4), in the final tooth frame.
        lengths_mm: the averaged lengths (N, n).
        sigma_mm: the length standard deviation used for each string (n,).
        bounds: what ``ok`` was judged against.
    """

    nominal: StringGeometry
    calibration: AnchorCalibration
    strings: tuple[StringReport, ...]
    poses: np.ndarray
    lengths_mm: np.ndarray
    sigma_mm: np.ndarray
    bounds: CalibrationBounds

    @property
    def geometry(self) -> StringGeometry:
        return self.calibration.geometry

    @property
    def ok(self) -> bool:
        return all(s.ok for s in self.strings)

    @property
    def rms_mm(self) -> float:
        """The rms residual over all poses and strings (mm)."""
        return float(np.sqrt(np.mean(np.asarray(self.calibration.residuals_mm) ** 2)))

    def anchors_yaml(self) -> str:
        """The identified anchors as the device file's ``tracker:`` keys (mm, 3 decimals)."""
        g = self.geometry
        lines = ["mount_anchors_mm:            # a_i in {M}, calibrated"]
        lines += [f"  - {_fmt(a)}" for a in g.mount_mm]
        lines += ["tooth_anchors_mm:            # b_i in {T}, calibrated"]
        lines += [f"  - {_fmt(b)}" for b in g.tooth_mm]
        return "\n".join(lines) + "\n"

    def tracker_config(self, config):
        """A copy of ``config`` (a :class:`~dentibot.io.devices.TrackerConfig`) with the
        identified anchors (mm, rounded to 0.001 mm)."""
        g = self.geometry
        return config.model_copy(update={
            "mount_anchors_mm": [tuple(round(float(x), 3) for x in a) for a in g.mount_mm],
            "tooth_anchors_mm": [tuple(round(float(x), 3) for x in b) for b in g.tooth_mm]})

    def report(self) -> str:
        """A table: per string the anchors' change (norm, mm) and its largest standard
        deviation, the rms residual, the condition number and pass/fail; then the anchors."""
        b = self.bounds
        rows = [f"tracker anchor calibration: {len(self.poses)} poses, "
                f"{'PASS' if self.ok else 'FAIL'} (bounds: change <= {b.max_change_mm:g} mm, "
                f"std <= {b.max_std_mm:g} mm, rms <= {b.max_rms_mm:g} mm)",
                "string  mount change (std)   tooth change (std)   rms mm   condition  result"]
        for s in self.strings:
            da, db = np.linalg.norm(s.mount_change_mm), np.linalg.norm(s.tooth_change_mm)
            rows.append(
                f"{s.string:>6}  {da:6.3f} ({s.mount_std_mm.max():.3f})"
                f"     {db:6.3f} ({s.tooth_std_mm.max():.3f})"
                f"     {s.rms_mm:6.4f}   {s.condition:9.0f}  "
                f"{'pass' if s.ok else 'FAIL: ' + s.why}")
        return "\n".join(rows) + "\n" + self.anchors_yaml()


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The rigid transform ``G`` (4x4) minimising ``sum |G src_i - dst_i|^2`` (Kabsch, by
    scipy's ``Rotation.align_vectors`` on the centred points)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    r = Rotation.align_vectors(dst - cd, src - cs)[0].as_matrix()
    g = np.eye(4)
    g[:3, :3] = r
    g[:3, 3] = cd - r @ cs
    return g


def identify(nominal: StringGeometry, flange_poses: Sequence, lengths_mm, *, start_pose,
             mount_in_flange=None, sigma_floor_mm: float = 0.0,
             fit_offsets: bool = False, bounds: CalibrationBounds = CalibrationBounds()
             ) -> TrackerCalibration:
    """The anchors from the flange poses ``0T_6(k)`` (N, 4x4, mm; the first the reference) and
    the averaged lengths (N x n, mm) measured there with the clamp static, and the report.

    ``start_pose``: the first guess of ``MT_T`` at the first pose (the device file's set-up
    position: the solve must start on the right side of the mount); ``mount_in_flange``:
    ``6T_M`` (default identity);
    ``sigma_floor_mm``: the smallest length standard deviation taken (see the module
    docstring). The tooth frame: fixed at the first pose, then fitted to the nominal tooth
    anchors (the module docstring).

    Raises:
        IdentificationError: the poses do not determine a string's anchors.
    """
    m = np.asarray(lengths_mm, dtype=float)
    t6m = np.eye(4) if mount_in_flange is None else np.asarray(mount_in_flange, float)
    t0m = [np.asarray(t, float) @ t6m for t in flange_poses]
    s = forward(nominal, m[0], start_pose).pose
    poses = np.array([np.linalg.inv(t) @ t0m[0] @ s for t in t0m])
    first = calibrate_anchors(nominal, list(poses), m, sigma_mm=1.0, fit_offsets=fit_offsets)
    g = _kabsch(np.asarray(first.geometry.tooth_mm), np.asarray(nominal.tooth_mm))
    poses = np.array([p @ np.linalg.inv(g) for p in poses])
    cal = calibrate_anchors(nominal, list(poses), m, sigma_mm=1.0, fit_offsets=fit_offsets)
    k = 7 if fit_offsets else 6
    n_poses = m.shape[0]
    res = np.asarray(cal.residuals_mm)
    pooled = float(np.sqrt(np.sum(res**2) / max(res.size - k * nominal.n, 1)))
    sigma = np.full(nominal.n, max(pooled, sigma_floor_mm))
    reports = []
    for i in range(nominal.n):
        da = np.asarray(cal.mount_correction_mm[i])
        db = np.asarray(cal.tooth_correction_mm[i])
        sa = sigma[i] * np.asarray(cal.mount_std_mm[i])
        sb = sigma[i] * np.asarray(cal.tooth_std_mm[i])
        rms = float(cal.rms_by_string_mm[i])
        why = []
        worst = max(np.linalg.norm(da), np.linalg.norm(db))
        if worst > bounds.max_change_mm:
            why.append(f"an anchor moved {worst:.2f} mm > {bounds.max_change_mm:g} mm")
        if max(sa.max(), sb.max()) > bounds.max_std_mm:
            why.append(f"std {max(sa.max(), sb.max()):.3f} mm > {bounds.max_std_mm:g} mm")
        if rms > bounds.max_rms_mm:
            why.append(f"rms residual {rms:.4f} mm > {bounds.max_rms_mm:g} mm")
        reports.append(StringReport(
            i + 1, da, db, sa, sb, float(cal.offsets_mm[i]), rms,
            calibration_condition(cal.geometry, i, poses, fit_offsets), not why, "; ".join(why)))
    return TrackerCalibration(nominal, cal, tuple(reports), poses, m, sigma, bounds)


# ------------------------------------------------------------------ on a running procedure
class _Recorder:
    """The tracker as the runtime reads it, keeping the last sample it returned."""

    def __init__(self, tracker) -> None:
        self.inner = tracker
        self.last = None

    async def read(self):
        self.last = s = await self.inner.read()
        return s

    def __getattr__(self, name):
        return getattr(self.inner, name)


async def calibrate_tracker(proc, *, nominal: StringGeometry | None = None,
                            params: TrackerCalibrationParams | None = None,
                            aborted: Callable[[], bool] = lambda: False) -> TrackerCalibration:
    """Run the calibration on the running procedure ``proc`` (see the module docstring) and
    return the identified anchors and their report. ``nominal``: the anchors to start from
    (default: the runtime's, i.e. the device file's). The arm ends at its start pose.

    The runtime must have a tracker and be idle (or done) with the file out of the canal;
    while the routine runs the arm is scripted (MoveJoints) as in the load calibration, and the
    supervisor, the state machine's faults and the operator's stop stay in force: a fault
    ends the routine (TrackerCalibrationError).

    Raises:
        ConfigError: no tracker, the runtime busy or the file maybe in the canal, or a pose
            that would bring a string near its slack minimum or range end (before any motion).
        TrackerCalibrationError: a pose not reached, the clamp moved, a fault or an abort.
        IdentificationError: the poses do not determine the anchors.
    """
    rt = proc.runtime
    p = params or TrackerCalibrationParams()
    tooth = rt.cfg.tooth
    if rt.dev.tracker is None or tooth is None:
        raise ConfigError("patient.tracker", False, "a patient tracker (the anchors are "
                          "identified from its string lengths)")
    nominal = nominal or tooth.geometry
    tr = rt.treatment
    if rt.state not in START_STATES:
        raise ConfigError("state", rt.state, f"one of {', '.join(START_STATES)} (the arm "
                          "still, no treatment under way)")
    if tr.depth_known or tr.maybe_in:
        raise ConfigError("file", "maybe in the canal", "out of the canal: withdraw it first "
                          "(the calibration turns the handpiece)")
    rec = _Recorder(rt.dev.tracker)
    state0 = rt.state

    def setup() -> None:
        rt.dev.tracker = rec
        rt.mode = _SCRIPT
        rt.ctx.script_target = None

    def restore() -> None:
        rt.dev.tracker = rec.inner
        rt.ctx.script_target = None
        if rt.mode is _SCRIPT:
            rt.mode = MODES[rt.state]

    def check() -> None:
        if rt.state != state0 or rt.mode is not _SCRIPT:
            causes = "; ".join(tr.fault_causes) if rt.state == "fault" else rt.state
            raise TrackerCalibrationError(f"tracker calibration stopped: {causes}")
        if aborted():
            raise TrackerCalibrationError("tracker calibration aborted")

    async def hold() -> tuple[np.ndarray, np.ndarray]:
        qs: list = []
        ls: list = []

        def collect(r) -> bool:
            s = rec.last
            if s is not None and s.ok and r.last is not None:
                qs.append(np.asarray(r.last.q_deg, float))
                ls.append(np.asarray(s.lengths_mm, float))
            return aborted() or r.state != state0
        await proc.run_for(p.average_s, until=collect)
        check()
        if len(ls) < 2:
            raise TrackerCalibrationError("no valid tracker sample during a hold")
        ls_a = np.array(ls)
        spread = np.ptp(ls_a, axis=0)
        if spread.max() > p.max_spread_mm:
            i = int(np.argmax(spread))
            raise TrackerCalibrationError(
                f"string {i + 1} changed by {spread[i]:.3f} mm during a hold (> "
                f"{p.max_spread_mm:g} mm): the clamp or the mount moved")
        return np.mean(qs, axis=0), ls_a.mean(axis=0)

    async def go(q_target: np.ndarray) -> None:
        def send() -> None:
            rt.ctx.script_target = tuple(float(x) for x in q_target)
        await proc.call(send)
        await proc.run_for(ticks=1)
        await proc.call(lambda: setattr(rt.ctx, "script_target", None))
        reached = await proc.run_for(p.timeout_s, until=lambda r: aborted() or r.state != state0
                                     or (r.last is not None and np.max(np.abs(
                                         np.asarray(r.last.q_deg) - q_target)) < p.tol_deg))
        check()
        if not reached:
            raise TrackerCalibrationError(
                f"joints not within {p.tol_deg} deg of {np.round(q_target, 3).tolist()} after "
                f"{p.timeout_s} s")
        await proc.run_for(p.settle_s, until=lambda r: aborted() or r.state != state0)
        check()

    await proc.run_for(ticks=1)        # the state's entry (a first tick, a command) is done
    await proc.call(setup)
    finished = False
    try:
        check()
        q0 = np.asarray(rt.last.q_deg, float) if rt.last is not None else None
        await proc.run_for(p.settle_s)
        check()
        q_mean, m0 = await hold()
        q0 = q_mean if q0 is None else q0
        kin = rt.kin
        t6m = np.asarray(tooth.mount_in_flange, float)
        t0h = kin.fk_tool(q0)
        s = forward(nominal, m0, tooth.start_pose).pose
        t0t = kin.fk(q0) @ t6m @ s
        targets = []
        for r, t in pose_set(p.rotation_deg, p.translation_mm)[1:]:
            t06 = t0h @ move_matrix(r, t) @ np.linalg.inv(kin.tool)
            q = joint_target(kin, q0, t06)
            step = float(np.max(np.abs(q - q0)))
            if step > p.max_joint_step_deg or not kin.within_limits(q):
                raise ConfigError("tracker_calibration.pose", np.round(q, 2).tolist(),
                                  f"joints within their range and within "
                                  f"{p.max_joint_step_deg:g} deg of the start pose")
            predicted = lengths(nominal, np.linalg.inv(t06 @ t6m) @ t0t)
            lo = tooth.limits.min_mm + p.min_margin_mm
            hi = tooth.limits.max_mm - p.min_margin_mm
            if predicted.min() < lo or predicted.max() > hi:
                raise ConfigError("tracker_calibration.pose", np.round(predicted, 1).tolist(),
                                  f"string lengths within {lo:g} .. {hi:g} mm (the strings' "
                                  f"range less {p.min_margin_mm:g} mm)")
            targets.append(q)
        qs, ms = [q_mean], [m0]
        for q in targets:
            await go(q)
            q_mean, m = await hold()
            qs.append(q_mean)
            ms.append(m)
        await go(q0)
        finished = True
    finally:
        async def end() -> None:
            restore()
            if not finished:           # a MoveJoints under way is dropped: the arm stops
                await rt.dev.arm.stop()

        try:
            await proc.call(end)
        except DentibotError:          # the loop has stopped: nothing reads the tracker
            restore()
    step = getattr(tooth, "sigma_mm", 0.01)
    n_avg = max(1, round(p.average_s / rt.ts))
    return identify(nominal, [kin.fk(q) for q in qs], np.array(ms), mount_in_flange=t6m,
                    start_pose=tooth.start_pose, sigma_floor_mm=step / np.sqrt(12 * n_avg),
                    fit_offsets=p.fit_offsets, bounds=p.bounds)


__all__ = ["CalibrationBounds", "START_STATES", "StringReport", "TrackerCalibration",
           "TrackerCalibrationError", "TrackerCalibrationParams", "calibrate_tracker",
           "identify", "joint_target", "move_matrix", "pose_set"]
