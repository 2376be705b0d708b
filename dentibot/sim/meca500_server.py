"""Meca500 wire simulator: the TCP text API (control and monitoring ports) over a World.

:class:`Meca500Server` speaks the bytes of :mod:`dentibot.io.meca500_protocol` so that the
project's driver, the vendor's client or any other Meca500 client can talk to it. It never steps
the World: it reads and commands ``world.arm`` when a command arrives, when a monitoring cycle
is due and at every poll (``poll_s``) while a RealTimeStepper (or anyone) steps the world.

Behaviour (programming manual, firmware 9.x; devices.md):

- control port: greeting ``[3000][Connected to Meca500 R3 v9.3.0]``; one control client only, a
  second one gets ``[3001][Another user is already connected, closing connection.]`` and is
  closed. Monitoring port (control port + 1 unless given): several clients; each gets the
  status (2007) on connection and on every change, and one cycle per monitoring interval.
- activation and homing: motion-queue commands before activation -> [1005], before homing ->
  [1006], while in error -> [1011]. Repeated ActivateRobot / Home answer [2000] / [2002] again
  (assumption: the 9.x manual lists no "already" codes; 2001/2003 were firmware < 9).
- the motion queue: MoveJoints (one target after the other), MoveJointsVel (applied when it
  reaches the head of the queue, i.e. at once while streaming), SetVelTimeout (0.001..1 s,
  else [1003]; written into the World's ArmParams; reset to the default at every activation, as
  the manual says), SetCheckpoint(n) -> [3030][n] when reached, [3040][n] when discarded;
  [3012] end of block when the queue is empty and the arm at rest.
- errors: a joint that reaches its limit or the wrist singularity (``world.arm.error_code``
  1007 / 1012) and MoveJoints outside the joint ranges ([1007]) put the robot in error mode:
  the error message on the control port, then a 2007 with es=1 (and pm=1, as the manual says).
  ResetError -> [2005] (or [2006] without error); motion stays paused until ResumeMotion.
- PauseMotion / ClearMotion stop the arm (ClearMotion also empties the queue; both leave
  pm=1); ResumeMotion continues.
- a dropped control connection pauses the arm: it stops, the queue is cleared (assumption:
  nothing queued survives a lost link) and pm=1 until a client sends ResumeMotion.
- connection watchdog (devices.md: ``ConnectionWatchdog(t)`` -> [2177][1], [2177][0] for
  t = 0, which disables it). What the robot does is Mecademic's documentation (mecademicpy,
  ``Robot.ConnectionWatchdog``): only another ``ConnectionWatchdog`` refreshes it (other
  commands do not); when it expires the robot "will close the socket connections with this
  application, raise the MX_SAFE_STOP_CONNECTION_DROPPED safety stop condition, and pause
  motion (if robot is activated)". Here: the arm stops (as for a dropped link: queue cleared,
  pm=1, a [2007] with pm=1 goes out first), then the control connection and the monitoring
  connections from the same host are closed (the socket is *not* kept). The robot is not put
  in error (es stays 0): the safety stop is a stop condition that ResumeMotion clears, as the
  dropped link's. Firmware 9.x has no status message for it; the [3086] safety-stop status of
  later firmware is not simulated.
- monitoring: 2200 target joints, 2201 target pose, the optional 2202/2210/2211/2212/2213
  enabled with SetRealTimeMonitoring, then 2230 end of cycle. Decision on timestamps: they are
  the World's time ``round(world.t * 1e6)`` (us), so every record says which world state it
  reports, and cycles are due on the World's clock: one each time world time passes the next
  multiple of the interval. If the World jumps several intervals between two polls (the
  stepper caught up), one cycle goes out and the missed ones are counted in
  ``skipped_cycles``: clients see the gap in the timestamps. While nobody steps the World, a
  cycle still goes out every max(3 intervals, 50 ms) with an unchanged timestamp. Timestamps
  never decrease. 2200 is the exact joint state, 2210 the encoder-quantised reading; 2213 is
  zero (no joint dynamics in the World).
- bad bytes: unknown command [1001], syntax [1002], argument count or range [1003], a frame
  longer than ``max_frame_len`` [3003]; nothing crashes the server. A client that stops reading
  is disconnected once ``max_client_buffer`` bytes are waiting for it.

Not simulated: MovePose, MoveLin*, SetTrf/SetWrf/SetJointVel and the other commands answer
[1001]; GetPose reports the flange (TRF = FRF, WRF = BRF); SetRealTimeMonitoring(all) is not
accepted (arguments are numbers only).
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import time
from collections import deque
from typing import Self

import structlog

from dentibot.control.kinematics import pose_from_matrix
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
_LOG_FIRST, _LOG_EVERY = 10, 1000


@dataclasses.dataclass
class _Queued:
    kind: str                # "joints" | "vel" | "timeout" | "checkpoint"
    args: tuple[float, ...]
    started: bool = False


class _Conn(asyncio.Protocol):
    """One TCP client of the simulator (control or monitoring port)."""

    def __init__(self, server: Meca500Server, kind: str) -> None:
        self.server = server
        self.kind = kind
        self.transport: asyncio.Transport | None = None
        self.peer = None
        self.splitter = FrameSplitter(server.max_frame_len)
        self.refused = False
        self.monitoring = kind == "monitor"   # receives monitoring cycles
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
        self.server._on_disconnect(self)

    # helpers
    @property
    def open(self) -> bool:
        return self.transport is not None and not self.transport.is_closing()

    def send(self, data: bytes) -> bool:
        if not self.open:
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
        monitoring_interval_s: initial monitoring interval (s), devices.md's ~16.7 ms.
        poll_s: how often the World is looked at: queue, errors, status, and whether a
            monitoring cycle is due (s). Keep it below the World's period.
        max_frame_len: longest command accepted (bytes); longer ones answer [3003].
        max_client_buffer: bytes waiting for a client before it is disconnected.
    """

    def __init__(self, world: World, host: str = "127.0.0.1", port: int = CONTROL_PORT,
                 monitor_port: int | None = None, *,
                 monitoring_interval_s: float = MONITORING_INTERVAL_DEFAULT_S,
                 poll_s: float = 0.001, max_frame_len: int = MAX_FRAME_LEN,
                 max_client_buffer: int = 1 << 20, serial: str = SERIAL,
                 greeting: str = GREETING) -> None:
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
        self._handlers = {key: getattr(self, "_cmd_" + key) for key in COMMANDS}
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
            self._monitors.append(conn)
            conn.send(encode_response(2007, self.status().to_payload()))

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
        if conn.kind != "control" or conn.refused:
            return                               # the monitoring port ignores input
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
            item.started = False             # an interrupted MoveJoints restarts on resume
        self._send_ctrl(2042, "Motion paused.")

    def _cmd_resumemotion(self, conn, args, text) -> None:
        if self.in_error:
            self._send_ctrl(1011, self._error_text(1011))
            return
        self.paused = False
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
            if item.kind == "joints":
                if not item.started:
                    arm.command_position(item.args)
                    item.started = True
                    return
                if max(abs(a - b) for a, b in zip(arm.q, item.args)) > ARRIVED_DEG or \
                        max(abs(v) for v in arm.qdot) > ARRIVED_DEG_S:
                    return
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
        if ctrl is None:
            return
        host = ctrl.peer[0] if isinstance(ctrl.peer, tuple) else ctrl.peer
        for c in [ctrl, *self._monitors]:
            peer_host = c.peer[0] if isinstance(c.peer, tuple) else c.peer
            if (c is ctrl or peer_host == host) and c.transport is not None:
                c.transport.close()             # flushes the [2007] with pm=1 first

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
        pose = pose_from_matrix(self.world.kin.fk(q))
        payload = format_values(0.0 if abs(v) < 1e-9 else float(v) for v in pose)
        self._pose_cache = (q, payload)
        return payload

    def _cycle(self) -> bytes:
        w = self.world
        arm = w.arm
        ts = max(0, round(w.t * 1e6))
        q = tuple(arm.q)
        q_meas, qd = arm.reading()
        pose = self._pose_payload(q)
        parts = [encode_rt(2200, ts, q), encode_response(2201, f"{ts},{pose}")]
        for code in sorted(self.rt_enabled):
            if code == 2210:
                parts.append(encode_rt(code, ts, q_meas))
            elif code == 2211:
                parts.append(encode_response(code, f"{ts},{pose}"))
            elif code in (2202, 2212):
                parts.append(encode_rt(code, ts, qd))
            else:                                         # 2213 torque (%): no dynamics
                parts.append(encode_rt(code, ts, (0.0,) * 6))
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
