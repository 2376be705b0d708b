"""Meca500 wire simulator: the TCP text API (control and monitoring ports) over a World.

:class:`Meca500Server` speaks the bytes of :mod:`dentibot.io.meca500_protocol` so that the
project's driver, the vendor's client or any other Meca500 client can talk to it. It never steps
the World: it reads and commands ``world.arm`` when a command arrives, when a monitoring cycle
is due and at every poll (``poll_s``) while a RealTimeStepper (or anyone) steps the world.

Behaviour (Meca500 programming manual, firmware 9.x; the command table with answer codes
is in ``docs/meca500-simulator.md``):

- control port: greeting ``[3000][Connected to Meca500 R3 v9.3.0]``; one control client only, a
  second one gets ``[3001][Another user is already connected, closing connection.]`` and is
  closed. Monitoring port (control port + 1 unless given): several clients. A client that
  announces itself with bytes (the official client sends a NUL: "so it knows we're not a
  WebSocket") gets the greeting [3000] at once, then the status [2007]; one that sends
  nothing gets the status after ``monitor_greeting_wait_s`` without a greeting (assumption:
  the manual does not say what the robot sends a silent client). Then the status on every
  change and one cycle per monitoring interval.
- activation and homing: motion-queue commands before activation -> [1005], before homing ->
  [1006], while in error -> [1011]. Repeated ActivateRobot / Home answer [2000] / [2002] again
  (the 9.x manual lists no "already" codes; 2001/2003 were firmware < 9). Activation restores
  the motion-queue settings (SetJointVel, SetCartLinVel, SetTrf, SetWrf, SetVelTimeout, ...)
  to their defaults.
- the motion queue (section "Motion commands"), executed in order, answering nothing on
  success: MoveJoints, MoveJointsRel, MovePose (joint-space moves: they cross singularities,
  only the joint ranges stop them: [1007]; MovePose without a joint set within the ranges:
  [1016]); MoveLin, MoveLinRelTrf, MoveLinRelWrf (straight line, orientation along the
  shortest rotation, planned whole before the arm moves: a singularity on the way [1012], a
  joint range [1007], unreachable [1016]); MoveJointsVel (applied when it reaches the head of
  the queue); Delay; SetCheckpoint(n) -> [3030][n] when reached, [3040][n] when discarded;
  the settings SetJointVel, SetJointAcc, SetCartLinVel, SetCartAngVel, SetCartAcc,
  SetBlending, SetAutoConf, SetTrf, SetWrf, SetVelTimeout (a bad argument: [1003] at once).
  [3012] end of block when the queue is empty and the arm at rest. Joint moves run at
  SetJointVel percent of the joint speed limits; linear moves at SetCartLinVel /
  SetCartAngVel, slowed down where a joint would exceed its speed limit. Accelerations
  (SetJointAcc, SetCartAcc) and blending are accepted and kept but not modelled: every move
  ends at rest after the arm model's first-order servo lag.
- poses (GetPose, 2201, 2211) are the TRF in the WRF, mobile XYZ Euler angles.
- errors: a joint that reaches its limit, the wrist singularity under MoveJointsVel
  (``world.arm.error_code`` 1007 / 1012) and a refused move put the robot in error mode: the
  error message on the control port, then a 2007 with es=1 (and pm=1, as the manual says).
  ResetError -> [2005] (or [2006] without error); motion stays paused until ResumeMotion.
- PauseMotion / ClearMotion stop the arm (ClearMotion also empties the queue; both leave
  pm=1); ResumeMotion continues (an interrupted move restarts toward its target).
- a dropped control connection pauses the arm: it stops, the queue is cleared (assumption:
  nothing queued survives a lost link) and pm=1 until a client sends ResumeMotion or the
  robot is deactivated and activated again.
- connection watchdog (section "ConnectionWatchdog": ``ConnectionWatchdog(t)`` -> [2177][1],
  [2177][0] for t = 0, which disables it): only another ``ConnectionWatchdog`` refreshes it.
  When it expires the robot "will automatically stop moving and report a safety stop with the
  message [3086][1]". Here: the arm stops (as for a dropped link: queue cleared, pm=1, a [2007]
  with pm=1 goes out first), [3086][1] goes out on the monitoring stream (monitoring clients
  and a control client with SetCtrlPortMonitoring(1)), then the control connection and the
  monitoring connections from the same host are closed. The robot is not put in error (es
  stays 0): ResumeMotion clears the stop condition ([3086][0]).
- real-time data: the GetRt* queries answer the same record a monitoring cycle carries, with
  the World's timestamp. Monitoring: 2200 target joints, 2201 target pose, the optional
  records enabled with SetRealTimeMonitoring, then 2230 end of cycle. Timestamps are the
  World's time ``round(world.t * 1e6)`` (us), so every record says which world state it
  reports, and cycles are due on the World's clock: one each time world time passes the next
  multiple of the interval. If the World jumps several intervals between two polls (the
  stepper caught up), one cycle goes out and the missed ones are counted in
  ``skipped_cycles``: clients see the gap in the timestamps. While nobody steps the World, a
  cycle still goes out every max(3 intervals, 50 ms) with an unchanged timestamp. Timestamps
  never decrease. Target records are the exact joint state, measured ones (2210, 2211) the
  encoder-quantised reading; torques (2203, 2213) are zero (no joint dynamics in the World).
- bad bytes: unknown command [1001], syntax [1002], argument count or range [1003], a frame
  longer than ``max_frame_len`` [3003]; nothing crashes the server. A client that stops reading
  is disconnected once ``max_client_buffer`` bytes are waiting for it.

Fault hooks: ``freeze()`` makes the link half-open (connections kept, nothing sent, nothing
received handled); ``refuse_next(command, code)`` answers the next such command with an
error code instead of executing it.

Not simulated (answered [1001]): the other commands (SetConf, SetConfTurn, GetRtConf, the
gripper and I/O commands, MoveLinVelTrf/Wrf, ...); SetRealTimeMonitoring(all) is refused
([1003]: arguments are numbers only).
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import time
from collections import deque
from typing import Self

import numpy as np
import structlog
from scipy.spatial.transform import Rotation, Slerp

from dentibot.control.kinematics import damped_least_squares, matrix_from_pose, pose_from_matrix
from dentibot.control.strings_kernels import matrix_rotvec
from dentibot.errors import ConfigError, ProtocolError
from dentibot.io.meca500_protocol import (
    ANOTHER_USER,
    CHECKPOINT_ID_RANGE,
    COMMANDS,
    CONTROL_PORT,
    GREETING,
    MAX_FRAME_LEN,
    MONITORING_INTERVAL_DEFAULT_S,
    MONITORING_INTERVAL_RANGE_S,
    RT_ALWAYS,
    RT_CYCLE_END,
    RT_OPTIONAL,
    RT_QUERIES,
    VEL_TIMEOUT_RANGE_S,
    CommandError,
    FrameSplitter,
    RobotStatus,
    code_info,
    decode_command,
    encode_response,
    encode_rt,
    format_number,
    format_values,
)
from dentibot.sim.world import World

log = structlog.get_logger(__name__)

# assumptions: serial number and full-version format of the simulated robot.
SERIAL = "M500-SIM-0001"
FW_VERSION = "v9.3.0"
FW_VERSION_FULL = "9.3.0.0-sim"
#: A MoveJoints target counts as reached when every joint is within ARRIVED_DEG (the
#: encoder resolution of the World's arm) and slower than ARRIVED_DEG_S (the World's position
#: loop overshoots a little, so passing through the target is not arriving).
ARRIVED_DEG = 1e-3
ARRIVED_DEG_S = 1e-2
# assumption: queue capacity of the simulated robot (the manual gives none); beyond it [1000].
MAX_QUEUE = 10000
#: Product type answered to GetProductType (mecademicpy's official model name).
PRODUCT_TYPE = "Meca500"
#: Motion-queue settings: (argument range, default restored at every activation). Ranges and
#: defaults: programming manual, section "Motion commands" (mecademicpy's MX_MQ_DEFAULT_*),
#: except SetJointVel's default (see ``Meca500Server``'s ``joint_vel_default_pct``).
SETTINGS: dict[str, tuple[tuple[float, float], float]] = {
    "setjointvel": ((0.001, 100.0), 25.0),          # % of the top joint speeds
    "setjointacc": ((0.001, 150.0), 80.0),          # % of the top joint accelerations
    "setcartlinvel": ((0.001, 1000.0), 150.0),      # mm/s
    "setcartangvel": ((0.001, 300.0), 45.0),        # deg/s
    "setcartacc": ((0.001, 600.0), 50.0),           # %
    "setblending": ((0.0, 100.0), 100.0),           # %
    "setautoconf": ((0.0, 1.0), 1.0),               # 1 = automatic posture configuration
}
#: Cartesian planner: a MoveLin path is checked at one sample per PATH_STEP_MM (and per
#: PATH_STEP_DEG of reorientation), at most PATH_MAX_SAMPLES samples.
PATH_STEP_MM = 1.0
PATH_STEP_DEG = 1.0
PATH_MAX_SAMPLES = 400
#: Singular postures a linear move may not cross (assumption: thresholds of the simulator):
#: wrist |sin q5| and elbow below sin(0.5 deg) (the arm model's wrist band), shoulder (wrist
#: centre to the J1 axis) below 1 mm; a joint jump above PATH_JUMP_DEG between two samples.
SINGULAR_SIN = math.sin(math.radians(0.5))
SINGULAR_SHOULDER_MM = 1.0
PATH_JUMP_DEG = 10.0
#: Inverse kinematics (damped Newton): converged below IK_TOL_MM and IK_TOL_RAD.
IK_TOL_MM = 1e-6
IK_TOL_RAD = 1e-9
IK_MAX_ITER = 100
_LOG_FIRST, _LOG_EVERY = 10, 1000


@dataclasses.dataclass
class _Queued:
    #: "joints" | "jointsrel" | "pose" | "lin" | "linreltrf" | "linrelwrf" | "vel" |
    #: "timeout" | "checkpoint" | "delay" | "setting"
    kind: str
    args: tuple[float, ...]
    started: bool = False
    name: str = ""                        # the setting's command (kind "setting")
    target: tuple[float, ...] | None = None   # absolute joints or pose, fixed at first start
    final: tuple[float, ...] = ()         # the joint set the move ends at (planned at start)
    path: np.ndarray | None = None        # joint samples of a linear move
    duration: float = 0.0                 # s, world time
    t0: float = 0.0                       # world time the move (or delay) started


#: Queue items that move the arm in position mode.
MOVES = frozenset({"joints", "jointsrel", "pose", "lin", "linreltrf", "linrelwrf"})
#: A seed of the inverse kinematics: the simulated World's home posture.
HOME_SEED = (0.0, -10.0, 20.0, 0.0, 80.0, 0.0)


class _PlanError(Exception):
    """A move the robot refuses to start: ``code`` is the error it reports."""

    def __init__(self, code: int, why: str) -> None:
        super().__init__(why)
        self.code = code


class _Conn(asyncio.Protocol):
    """One TCP client of the simulator (control or monitoring port)."""

    def __init__(self, server: Meca500Server, kind: str) -> None:
        self.server = server
        self.kind = kind
        self.transport: asyncio.Transport | None = None
        self.peer = None
        self.splitter = FrameSplitter(server.max_frame_len)
        self.refused = False
        self.monitoring = False               # receives monitoring cycles
        self.greeted = kind == "control"      # a monitoring client is greeted on its first bytes
        self.greet_timer: asyncio.TimerHandle | None = None
        self.cycles_sent = 0
        self.bytes_sent = 0
        self.closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    # asyncio.Protocol
    def connection_made(self, transport) -> None:
        self.transport = transport
        self.peer = transport.get_extra_info("peername")
        self.server._on_connect(self)

    def data_received(self, data: bytes) -> None:
        self.server._on_data(self, data)

    def connection_lost(self, exc) -> None:
        if not self.closed.done():
            self.closed.set_result(None)
        if self.greet_timer is not None:
            self.greet_timer.cancel()
        self.server._on_disconnect(self)

    # helpers
    @property
    def open(self) -> bool:
        return self.transport is not None and not self.transport.is_closing()

    def send(self, data: bytes) -> bool:
        if not self.open or self.server.frozen:
            return False
        if self.transport.get_write_buffer_size() > self.server.max_client_buffer:
            self.server.dropped_clients += 1
            log.warning("meca500_sim.slow_client_dropped", port=self.kind, peer=self.peer,
                        waiting_bytes=self.transport.get_write_buffer_size())
            self.transport.abort()
            return False
        self.transport.write(data)
        self.bytes_sent += len(data)
        return True


class Meca500Server:
    """Simulated Meca500 on TCP over a :class:`~dentibot.sim.world.World`.

    Args:
        world: the World whose arm is reported and commanded.
        host: address to bind (loopback by default).
        port: control port (10000; 0 = ephemeral). ``self.port`` is the bound port.
        monitor_port: monitoring port; None = ``port + 1`` (or ephemeral when ``port`` is 0).
            ``self.monitor_port`` is the bound port.
        monitoring_interval_s: initial monitoring interval (s), ~16.7 ms.
        poll_s: how often the World is looked at: queue, errors, status, and whether a
            monitoring cycle is due (s). Keep it below the World's period.
        max_frame_len: longest command accepted (bytes); longer ones answer [3003].
        max_client_buffer: bytes waiting for a client before it is disconnected.
        joint_vel_default_pct: SetJointVel restored at every activation (%). The manual's
            default is 25 %; the simulator's is 100 % (full speed), which the simulated runs
            are timed with. Pass 25 to reproduce the robot's default.
        monitor_greeting_wait_s: how long a monitoring client that sends nothing waits for the
            status (see the module docstring, "monitoring port").
    """

    def __init__(self, world: World, host: str = "127.0.0.1", port: int = CONTROL_PORT,
                 monitor_port: int | None = None, *,
                 monitoring_interval_s: float = MONITORING_INTERVAL_DEFAULT_S,
                 poll_s: float = 0.001, max_frame_len: int = MAX_FRAME_LEN,
                 max_client_buffer: int = 1 << 20, serial: str = SERIAL,
                 greeting: str = GREETING, joint_vel_default_pct: float = 100.0,
                 monitor_greeting_wait_s: float = 0.05) -> None:
        lo, hi = MONITORING_INTERVAL_RANGE_S
        if not lo <= monitoring_interval_s <= hi:
            raise ConfigError("meca500_sim.monitoring_interval_s", monitoring_interval_s,
                              f"{lo}..{hi} s")
        if not 0.0 < poll_s <= 0.1:
            raise ConfigError("meca500_sim.poll_s", poll_s, "0 < poll_s <= 0.1 s")
        self.world = world
        self.host = host
        self.port = port
        if monitor_port is None:
            monitor_port = 0 if port == 0 else port + 1
        self.monitor_port = monitor_port
        self.monitoring_interval_s = monitoring_interval_s
        self.poll_s = poll_s
        self.max_frame_len = max_frame_len
        self.max_client_buffer = max_client_buffer
        self.serial = serial
        self.greeting = greeting
        lo, hi = SETTINGS["setjointvel"][0]
        if not lo <= joint_vel_default_pct <= hi:
            raise ConfigError("meca500_sim.joint_vel_default_pct", joint_vel_default_pct,
                              f"{lo}..{hi} %")
        self.defaults = {k: d for k, (_, d) in SETTINGS.items()}
        self.defaults["setjointvel"] = float(joint_vel_default_pct)
        #: motion-queue settings in force (lower-case command -> value), see SETTINGS
        self.settings = dict(self.defaults)
        #: tool (flange -> TRF) and world (BRF -> WRF) reference frames, 4x4 (mm)
        self.trf = np.eye(4)
        self.wrf = np.eye(4)
        self.monitor_greeting_wait_s = monitor_greeting_wait_s
        self.safety_stop = False       # connection-dropped safety stop ([3086][1]) active
        # robot state
        self.activated = False
        self.homed = False
        self.paused = False
        self.error_code = 0            # errors of the robot itself (the arm model has its own)
        self.rt_enabled: set[int] = set()
        self.default_vel_timeout_s = world.arm.p.vel_timeout_s
        self.watchdog_s = 0.0
        self.rtc_s: float | None = None
        self._queue: deque[_Queued] = deque()
        #: one handler per entry of the protocol's command table (``_cmd_<lower-case name>``)
        rt_queries = {name.lower(): code for name, code in RT_QUERIES.items()}
        self._handlers = {
            key: (getattr(self, "_cmd_" + key) if key not in rt_queries else
                  (lambda conn, args, text, c=rt_queries[key]: self._rt_query(c)))
            for key in COMMANDS}
        self._arm_error_seen = 0
        self._last_status: RobotStatus | None = None
        self._pose_cache: tuple[tuple, str] | None = None
        # connections and tasks
        self._ctrl: _Conn | None = None
        self._monitors: list[_Conn] = []
        self._conns: set[_Conn] = set()
        self._servers: list[asyncio.AbstractServer] = []
        self._task: asyncio.Task | None = None
        self._reschedule = True
        self._watchdog_fed_at = 0.0
        self._closed = False
        # counters
        self.commands = 0            # commands received (empty ones excluded)
        self.bad_frames = 0          # frames answered 1001/1002/1003/3003
        self.cycles = 0              # monitoring cycles generated
        self.skipped_cycles = 0      # cycles skipped because the World moved on by several
        self.refused_clients = 0     # second control clients refused with 3001
        self.dropped_clients = 0     # slow clients disconnected
        self.control_drops = 0       # control connections lost (link drop or close)
        self.watchdog_expiries = 0   # connection watchdog safety stops
        #: a half-open link (:meth:`freeze`): nothing goes out, nothing received is handled
        self.frozen = False
        #: (command name, error code): the next such command is refused with that code
        self._refuse: tuple[str, int] | None = None

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Bind both ports and start the monitoring loop."""
        if self._servers:
            return
        loop = asyncio.get_running_loop()
        try:
            ctrl = await loop.create_server(lambda: _Conn(self, "control"), self.host, self.port)
            self._servers.append(ctrl)
            self.port = ctrl.sockets[0].getsockname()[1]
            mon = await loop.create_server(lambda: _Conn(self, "monitor"), self.host,
                                           self.monitor_port)
            self._servers.append(mon)
            self.monitor_port = mon.sockets[0].getsockname()[1]
        except BaseException:
            await self.close()
            raise
        self._closed = False
        self._task = asyncio.create_task(self._run(), name="meca500-sim")
        log.info("meca500_sim.started", host=self.host, port=self.port,
                 monitor_port=self.monitor_port)

    async def close(self) -> None:
        """Stop the loop, close the listening sockets and every client (idempotent)."""
        if self._closed and not self._servers and self._task is None:
            return
        self._closed = True
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        servers, self._servers = self._servers, []
        for s in servers:
            s.close()
        conns = list(self._conns)
        for c in conns:                  # close() flushes what is already written
            if c.transport is not None:
                c.transport.close()
        if conns:
            await asyncio.wait([c.closed for c in conns], timeout=1.0)
        for c in conns:
            if c.transport is not None and not c.closed.done():
                c.transport.abort()
        for s in servers:
            await s.wait_closed()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    # ------------------------------------------------------------------ test helpers
    @property
    def monitor_clients(self) -> tuple[_Conn, ...]:
        """Connected monitoring clients (``cycles_sent``, ``bytes_sent``, ``peer``)."""
        return tuple(self._monitors)

    @property
    def control_client(self) -> _Conn | None:
        return self._ctrl

    def drop_clients(self) -> None:
        """Cut every client connection at once, like a pulled cable (no flush)."""
        for c in list(self._conns):
            if c.transport is not None:
                c.transport.abort()

    def freeze(self, frozen: bool = True) -> None:
        """The link goes half-open (a cable cut without a reset, a hung network stack): the
        connections stay open, but no answer, status or monitoring cycle goes out and nothing
        received is handled. The robot itself goes on: its velocity timeout stops a
        MoveJointsVel, its connection watchdog stops the arm (the sockets it then closes never
        tell the client). ``freeze(False)`` ends it."""
        self.frozen = frozen

    def refuse_next(self, command: str = "MoveJointsVel", code: int = 1000) -> None:
        """Refuse the next ``command`` with error ``code`` (default [1000] "Command buffer is
        full.") instead of executing it, e.g. a velocity command failing mid-cycle."""
        self._refuse = (command, code)

    def inject(self, data: bytes, to: str = "monitor") -> None:
        """Send raw bytes to the control client (``to="control"``) or every monitoring
        client, e.g. garbage, to test a client's robustness."""
        targets = [self._ctrl] if to == "control" else list(self._monitors)
        for c in targets:
            if c is not None:
                c.send(data)

    def status(self) -> RobotStatus:
        """The status word the robot would report now."""
        arm = self.world.arm
        err = self.in_error
        eom = not arm.moving
        return RobotStatus(self.activated, self.homed, False, err, self.paused or err,
                           eom and not self._queue, eom)

    @property
    def in_error(self) -> bool:
        return bool(self.error_code or self.world.arm.error_code)

    # ------------------------------------------------------------------ connections
    def _on_connect(self, conn: _Conn) -> None:
        self._conns.add(conn)
        if conn.kind == "control":
            if self._ctrl is not None:
                conn.refused = True
                self.refused_clients += 1
                conn.send(encode_response(3001, ANOTHER_USER))
                conn.transport.close()          # flushes the refusal, then closes
                log.info("meca500_sim.control_refused", peer=conn.peer)
                return
            self._ctrl = conn
            conn.send(encode_response(3000, self.greeting))
            log.info("meca500_sim.control_connected", peer=conn.peer)
        else:
            loop = asyncio.get_running_loop()
            conn.greet_timer = loop.call_later(self.monitor_greeting_wait_s,
                                               self._greet_monitor, conn, False)

    def _greet_monitor(self, conn: _Conn, announced: bool) -> None:
        """Start a monitoring client's stream: the greeting [3000] (only to a client that
        announced itself with bytes, as the official client does with a NUL), then its
        state [2007], then every status change and monitoring cycle."""
        if conn.greeted or not conn.open:
            return
        conn.greeted = True
        if conn.greet_timer is not None:
            conn.greet_timer.cancel()
            conn.greet_timer = None
        if announced:
            conn.send(encode_response(3000, self.greeting))
        conn.send(encode_response(2007, self.status().to_payload()))
        if self.safety_stop:
            conn.send(encode_response(3086, "1"))
        conn.monitoring = True
        self._monitors.append(conn)

    def _on_disconnect(self, conn: _Conn) -> None:
        self._conns.discard(conn)
        if conn in self._monitors:
            self._monitors.remove(conn)
        if conn is self._ctrl:
            self._ctrl = None
            self.control_drops += 1
            self.watchdog_s = 0.0
            self._link_lost("control connection lost")

    def _link_lost(self, why: str) -> None:
        """What the robot does when its controlling client goes away: pause and clear."""
        if self.activated:
            self._clear_queue(report=self._ctrl is not None)
            self.world.arm.stop()
            self.paused = True
            log.warning("meca500_sim.motion_paused", reason=why)
        self._publish_status()

    def _on_data(self, conn: _Conn, data: bytes) -> None:
        if self.frozen:
            return
        if conn.kind != "control":
            if not conn.greeted:
                self._greet_monitor(conn, True)
            return                               # the monitoring port ignores input
        if conn.refused:
            return
        for item in conn.splitter.feed(data):
            if isinstance(item, ProtocolError):
                self._bad(conn, 3003, "Command too long.", item)
            else:
                self._handle(conn, item)

    def _bad(self, conn: _Conn, code: int, text: str, exc: Exception) -> None:
        self.bad_frames += 1
        if self.bad_frames <= _LOG_FIRST or self.bad_frames % _LOG_EVERY == 0:
            log.warning("meca500_sim.bad_command", code=code, error=str(exc),
                        count=self.bad_frames)
        conn.send(encode_response(code, text))

    def _send_ctrl(self, code: int, payload: str = "") -> None:
        if self._ctrl is not None:
            self._ctrl.send(encode_response(code, payload))

    def _error_text(self, code: int, command: str = "") -> str:
        info = code_info(code)
        text = info.meaning if info is not None else ""
        return f"{text} - Command: '{command}'" if command else text

    # ------------------------------------------------------------------ commands
    def _handle(self, conn: _Conn, frame: bytes) -> None:
        try:
            cmd = decode_command(frame)
        except CommandError as exc:
            self._bad(conn, exc.code, self._error_text(exc.code, exc.text), exc)
            return
        if cmd is None:
            return                               # empty command: ignored
        self.commands += 1
        text = frame.decode("ascii", "replace")
        spec = cmd.spec
        if spec is None:
            self._bad(conn, 1001, self._error_text(1001, text),
                      ProtocolError("meca500_sim", f"unknown command {cmd.name}"))
            return
        lo, hi = spec.nargs
        if not lo <= len(cmd.args) <= hi:
            self._bad(conn, 1003, self._error_text(1003, text), ProtocolError(
                "meca500_sim", f"{spec.name} takes {lo}..{hi} arguments, got {len(cmd.args)}"))
            return
        self._poll()
        if spec.requires != "none" and not self.activated:
            self._send_ctrl(1005, self._error_text(1005))
            return
        if spec.requires == "homed" and not self.homed:
            self._send_ctrl(1006, self._error_text(1006))
            return
        if spec.queued and self.in_error:
            self._send_ctrl(1011, self._error_text(1011))
            return
        if spec.queued and len(self._queue) >= MAX_QUEUE:
            self._send_ctrl(1000, self._error_text(1000))
            return
        if self._refuse is not None and self._refuse[0] == spec.name:
            code, self._refuse = self._refuse[1], None
            self._send_ctrl(code, self._error_text(code, text))
            return
        self._handlers[cmd.key](conn, cmd.args, text)
        self._poll()

    def _arg_error(self, text: str) -> None:
        self.bad_frames += 1
        self._send_ctrl(1003, self._error_text(1003, text))

    def _cmd_activaterobot(self, conn, args, text) -> None:
        if self.in_error:
            self._send_ctrl(1011, self._error_text(1011))
            return
        if not self.activated:
            self.activated = True
            self.paused = False
            arm = self.world.arm
            arm.p = dataclasses.replace(arm.p, vel_timeout_s=self.default_vel_timeout_s)
            self.settings = dict(self.defaults)
            self.trf = np.eye(4)
            self.wrf = np.eye(4)
            self._set_safety_stop(False)
        self._send_ctrl(2000, "Motors activated.")

    def _cmd_deactivaterobot(self, conn, args, text) -> None:
        self._clear_queue(report=True)
        self.world.arm.stop()
        self.activated = self.homed = self.paused = False
        self._send_ctrl(2004, "Motors deactivated.")

    def _cmd_home(self, conn, args, text) -> None:
        if self.in_error:
            self._send_ctrl(1011, self._error_text(1011))
            return
        self.homed = True
        self._send_ctrl(2002, "Homing done.")

    def _cmd_reseterror(self, conn, args, text) -> None:
        if not self.in_error:
            self._send_ctrl(2006, "There was no error to reset.")
            return
        self.world.arm.reset_error()
        self.error_code = 0
        self._arm_error_seen = 0
        self._send_ctrl(2005, "The error was reset.")

    def _cmd_getstatusrobot(self, conn, args, text) -> None:
        self._send_ctrl(2007, self.status().to_payload())

    def _cmd_pausemotion(self, conn, args, text) -> None:
        self.paused = True
        self.world.arm.stop()
        for item in self._queue:
            item.started = False             # an interrupted move restarts on resume
            item.path = None                 # (a linear move is planned again from there)
        self._send_ctrl(2042, "Motion paused.")

    def _cmd_resumemotion(self, conn, args, text) -> None:
        if self.in_error:
            self._send_ctrl(1011, self._error_text(1011))
            return
        self.paused = False
        self._set_safety_stop(False)
        self._send_ctrl(2043, "Motion resumed.")

    def _cmd_clearmotion(self, conn, args, text) -> None:
        self._clear_queue(report=True)
        self.world.arm.stop()
        self.paused = True
        self._send_ctrl(2044, "The motion was cleared.")

    def _cmd_getjoints(self, conn, args, text) -> None:
        self._send_ctrl(2026, format_values(self.world.arm.reading()[0]))

    def _cmd_getpose(self, conn, args, text) -> None:
        self._send_ctrl(2027, self._pose_payload(tuple(self.world.arm.q)))

    def _cmd_getfwversion(self, conn, args, text) -> None:
        self._send_ctrl(2081, FW_VERSION)

    def _cmd_getfwversionfull(self, conn, args, text) -> None:
        self._send_ctrl(2082, FW_VERSION_FULL)

    def _cmd_getrobotserial(self, conn, args, text) -> None:
        self._send_ctrl(2083, self.serial)

    def _cmd_getmonitoringinterval(self, conn, args, text) -> None:
        self._send_ctrl(2116, format_number(self.monitoring_interval_s))

    def _cmd_setmonitoringinterval(self, conn, args, text) -> None:
        lo, hi = MONITORING_INTERVAL_RANGE_S
        if not lo <= args[0] <= hi:
            self._arg_error(text)
            return
        self.monitoring_interval_s = args[0]
        self._reschedule = True

    def _rt_payload(self) -> str:
        return ",".join(str(c) for c in sorted(self.rt_enabled))

    def _cmd_getrealtimemonitoring(self, conn, args, text) -> None:
        self._send_ctrl(2117, self._rt_payload())

    def _cmd_setrealtimemonitoring(self, conn, args, text) -> None:
        codes = set()
        for a in args:
            if a != int(a) or not (a == 0 or int(a) in RT_OPTIONAL or int(a) in RT_ALWAYS):
                self._arg_error(text)
                return
            if int(a) in RT_OPTIONAL:
                codes.add(int(a))
        self.rt_enabled = codes
        self._send_ctrl(2117, self._rt_payload())

    def _cmd_setctrlportmonitoring(self, conn, args, text) -> None:
        conn.monitoring = bool(args[0])
        self._send_ctrl(2096, "1" if conn.monitoring else "0")
        self._send_ctrl(2007, self.status().to_payload())

    def _cmd_synccmdqueue(self, conn, args, text) -> None:
        self._send_ctrl(2097, format_number(args[0]))

    def _cmd_connectionwatchdog(self, conn, args, text) -> None:
        if args[0] < 0:
            self._arg_error(text)
            return
        self.watchdog_s = args[0]
        self._watchdog_fed_at = time.monotonic()      # enabled or refreshed from now
        self._send_ctrl(2177, "1" if self.watchdog_s > 0 else "0")

    def _cmd_setrtc(self, conn, args, text) -> None:
        self.rtc_s = args[0]                  # no answer (official client handshake)

    def _cmd_movejoints(self, conn, args, text) -> None:
        arm = self.world.arm
        for q, lo, hi in zip(args, arm.lo, arm.hi):
            if not lo <= q <= hi:
                self._enter_error(1007)
                return
        self._queue.append(_Queued("joints", args))

    def _cmd_movejointsvel(self, conn, args, text) -> None:
        if any(abs(v) > m for v, m in zip(args, self.world.arm.vmax)):
            self._arg_error(text)          # assumption: over-speed is refused, not clamped
            return
        self._queue.append(_Queued("vel", args))

    def _cmd_setveltimeout(self, conn, args, text) -> None:
        lo, hi = VEL_TIMEOUT_RANGE_S
        if not lo <= args[0] <= hi:
            self._arg_error(text)
            return
        self._queue.append(_Queued("timeout", args))

    def _cmd_setcheckpoint(self, conn, args, text) -> None:
        lo, hi = CHECKPOINT_ID_RANGE
        n = args[0]
        if n != int(n) or not lo <= n <= hi:
            self._arg_error(text)
            return
        self._queue.append(_Queued("checkpoint", (int(n),)))

    def _cmd_getproducttype(self, conn, args, text) -> None:
        self._send_ctrl(2084, PRODUCT_TYPE)

    def _cmd_movejointsrel(self, conn, args, text) -> None:
        self._queue.append(_Queued("jointsrel", args))

    def _cmd_movepose(self, conn, args, text) -> None:
        self._queue.append(_Queued("pose", args))

    def _cmd_movelin(self, conn, args, text) -> None:
        self._queue.append(_Queued("lin", args))

    def _cmd_movelinreltrf(self, conn, args, text) -> None:
        self._queue.append(_Queued("linreltrf", args))

    def _cmd_movelinrelwrf(self, conn, args, text) -> None:
        self._queue.append(_Queued("linrelwrf", args))

    def _cmd_delay(self, conn, args, text) -> None:
        if not args[0] > 0:
            self._arg_error(text)
            return
        self._queue.append(_Queued("delay", args))

    def _setting(self, conn, args, text, key: str) -> None:
        (lo, hi), _ = SETTINGS[key]
        if not lo <= args[0] <= hi or (key == "setautoconf" and args[0] not in (0, 1)):
            self._arg_error(text)
            return
        self._queue.append(_Queued("setting", args, name=key))

    def _cmd_setjointvel(self, conn, args, text) -> None:
        self._setting(conn, args, text, "setjointvel")

    def _cmd_setjointacc(self, conn, args, text) -> None:
        self._setting(conn, args, text, "setjointacc")

    def _cmd_setcartlinvel(self, conn, args, text) -> None:
        self._setting(conn, args, text, "setcartlinvel")

    def _cmd_setcartangvel(self, conn, args, text) -> None:
        self._setting(conn, args, text, "setcartangvel")

    def _cmd_setcartacc(self, conn, args, text) -> None:
        self._setting(conn, args, text, "setcartacc")

    def _cmd_setblending(self, conn, args, text) -> None:
        self._setting(conn, args, text, "setblending")

    def _cmd_setautoconf(self, conn, args, text) -> None:
        self._setting(conn, args, text, "setautoconf")

    def _cmd_settrf(self, conn, args, text) -> None:
        self._queue.append(_Queued("setting", args, name="settrf"))

    def _cmd_setwrf(self, conn, args, text) -> None:
        self._queue.append(_Queued("setting", args, name="setwrf"))

    def _rt_query(self, code: int) -> None:
        ts = max(0, round(self.world.t * 1e6))
        self._send_ctrl(code, f"{ts},{format_values(self._rt_values(code))}")

    # ------------------------------------------------------------------ kinematics
    def _trf_pose(self, q) -> np.ndarray:
        """TRF in the WRF (4x4) at joints ``q``: WRF^-1 . 0T6(q) . TRF."""
        return np.linalg.solve(self.wrf, self.world.kin.fk(q)) @ self.trf

    def _flange_for(self, pose_wrf: np.ndarray) -> np.ndarray:
        """Flange pose 0T6 (4x4) that puts the TRF at ``pose_wrf`` (4x4, in the WRF)."""
        return self.wrf @ pose_wrf @ np.linalg.inv(self.trf)

    def _ik(self, target: np.ndarray, seed) -> np.ndarray | None:
        """Joints (deg) near ``seed`` with 0T6 = ``target``, by damped Newton steps on the
        geometric Jacobian; None if it does not converge."""
        kin = self.world.kin
        q = np.array(seed, dtype=float)
        for _ in range(IK_MAX_ITER):
            t = kin.fk(q)
            dp = target[:3, 3] - t[:3, 3]
            dr = matrix_rotvec(target[:3, :3] @ t[:3, :3].T)
            if np.linalg.norm(dp) < IK_TOL_MM and np.linalg.norm(dr) < IK_TOL_RAD:
                return q
            dq = damped_least_squares(kin.jacobian(q), np.concatenate([dp, dr]),
                                      sigma_min_ok=1e-3, lambda_max=1e-2)
            step = np.degrees(dq)
            big = np.max(np.abs(step))
            if big > 20.0:                   # keep Newton steps local
                step *= 20.0 / big
            q = q + step
        return None

    def _within_limits(self, q) -> bool:
        arm = self.world.arm
        return all(lo <= x <= hi for x, lo, hi in zip(q, arm.lo, arm.hi))

    def _singular(self, q) -> bool:
        m = self.world.kin.singularity(tuple(q))
        return m.wrist < SINGULAR_SIN or m.elbow < SINGULAR_SIN or \
            m.shoulder_mm < SINGULAR_SHOULDER_MM

    def _solve_pose(self, pose_wrf: np.ndarray, q0) -> tuple[float, ...]:
        """MovePose's joint set: of the inverse-kinematic solutions found from several
        seeds, the one within the joint ranges with the smallest largest joint displacement
        from ``q0`` (the manual's automatic configuration). [1016] if there is none."""
        target = self._flange_for(pose_wrf)
        q0 = np.array(q0, dtype=float)
        flip = q0 + np.array([0.0, 0.0, 0.0, 180.0, 0.0, 180.0])
        flip[4] = -q0[4]
        seeds = [q0, flip, np.array(HOME_SEED), np.array((0.0, 0.0, 0.0, 0.0, 45.0, 0.0)),
                 np.array((0.0, 0.0, 0.0, 0.0, -45.0, 0.0)),
                 np.array((0.0, 30.0, -30.0, 0.0, 45.0, 0.0))]
        best, best_d = None, math.inf
        for seed in seeds:
            q = self._ik(target, seed)
            if q is None:
                continue
            for i in (0, 3, 5):               # the turn nearest the start for revolute wraps
                q[i] -= 360.0 * round((q[i] - q0[i]) / 360.0)
            if not self._within_limits(q):
                continue
            d = float(np.max(np.abs(q - q0)))
            if d < best_d:
                best, best_d = q, d
        if best is None:
            raise _PlanError(1016, "no joint set within the ranges reaches the pose")
        return tuple(float(x) for x in best)

    def _plan_line(self, item: _Queued, q0) -> None:
        """A linear move from the arm's pose to ``item.target`` (pose in the WRF): position
        on a straight line, orientation along the shortest rotation, both at constant speed
        bounded by SetCartLinVel / SetCartAngVel and the joint speeds. The whole path is
        checked before the arm moves (manual, MoveLin: "if the complete motion cannot be
        performed due to singularities or joint limits, it will not even start")."""
        start = self._trf_pose(q0)
        goal = matrix_from_pose(item.target)
        dist = float(np.linalg.norm(goal[:3, 3] - start[:3, 3]))
        rots = Rotation.from_matrix(np.stack([start[:3, :3], goal[:3, :3]]))
        angle = math.degrees(float((rots[1] * rots[0].inv()).magnitude()))
        n = int(min(PATH_MAX_SAMPLES, max(2, math.ceil(dist / PATH_STEP_MM),
                                          math.ceil(angle / PATH_STEP_DEG))))
        slerp = Slerp([0.0, 1.0], rots)
        qs = [np.array(q0, dtype=float)]
        for k in range(1, n + 1):
            s = k / n
            pose = np.eye(4)
            pose[:3, :3] = slerp([s]).as_matrix()[0]
            pose[:3, 3] = start[:3, 3] + s * (goal[:3, 3] - start[:3, 3])
            q = self._ik(self._flange_for(pose), qs[-1])
            if q is None:
                raise _PlanError(1012 if self._singular(qs[-1]) else 1016,
                                 f"no joint set at {s:.0%} of the line")
            if float(np.max(np.abs(q - qs[-1]))) > PATH_JUMP_DEG or self._singular(q):
                raise _PlanError(1012, f"the line crosses a singularity at {s:.0%}")
            if not self._within_limits(q):
                raise _PlanError(1007, f"a joint passes its limit at {s:.0%} of the line")
            qs.append(q)
        path = np.array(qs)
        if self._singular(path[0]) and len(path) > 1:
            raise _PlanError(1012, "the line starts in a singular posture")
        vmax = np.array(self.world.arm.vmax)
        seg = float(np.max(np.abs(np.diff(path, axis=0)) / vmax)) * n if n else 0.0
        item.path = path
        item.duration = max(dist / self.settings["setcartlinvel"],
                            angle / self.settings["setcartangvel"], seg, self.world.ts)

    def _start_move(self, item: _Queued) -> tuple[float, ...]:
        """Plan ``item`` from where the arm is; returns the final joint set. Relative moves
        fix their absolute target the first time (a paused move restarts toward it)."""
        arm = self.world.arm
        q0 = tuple(arm.q)
        kind = item.kind
        if item.target is None:
            if kind == "joints":
                item.target = item.args
            elif kind == "jointsrel":
                item.target = tuple(a + b for a, b in zip(q0, item.args))
            elif kind in ("pose", "lin"):
                item.target = item.args
            else:                                   # relative linear moves
                cur = self._trf_pose(q0)
                delta = matrix_from_pose(item.args)
                if kind == "linreltrf":
                    goal = cur @ delta
                else:                               # WRF axes, about the TCP
                    goal = np.eye(4)
                    goal[:3, :3] = delta[:3, :3] @ cur[:3, :3]
                    goal[:3, 3] = cur[:3, 3] + delta[:3, 3]
                item.target = tuple(float(v) for v in pose_from_matrix(goal))
        if kind in ("joints", "jointsrel"):
            if not self._within_limits(item.target):
                raise _PlanError(1007, "target outside the joint ranges")
            return item.target
        if kind == "pose":
            return self._solve_pose(matrix_from_pose(item.target), q0)
        self._plan_line(item, q0)
        return tuple(float(x) for x in item.path[-1])

    def _apply_setting(self, item: _Queued) -> None:
        if item.name == "settrf":
            self.trf = matrix_from_pose(item.args)
        elif item.name == "setwrf":
            self.wrf = matrix_from_pose(item.args)
        else:
            self.settings[item.name] = float(item.args[0])
        self._pose_cache = None

    # ------------------------------------------------------------------ motion
    def _clear_queue(self, report: bool) -> None:
        for item in self._queue:
            if item.kind == "checkpoint" and report:
                self._send_ctrl(3040, str(item.args[0]))
        self._queue.clear()

    def _enter_error(self, code: int) -> None:
        """The robot's own error (the arm model latches its errors itself)."""
        self.error_code = code
        self.paused = True
        self._clear_queue(report=True)
        self.world.arm.stop()
        self._send_ctrl(code, self._error_text(code))
        log.warning("meca500_sim.error", code=code)

    def _advance_queue(self) -> None:
        if not (self.activated and self.homed) or self.paused or self.in_error:
            return
        w = self.world
        arm = w.arm
        q = self._queue
        while q:
            item = q[0]
            if item.kind in MOVES:
                if not item.started:
                    try:
                        item.final = self._start_move(item)
                    except _PlanError as exc:
                        log.warning("meca500_sim.move_refused", move=item.kind, why=str(exc))
                        self._enter_error(exc.code)
                        return
                    item.started = True
                    item.t0 = w.t
                    arm.pos_speed_scale = (self.settings["setjointvel"] / 100.0
                                           if item.path is None else 1.0)
                    arm.command_position(item.final if item.path is None else item.path[0])
                if item.path is not None:
                    s = (w.t - item.t0) / item.duration
                    if s < 1.0:
                        x = s * (len(item.path) - 1)
                        k = int(x)
                        ref = item.path[k] + (x - k) * (item.path[k + 1] - item.path[k])
                        arm.command_position(ref)
                        return
                    arm.command_position(item.final)
                if max(abs(a - b) for a, b in zip(arm.q, item.final)) > ARRIVED_DEG or \
                        max(abs(v) for v in arm.qdot) > ARRIVED_DEG_S:
                    return
            elif item.kind == "delay":
                if not item.started:
                    item.started = True
                    item.t0 = w.t
                if w.t - item.t0 < item.args[0]:
                    return
            elif item.kind == "setting":
                self._apply_setting(item)
            elif item.kind == "vel":
                arm.command_velocity(item.args, w.t)
            elif item.kind == "timeout":
                arm.p = dataclasses.replace(arm.p, vel_timeout_s=item.args[0])
            else:
                self._send_ctrl(3030, str(item.args[0]))
            q.popleft()

    def _poll(self) -> None:
        """Bring the robot state up to date with the World (between commands and cycles)."""
        arm = self.world.arm
        if arm.error_code and arm.error_code != self._arm_error_seen:
            self._arm_error_seen = arm.error_code
            self.paused = True                    # stays paused after ResetError
            self._clear_queue(report=True)
            self._send_ctrl(arm.error_code, self._error_text(arm.error_code))
            log.warning("meca500_sim.error", code=arm.error_code)
        self._advance_queue()
        if self.watchdog_s > 0 and self._ctrl is not None and \
                time.monotonic() - self._watchdog_fed_at > self.watchdog_s:
            self._watchdog_expired()
        self._publish_status()

    def _watchdog_expired(self) -> None:
        """The safety stop of an expired connection watchdog: pause (the dropped link's
        reaction), then close the application's sockets (see the module docstring)."""
        ctrl = self._ctrl
        self.watchdog_expiries += 1
        log.warning("meca500_sim.connection_watchdog_expired", timeout_s=self.watchdog_s,
                    peer=ctrl.peer if ctrl is not None else None)
        self.watchdog_s = 0.0
        self._link_lost("connection watchdog expired")
        self._set_safety_stop(True)
        if ctrl is None or self.frozen:
            return                              # a half-open link: the client never learns
        host = ctrl.peer[0] if isinstance(ctrl.peer, tuple) else ctrl.peer
        for c in [ctrl, *self._monitors]:
            peer_host = c.peer[0] if isinstance(c.peer, tuple) else c.peer
            if (c is ctrl or peer_host == host) and c.transport is not None:
                c.transport.close()             # flushes the [2007] with pm=1 first

    def _set_safety_stop(self, active: bool) -> None:
        """The connection-dropped safety stop: [3086][1] when it is raised, [3086][0] when
        ResumeMotion clears it; sent on the monitoring stream (monitoring clients and a control
        client that asked SetCtrlPortMonitoring(1))."""
        if self.safety_stop == active:
            return
        self.safety_stop = active
        data = encode_response(3086, "1" if active else "0")
        targets = list(self._monitors)
        if self._ctrl is not None and self._ctrl.monitoring:
            targets.append(self._ctrl)
        for c in targets:
            c.send(data)

    def _publish_status(self) -> None:
        st = self.status()
        last = self._last_status
        if st == last:
            return
        self._last_status = st
        data = encode_response(2007, st.to_payload())
        if self._ctrl is not None:
            self._ctrl.send(data)
        for c in self._monitors:
            c.send(data)
        if self.activated and last is not None and not last.eob and st.eob:
            self._send_ctrl(3012, "End of block.")

    # ------------------------------------------------------------------ monitoring
    def _pose_payload(self, q: tuple) -> str:
        cache = self._pose_cache
        if cache is not None and cache[0] == q:
            return cache[1]
        pose = pose_from_matrix(self._trf_pose(q))
        payload = format_values(0.0 if abs(v) < 1e-9 else float(v) for v in pose)
        self._pose_cache = (q, payload)
        return payload

    def _cart_vel(self, q, qd) -> tuple[float, ...]:
        """TCP velocity in the WRF: (mm/s, deg/s)."""
        if not any(qd):
            return (0.0,) * 6
        kin = self.world.kin
        tw = kin.jacobian(q) @ np.radians(qd)            # flange origin, base frame
        t = kin.fk(q)
        w = tw[3:]
        v = tw[:3] + np.cross(w, t[:3, :3] @ self.trf[:3, 3])
        r = self.wrf[:3, :3].T
        return (*(r @ v), *np.degrees(r @ w))

    def _rt_values(self, code: int) -> tuple[float, ...]:
        """The values (after the timestamp) of real-time record ``code`` now."""
        arm = self.world.arm
        if code in (2200, 2201, 2202, 2203, 2204):        # target (exact) state
            q, qd = tuple(arm.q), tuple(arm.qdot)
        else:                                              # measured (encoder) state
            q, qd = arm.reading()
        if code in (2200, 2210):
            return q
        if code in (2201, 2211):
            return tuple(float(v) for v in self._pose_payload(tuple(q)).split(","))
        if code in (2202, 2212):
            return qd
        if code in (2204, 2214):
            return self._cart_vel(q, qd)
        if code == 2228:
            return tuple(float(v) for v in pose_from_matrix(self.wrf))
        if code == 2229:
            return tuple(float(v) for v in pose_from_matrix(self.trf))
        return (0.0,) * 6                                  # 2203/2213 torques: no dynamics

    def _cycle(self) -> bytes:
        w = self.world
        arm = w.arm
        ts = max(0, round(w.t * 1e6))
        q = tuple(arm.q)
        pose = self._pose_payload(q)
        parts = [encode_rt(2200, ts, q), encode_response(2201, f"{ts},{pose}")]
        for code in sorted(self.rt_enabled):
            parts.append(encode_rt(code, ts, self._rt_values(code)))
        parts.append(encode_rt(RT_CYCLE_END, ts))
        return b"".join(parts)

    def _emit_cycle(self) -> None:
        self.cycles += 1
        targets = list(self._monitors)
        if self._ctrl is not None and self._ctrl.monitoring:
            targets.append(self._ctrl)
        if not targets:
            return
        data = self._cycle()
        for c in targets:
            if c.send(data):
                c.cycles_sent += 1

    async def _run(self) -> None:
        """Poll every ``poll_s``; emit a cycle each time the World's clock passes the next
        multiple of the monitoring interval (a world jump over several intervals emits one
        cycle and counts the others in ``skipped_cycles``). While the World is not stepped,
        a cycle still goes out every ``max(3 intervals, 50 ms)`` of wall-clock time."""
        loop = asyncio.get_running_loop()
        w = self.world
        next_t: float | None = None
        last_emit = loop.time()
        while True:
            try:
                self._poll()
                now = loop.time()
                if self._reschedule:
                    self._reschedule = False
                    next_t = None
                step = max(self.monitoring_interval_s, w.ts)
                wt = w.t + 1e-9
                if next_t is None:
                    next_t = w.t
                if wt >= next_t:
                    self._emit_cycle()
                    last_emit = now
                    next_t += step
                    if wt >= next_t:
                        missed = math.floor((wt - next_t) / step) + 1
                        self.skipped_cycles += missed
                        next_t += missed * step
                elif now - last_emit > max(3.0 * self.monitoring_interval_s, 0.05):
                    self._emit_cycle()                # the World is not being stepped
                    last_emit = now
            except Exception:                      # never let one bad cycle stop the robot
                log.exception("meca500_sim.cycle_failed")
            await asyncio.sleep(self.poll_s)
