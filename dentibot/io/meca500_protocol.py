"""Meca500 TCP text API: response codes, framing, command and response encoding (pure code).

Shared by the driver (:mod:`dentibot.io.meca500`) and the wire simulator
(:mod:`dentibot.sim.meca500_server`), so both speak exactly the same bytes. No I/O here.

Wire format (programming manual for firmware 9.x, section "TCP/IP communication"):

- commands: ASCII ``Name(a,b,...)`` terminated by NUL (a newline is also accepted); names are
  case-insensitive, parentheses are optional without arguments, a leading ``-`` marks a
  "silent" command (not logged by the robot), a lone NUL is an empty command and is ignored;
- responses: ``[NNNN][payload]`` + NUL; 1xxx command errors, 2xxx responses and data, 3xxx
  status messages. Real-time monitoring payloads (22xx) start with a timestamp in microseconds.

Sources for the code table: the project's device notes; the Meca500 programming
manual for firmware 9.2 (tables "command error messages", "command responses", "monitoring port
messages", and the ``SetVelTimeout`` page); Mecademic's public Python client (``mecademicpy``,
``mx_robot_def.py``, status code list). ``confirmed=False`` marks what none of them states.
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Iterable
from dataclasses import dataclass

from dentibot.errors import ConfigError, ProtocolError

#: Device name used in every error and log line.
DEVICE = "meca500"
#: Mecademic's factory address and ports (control: commands/responses; monitoring: periodic).
DEFAULT_HOST = "192.168.0.100"
CONTROL_PORT = 10000
MONITOR_PORT = 10001
#: Frame terminators: NUL, or a newline (accepted for convenience by the robot).
TERMINATORS = b"\0\n"
# assumption: the robot's own limit on a command's length is not documented (it answers
# [3003] "command too long"); 1024 bytes is far above the longest real command or response.
MAX_FRAME_LEN = 1024

#: Greeting on the control port (model, revision, firmware version).
GREETING = "Connected to Meca500 R3 v9.3.0"
#: Answer to a second control client, which is then disconnected.
ANOTHER_USER = "Another user is already connected, closing connection."

# ---------------------------------------------------------------------------------- limits
#: Joint ranges (deg), J1..J6 (Meca500 R3 user manual).
JOINT_LIMITS_DEG: tuple[tuple[float, float], ...] = (
    (-175.0, 175.0), (-70.0, 90.0), (-135.0, 70.0), (-170.0, 170.0), (-115.0, 115.0),
    (-36000.0, 36000.0),
)
#: Maximum joint speeds (deg/s), J1..J6 (Meca500 R3 user manual).
JOINT_SPEED_LIMITS_DEG_S: tuple[float, ...] = (150.0, 150.0, 180.0, 300.0, 300.0, 500.0)
#: SetVelTimeout argument range (s) and default, applied at every activation (manual).
VEL_TIMEOUT_RANGE_S = (0.001, 1.0)
VEL_TIMEOUT_DEFAULT_S = 0.05
#: SetMonitoringInterval argument range (s): 1..1000 ms (programming manual). The argument is in
#: seconds (mecademicpy: "Monitoring interval duration in seconds").
MONITORING_INTERVAL_RANGE_S = (0.001, 1.0)
# assumption (a default of about 16.7 ms, unconfirmed): read it with GetMonitoringInterval.
MONITORING_INTERVAL_DEFAULT_S = 1.0 / 60.0
#: SetCheckpoint ids accepted (programming manual: up to 8191; mecademicpy allows 1..8000).
CHECKPOINT_ID_RANGE = (1, 8191)
#: ConnectionWatchdog(t) timeouts the driver uses (s); 0 disables it. Mecademic documents
#: "a non-zero value to enable or refresh" with no range; the bounds are this project's: below
#: 5 ms no TCP link refreshes it reliably, beyond 60 s it watches nothing useful.
CONNECTION_WATCHDOG_RANGE_S = (0.005, 60.0)


# ---------------------------------------------------------------------------------- codes
@dataclass(frozen=True, slots=True)
class CodeInfo:
    """One response code: ``kind`` is "error" (1xxx), "response" (2xxx) or "status" (3xxx).

    ``latches``: the robot enters error mode (status es=1; ResetError needed) when it sends
    this code. ``confirmed`` is False where no source states the code or its meaning.
    """

    code: int
    name: str
    meaning: str
    kind: str
    latches: bool = False
    confirmed: bool = True


def _rows(kind: str, rows) -> list[CodeInfo]:
    return [CodeInfo(c, n, m, kind, *rest) for c, n, m, *rest in rows]


#: code -> CodeInfo. Meanings follow the manual's message texts where they were found.
RESPONSE_CODES: dict[int, CodeInfo] = {info.code: info for info in (
    *_rows("error", (
        (1000, "BUFFER_FULL", "Command buffer is full."),
        (1001, "UNKNOWN_COMMAND", "Empty command or command unrecognized."),
        (1002, "SYNTAX_ERROR", "Syntax error, symbol missing."),
        (1003, "ARGUMENT_ERROR", "Argument error: wrong argument count or value out of range."),
        (1005, "NOT_ACTIVATED", "The robot is not activated."),
        (1006, "NOT_HOMED", "The robot is not homed."),
        # assumption (latches=True for 1007/1012/1013/1014/1016 only): the manual says the
        # robot goes into error mode on an error while *executing* a command; refusals of a
        # command (1000..1006, 1011) leave the robot's state as it was.
        (1007, "JOINT_OVER_LIMIT", "Joint over limit: a joint would pass its limit.", True),
        (1010, "BLOCKED_BY_180_DEG_PROT", "Move blocked: a joint would turn over 180 deg."),
        (1011, "ALREADY_IN_ERROR", "The robot is already in error."),
        (1012, "SINGULARITY", "Singularity: the move would go through a singularity.", True),
        (1013, "ACTIVATION_FAILED", "Activation failed.", True),
        (1014, "HOMING_FAILED", "Homing failed.", True),
        (1016, "OUT_OF_REACH", "Destination pose out of reach.", True),
        (1025, "RESET_IMPOSSIBLE", "This error cannot be reset; power-cycle the robot."),
        (1026, "MUST_BE_DEACTIVATED", "Command available only when the robot is deactivated."),
        (1040, "COMMAND_FAILED", "Command failed."),
    )),
    *_rows("response", (
        (2000, "ACTIVATED", "Motors activated."),
        # firmware < 9 only (mecademicpy's older code list); 9.x answers 2000/2002 again.
        (2001, "ALREADY_ACTIVATED", "Motors already activated."),
        (2002, "HOMED", "Homing done."),
        (2003, "ALREADY_HOMED", "Homing already done."),
        (2004, "DEACTIVATED", "Motors deactivated."),
        (2005, "ERROR_RESET", "The error was reset."),
        (2006, "NO_ERROR_TO_RESET", "There was no error to reset."),
        (2007, "STATUS_ROBOT", "Robot status as,hs,sm,es,pm,eob,eom."),
        (2026, "JOINTS", "Joint positions (deg)."),
        (2027, "POSE", "Pose x,y,z (mm), alpha,beta,gamma (deg)."),
        (2042, "MOTION_PAUSED", "Motion paused."),
        (2043, "MOTION_RESUMED", "Motion resumed."),
        (2044, "MOTION_CLEARED", "The motion was cleared."),
        (2081, "FW_VERSION", "Firmware version."),
        (2082, "FW_VERSION_FULL", "Full firmware version."),
        (2083, "ROBOT_SERIAL", "Robot serial number."),
        # assumption (payload unconfirmed): the official client only waits for the 2007 after.
        (2096, "CTRL_PORT_MONITORING", "Monitoring data on the control port set."),
        (2097, "SYNC_CMD_QUEUE", "SyncCmdQueue echo."),
        (2116, "MONITORING_INTERVAL", "Monitoring interval (s)."),
        (2117, "REAL_TIME_MONITORING", "Enabled optional real-time monitoring codes."),
        (2177, "CONNECTION_WATCHDOG", "Connection watchdog enabled (1) or not (0)."),
        (2084, "PRODUCT_TYPE", "Product type (robot model)."),
        (2200, "RT_TARGET_JOINT_POS", "t (us), target joint positions (deg)."),
        (2201, "RT_TARGET_CART_POS", "t (us), target pose (mm, deg)."),
        (2202, "RT_TARGET_JOINT_VEL", "t (us), target joint velocities (deg/s)."),
        (2203, "RT_TARGET_JOINT_TORQ", "t (us), target joint torques (% of maximum)."),
        (2204, "RT_TARGET_CART_VEL", "t (us), target TCP velocity in the WRF (mm/s, deg/s)."),
        (2210, "RT_JOINT_POS", "t (us), measured joint positions (deg)."),
        (2211, "RT_CART_POS", "t (us), measured pose (mm, deg)."),
        (2212, "RT_JOINT_VEL", "t (us), measured joint velocities (deg/s)."),
        (2213, "RT_JOINT_TORQ", "t (us), joint torques (% of maximum)."),
        (2214, "RT_CART_VEL", "t (us), TCP velocity in the WRF (mm/s, deg/s)."),
        (2228, "RT_WRF", "t (us), world reference frame in the BRF (mm, deg)."),
        (2229, "RT_TRF", "t (us), tool reference frame in the FRF (mm, deg)."),
        (2230, "RT_CYCLE_END", "t (us): end of a monitoring cycle."),
    )),
    *_rows("status", (
        (3000, "CONNECTED", "Connected (model, revision, firmware)."),
        (3001, "ANOTHER_USER", "Another user is already connected; connection closed."),
        (3003, "COMMAND_TOO_LONG", "Command too long (or missing NUL terminator)."),
        (3004, "END_OF_MOVEMENT", "End of movement."),
        (3005, "MOTION_ERROR", "Motion error (collision or overload); it can be reset.", True),
        (3012, "END_OF_BLOCK", "End of block: motion queue empty and robot at rest."),
        # 3026 is sometimes read as "robot in error"; Mecademic's list says a maintenance check.
        (3026, "MAINTENANCE_CHECK", "Hardware problem detected; contact Mecademic support."),
        (3030, "CHECKPOINT_REACHED", "Checkpoint reached."),
        (3040, "CHECKPOINT_DISCARDED", "Checkpoint discarded (motion cleared or error)."),
        # mecademicpy's MX_ST_SAFE_STOP_CONNECTION_DROPPED; payload 1 = active, 0 = cleared.
        (3086, "SAFE_STOP_CONNECTION_DROPPED",
         "Safety stop: connection dropped or connection watchdog expired."),
    )),
)}


def code_info(code: int) -> CodeInfo | None:
    """The table entry for ``code``, or None."""
    return RESPONSE_CODES.get(code)


def describe_code(code: int) -> str:
    """``"[1005] NOT_ACTIVATED: The robot is not activated."`` (or "unknown code")."""
    info = RESPONSE_CODES.get(code)
    if info is None:
        return f"[{code}] unknown code"
    return f"[{code}] {info.name}: {info.meaning}"


def kind_of(code: int) -> str:
    """"error", "response" or "status" from the thousands digit; "unknown" otherwise."""
    return {1: "error", 2: "response", 3: "status"}.get(code // 1000, "unknown")


# ------------------------------------------------------------------------ real-time data
#: Number of values after the timestamp for each real-time monitoring code.
RT_VALUE_COUNTS: dict[int, int] = {
    2200: 6, 2201: 6, 2202: 6, 2203: 6, 2204: 6, 2210: 6, 2211: 6, 2212: 6, 2213: 6, 2214: 6,
    2228: 6, 2229: 6, 2230: 0,
}
#: Sent every cycle whatever SetRealTimeMonitoring says (programming manual).
RT_ALWAYS = (2200, 2201)
#: May be enabled with SetRealTimeMonitoring (the subset of the robot's codes simulated here).
RT_OPTIONAL = frozenset({2202, 2203, 2204, 2210, 2211, 2212, 2213, 2214, 2228, 2229})
#: Real-time queries (section "Real-time data request commands") -> the code they answer.
RT_QUERIES: dict[str, int] = {
    "GetRtTargetJointPos": 2200, "GetRtTargetCartPos": 2201, "GetRtTargetJointVel": 2202,
    "GetRtTargetJointTorq": 2203, "GetRtTargetCartVel": 2204, "GetRtJointPos": 2210,
    "GetRtCartPos": 2211, "GetRtJointVel": 2212, "GetRtJointTorq": 2213, "GetRtCartVel": 2214,
    "GetRtWrf": 2228, "GetRtTrf": 2229,
}
RT_CYCLE_END = 2230


# ---------------------------------------------------------------------------- commands
@dataclass(frozen=True, slots=True)
class CommandSpec:
    """What a command takes and answers.

    ``nargs``: (min, max) number of arguments. ``answers``: success codes (empty: the command
    answers nothing on success). ``errors``: error codes the robot may answer it with.
    ``queued``: a motion-queue command. ``requires``: "none", "activated" or "homed"
    (otherwise [1005] / [1006]).
    """

    name: str
    nargs: tuple[int, int] = (0, 0)
    answers: tuple[int, ...] = ()
    errors: tuple[int, ...] = ()
    queued: bool = False
    requires: str = "none"


_MOTION_ERRORS = (1005, 1006, 1011)

#: lower-case name -> CommandSpec, for the commands the driver uses and the simulator serves.
COMMANDS: dict[str, CommandSpec] = {spec.name.lower(): spec for spec in (
    CommandSpec("ActivateRobot", answers=(2000, 2001), errors=(1011, 1013)),
    CommandSpec("DeactivateRobot", answers=(2004,)),
    CommandSpec("Home", answers=(2002, 2003), errors=(1005, 1011, 1014), requires="activated"),
    CommandSpec("ResetError", answers=(2005, 2006), errors=(1025,)),
    CommandSpec("GetStatusRobot", answers=(2007,)),
    CommandSpec("PauseMotion", answers=(2042,)),
    CommandSpec("ResumeMotion", answers=(2043,), errors=_MOTION_ERRORS, requires="homed"),
    CommandSpec("ClearMotion", answers=(2044,)),
    CommandSpec("GetJoints", answers=(2026,)),
    CommandSpec("GetPose", answers=(2027,)),
    CommandSpec("GetFwVersion", answers=(2081,)),
    CommandSpec("GetFwVersionFull", answers=(2082,)),
    CommandSpec("GetRobotSerial", answers=(2083,)),
    CommandSpec("GetMonitoringInterval", answers=(2116,)),
    CommandSpec("SetMonitoringInterval", (1, 1), errors=(1003,)),
    CommandSpec("GetRealTimeMonitoring", answers=(2117,)),
    CommandSpec("SetRealTimeMonitoring", (1, 16), answers=(2117,), errors=(1001, 1003)),
    CommandSpec("SetCtrlPortMonitoring", (1, 1), answers=(2096,), errors=(1003,)),
    CommandSpec("SyncCmdQueue", (1, 1), answers=(2097,), errors=(1003,)),
    CommandSpec("ConnectionWatchdog", (1, 1), answers=(2177,), errors=(1001, 1003)),
    CommandSpec("SetRtc", (1, 1)),
    CommandSpec("MoveJoints", (6, 6), errors=(*_MOTION_ERRORS, 1007), queued=True,
                requires="homed"),
    CommandSpec("MoveJointsVel", (6, 6), errors=(*_MOTION_ERRORS, 1003), queued=True,
                requires="homed"),
    CommandSpec("SetVelTimeout", (1, 1), errors=(*_MOTION_ERRORS, 1003), queued=True,
                requires="homed"),
    CommandSpec("SetCheckpoint", (1, 1), answers=(3030,), errors=(*_MOTION_ERRORS, 1003, 3040),
                queued=True, requires="homed"),
    CommandSpec("GetProductType", answers=(2084,)),
    # position-mode moves (section "Motion commands"); errors while executing latch
    CommandSpec("MoveJointsRel", (6, 6), errors=(*_MOTION_ERRORS, 1007), queued=True,
                requires="homed"),
    CommandSpec("MovePose", (6, 6), errors=(*_MOTION_ERRORS, 1016), queued=True,
                requires="homed"),
    CommandSpec("MoveLin", (6, 6), errors=(*_MOTION_ERRORS, 1007, 1012, 1016), queued=True,
                requires="homed"),
    CommandSpec("MoveLinRelTrf", (6, 6), errors=(*_MOTION_ERRORS, 1007, 1012, 1016),
                queued=True, requires="homed"),
    CommandSpec("MoveLinRelWrf", (6, 6), errors=(*_MOTION_ERRORS, 1007, 1012, 1016),
                queued=True, requires="homed"),
    CommandSpec("Delay", (1, 1), errors=(*_MOTION_ERRORS, 1003), queued=True, requires="homed"),
    # motion-queue settings: no answer on success, default restored at every activation
    *(CommandSpec(name, (n, n), errors=(*_MOTION_ERRORS, 1003), queued=True, requires="homed")
      for name, n in (("SetJointVel", 1), ("SetJointAcc", 1), ("SetCartLinVel", 1),
                      ("SetCartAngVel", 1), ("SetCartAcc", 1), ("SetBlending", 1),
                      ("SetAutoConf", 1), ("SetTrf", 6), ("SetWrf", 6))),
    # real-time data requests: answered with the same record as the monitoring cycle
    *(CommandSpec(name, answers=(code,)) for name, code in RT_QUERIES.items()),
)}


class CommandError(ProtocolError):
    """A command the robot refuses before executing it; ``code`` is its answer (1001..1003)."""

    def __init__(self, code: int, text: str, detail: str) -> None:
        self.code = code
        self.text = text
        super().__init__(DEVICE, f"{describe_code(code)} {detail}: {text[:80]!r}")


@dataclass(frozen=True, slots=True)
class Command:
    """A decoded command: ``name`` as sent, ``args`` as floats, ``silent`` if it had a '-'."""

    name: str
    args: tuple[float, ...] = ()
    silent: bool = False

    @property
    def key(self) -> str:
        """Lower-case name (commands are case-insensitive)."""
        return self.name.lower()

    @property
    def spec(self) -> CommandSpec | None:
        return COMMANDS.get(self.name.lower())


_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_BLANK = " \t\r\n\0"


def is_number(x) -> bool:
    """A real number a command may carry (bool is not one). Floats (numpy's included) and
    ints are told by their concrete type first: the ABC check costs microseconds, and a
    joint-velocity command at 500 Hz carries six."""
    if isinstance(x, (float, int)):
        return not isinstance(x, bool)
    return isinstance(x, numbers.Real)


def format_number(x: float) -> str:
    """Shortest text for a wire number: integers without a point, else up to 6 decimals."""
    if not isinstance(x, float):
        if not is_number(x):
            raise TypeError(f"not a number: {x!r}")
        if isinstance(x, (int, numbers.Integral)):
            return str(int(x))
    x = float(x)
    if x == int(x) and abs(x) < 1e15:
        return str(int(x))
    s = f"{x:.6f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def encode_command(name: str, *args: float, silent: bool = False) -> bytes:
    """``Name(a,b,...)`` + NUL (``Name`` alone without arguments, like the official client).

    Raises ConfigError for a malformed name or a non-finite argument (nothing is sent).
    """
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ConfigError("meca500.command", name, "an ASCII identifier")
    parts = []
    for i, a in enumerate(args):
        if not is_number(a) or not math.isfinite(a):
            raise ConfigError(f"meca500.{name}.args[{i}]", a, "a finite number")
        parts.append(format_number(a))
    text = ("-" if silent else "") + name + (f"({','.join(parts)})" if parts else "")
    return text.encode("ascii") + b"\0"


def _text(frame: bytes | str) -> str:
    if isinstance(frame, str):
        return frame
    try:
        return frame.decode("ascii")
    except UnicodeDecodeError as exc:
        raise ProtocolError(DEVICE, f"non-ASCII bytes in frame {frame[:40]!r}") from exc


def decode_command(frame: bytes | str) -> Command | None:
    """Parse one command frame (terminator removed). None for an empty command.

    Raises :class:`CommandError` with the robot's answer code: 1001 (not a command name),
    1002 (a parenthesis or comma missing), 1003 (an argument that is not a finite number).
    """
    try:
        s = _text(frame).strip(_BLANK)
    except ProtocolError as exc:
        raise CommandError(1001, repr(frame[:40]), "non-ASCII command") from exc
    if not s:
        return None
    silent = s.startswith("-")
    body = s[1:].lstrip() if silent else s
    if "(" in body:
        name, rest = body.split("(", 1)
        rest = rest.rstrip()
        if not rest.endswith(")") or "(" in rest[:-1] or ")" in rest[:-1]:
            raise CommandError(1002, s, "unbalanced parentheses")
        inner = rest[:-1].strip()
        raw = [] if not inner else [a.strip() for a in inner.split(",")]
    else:
        name, raw = body, []
        if ")" in name or "," in name:
            raise CommandError(1002, s, "arguments without parentheses")
    name = name.strip()
    if not _NAME_RE.match(name):
        raise CommandError(1001, s, "not a command name")
    args = []
    for a in raw:
        if not a:
            raise CommandError(1002, s, "empty argument")
        try:
            v = float(a)
        except ValueError:
            raise CommandError(1003, s, f"argument {a!r} is not a number") from None
        if not math.isfinite(v):
            raise CommandError(1003, s, f"argument {a!r} is not finite")
        args.append(v)
    return Command(name, tuple(args), silent)


# --------------------------------------------------------------------------- responses
@dataclass(frozen=True, slots=True)
class Response:
    """A decoded response ``[code][payload]``."""

    code: int
    payload: str = ""

    @property
    def info(self) -> CodeInfo | None:
        return RESPONSE_CODES.get(self.code)

    @property
    def kind(self) -> str:
        return kind_of(self.code)

    def values(self) -> tuple[float, ...]:
        """The payload as comma-separated numbers (empty payload: ())."""
        return parse_values(self.payload, self.code)

    def describe(self) -> str:
        return f"{describe_code(self.code)} ({self.payload})"


_RESPONSE_RE = re.compile(r"\[(\d{4})\]\[(.*)\]\Z", re.DOTALL)


def parse_values(payload: str, code: int = 0) -> tuple[float, ...]:
    """Comma-separated finite numbers; ProtocolError naming the code otherwise. (One pass
    in C for a good payload, the monitoring stream's every record; the value at fault is
    looked for only when it is not.)"""
    try:
        out = tuple(map(float, payload.split(",")))
    except ValueError:
        if not payload.strip():
            return ()
        out = None
    if out is not None and all(map(math.isfinite, out)):
        return out
    for part in payload.split(","):
        try:
            v = float(part)
        except ValueError:
            raise ProtocolError(DEVICE, f"[{code}] payload value {part!r} is not a number "
                                        f"(payload {payload[:80]!r})") from None
        if not math.isfinite(v):
            raise ProtocolError(DEVICE, f"[{code}] payload value {part!r} is not finite")
    raise AssertionError("unreachable: a bad value was found above")  # pragma: no cover


def encode_response(code: int, payload: str = "") -> bytes:
    """``[NNNN][payload]`` + NUL."""
    if isinstance(code, bool) or not isinstance(code, int) or not 0 <= code <= 9999:
        raise ConfigError("meca500.response.code", code, "an integer 0..9999")
    if "\0" in payload or "\n" in payload:
        raise ConfigError("meca500.response.payload", payload, "no NUL or newline")
    return f"[{code:04d}][{payload}]".encode("ascii") + b"\0"


def decode_response(frame: bytes | str) -> Response:
    """Parse one response frame (terminator removed); ProtocolError if it is not one."""
    s = _text(frame).strip(_BLANK)
    m = _RESPONSE_RE.match(s)
    if m is None:
        raise ProtocolError(DEVICE, f"not a [NNNN][payload] response: {s[:80]!r}")
    return Response(int(m.group(1)), m.group(2))


def format_values(values: Iterable[float]) -> str:
    return ",".join(format_number(float(v)) for v in values)


# ------------------------------------------------------------------------------ status
@dataclass(frozen=True, slots=True)
class RobotStatus:
    """Payload of [2007]: activated, homed, sim mode, error, paused, end of block, end of
    movement. The manual: ``paused`` is also 1 after ClearMotion and while in error."""

    activated: bool = False
    homed: bool = False
    sim_mode: bool = False
    error: bool = False
    paused: bool = False
    eob: bool = True
    eom: bool = True

    @classmethod
    def from_payload(cls, payload: str) -> RobotStatus:
        parts = [p.strip() for p in payload.split(",")]
        if len(parts) != 7:
            raise ProtocolError(DEVICE, f"[2007] status has {len(parts)} fields, expected 7 "
                                        f"(as,hs,sm,es,pm,eob,eom): {payload[:80]!r}")
        flags = []
        for i, p in enumerate(parts):
            # sm may be a simulation-mode number (newer firmware); the others are 0/1.
            ok = p.isdigit() if i == 2 else p in ("0", "1")
            if not ok:
                raise ProtocolError(DEVICE, f"[2007] status field {i} = {p!r} is not 0/1: "
                                            f"{payload[:80]!r}")
            flags.append(int(p) != 0)
        return cls(*flags)

    def to_payload(self) -> str:
        return ",".join("1" if f else "0" for f in (
            self.activated, self.homed, self.sim_mode, self.error, self.paused, self.eob,
            self.eom))


# ------------------------------------------------------------------------- monitoring
@dataclass(frozen=True, slots=True)
class RtRecord:
    """One real-time monitoring record: ``timestamp_us`` then ``values``."""

    code: int
    timestamp_us: int
    values: tuple[float, ...]


def decode_rt(resp: Response) -> RtRecord:
    """Parse a 22xx payload ``t,v1,...``; ProtocolError on a wrong count or bad number."""
    t, _, rest = resp.payload.partition(",")
    t = t.strip()
    if not t.isdigit():
        raise ProtocolError(DEVICE, f"[{resp.code}] timestamp {t!r} is not an integer number "
                                    f"of microseconds")
    values = parse_values(rest, resp.code) if rest else ()
    want = RT_VALUE_COUNTS.get(resp.code)
    if want is not None and len(values) != want:
        raise ProtocolError(DEVICE, f"[{resp.code}] has {len(values)} values after the "
                                    f"timestamp, expected {want}")
    return RtRecord(resp.code, int(t), values)


def encode_rt(code: int, timestamp_us: int, values: Iterable[float] = ()) -> bytes:
    """``[22xx][t,v1,...]`` + NUL."""
    vals = tuple(values)
    want = RT_VALUE_COUNTS.get(code)
    if want is not None and len(vals) != want:
        raise ConfigError(f"meca500.rt[{code}]", len(vals), f"{want} values")
    if timestamp_us < 0:
        raise ConfigError(f"meca500.rt[{code}].timestamp_us", timestamp_us, ">= 0")
    payload = str(int(timestamp_us)) + ("," + format_values(vals) if vals else "")
    return encode_response(code, payload)


# ----------------------------------------------------------------------------- framing
_TERM_RE = re.compile(rb"[\0\n]")


class FrameSplitter:
    """Incremental splitter of a TCP byte stream into frames (NUL- or newline-terminated).

    ``feed(data)`` returns, in order, the complete frames found (bytes, surrounding
    whitespace stripped, so CR-LF works) and a :class:`ProtocolError` for every frame longer
    than ``max_len`` (discarded up to its terminator: the splitter resynchronises on the next
    terminator). Empty frames (a lone NUL) are counted in ``empty`` and dropped. A split read
    simply stays buffered until its terminator arrives; the buffer never exceeds ``max_len``.
    """

    def __init__(self, max_len: int = MAX_FRAME_LEN) -> None:
        if max_len < 1:
            raise ConfigError("meca500.max_frame_len", max_len, ">= 1")
        self.max_len = max_len
        self._buf = bytearray()
        self._discarding = False
        self.frames = 0
        self.empty = 0
        self.oversized = 0

    @property
    def pending(self) -> int:
        """Bytes buffered of an unfinished frame."""
        return len(self._buf)

    def _too_long(self, n: int) -> ProtocolError:
        self.oversized += 1
        return ProtocolError(DEVICE, f"frame longer than {self.max_len} bytes (at least {n} "
                                     f"bytes without a terminator); discarded")

    def feed(self, data: bytes) -> list[bytes | ProtocolError]:
        out: list[bytes | ProtocolError] = []
        parts = _TERM_RE.split(data)
        tail = parts.pop()                 # after the last terminator: a frame not ended yet
        buf, max_len = self._buf, self.max_len
        for chunk in parts:                # each one ends at a terminator
            if self._discarding:           # the oversized frame ends at this terminator
                self._discarding = False
                continue
            if buf:
                if len(buf) + len(chunk) > max_len:
                    out.append(self._too_long(len(buf) + len(chunk)))
                    buf.clear()
                    continue
                buf += chunk
                chunk = bytes(buf)
                buf.clear()
            elif len(chunk) > max_len:
                out.append(self._too_long(len(chunk)))
                continue
            frame = chunk.strip()
            if frame:
                self.frames += 1
                out.append(frame)
            else:
                self.empty += 1
        if self._discarding:               # the rest of an oversized frame: dropped
            return out
        if len(buf) + len(tail) > max_len:
            out.append(self._too_long(len(buf) + len(tail)))
            buf.clear()
            self._discarding = True
        else:
            buf += tail
        return out
