"""Meca500 driver over the TCP text API (asyncio); implements :class:`dentibot.io.Arm`.

Two TCP connections: the control port (commands, their answers, status and errors) and the
monitoring port (one cycle of real-time records per monitoring interval). Both are read by
asyncio protocol callbacks, which are the background readers: every frame is handled as it
arrives, the newest monitoring cycle wins, and bad bytes are counted and logged, never raised
into the reader.

``connect()``: open the control port and read the greeting ([3000]; [3001] "another user" ->
DeviceFault), read the status (GetStatusRobot), open the monitoring port, then
SetMonitoringInterval, SetRealTimeMonitoring(2210, 2212) (measured joints and velocities; if
the robot refuses, the target joints 2200 are used), a read-back of the interval, and the first
monitoring cycle (so ``read()`` works when ``connect()`` returns). The
robot resets the velocity timeout at every activation, so SetVelTimeout is sent after
``home()`` and at connection when the robot is already homed.

State is tracked from the control port only: the robot pushes [2007] there on every change,
ordered with the answers to the commands (the monitoring port's copies are ignored, as the two
sockets are not ordered with each other).

Faults: an error code (1xxx) that answers no pending request (e.g. [1005] for a MoveJointsVel
before activation, or [1007] when a joint reaches its limit) latches a fault, and so does a
status with es=1. ``read()`` and the next motion command raise :class:`DeviceFault` naming the
code and its meaning until ``reset_error()``. ``error_code`` is the first code latched (the root
cause; the [1011] answers to commands already on their way are only counted).

A dropped link makes ``read()`` raise until ``reconnect()``. The robot pauses motion when its
control connection drops; ``reconnect()`` re-reads the status and, if paused, leaves it so:
``paused`` is True and motion commands raise until an explicit ``resume_motion()``.

End of a run and the next one: ``close()`` parks an activated arm (ClearMotion, then
DeactivateRobot), so the next connection activates and homes a robot with nothing paused.
An arm found paused or in error at connection (the previous run did not park it) is resumed
only on the operator's request, by ``resume()``, which refuses to reset an error blindly.

Connection watchdog (``ConnectionWatchdog(t)`` answered [2177]): ``connect()``
arms it with ``connection_watchdog_s`` and waits for [2177][1]; a robot that does not know the
command fails the connection. Mecademic documents what the robot then does (mecademicpy,
``Robot.ConnectionWatchdog``): unless the watchdog is refreshed by another
``ConnectionWatchdog`` before it expires, the robot "will close the socket connections with
this application, raise the MX_SAFE_STOP_CONNECTION_DROPPED safety stop condition, and pause
motion"; only the command itself refreshes it, other traffic does not. The driver refreshes it
(``-ConnectionWatchdog(t)``, the silent form the vendor's client uses) from the control path:
whenever a command goes out, at every ``read()`` (the control task reads every tick) and while
a request is awaited (activation, homing, checkpoints), each time at most every quarter of the
timeout. So it stops with the process and with a frozen or stuck control task, which the
velocity timeout covers for velocity streaming only: a queued ``MoveJoints`` runs to its end
without the watchdog. Mecademic advises exactly this against its own automatic refresh, which
"may continue to acknowledge the robot even if the application is unresponsive".

Time bounds: ``connect()`` as a whole takes at most ``connect_timeout_s``; a peer that accepts
the connection and never greets is a :class:`~dentibot.io.interfaces.ConnectTimeout` naming
the address after ``response_timeout_s``; every request waits at most ``response_timeout_s``
(``motion_timeout_s`` for activation, homing and checkpoints).

Units: joint angles deg, joint velocities deg/s, times s (the robot's timestamps are us).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Self

import structlog

from dentibot.errors import ConfigError, DeviceFault, ProtocolError
from dentibot.io.interfaces import ConnectTimeout, JointState
from dentibot.io.meca500_protocol import (
    COMMANDS,
    CONNECTION_WATCHDOG_RANGE_S,
    CONTROL_PORT,
    DEFAULT_HOST,
    DEVICE,
    JOINT_LIMITS_DEG,
    JOINT_SPEED_LIMITS_DEG_S,
    MAX_FRAME_LEN,
    MONITOR_PORT,
    MONITORING_INTERVAL_RANGE_S,
    RT_CYCLE_END,
    VEL_TIMEOUT_RANGE_S,
    FrameSplitter,
    Response,
    RobotStatus,
    RtRecord,
    code_info,
    decode_response,
    decode_rt,
    describe_code,
    encode_command,
    is_number,
)

log = structlog.get_logger(__name__)

#: Checkpoint ids the driver uses (mecademicpy's 1..8000, inside the programming manual's 1..8191).
CHECKPOINT_IDS = (1, 8000)
#: Errors ``resume(reset_error=True)`` may reset: refusals of a commanded motion (joint over
#: limit, singularity, destination out of reach), which leave the arm stopped and intact.
#: Everything else (activation or homing failure, motion error / collision, hardware) needs
#: the arm looked at first.
RESETTABLE_ERRORS = frozenset({1007, 1012, 1016})
_LOG_FIRST, _LOG_EVERY = 10, 1000


@dataclass(frozen=True, slots=True)
class MonitoringCycle:
    """One monitoring cycle as received: the robot's ``timestamp_us`` (end of cycle), the
    monotonic reception time ``received_t`` (s) and ``records`` code -> values."""

    timestamp_us: int
    received_t: float
    records: dict[int, tuple[float, ...]]


class _Link(asyncio.Protocol):
    def __init__(self, driver: Meca500Driver, kind: str) -> None:
        self.driver = driver
        self.kind = kind
        self.transport: asyncio.Transport | None = None
        self.splitter = FrameSplitter(driver.max_frame_len)
        self.closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def connection_made(self, transport) -> None:
        self.transport = transport

    def data_received(self, data: bytes) -> None:
        self.driver._on_bytes(self, data, time.monotonic())

    def connection_lost(self, exc) -> None:
        if not self.closed.done():
            self.closed.set_result(None)
        self.driver._on_link_lost(self, exc)


class _Waiter:
    __slots__ = ("errors", "expect", "fail_on_fault", "future", "match", "name")

    def __init__(self, name: str, expect, errors, match, fail_on_fault: bool) -> None:
        self.name = name
        self.expect = frozenset(expect)
        self.errors = frozenset(errors)
        self.match = match
        self.fail_on_fault = fail_on_fault
        self.future: asyncio.Future[Response] = asyncio.get_running_loop().create_future()

    def fail(self, exc: Exception) -> None:
        if not self.future.done():
            self.future.set_exception(exc)


def _in_range(field: str, value: float, lo: float, hi: float, unit: str) -> float:
    if not (is_number(value) and math.isfinite(value) and lo <= value <= hi):
        raise ConfigError(field, value, f"{lo}..{hi} {unit}")
    return float(value)


class Meca500Driver:
    """Meca500 over TCP (implements ``dentibot.io.Arm``).

    Args:
        host: the robot's address; ``"192.168.0.100"`` is Mecademic's factory default.
        control_port: control port (10000).
        monitor_port: monitoring port (10001).
        monitoring_interval_s: SetMonitoringInterval (s, 0.001..1); 0.002 = the 500 Hz tick.
        vel_timeout_s: SetVelTimeout (s, 0.001..1): with no new MoveJointsVel for this long
            the arm decelerates to rest. 0.01 = 5 periods at 500 Hz; the runtime passes its own.
        connect_timeout_s: whole connect() (TCP connections, greeting, set-up) (s).
        response_timeout_s: answer to an immediate command (s).
        motion_timeout_s: ActivateRobot, Home and checkpoints (s); activation and homing take
            a few seconds on the real robot.
        realtime_monitoring: optional monitoring codes asked at connection (measured joints
            2210 and velocities 2212); ``()`` uses the target joints 2200 only.
        stale_after_s: ``read()`` raises when the newest cycle is older than this (s); None:
            never (the control task checks ``t`` and ``seq`` itself).
        max_frame_len: longest frame accepted from the robot (bytes).
        connection_watchdog_s: ConnectionWatchdog timeout armed at connection (s; 0.2: a
            control task stuck for 100 control periods loses the arm); 0 leaves it off.
    """

    device = DEVICE

    def __init__(self, host: str = DEFAULT_HOST, control_port: int = CONTROL_PORT,
                 monitor_port: int = MONITOR_PORT, *, monitoring_interval_s: float = 0.002,
                 vel_timeout_s: float = 0.01, connect_timeout_s: float = 5.0,
                 response_timeout_s: float = 2.0, motion_timeout_s: float = 30.0,
                 realtime_monitoring: tuple[int, ...] = (2210, 2212),
                 stale_after_s: float | None = None,
                 max_frame_len: int = MAX_FRAME_LEN,
                 connection_watchdog_s: float = 0.2) -> None:
        self.host = host
        self.control_port = control_port
        self.monitor_port = monitor_port
        self.monitoring_interval_s = _in_range("meca500.monitoring_interval_s",
                                               monitoring_interval_s,
                                               *MONITORING_INTERVAL_RANGE_S, "s")
        self.vel_timeout_s = _in_range("meca500.vel_timeout_s", vel_timeout_s,
                                       *VEL_TIMEOUT_RANGE_S, "s")
        for name, v in (("connect_timeout_s", connect_timeout_s),
                        ("response_timeout_s", response_timeout_s),
                        ("motion_timeout_s", motion_timeout_s)):
            _in_range(f"meca500.{name}", v, 1e-3, 3600.0, "s")
        if stale_after_s is not None:
            _in_range("meca500.stale_after_s", stale_after_s, 1e-3, 3600.0, "s")
        if connection_watchdog_s != 0:
            _in_range("meca500.connection_watchdog_s", connection_watchdog_s,
                      *CONNECTION_WATCHDOG_RANGE_S, "s (0 = off)")
        self.connection_watchdog_s = float(connection_watchdog_s)
        self.connect_timeout_s = connect_timeout_s
        self.response_timeout_s = response_timeout_s
        self.motion_timeout_s = motion_timeout_s
        self.realtime_monitoring = tuple(int(c) for c in realtime_monitoring)
        self.stale_after_s = stale_after_s
        self.max_frame_len = max_frame_len
        # what the robot said
        self.status: RobotStatus | None = None
        self.error_code = 0
        self.firmware = ""
        self.realtime_codes: tuple[int, ...] = ()
        self.last_cycle: MonitoringCycle | None = None
        # counters
        self.received = 0            # monitoring cycles turned into a JointState
        self.records = 0             # real-time records received
        self.lost = 0                # cycles that arrived without usable joint positions
        self.gaps = 0                # cycles missing according to the robot's timestamps
        self.repeated = 0            # cycles with the previous cycle's timestamp (no new data)
        self.errors = 0              # bad frames / payloads on either port
        self.unsolicited_errors = 0  # 1xxx codes that answered no request (latched faults)
        self.commands_sent = 0
        self.reconnects = 0
        self.watchdog_feeds = 0      # ConnectionWatchdog refreshes sent
        self._watchdog_armed = False
        self._watchdog_fed_t = -math.inf
        # internals
        self._ctrl: _Link | None = None
        self._mon: _Link | None = None
        self._link_error: str | None = "not connected"
        self._refusal: Response | None = None
        self._waiters: list[_Waiter] = []
        self._sample: JointState | None = None
        self._seq = 0
        self._cycle: dict[int, RtRecord] = {}
        self._prev_ts: int | None = None
        self._prev_q: tuple[float, ...] | None = None
        self._interval_us = self.monitoring_interval_s * 1e6
        self._checkpoint_id = 0
        self._sync_id = 0
        self._first_cycle: _Waiter | None = None

    # ------------------------------------------------------------------ state
    @property
    def connected(self) -> bool:
        return self._link_error is None and self._ctrl is not None and self._mon is not None

    @property
    def paused(self) -> bool:
        """Motion paused (PauseMotion, ClearMotion, a dropped link or an error)."""
        return self.status is not None and self.status.paused

    @property
    def activated(self) -> bool:
        return self.status is not None and self.status.activated

    @property
    def homed(self) -> bool:
        return self.status is not None and self.status.homed

    @property
    def fault(self) -> str | None:
        """Why ``read()`` and motion commands raise, or None."""
        if self._refusal is not None:
            r = self._refusal
            return f"{describe_code(r.code)} (robot said {r.payload!r}); call reset_error()"
        if self.status is not None and self.status.error:
            last = f"; last error {describe_code(self.error_code)}" if self.error_code else ""
            return f"robot in error (status es=1{last}); call reset_error()"
        return None

    # ------------------------------------------------------------------ lifecycle
    async def connect(self) -> None:
        """Open both connections and configure monitoring (see the module docstring)."""
        if self.connected:
            return
        await self._teardown("reconnecting")
        self._reset_stream()
        stage = ["TCP connection"]
        try:
            await asyncio.wait_for(self._open(stage), self.connect_timeout_s)
        except TimeoutError:
            await self._teardown("connect timed out")
            raise ConnectTimeout(DEVICE, f"{self.host}:{self.control_port}", stage[0],
                                 self.connect_timeout_s) from None
        except ConnectTimeout:
            await self._teardown("connect timed out")
            raise
        except OSError as exc:
            await self._teardown(f"connect failed: {exc}")
            raise DeviceFault(DEVICE, f"cannot connect to {self.host}:{self.control_port} / "
                                      f"{self.monitor_port}: {exc}") from exc
        except BaseException:
            await self._teardown("connect failed")
            raise

    async def _open(self, stage: list[str]) -> None:
        loop = asyncio.get_running_loop()
        self._link_error = None
        self._watchdog_armed = False
        greeting = self._add_waiter("greeting", (3000, 3001), ())
        try:
            _, self._ctrl = await loop.create_connection(lambda: _Link(self, "control"),
                                                         self.host, self.control_port)
            stage[0] = "greeting [3000]"
            try:
                resp = await self._await(greeting, self.response_timeout_s)
            except DeviceFault as exc:
                if self._link_error is not None:
                    raise
                raise ConnectTimeout(DEVICE, f"{self.host}:{self.control_port}",
                                     "greeting [3000]", self.response_timeout_s) from exc
        finally:
            self._remove_waiter(greeting)
        stage[0] = "answer after the greeting"
        if resp.code == 3001:
            raise DeviceFault(DEVICE, f"[3001] control connection refused: {resp.payload!r} "
                                      f"(the robot accepts one control client at a time)")
        self.firmware = resp.payload
        await self.get_status()
        if self.connection_watchdog_s:
            stage[0] = f"answer to ConnectionWatchdog({self.connection_watchdog_s:g})"
            armed = await self._request("ConnectionWatchdog", self.connection_watchdog_s,
                                        check=False)
            if armed.payload.strip() != "1":
                raise DeviceFault(DEVICE, f"{self.host}:{self.control_port}: "
                                          f"ConnectionWatchdog({self.connection_watchdog_s:g}) "
                                          f"answered {armed.describe()}, not enabled")
            self._watchdog_armed = True
            self._watchdog_fed_t = time.monotonic()
        stage[0] = f"monitoring connection on port {self.monitor_port}"
        _, self._mon = await loop.create_connection(lambda: _Link(self, "monitor"),
                                                    self.host, self.monitor_port)
        # an empty command announces a plain TCP client (not a WebSocket), as the vendor's
        # client does: the robot then greets and streams at once
        self._mon.transport.write(b"\0")
        stage[0] = "answers setting up the monitoring"
        self._send("SetMonitoringInterval", self.monitoring_interval_s, check=False)
        self.realtime_codes = ()
        if self.realtime_monitoring:
            try:
                resp = await self._request("SetRealTimeMonitoring", *self.realtime_monitoring,
                                           check=False)
                self.realtime_codes = tuple(int(v) for v in resp.values())
            except DeviceFault as exc:
                log.warning("meca500.realtime_monitoring_refused", error=str(exc),
                            fallback="target joints 2200")
        interval = (await self._request("GetMonitoringInterval", check=False)).values()
        if len(interval) != 1 or not math.isclose(interval[0], self.monitoring_interval_s,
                                                  abs_tol=1e-6):    # 6 decimals on the wire
            raise DeviceFault(DEVICE, f"monitoring interval reads {interval} s after "
                                      f"SetMonitoringInterval({self.monitoring_interval_s})")
        self._interval_us = interval[0] * 1e6
        st = self.status
        if st is not None and st.activated and st.homed and not st.error:
            self._send("SetVelTimeout", self.vel_timeout_s, check=False)
        first = self._add_waiter("first monitoring cycle", (), ())
        self._first_cycle = first
        try:                                   # so that read() works when connect() returns
            if self._sample is None:
                await self._await(first, self.response_timeout_s)
        finally:
            self._first_cycle = None
            self._remove_waiter(first)
        if self.paused:
            log.warning("meca500.paused", reason="robot reports motion paused at connection",
                        hint="call resume() on the operator's request when it is safe")
        log.info("meca500.connected", host=self.host, firmware=self.firmware,
                 status=st, realtime=self.realtime_codes, interval_s=interval[0])

    async def reconnect(self) -> None:
        """Close whatever is left of both connections and connect again.

        The robot paused motion when the link dropped; this does not resume it: check
        ``paused`` and call ``resume_motion()`` explicitly. The latched refusal (if any) is
        forgotten; a robot error shows again through the status read at connection.
        """
        await self._teardown("reconnecting")
        self._refusal = None
        await self.connect()
        self.reconnects += 1

    async def close(self, *, deactivate: bool = True) -> None:
        """Close both connections (idempotent).

        With ``deactivate`` (the end of a run), an activated arm is parked first: ClearMotion
        (the arm stops, the queue is emptied) then DeactivateRobot (brakes on), each bounded
        by ``response_timeout_s``. The robot pauses motion when its control connection drops
        and keeps that pause across connections; a deactivated robot has nothing to resume,
        and the next run's ``activate()`` / ``home()`` start from a clean state (manual:
        the motion-queue settings return to their defaults at every activation). An arm in
        error is deactivated too; the error stays for the next connection to report
        (``resume(reset_error=True)`` decides about it). Failures here are logged, never
        raised: the connections are closed whatever the robot answers.
        """
        if deactivate and self.connected and self.activated:
            try:
                await self._request("ClearMotion", check=False)
                await self._request("DeactivateRobot", check=False)
                await self.get_status()
            except DeviceFault as exc:
                log.warning("meca500.park_failed", error=str(exc),
                            hint="the robot keeps motion paused; resume() at next connection")
        await self._teardown("closed")

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    async def _teardown(self, reason: str) -> None:
        if self._link_error is None:
            self._link_error = reason
        links = [lk for lk in (self._ctrl, self._mon) if lk is not None]
        self._ctrl = self._mon = None
        for lk in links:
            if lk.transport is not None:
                lk.transport.close()
        pending = [lk.closed for lk in links if lk.transport is not None]
        if pending:
            await asyncio.wait(pending, timeout=1.0)
        for lk in links:
            if lk.transport is not None and not lk.closed.done():
                lk.transport.abort()
        self._fail_waiters(DeviceFault(DEVICE, f"link closed ({reason})"))

    def _reset_stream(self) -> None:
        self._sample = None
        self._cycle = {}
        self._prev_ts = None
        self._prev_q = None

    # ------------------------------------------------------------------ receiving
    def _on_link_lost(self, link: _Link, exc) -> None:
        if link is not self._ctrl and link is not self._mon:
            return                               # an old or closing link
        if self._link_error is None:
            self._link_error = f"{link.kind} connection lost" + (f": {exc}" if exc else "")
            log.warning("meca500.link_lost", port=link.kind, error=str(exc) if exc else None)
        self._fail_waiters(DeviceFault(DEVICE, f"link lost ({self._link_error})"))

    def _bad(self, link: _Link, exc: Exception) -> None:
        self.errors += 1
        if self.errors <= _LOG_FIRST or self.errors % _LOG_EVERY == 0:
            log.warning("meca500.bad_frame", port=link.kind, error=str(exc), count=self.errors)

    def _on_bytes(self, link: _Link, data: bytes, t_rx: float) -> None:
        for item in link.splitter.feed(data):
            if isinstance(item, ProtocolError):
                self._bad(link, item)
                continue
            try:
                resp = decode_response(item)
                if link.kind == "monitor":
                    self._on_monitor(resp, t_rx)
                else:
                    self._on_control(resp)
            except ProtocolError as exc:
                self._bad(link, exc)

    def _on_monitor(self, resp: Response, t_rx: float) -> None:
        code = resp.code
        if 2200 <= code < 2300:
            self.records += 1
            rec = decode_rt(resp)
            if code == RT_CYCLE_END:
                self._end_cycle(rec, t_rx)
            else:
                self._cycle[code] = rec
        # 2007 and the rest on the monitoring port: the control port's copy is tracked.

    def _end_cycle(self, end: RtRecord, t_rx: float) -> None:
        recs, self._cycle = self._cycle, {}
        ts = end.timestamp_us
        qrec = recs.get(2210) or recs.get(2200)
        if qrec is None:
            self.lost += 1
            log.warning("meca500.cycle_without_joints", timestamp_us=ts, codes=sorted(recs))
            return
        prev_ts = self._prev_ts
        if prev_ts is not None:
            dt = ts - prev_ts
            if dt < 0:
                self.errors += 1
                log.warning("meca500.timestamp_backwards", timestamp_us=ts, previous=prev_ts)
            elif dt == 0:
                self.repeated += 1
            elif dt > 1.5 * self._interval_us:
                self.gaps += round(dt / self._interval_us) - 1
        q = qrec.values
        vrec = recs.get(2212) or recs.get(2202)
        if vrec is not None:
            qd = vrec.values
        elif self._prev_q is not None and prev_ts is not None and ts > prev_ts:
            k = 1e6 / (ts - prev_ts)
            qd = tuple((a - b) * k for a, b in zip(q, self._prev_q))
        else:
            qd = (0.0,) * 6
        self._prev_ts, self._prev_q = ts, q
        self._seq += 1
        self.received += 1
        self._sample = JointState(t_rx, self._seq, q, qd)
        self.last_cycle = MonitoringCycle(ts, t_rx, {c: r.values for c, r in recs.items()})
        if self._first_cycle is not None and not self._first_cycle.future.done():
            self._first_cycle.future.set_result(Response(RT_CYCLE_END, str(ts)))

    def _on_control(self, resp: Response) -> None:
        code = resp.code
        if 2200 <= code < 2300:
            return                          # monitoring copy on the control port: not used
        if code == 2007:
            self.status = RobotStatus.from_payload(resp.payload)
            if self.status.error:
                self._fail_waiters(DeviceFault(DEVICE, f"robot in error ({self.fault})"),
                                   only_fail_on_fault=True)
        for w in self._waiters:
            if w.future.done():
                continue
            if code in w.expect and (w.match is None or w.match(resp)):
                w.future.set_result(resp)
                break
            if code in w.errors:
                w.fail(DeviceFault(DEVICE, f"{w.name} refused: {resp.describe()}"))
                info = code_info(code)
                if info is not None and info.latches:
                    self._latch(resp)
                break
        else:
            if 1000 <= code < 2000:
                self._latch(resp)
            elif code == 3040:
                log.info("meca500.checkpoint_discarded", checkpoint=resp.payload)

    def _latch(self, resp: Response) -> None:
        """Latch the first error until reset_error(): the root cause, not the [1011]s that
        answer the commands that were already on their way."""
        self.unsolicited_errors += 1
        log.warning("meca500.error", code=resp.code, meaning=describe_code(resp.code),
                    payload=resp.payload)
        if self._refusal is not None:
            return
        self._refusal = resp
        self.error_code = resp.code
        self._fail_waiters(DeviceFault(DEVICE, self.fault or describe_code(resp.code)),
                           only_fail_on_fault=True)

    # ------------------------------------------------------------------ requests
    def _add_waiter(self, name: str, expect, errors, match: Callable | None = None,
                    fail_on_fault: bool = False) -> _Waiter:
        w = _Waiter(name, expect, errors, match, fail_on_fault)
        self._waiters.append(w)
        return w

    def _remove_waiter(self, w: _Waiter) -> None:
        if w in self._waiters:
            self._waiters.remove(w)

    def _fail_waiters(self, exc: Exception, only_fail_on_fault: bool = False) -> None:
        for w in list(self._waiters):
            if not only_fail_on_fault or w.fail_on_fault:
                w.fail(exc)

    async def _await(self, w: _Waiter, timeout: float) -> Response:
        """Wait for ``w``'s answer, refreshing the connection watchdog meanwhile (the caller
        awaiting the robot is the control path: activation and homing take seconds)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        slice_s = self.connection_watchdog_s / 4 if self.connection_watchdog_s else timeout
        while not w.future.done():
            left = deadline - loop.time()
            if left <= 0:
                raise DeviceFault(DEVICE, f"no answer to {w.name} within {timeout} s "
                                          f"(expected {sorted(w.expect)})")
            await asyncio.wait({w.future}, timeout=min(left, slice_s))
            self._feed_watchdog()
        return w.future.result()

    def _feed_watchdog(self) -> None:
        """Refresh the connection watchdog if a quarter of its time has passed since the last
        refresh (``-ConnectionWatchdog(t)``; its [2177] answer needs no waiter)."""
        if not self._watchdog_armed or self._ctrl is None or self._link_error is not None:
            return
        now = time.monotonic()
        if now - self._watchdog_fed_t < self.connection_watchdog_s / 4:
            return
        self._watchdog_fed_t = now
        self._ctrl.transport.write(encode_command("ConnectionWatchdog",
                                                  self.connection_watchdog_s, silent=True))
        self.watchdog_feeds += 1

    def _check_link(self) -> None:
        if self._link_error is not None or self._ctrl is None:
            raise DeviceFault(DEVICE, f"link down ({self._link_error}); call reconnect()")

    def _send(self, name: str, *args: float, check: bool = True) -> None:
        self._check_link()
        if check and (fault := self.fault) is not None:
            raise DeviceFault(DEVICE, fault)
        data = encode_command(name, *args)
        self._ctrl.transport.write(data)
        self.commands_sent += 1
        self._feed_watchdog()

    async def _request(self, name: str, *args: float, check: bool = True,
                       timeout: float | None = None, match: Callable | None = None) -> Response:
        spec = COMMANDS[name.lower()]
        w = self._add_waiter(name, spec.answers, spec.errors, match)
        try:
            self._send(name, *args, check=check)
            return await self._await(w, timeout or self.response_timeout_s)
        finally:
            self._remove_waiter(w)

    # ------------------------------------------------------------------ robot commands
    async def get_status(self) -> RobotStatus:
        """GetStatusRobot -> [2007]."""
        resp = await self._request("GetStatusRobot", check=False)
        return RobotStatus.from_payload(resp.payload)

    async def activate(self) -> None:
        """ActivateRobot -> [2000] (the robot resets its velocity timeout to 0.05 s)."""
        await self._request("ActivateRobot", timeout=self.motion_timeout_s)
        await self.get_status()

    async def home(self) -> None:
        """Home -> [2002], then SetVelTimeout(vel_timeout_s)."""
        await self._request("Home", timeout=self.motion_timeout_s)
        self._send("SetVelTimeout", self.vel_timeout_s)
        await self.get_status()

    async def set_vel_timeout(self, seconds: float) -> None:
        """SetVelTimeout (s, 0.001..1); kept and sent again after ``home()`` / connection."""
        self.vel_timeout_s = _in_range("meca500.vel_timeout_s", seconds, *VEL_TIMEOUT_RANGE_S,
                                       "s")
        self._send("SetVelTimeout", self.vel_timeout_s)

    async def reset_error(self) -> int:
        """ResetError -> [2005] (or [2006]: nothing to reset); clears the latched fault.
        Motion stays paused: call ``resume_motion()``. Returns the answer code."""
        resp = await self._request("ResetError", check=False)
        self._refusal = None
        self.error_code = 0
        await self.get_status()
        return resp.code

    async def resume_motion(self) -> None:
        """ResumeMotion -> [2043]."""
        await self._request("ResumeMotion")
        await self.get_status()

    async def resume(self, *, reset_error: bool = False) -> None:
        """Operator-requested resume of an arm found paused or in error at connection (a run
        that ended without parking the arm, a dropped link, an expired connection watchdog).

        Reads the status, then:

        - not activated or not homed: nothing to resume; raises (call ``activate()`` and
          ``home()``);
        - in error (es=1): raises unless ``reset_error``; with it, resets only an error whose
          cause this connection received and which a reset may clear
          (:data:`RESETTABLE_ERRORS`: joint limit, singularity, pose out of reach). An error
          that was raised before this connection is refused: the robot's status word says
          *that* it is in error, not *why* (firmware 9.x), so resetting it would be blind
          to a collision, an overload or a hardware fault. Such an error is read and reset
          at the robot (its web interface);
        - paused: ClearMotion first (nothing queued before the pause may run on), then
          ResumeMotion; the arm stays at rest until the next motion command.

        Raises :class:`DeviceFault` saying why when it refuses; the robot's state is then
        unchanged.
        """
        self._check_link()
        st = await self.get_status()
        if not (st.activated and st.homed):
            raise DeviceFault(DEVICE, "resume refused: the robot is not activated and homed "
                                      "(nothing to resume); call activate() and home()")
        if st.error:
            code = self.error_code
            if not reset_error:
                what = describe_code(code) if code else "cause not reported"
                raise DeviceFault(DEVICE, f"resume refused: the robot is in error ({what}); "
                                          f"resume(reset_error=True) resets it only if it is "
                                          f"one of {sorted(RESETTABLE_ERRORS)}")
            if not code:
                raise DeviceFault(DEVICE, "resume refused: the robot was in error before this "
                                          "connection and its status does not say which "
                                          "error (firmware 9.x); a blind reset could hide a "
                                          "collision, an overload or a hardware fault. Read "
                                          "and reset the error at the robot (web interface)")
            if code not in RESETTABLE_ERRORS:
                raise DeviceFault(DEVICE, f"resume refused: {describe_code(code)} is not "
                                          f"cleared remotely; it needs the arm inspected and "
                                          f"the error reset at the robot")
            await self.reset_error()
        self._refusal = None
        if self.status is not None and self.status.paused:
            await self._request("ClearMotion", check=False)
            await self._request("ResumeMotion")
        st = await self.get_status()
        if st.error or st.paused:
            raise DeviceFault(DEVICE, f"resume failed: status after ResumeMotion {st}")

    async def recover(self) -> None:
        """After a fault, on the operator's reset: reconnect a dropped link, reset a latched
        error, resume motion (the stop cleared the queue: nothing moves until commanded)."""
        if not self.connected:
            await self.reconnect()
        if self.error_code:
            await self.reset_error()
        if self.paused:
            await self.resume_motion()

    async def pause_motion(self) -> None:
        """PauseMotion -> [2042]: the arm decelerates, the queue is kept."""
        await self._request("PauseMotion", check=False)
        await self.get_status()

    async def clear_motion(self) -> None:
        """ClearMotion -> [2044]: the arm stops, the queue is emptied, motion stays paused."""
        await self._request("ClearMotion", check=False)
        await self.get_status()

    async def get_joints(self) -> tuple[float, ...]:
        """GetJoints -> [2026] joint positions (deg)."""
        resp = await self._request("GetJoints", check=False)
        q = resp.values()
        if len(q) != 6:
            raise ProtocolError(DEVICE, f"[2026] has {len(q)} values, expected 6")
        return q

    async def get_pose(self) -> tuple[float, ...]:
        """GetPose -> [2027] (x, y, z mm, alpha, beta, gamma deg)."""
        resp = await self._request("GetPose", check=False)
        p = resp.values()
        if len(p) != 6:
            raise ProtocolError(DEVICE, f"[2027] has {len(p)} values, expected 6")
        return p

    async def sync(self) -> None:
        """SyncCmdQueue(n) -> [2097][n]: every command sent before has been read and answered
        by the robot (its refusals, if any, have arrived)."""
        self._sync_id = self._sync_id % 1_000_000 + 1
        n = self._sync_id
        await self._request("SyncCmdQueue", n, check=False,
                            match=lambda r: r.payload.strip() == str(n))

    async def checkpoint(self, n: int | None = None, timeout: float | None = None) -> int:
        """SetCheckpoint(n) and wait for [3030][n] (everything queued before it is done).

        Raises DeviceFault if the robot discards it ([3040]: ClearMotion, error, lost link),
        on a fault, or after ``timeout`` (default ``motion_timeout_s``). Returns ``n``.
        """
        if n is None:
            lo, hi = CHECKPOINT_IDS
            self._checkpoint_id = self._checkpoint_id % hi + lo
            n = self._checkpoint_id
        n = int(_in_range("meca500.checkpoint", n, *CHECKPOINT_IDS, ""))
        w = self._add_waiter(f"SetCheckpoint({n})", (3030, 3040), (),
                             match=lambda r: r.payload.strip() == str(n), fail_on_fault=True)
        try:
            self._send("SetCheckpoint", n)
            resp = await self._await(w, timeout or self.motion_timeout_s)
        finally:
            self._remove_waiter(w)
        if resp.code == 3040:
            raise DeviceFault(DEVICE, f"checkpoint {n} discarded ([3040]: motion cleared, "
                                      f"robot in error or link lost) before it was reached")
        return n

    async def wait_idle(self, timeout: float | None = None) -> None:
        """Wait until every queued motion is done (a checkpoint)."""
        await self.checkpoint(timeout=timeout)

    # ------------------------------------------------------------------ Arm protocol
    async def read(self) -> JointState:
        """Newest joint state (measured joints 2210, else target 2200; velocities 2212);
        ``t`` = monotonic reception time, ``seq`` = monitoring cycles received. Refreshes
        the connection watchdog when due (the control task reads every tick)."""
        self._feed_watchdog()
        if self._link_error is not None:
            raise DeviceFault(DEVICE, f"link down ({self._link_error}); call reconnect()")
        if (fault := self.fault) is not None:
            raise DeviceFault(DEVICE, fault)
        s = self._sample
        if s is None:
            raise DeviceFault(DEVICE, "no monitoring cycle received yet")
        if self.stale_after_s is not None:
            age = time.monotonic() - s.t
            if age > self.stale_after_s:
                raise DeviceFault(DEVICE, f"newest joint state is {age:.3f} s old "
                                          f"(stale_after_s = {self.stale_after_s} s)")
        return s

    def _motion_allowed(self) -> None:
        self._check_link()
        if (fault := self.fault) is not None:
            raise DeviceFault(DEVICE, fault)
        if self.paused:
            raise DeviceFault(DEVICE, "motion is paused (PauseMotion, ClearMotion, a dropped "
                                      "link or an expired connection watchdog); on the "
                                      "operator's request call resume() (or resume_motion()) "
                                      "when it is safe")

    @staticmethod
    def _vec6(field: str, values) -> tuple[float, ...]:
        v = tuple(values)
        if len(v) != 6:
            raise ConfigError(f"meca500.{field}", v, "6 values (J1..J6)")
        for i, x in enumerate(v):
            if not is_number(x) or not math.isfinite(x):
                raise ConfigError(f"meca500.{field}.J{i + 1}", x, "a finite number")
        return tuple(float(x) for x in v)

    async def move_joints_vel(self, qdot_deg_s) -> None:
        """MoveJointsVel (deg/s). No answer on success; a refusal arrives later and latches a
        fault. Raises ConfigError (nothing sent) above a joint speed limit."""
        v = self._vec6("qdot_deg_s", qdot_deg_s)
        for i, (x, lim) in enumerate(zip(v, JOINT_SPEED_LIMITS_DEG_S)):
            if abs(x) > lim:
                raise ConfigError(f"meca500.qdot_deg_s.J{i + 1}", x,
                                  f"|qdot| <= {lim} deg/s (Meca500 joint speed limit)")
        self._motion_allowed()
        self._send("MoveJointsVel", *v, check=False)

    async def move_joints(self, q_deg, wait: bool = False) -> None:
        """MoveJoints (deg); with ``wait`` until it is done (a checkpoint). Raises ConfigError
        (nothing sent) outside the joint ranges."""
        q = self._vec6("q_deg", q_deg)
        for i, (x, (lo, hi)) in enumerate(zip(q, JOINT_LIMITS_DEG)):
            if not lo <= x <= hi:
                raise ConfigError(f"meca500.q_deg.J{i + 1}", x,
                                  f"{lo} <= q <= {hi} deg (Meca500 joint range)")
        self._motion_allowed()
        self._send("MoveJoints", *q, check=False)
        if wait:
            await self.checkpoint()

    async def stop(self, keep_paused: bool = False) -> None:
        """Decelerate to rest and drop pending motion: MoveJointsVel(0...) + ClearMotion.

        ClearMotion leaves the robot paused; unless ``keep_paused`` (or it was already paused
        or in error), ResumeMotion follows, so that the next motion command runs, as with the
        in-process SimArm. The queue is empty then, so nothing old resumes.
        """
        self._check_link()
        st = self.status
        was_paused = st is not None and st.paused
        ready = st is not None and st.activated and st.homed and not st.error
        if ready and not was_paused:
            self._send("MoveJointsVel", *(0.0,) * 6, check=False)
        await self._request("ClearMotion", check=False)
        if ready and not was_paused and not keep_paused and self.fault is None:
            await self._request("ResumeMotion", check=False)
        await self.get_status()
