"""The simulated world: arm + F/T sensor + handpiece + NiTi file + tooth phantom + patient.

``World.step()`` advances everything by exactly one period ``ts`` (0.002 s, the thesis's
500 Hz). Order within a step: arm servo -> tool pose (FK) -> phantom pose (patient motion) ->
file/canal geometry and resistances -> handpiece against that load -> cutting, debris, fatigue
-> fracture check -> sensor reading of the resulting wrench.

Frames: {0} robot base, {6} flange, {S} sensor (see ftsensor), {H} file tip with z along the
file towards the tip, {P} phantom (see canal). Lengths mm, forces N, torques N*m at the sensor,
file torque mNm.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dentibot.control.kinematics import Meca500
from dentibot.sim.arm import ArmParams, SimArmModel
from dentibot.sim.canal import Canal, CanalParams, Interaction
from dentibot.sim.ftsensor import FTSensorModel, FTSensorParams
from dentibot.sim.handpiece import HandpieceModel, HandpieceParams
from dentibot.sim.nitifile import FileFractured, NiTiFile
from dentibot.sim.patient import (
    PATIENT_MOTIONS,
    HeadMotion,
    MotionProfile,
    StaticPose,
    StewartSquare,
    patient_motion,
)

#: Control period (s), thesis 3.1 (500 Hz).
TS = 0.002
# assumption: straight handpiece, file tip 90 mm from the flange along the flange z axis
# (10 mm sensor + adapter, ~55 mm handpiece head, file protruding ~25 mm).
TOOL_LENGTH_MM = 90.0
# assumption: a home pose pointing the file straight down, well away from singularities.
HOME_Q_DEG = (0.0, -10.0, 20.0, 0.0, 80.0, 0.0)


def _tz(d: float) -> np.ndarray:
    t = np.eye(4)
    t[2, 3] = d
    return t


@dataclass
class WorldConfig:
    seed: int = 0
    ts: float = TS
    q0_deg: tuple = HOME_Q_DEG
    tool: np.ndarray = field(default_factory=lambda: _tz(TOOL_LENGTH_MM))
    arm: ArmParams = field(default_factory=ArmParams)
    sensor: FTSensorParams = field(default_factory=FTSensorParams)
    handpiece: HandpieceParams = field(default_factory=HandpieceParams)
    file: NiTiFile = field(default_factory=NiTiFile)
    canal: CanalParams = field(default_factory=CanalParams)
    #: 0T_P at rest (4x4, mm); None: orifice ``orifice_gap_mm`` ahead of the file tip at q0,
    #: {P} z along the file.
    phantom_pose: np.ndarray | None = None
    orifice_gap_mm: float = 2.0
    #: "static", "square" (thesis experiment 1), "head" (random small motion), "tremor",
    #: "swallowing", "patient" (head sway, tremor and swallows: sim.patient) or a profile.
    motion: str | MotionProfile = "static"


class World:
    """Everything the devices see. Deterministic given ``config.seed``."""

    def __init__(self, config: WorldConfig | None = None) -> None:
        self.config = cfg = config or WorldConfig()
        self.ts = cfg.ts
        self.t = 0.0
        self.steps = 0
        root = np.random.SeedSequence(cfg.seed)
        s_sensor, s_motor, s_patient = root.spawn(3)
        self.kin = Meca500(tool=cfg.tool)
        self.arm = SimArmModel(self.kin, cfg.q0_deg, cfg.arm)
        self._fk = self.kin.flange_floats
        self.sensor = FTSensorModel(cfg.sensor, np.random.default_rng(s_sensor))
        self.handpiece = HandpieceModel(cfg.handpiece, np.random.default_rng(s_motor))
        self.file = cfg.file
        self.canal = Canal(cfg.canal)
        m = cfg.motion
        if m == "static":
            self.motion: MotionProfile = StaticPose()
        elif m == "square":
            self.motion = StewartSquare()
        elif m == "head":
            self.motion = HeadMotion(np.random.default_rng(s_patient))
        elif m in PATIENT_MOTIONS:
            self.motion = StaticPose()         # until the tooth is placed (below)
        else:
            self.motion = m
        self.platform_mm = (0.0, 0.0, 0.0)    # commanded through AuxIO.set_platform
        self.pedal = False
        self.estop = False
        self.indicators: dict[str, bool] = {}
        # The operator's hand on the handpiece (dragging, TCP calibration): a force (N, {0})
        # at the grip, given in the flange frame (mm). Scripted by protocols and tests.
        self.hand_force_0 = (0.0, 0.0, 0.0)
        self.hand_point_6_mm = (0.0, 0.0, TOOL_LENGTH_MM - 50.0)
        self.fractured: FileFractured | None = None
        self.fatigue_damage = 0.0
        self.interaction = Interaction()
        self.contact_force_0 = (0.0, 0.0, 0.0)   # net force of the canal on the file, {0}
        self._completeness_key: tuple | None = None
        self._completeness = 0.0
        self._tool_p = tuple(float(x) for x in cfg.tool[:3, 3])
        self._tool_z = tuple(float(x) for x in cfg.tool[:3, 2])
        self._pose_q = None
        self._update_pose()
        if cfg.phantom_pose is None:
            t0h = self.kin.fk_tool(cfg.q0_deg)
            t0h[:3, 3] += cfg.orifice_gap_mm * t0h[:3, 2]
            self.phantom_pose = t0h
        else:
            self.phantom_pose = np.asarray(cfg.phantom_pose, dtype=float).copy()
        self._RP = self.phantom_pose[:3, :3].tolist()
        self._pP = tuple(self.phantom_pose[:3, 3].tolist())
        self._RP0, self._pP0 = self._RP, self._pP     # before any rotation of the patient
        if isinstance(m, str) and m in PATIENT_MOTIONS:   # about this tooth's jaw hinge
            self.motion = patient_motion(m, np.random.default_rng(s_patient),
                                         *self.canal_axis_0())
        self._sense()

    # ------------------------------------------------------------------ geometry
    def _update_pose(self) -> None:
        q = self.arm.q
        if q == self._pose_q:
            return
        self._R06, self._p06 = R, p = self._fk(q)
        a, b = self._tool_p, self._tool_z
        r0, r1, r2 = R
        self.tip_0 = (p[0] + r0[0] * a[0] + r0[1] * a[1] + r0[2] * a[2],
                      p[1] + r1[0] * a[0] + r1[1] * a[1] + r1[2] * a[2],
                      p[2] + r2[0] * a[0] + r2[1] * a[1] + r2[2] * a[2])
        self.axis_0 = (r0[0] * b[0] + r0[1] * b[1] + r0[2] * b[2],
                       r1[0] * b[0] + r1[1] * b[1] + r1[2] * b[2],
                       r2[0] * b[0] + r2[1] * b[1] + r2[2] * b[2])
        self._pose_q = list(q)

    def phantom_origin_0(self) -> tuple[float, float, float]:
        """Canal orifice (origin of {P}) in {0} now (mm), including patient motion."""
        off = self.motion.offset_mm(self.t)
        pl, pp = self.platform_mm, self._pP
        return (pp[0] + off[0] + pl[0], pp[1] + off[1] + pl[1], pp[2] + off[2] + pl[2])

    def to_phantom(self, v0, point: bool) -> tuple[float, float, float]:
        """A point (or a direction) from {0} to {P}."""
        if point:
            o = self.phantom_origin_0()
            v0 = (v0[0] - o[0], v0[1] - o[1], v0[2] - o[2])
        R = self._RP
        return tuple(R[0][j] * v0[0] + R[1][j] * v0[1] + R[2][j] * v0[2] for j in range(3))

    def from_phantom(self, vp, point: bool) -> tuple[float, float, float]:
        r0, r1, r2 = self._RP
        v = (r0[0] * vp[0] + r0[1] * vp[1] + r0[2] * vp[2],
             r1[0] * vp[0] + r1[1] * vp[1] + r1[2] * vp[2],
             r2[0] * vp[0] + r2[1] * vp[1] + r2[2] * vp[2])
        if point:
            o = self.phantom_origin_0()
            v = (v[0] + o[0], v[1] + o[1], v[2] + o[2])
        return v

    def canal_axis_0(self) -> tuple[tuple, tuple]:
        """(orifice point, unit direction of the straight canal part), both in {0}."""
        return self.phantom_origin_0(), self.from_phantom(self.canal.t0, point=False)

    def fracture_now(self, cause: str) -> None:
        """The file breaks now (fault injection): from the next step the canal holds the
        broken tip and nothing resists the stub."""
        if self.fractured is None:
            self.fractured = FileFractured(cause, self.t, abs(self.handpiece.torque_mnm),
                                           self.interaction.depth_mm)
            self.interaction = Interaction()

    @property
    def phantom_rotation(self) -> np.ndarray:
        """0R_P now (3x3): the phantom's orientation, turned by the patient's motion."""
        return np.array(self._RP)

    def _rotate_patient(self, t: float) -> None:
        """A motion that turns the patient (``rotation_at(t)`` -> (R 3x3, centre mm in {0}))
        turns the phantom about the centre: 0R_P = R 0R_P0, and its origin
        c + R (p0 - c); the translation (``offset_mm``) comes on top."""
        R, c = self.motion.rotation_at(t)
        r0 = self._RP0
        self._RP = [[sum(R[i][k] * r0[k][j] for k in range(3)) for j in range(3)]
                    for i in range(3)]
        d = [self._pP0[k] - c[k] for k in range(3)]
        self._pP = tuple(c[i] + R[i][0] * d[0] + R[i][1] * d[1] + R[i][2] * d[2]
                         for i in range(3))

    # ------------------------------------------------------------------ stepping
    def step(self) -> None:
        """Advance the world by exactly one period ``ts``."""
        ts = self.ts
        self.t = t = (self.steps + 1) * ts
        self.steps += 1
        if hasattr(self.motion, "rotation_at"):
            self._rotate_patient(t)
        arm = self.arm
        arm.step(t, ts)
        if arm.moving:
            self._update_pose()
        hp = self.handpiece
        if self.fractured is None:
            off = self.motion.offset_mm(t)
            pl, pP, R = self.platform_mm, self._pP, self._RP
            tip, ax = self.tip_0, self.axis_0
            d0 = tip[0] - pP[0] - off[0] - pl[0]
            d1 = tip[1] - pP[1] - off[1] - pl[1]
            d2 = tip[2] - pP[2] - off[2] - pl[2]
            r0, r1, r2 = R
            tip_p = (r0[0] * d0 + r1[0] * d1 + r2[0] * d2, r0[1] * d0 + r1[1] * d1 + r2[1] * d2,
                     r0[2] * d0 + r1[2] * d1 + r2[2] * d2)
            axis_p = (r0[0] * ax[0] + r1[0] * ax[1] + r2[0] * ax[2],
                      r0[1] * ax[0] + r1[1] * ax[1] + r2[1] * ax[2],
                      r0[2] * ax[0] + r1[2] * ax[1] + r2[2] * ax[2])
            canal = self.canal
            if canal._drag:
                canal.turning = hp.omega_rpm != 0.0
            it = canal.interact(tip_p, axis_p, self.file, ts)
            self.interaction = it
            resist = it.resist_mnm
            dpos = hp.step(ts, resist, resist * self.canal.p.reverse_factor)
            rev = dpos / 360.0
            if it.engagement_mm2 > 0.0 or rev < 0.0:
                self.canal.cut(rev)
                it.f_axial_n -= self.canal.screw_in_n(rev)
            if it.max_strain > 0.0 and rev:
                self.fatigue_damage += abs(rev) / self.file.cycles_to_failure(it.max_strain)
            torque = hp.torque_mnm
            if abs(torque) > self.file.torsional_strength_mnm:
                self.fractured = FileFractured("torsion", t, abs(torque), it.depth_mm)
            elif self.fatigue_damage >= 1.0:
                self.fractured = FileFractured("fatigue", t, abs(torque), it.depth_mm)
            if self.fractured is not None:
                self.interaction = it = Interaction()
        else:
            it = self.interaction
            hp.step(ts, 0.0, 0.0)
        self._sense()

    def _sense(self) -> None:
        it = self.interaction
        if self.fractured is None and (it.f_axial_n or it.resist_mnm or any(it.f_lat)
                                       or any(it.m_lat)):
            fp, gp = it.f_lat, it.m_lat
            r0, r1, r2 = self._RP
            fl = (r0[0] * fp[0] + r0[1] * fp[1] + r0[2] * fp[2],
                  r1[0] * fp[0] + r1[1] * fp[1] + r1[2] * fp[2],
                  r2[0] * fp[0] + r2[1] * fp[1] + r2[2] * fp[2])
            # the lateral loads' moment arms about the tip (mm -> m for torques)
            gl = ((r0[0] * gp[0] + r0[1] * gp[1] + r0[2] * gp[2]) * 1e-3,
                  (r1[0] * gp[0] + r1[1] * gp[1] + r1[2] * gp[2]) * 1e-3,
                  (r2[0] * gp[0] + r2[1] * gp[1] + r2[2] * gp[2]) * 1e-3)
            ax = self.axis_0
            tip = self.tip_0
            fa = it.f_axial_n
            o = self.sensor.origin(self._R06, self._p06)
            # lateral loads along the file (their moment about the tip is -axis x m_lat),
            # axial force at the tip
            rt = ((tip[0] - o[0]) * 1e-3, (tip[1] - o[1]) * 1e-3, (tip[2] - o[2]) * 1e-3)
            fax = (-fa * ax[0], -fa * ax[1], -fa * ax[2])
            f = (fl[0] + fax[0], fl[1] + fax[1], fl[2] + fax[2])
            # canal's torque on the file: opposes the motor's torque, about the file axis
            tq = -self.handpiece.torque_mnm * 1e-3
            tau = (
                rt[1] * f[2] - rt[2] * f[1] - (ax[1] * gl[2] - ax[2] * gl[1]) + tq * ax[0],
                rt[2] * f[0] - rt[0] * f[2] - (ax[2] * gl[0] - ax[0] * gl[2]) + tq * ax[1],
                rt[0] * f[1] - rt[1] * f[0] - (ax[0] * gl[1] - ax[1] * gl[0]) + tq * ax[2],
            )
            self.contact_force_0 = f
        else:
            f = tau = (0.0, 0.0, 0.0)
            self.contact_force_0 = f
        if self.hand_force_0 != (0.0, 0.0, 0.0):
            f, tau = self._add_hand(f, tau)
        self.external_tau_0 = tau
        self.sensor.sample(self._R06, f, tau)

    def _add_hand(self, f, tau):
        """Add the operator's hand: ``hand_force_0`` (N, {0}) applied at ``hand_point_6_mm``
        (the grip, in the flange frame), with its moment about the sensor origin."""
        R, p = self._R06, self._p06
        g = self.hand_point_6_mm
        pt = [p[i] + R[i][0] * g[0] + R[i][1] * g[1] + R[i][2] * g[2] for i in range(3)]
        o = self.sensor.origin(R, p)
        r = [(pt[i] - o[i]) * 1e-3 for i in range(3)]
        h = self.hand_force_0
        f = (f[0] + h[0], f[1] + h[1], f[2] + h[2])
        tau = (tau[0] + r[1] * h[2] - r[2] * h[1], tau[1] + r[2] * h[0] - r[0] * h[2],
               tau[2] + r[0] * h[1] - r[1] * h[0])
        return f, tau

    def run(self, seconds: float) -> None:
        """Step ``round(seconds / ts)`` times."""
        for _ in range(round(seconds / self.ts)):
            self.step()

    # ------------------------------------------------------------------ helpers
    def teleport_arm(self, q_deg) -> None:
        """Put the arm at ``q_deg`` at rest (set-up and tests), and refresh the reading."""
        self.arm.teleport(q_deg)
        self._update_pose()
        self.canal._last_depth = -1.0
        self._sense()

    def tool_rates(self, v_h_mm_s, w_h_deg_s=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Joint rates (deg/s) that move the file tip at ``v_h`` (mm/s, {H} axes) and turn the
        tool at ``w_h`` (deg/s, {H}) at the current joint positions (tool Jacobian, eq 3.14)."""
        j = self.kin.tool_jacobian(self.arm.q)
        twist = np.concatenate([np.asarray(v_h_mm_s, float), np.radians(w_h_deg_s)])
        return np.degrees(np.linalg.solve(j, twist))

    @property
    def flange_rotation(self) -> np.ndarray:
        """0R_6 now (3x3)."""
        return np.array(self._R06)

    def completeness(self) -> float:
        """Eq 6.1 for the phantom's canal, in [0, 1]: :meth:`Canal.completeness`, computed
        again only when the file has cut the lumen since (the telemetry asks every tick)."""
        canal = self.canal
        key = (canal, canal.version)
        if key != self._completeness_key:
            self._completeness = canal.completeness()
            self._completeness_key = key
        return self._completeness
