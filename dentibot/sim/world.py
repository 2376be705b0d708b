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

import dentibot.sim.world_kernels as wk
from dentibot.control.kinematics import Meca500
from dentibot.sim.arm import ArmParams, SimArmModel
from dentibot.sim.canal import Canal, CanalParams, Interaction, interaction_of
from dentibot.sim.ftsensor import FTSensorModel, FTSensorParams
from dentibot.sim.handpiece import HandpieceModel, HandpieceParams
from dentibot.sim.nitifile import FATIGUE_B, FATIGUE_C, FileFractured, NiTiFile
from dentibot.sim.patient import (
    PATIENT_MOTIONS,
    HeadMotion,
    MotionProfile,
    StaticPose,
    StewartSquare,
    offsets_mm,
    patient_motion,
)
from dentibot.sim.state_view import scalar, vector

#: Control period (s), thesis 3.1 (500 Hz).
TS = 0.002
# assumption: straight handpiece, file tip 90 mm from the flange along the flange z axis
# (10 mm sensor + adapter, ~55 mm handpiece head, file protruding ~25 mm).
TOOL_LENGTH_MM = 90.0
# assumption: a home pose pointing the file straight down, well away from singularities.
HOME_Q_DEG = (0.0, -10.0, 20.0, 0.0, 80.0, 0.0)


_ORIGIN, _FR_TORQUE, _FR_DEPTH = (wk.S["origin_x"], wk.S["fracture_torque"],
                                  wk.S["fracture_depth"])


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
        self.sensor = FTSensorModel(cfg.sensor, np.random.default_rng(s_sensor),
                                    period_s=cfg.ts)
        self.handpiece = HandpieceModel(cfg.handpiece, np.random.default_rng(s_motor))
        self.canal = Canal(cfg.canal)
        #: the world's state and constants (:mod:`dentibot.sim.world_kernels`)
        self.ws = np.zeros(len(wk.STATE_FIELDS))
        self.wp = np.zeros(len(wk.PARAM_FIELDS))
        self.wp[wk.P["tool_px"]:wk.P["tool_px"] + 3] = cfg.tool[:3, 3]
        self.wp[wk.P["tool_zx"]:wk.P["tool_zx"] + 3] = cfg.tool[:3, 2]
        self.wp[wk.P["fatigue_c"]], self.wp[wk.P["fatigue_b"]] = FATIGUE_C, FATIGUE_B
        self.file = cfg.file
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
        self._interaction: Interaction | None = None
        self._completeness_key: tuple | None = None
        self._completeness = 0.0
        self._F = np.zeros((4, 3))
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

    # ------------------------------------------------------------------ state
    tip_0 = vector("ws", wk.S["tip_x"], 3, "The file's tip in {0} (mm).")
    axis_0 = vector("ws", wk.S["axis_x"], 3, "The file's axis in {0} (unit, towards the tip).")
    contact_force_0 = vector("ws", wk.S["contact_x"], 3,
                             "The canal's net force on the file, {0} (N).")
    external_tau_0 = vector("ws", wk.S["ext_tau_x"], 3,
                            "The external torque about the sensor's origin, {0} (N*m).")
    hand_force_0 = vector("ws", wk.S["hand_x"], 3,
                          "The operator's hand on the handpiece, {0} (N).")
    hand_point_6_mm = vector("ws", wk.S["grip_x"], 3,
                             "Where the hand holds it, in the flange frame (mm).")
    fatigue_damage = scalar("ws", wk.S["fatigue_damage"],
                            doc="Miner's sum of the file's bending cycles (1: it breaks).",
                            settable=False)

    @property
    def file(self) -> NiTiFile:
        """The file in the handpiece."""
        return self._file

    @file.setter
    def file(self, f: NiTiFile) -> None:
        self._file = f
        self.wp[wk.P["torsional_strength_mnm"]] = f.torsional_strength_mnm

    @property
    def interaction(self) -> Interaction:
        """What the canal did to the file in the last step (phantom frame {P})."""
        it = self._interaction
        if it is None:
            it = self._interaction = interaction_of(self.canal)
        return it

    @property
    def _RP(self) -> list:
        """0R_P now (rows)."""
        return self._rp

    @_RP.setter
    def _RP(self, rows) -> None:
        self._rp = rows
        i = wk.S["rp00"]
        self.ws[i:i + 9] = (*rows[0], *rows[1], *rows[2])

    @property
    def _R06(self) -> tuple:
        """0R_6 now, as three row tuples."""
        c0, c1, c2, _ = self._F.tolist()
        return (c0[0], c1[0], c2[0]), (c0[1], c1[1], c2[1]), (c0[2], c1[2], c2[2])

    @property
    def _p06(self) -> tuple:
        """The flange's origin in {0} now (mm)."""
        return tuple(self._F[3].tolist())

    # ------------------------------------------------------------------ geometry
    def _update_pose(self) -> None:
        """The flange's pose and the file's tip and axis at the arm's joints (the step
        updates them itself when the arm moves)."""
        wk.update_pose(self.ws, self.wp, self._F, self.kin._dh_arr, self.arm._q)

    def phantom_origin_0(self) -> tuple[float, float, float]:
        """Canal orifice (origin of {P}) in {0} now (mm), including patient motion."""
        return self.origin_at(self.t)

    def origins_at(self, times: np.ndarray) -> np.ndarray:
        """:meth:`origin_at` at each of the ``times`` (n x 3), the same numbers."""
        pl, pp = np.array(self.platform_mm, dtype=float), np.array(self._pP, dtype=float)
        return (pp + offsets_mm(self.motion, times)) + pl

    def origin_at(self, t: float) -> tuple[float, float, float]:
        """Canal orifice in {0} (mm) at time ``t`` of a patient that does not turn (its
        motion's offset then; the platform where it is now)."""
        off = self.motion.offset_mm(t)
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
            self.ws[wk.S["fractured"]] = 1.0
            wk.clear_interaction(self.canal._out)
            self._interaction = None

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
        """Advance the world by exactly one period ``ts``: the patient's motion here, then the
        arm, the file in the canal, the handpiece, cutting, fatigue, fracture and the sensor's
        reading in one compiled call (:func:`dentibot.sim.world_kernels.step`)."""
        ts = self.ts
        self.t = t = (self.steps + 1) * ts
        self.steps += 1
        if hasattr(self.motion, "rotation_at"):
            self._rotate_patient(t)
        ws, arm, canal, hp, sensor = self.ws, self.arm, self.canal, self.handpiece, self.sensor
        if self.fractured is None:
            ws[_ORIGIN:_ORIGIN + 3] = self.phantom_origin_0()
        if canal._file_key is not self._file:
            canal._prepare(self._file)
        hp.refill()
        sensor.refill()
        b0, b1, b2 = canal._beam
        code = wk.step(ws, self.wp, self._F, self.kin._dh_arr, arm.ast, arm.ap, arm.lims,
                       arm._q, arm._qd, arm._vel_cmd, arm._target, arm._queue_t, arm._queue_v,
                       canal.st, canal.cp, canal.R, canal._h, canal.s, canal.kappa, b0, b1, b2,
                       canal._out, hp.hs, hp.hp, hp.noise, sensor.ss, sensor.sp, sensor.noise,
                       t, ts)
        self._interaction = None
        if code:
            self.fracture_from_step(code)

    def fracture_from_step(self, code: int) -> None:
        """The file broke in the step that just ended (``code``: the step kernel's cause)."""
        ws = self.ws
        self.fractured = FileFractured(wk.FRACTURE_CAUSES[code], self.t,
                                       float(ws[_FR_TORQUE]), float(ws[_FR_DEPTH]))

    def _sense(self) -> None:
        """The sensor's reading now (:func:`dentibot.sim.world_kernels.sense`)."""
        self.sensor.refill()
        wk.sense(self.ws, self.sensor.sp, self._F, self.canal._out, self.handpiece.torque_mnm,
                 self.sensor.ss, self.sensor.noise)

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
        return self._F[:3].T.copy()

    def completeness(self) -> float:
        """Eq 6.1 for the phantom's canal, in [0, 1]: :meth:`Canal.completeness`, computed
        again only when the file has cut the lumen since (the telemetry asks every tick)."""
        canal = self.canal
        key = (canal, canal.version)
        if key != self._completeness_key:
            self._completeness = canal.completeness()
            self._completeness_key = key
        return self._completeness
