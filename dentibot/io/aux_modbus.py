"""Auxiliary I/O driver over Modbus TCP (pymodbus ``AsyncModbusTcpClient``).

:class:`AuxModbusDriver` implements :class:`dentibot.io.AuxIO` against any device serving the
DentiBot register map (:mod:`dentibot.io.aux_registers`, ``docs/aux-io-register-map.md``):
the clinic's PLC or :class:`dentibot.sim.aux_modbus_server.AuxModbusServer`.

``connect()`` opens the TCP connection and reads input registers 0-1: anything but magic
0x4442 with map major version 1 is refused with a DeviceFault naming what was read and what
was expected. A background task then polls input registers 0..10 (one FC4 request: magic,
version, heartbeat, pedal/e-stop word, platform status and actual position, a consistent
snapshot) every ``poll_period_s`` on absolute deadlines. A poll whose heartbeat differs from
the previous one is a new sample: ``seq`` grows by one and ``t`` is ``time.monotonic()`` at its
reception. A poll with an unchanged heartbeat brings nothing new (counted in ``unchanged``).

``read()`` returns the newest sample without waiting, or raises DeviceFault when there is none
yet, the link is down, the newest poll failed (no answer, Modbus exception, malformed answer,
wrong magic) or the newest sample is older than ``stale_after_s`` (heartbeat frozen). A
dropped link is re-opened every ``reconnect_period_s`` by the same task; malformed answers are
counted and logged (on change, not at the poll rate) and never stop the task.

Host watchdog (map 1.1): on a 1.1+ device, ``connect()`` (and every reconnection) writes
``watchdog_ms`` to HR 7 and a counter to HR 6, and the poll task writes both again (one FC16
of HR 6-7: a new counter feeds the watchdog, the time re-arms it) once a quarter of the
watchdog time has passed since the last feed (by the clock, not by counting polls: polls
slowed by long round trips must not stretch it), so the device holds the platform, lights
FAULT and opens its host-lost output (in the clinic's safety chain: the handpiece drive's STO)
when DentiBot dies or the link breaks for longer than that. Modbus TCP has no authentication
and any client may write HR 6-7: a second client that switched the watchdog off
(``watchdog_ms`` = 0), re-timed it, or fed it (hiding this host's death) would go unnoticed by
a driver that only writes. So every poll
period the driver also reads HR 6-7 back (FC3) before any write of its own, and a value it did
not write latches :class:`WatchdogOverwritten`: ``read()`` raises it until
:meth:`AuxModbusDriver.clear_watchdog_fault` (the operator's reset), while the next feed
restores the registers. A 1.0 device is left as it is.

Time bounds: ``connect()`` as a whole takes at most ``connect_timeout_s`` (TCP connection,
identification, watchdog arming, first poll) or raises
:class:`~dentibot.io.interfaces.ConnectTimeout` naming the address; every request is bounded
by ``request_timeout_s`` (pymodbus's timeout, no retries), so a peer that accepts the
connection and never answers is a fault, never a hang.

Counters: ``polls`` (requests sent), ``received`` (well-formed answers), ``unchanged`` (answers
with the same heartbeat), ``errors`` (failed polls), ``lost`` (poll periods skipped because a
poll or the event loop overran), ``reconnects``, ``writes``, ``feeds`` (watchdog writes);
``readbacks`` (watchdog read-backs); ``seq`` is the sample count. Round trips: ``request_ms``
(the newest request's, sent to answered) and ``request_ms_worst`` (the longest since
:meth:`AuxModbusDriver.reset_request_times`), which bound how late a poll can see a change.
"""

from __future__ import annotations

import asyncio
import math
import time
from typing import Self

import structlog
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from dentibot.errors import ConfigError, DeviceFault, ProtocolError
from dentibot.io.aux_registers import (
    DEVICE,
    EXCEPTION_CODES,
    INDICATORS,
    MAGIC,
    MAP_VERSION,
    AuxInputs,
    Table,
    check_watchdog_ms,
    decode_inputs,
    encode_setpoint,
    point,
    span,
    version_text,
)
from dentibot.io.interfaces import AuxState, ConnectTimeout
from dentibot.io.tasks import cancel_until_done

log = structlog.get_logger(__name__)


class WatchdogOverwritten(DeviceFault):
    """The host watchdog registers (HR 6-7) hold values this driver did not write: another
    Modbus client changed them (switched the watchdog off, re-timed it, or fed it). Latched
    until :meth:`AuxModbusDriver.clear_watchdog_fault`. ``found`` and ``expected`` are the
    (host_watchdog, watchdog_ms) pairs."""

    def __init__(self, address: str, found: tuple[int, int], expected: tuple[int, int]) -> None:
        self.found, self.expected = found, expected
        what = []
        if found[1] != expected[1]:
            what.append(f"watchdog_ms (HR 7) = {found[1]}, written {expected[1]}"
                        + (" (watchdog OFF)" if found[1] == 0 else ""))
        if found[0] != expected[0]:
            what.append(f"host_watchdog (HR 6) = {found[0]}, written {expected[0]} "
                        "(someone else feeds it)")
        super().__init__(DEVICE, f"{address}: host watchdog overwritten by another Modbus "
                                 f"client: {'; '.join(what)}; restored at the next feed. "
                                 "Modbus TCP has no authentication: the aux I/O network must "
                                 "have DentiBot as its only client")


def _exception_text(response) -> str:
    code = getattr(response, "exception_code", None)
    return f"exception {code} ({EXCEPTION_CODES.get(code, 'unknown')})"


class AuxModbusDriver:
    """Pedal, e-stop, indicators and the motion platform over Modbus TCP (``AuxIO``).

    Args:
        host: the I/O PLC's address (``"192.168.0.50"``: the lab's convention, set in config).
        port: Modbus TCP port (502, the standard).
        device_id: Modbus unit id (1).
        poll_period_s: input polling period (0.01 s = 100 Hz).
        stale_after_s: ``read()`` faults when the newest sample (last heartbeat change) is
            older than this (0.1 s = 10 poll periods; the device's heartbeat must advance
            faster than this).
        request_timeout_s: connect and per-request answer timeout (0.2 s), no retries (the
            next poll is the retry).
        reconnect_period_s: pause between attempts to re-open a dropped link (0.5 s).
        watchdog_ms: host watchdog time armed on a 1.1+ device (200 ms = 20 poll periods;
            0 leaves it off).
        connect_timeout_s: bound on the whole ``connect()`` (1.0 s).
    """

    def __init__(self, host: str = "192.168.0.50", port: int = 502, device_id: int = 1,
                 poll_period_s: float = 0.01, stale_after_s: float = 0.1,
                 request_timeout_s: float = 0.2, reconnect_period_s: float = 0.5,
                 watchdog_ms: int = 200, connect_timeout_s: float = 1.0) -> None:
        for field, v in (("poll_period_s", poll_period_s), ("stale_after_s", stale_after_s),
                         ("request_timeout_s", request_timeout_s),
                         ("reconnect_period_s", reconnect_period_s),
                         ("connect_timeout_s", connect_timeout_s)):
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ConfigError(f"aux_modbus.{field}", v, "a positive number of seconds")
        if not (isinstance(device_id, int) and 0 <= device_id <= 255):
            raise ConfigError("aux_modbus.device_id", device_id, "0..255")
        if not (isinstance(port, int) and 0 < port < 65536):
            raise ConfigError("aux_modbus.port", port, "1..65535")
        self.host = host
        self.port = port
        self.device_id = device_id
        self.poll_period_s = float(poll_period_s)
        self.stale_after_s = float(stale_after_s)
        self.request_timeout_s = float(request_timeout_s)
        self.reconnect_period_s = float(reconnect_period_s)
        self.connect_timeout_s = float(connect_timeout_s)
        self.watchdog_ms = check_watchdog_ms(watchdog_ms)
        #: feed the watchdog when this long has passed since the last feed (s)
        self._feed_after_s = watchdog_ms / 4000.0
        self._fed_at = -math.inf                 # monotonic time of the last feed sent
        #: request round trips (ms): the newest and the longest since reset_request_times()
        self.request_ms = self.request_ms_worst = 0.0
        self._watchdog_on = False
        self.polls = self.received = self.unchanged = self.errors = self.lost = 0
        self.reconnects = self.writes = self.seq = self.feeds = self.readbacks = 0
        #: why the watchdog registers were found overwritten (latched), or None
        self.watchdog_fault: WatchdogOverwritten | None = None
        self._fed_value: int | None = None      # the host_watchdog value last written
        #: (magic, map_version) read at connect.
        self.identity: tuple[int, int] | None = None
        self._client: AsyncModbusTcpClient | None = None
        self._task: asyncio.Task | None = None
        self._sample: AuxState | None = None
        self._inputs: AuxInputs | None = None
        self._heartbeat: int | None = None
        self._last_error: str | None = None
        self._link_up = False
        self._stopping = False

    # ------------------------------------------------------------------ life cycle
    @property
    def connected(self) -> bool:
        """The TCP link is up (samples may still be stale)."""
        return self._link_up and self._client is not None and self._client.connected

    async def connect(self) -> None:
        """Open the link, check magic and version, take a first sample, start polling."""
        if self._task is not None:
            return
        self._stopping = False
        self._client = AsyncModbusTcpClient(
            self.host, port=self.port, name=DEVICE, timeout=self.request_timeout_s,
            retries=0, reconnect_delay=0)
        stage = ["TCP connection"]
        try:
            await asyncio.wait_for(self._open(stage), self.connect_timeout_s)
        except TimeoutError:
            await self._drop_client()
            raise ConnectTimeout(DEVICE, self.address, stage[0],
                                 self.connect_timeout_s) from None
        except BaseException:
            await self._drop_client()
            raise
        self._task = asyncio.create_task(self._run(), name=f"{DEVICE}-poll")
        log.info("aux_modbus.connected", host=self.host, port=self.port,
                 device_id=self.device_id, map_version=version_text(self.identity[1]))

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    async def _open(self, stage: list[str]) -> None:
        if not await self._client.connect():
            raise DeviceFault(DEVICE, f"cannot connect to {self.address}")
        stage[0] = "answer to the identification read (input registers 0-1)"
        self.identity = await self._check_identity()
        self._link_up = True
        stage[0] = "answer arming the host watchdog (holding registers 6-7)"
        await self._arm_watchdog()
        stage[0] = "answer to the first input-register poll"
        await self._poll_once()
        if self._last_error is not None:
            raise DeviceFault(DEVICE, f"{self.address}: first poll failed: {self._last_error}")

    async def close(self) -> None:
        """Stop polling and close the link; idempotent."""
        task, self._task = self._task, None
        self._stopping = True
        # the loop also checks _stopping; see cancel_until_done for why one cancel is not enough
        if (died := await cancel_until_done(task, reraise=False)) is not None:
            log.error("aux_modbus.poll_task_died", error=repr(died))
        self._link_up = False
        await self._drop_client()

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    async def _drop_client(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            client.close()
            for _ in range(2):          # let the transport's connection_lost close the socket
                await asyncio.sleep(0)

    async def _check_identity(self) -> tuple[int, int]:
        expected = f"magic 0x{MAGIC:04X} ('DB') with map version {MAP_VERSION[0]}.x"
        try:
            rr = await self._client.read_input_registers(0, count=2, device_id=self.device_id)
        except ModbusException as exc:
            raise DeviceFault(DEVICE, f"{self.address}: no answer reading input registers "
                                      f"0-1 ({exc}); expected {expected}") from exc
        if rr.isError():
            raise DeviceFault(DEVICE, f"{self.address}: input registers 0-1 answered "
                                      f"{_exception_text(rr)}; expected {expected}: not a "
                                      "DentiBot-map device?")
        regs = list(getattr(rr, "registers", []))
        if len(regs) != 2:
            raise DeviceFault(DEVICE, f"{self.address}: input registers 0-1 answered "
                                      f"{regs!r}; expected {expected}")
        magic, version = regs
        if magic != MAGIC or version >> 8 != MAP_VERSION[0]:
            raise DeviceFault(DEVICE, f"{self.address}: read magic 0x{magic:04X} with map "
                                      f"version {version_text(version)} at input registers "
                                      f"0-1; expected {expected}")
        return magic, version

    # ------------------------------------------------------------------ polling
    async def _run(self) -> None:
        period = self.poll_period_s
        deadline = time.monotonic()
        while not self._stopping:
            deadline += period
            now = time.monotonic()
            if now > deadline:                  # overran: skip whole periods, never burst
                missed = int((now - deadline) / period) + 1
                self.lost += missed
                deadline += missed * period
            await asyncio.sleep(deadline - now)
            try:
                if not self._client.connected:
                    await self._reconnect()
                    deadline = time.monotonic()
                    continue
                await self._poll_once()
                if self._watchdog_on:
                    try:
                        await self._check_watchdog()
                        if time.monotonic() - self._fed_at >= self._feed_after_s:
                            await self._feed()
                    except DeviceFault as exc:
                        self._fail(str(exc))
            except Exception as exc:   # noqa: BLE001 - nothing unforeseen may stop the reader
                self._fail(f"unexpected {type(exc).__name__}: {exc}")

    async def _reconnect(self) -> None:
        if self._link_up:
            self._link_up = False
            self._fail(f"link to {self.host}:{self.port} lost")
        while not self._client.connected:
            if self._stopping:
                return
            try:
                if await asyncio.wait_for(self._client.connect(), self.connect_timeout_s):
                    break
            except TimeoutError:
                pass
            await asyncio.sleep(self.reconnect_period_s)
        self.reconnects += 1
        self._heartbeat = None
        self._link_up = True
        log.info("aux_modbus.reconnected", host=self.host, port=self.port)
        try:
            await self._arm_watchdog()         # the device may have restarted (power-on: off)
        except DeviceFault as exc:
            self._fail(str(exc))

    async def _arm_watchdog(self) -> None:
        """Write the watchdog time on a 1.1+ device, feeding it in the same request."""
        self._watchdog_on = bool(self.watchdog_ms) and self.identity is not None \
            and (self.identity[1] & 0xFF) >= 1
        if self._watchdog_on:
            await self._feed()

    async def _feed(self) -> None:
        """One FC16 of HR 6-7: a new host_watchdog counter (feeds the watchdog) and the
        watchdog time (re-arms it, restoring it if someone changed it)."""
        value = (self.feeds + 1) & 0xFFFF or 1
        self._fed_value = None                  # unknown until the device acknowledged
        self._fed_at = time.monotonic()
        await self._send("the host watchdog", self._client.write_registers,
                         point(Table.HOLDING_REGISTER, "host_watchdog").address,
                         [value, self.watchdog_ms])
        self.feeds += 1
        self._fed_value = value

    async def _check_watchdog(self) -> None:
        """Read HR 6-7 back (FC3) and compare with what this driver last wrote; a difference
        latches :class:`WatchdogOverwritten` and the watchdog is written again at once."""
        if self._fed_value is None:
            return
        first = point(Table.HOLDING_REGISTER, "host_watchdog").address
        try:
            rr = await self._timed(self._client.read_holding_registers, first, count=2,
                                   device_id=self.device_id)
        except ModbusException as exc:
            raise DeviceFault(DEVICE, f"no answer reading the host watchdog back ({exc})"
                              ) from exc
        if rr.isError():
            raise DeviceFault(DEVICE, f"reading the host watchdog back: {_exception_text(rr)}")
        regs = tuple(getattr(rr, "registers", ()))
        if len(regs) != 2:
            raise DeviceFault(DEVICE, f"reading the host watchdog back gave {regs!r}")
        self.readbacks += 1
        expected = (self._fed_value, self.watchdog_ms)
        if regs != expected:
            fault = WatchdogOverwritten(self.address, regs, expected)
            if self.watchdog_fault is None:
                self.watchdog_fault = fault
            log.error("aux_modbus.watchdog_overwritten", host=self.host, port=self.port,
                      found=regs, expected=expected)
            await self._feed()                  # restore the protection now

    def clear_watchdog_fault(self) -> None:
        """Acknowledge a latched :class:`WatchdogOverwritten` (the operator's reset)."""
        self.watchdog_fault = None

    async def recover(self) -> None:
        """After a fault, on the operator's reset: acknowledge a watchdog fault."""
        self.clear_watchdog_fault()

    async def _poll_once(self) -> None:
        first, n = span(Table.INPUT_REGISTER)
        self.polls += 1
        try:
            rr = await self._timed(self._client.read_input_registers, first, count=n,
                                   device_id=self.device_id)
        except ModbusException as exc:
            self._fail(f"no answer to the input-register poll ({exc})")
            return
        t = time.monotonic()
        if rr.isError():
            self._fail(f"input registers {first}..{first + n - 1} answered {_exception_text(rr)}")
            return
        try:
            inp = decode_inputs(list(rr.registers))
        except ProtocolError as exc:
            self._fail(f"malformed answer: {exc}")
            return
        if not inp.identity_ok:
            self._fail(f"magic/version changed to 0x{inp.magic:04X}/"
                       f"{version_text(inp.map_version)} (device replaced?)")
            return
        self.received += 1
        if self._last_error is not None:
            log.info("aux_modbus.recovered", after=self._last_error)
            self._last_error = None
        if inp.heartbeat == self._heartbeat:
            self.unchanged += 1
            return
        self._heartbeat = inp.heartbeat
        self.seq += 1
        self._inputs = inp
        self._sample = AuxState(t, self.seq, inp.pedal, inp.estop, inp.platform_mm)

    async def _timed(self, method, *args, **kw):
        """One request through pymodbus, its round trip noted in ``request_ms``."""
        t = time.monotonic()
        try:
            return await method(*args, **kw)
        finally:
            self.request_ms = (time.monotonic() - t) * 1e3
            self.request_ms_worst = max(self.request_ms_worst, self.request_ms)

    def reset_request_times(self) -> None:
        """Start a new window for ``request_ms_worst``."""
        self.request_ms_worst = 0.0

    def _fail(self, why: str) -> None:
        self.errors += 1
        if why != self._last_error:            # log changes, not every failed poll
            log.warning("aux_modbus.poll_failed", host=self.host, port=self.port, reason=why,
                        errors=self.errors)
        self._last_error = why

    # ------------------------------------------------------------------ AuxIO
    async def read(self) -> AuxState:
        """Newest sample (pedal, e-stop, platform actual position mm); DeviceFault if none,
        link down, newest poll failed, or stale."""
        s = self._sample
        if s is None:
            raise DeviceFault(DEVICE, "no sample yet (connect() first)")
        if self.watchdog_fault is not None:
            raise self.watchdog_fault
        if self._task is None or self._task.done():
            raise DeviceFault(DEVICE, "not polling (closed)"
                              + (f"; last error: {self._last_error}" if self._last_error else ""))
        if not self.connected:
            raise DeviceFault(DEVICE, f"link to {self.host}:{self.port} down"
                                      + (f" ({self._last_error})" if self._last_error else ""))
        if self._last_error is not None:
            raise DeviceFault(DEVICE, f"newest poll failed: {self._last_error}")
        age = time.monotonic() - s.t
        if age > self.stale_after_s:
            raise DeviceFault(DEVICE, f"stale: heartbeat {self._heartbeat} last changed "
                                      f"{age * 1e3:.0f} ms ago, limit "
                                      f"{self.stale_after_s * 1e3:.0f} ms")
        return s

    @property
    def inputs(self) -> AuxInputs | None:
        """The newest full input snapshot (also platform moving/fault/setpoint-rejected and
        the raw heartbeat); no staleness check, use ``read()`` for that."""
        return self._inputs

    async def set_indicator(self, name: str, on: bool) -> None:
        """Switch a lamp or the buzzer (coil write, FC5)."""
        address = INDICATORS.get(name)
        if address is None:
            raise ConfigError("indicator", name, f"one of {', '.join(INDICATORS)}")
        await self._write(f"coil {address} ({name})",
                          self._client.write_coil if self._client else None,
                          address, bool(on))

    async def set_platform(self, mm) -> None:
        """Command the platform to (x, y, z) mm: range-checked here (ConfigError naming axis,
        value and limit) before anything is sent, then one FC16 write of HR 0..5."""
        words = encode_setpoint(mm)
        first, _ = span(Table.HOLDING_REGISTER)
        await self._write(f"platform setpoint {tuple(mm)} mm",
                          self._client.write_registers if self._client else None,
                          first, words)

    async def _write(self, what: str, method, address: int, value) -> None:
        """An operator's write (counted in ``writes``)."""
        await self._send(what, method, address, value)
        self.writes += 1

    async def _send(self, what: str, method, address: int, value) -> None:
        if method is None or not self.connected:
            raise DeviceFault(DEVICE, f"cannot write {what}: link to {self.host}:{self.port} "
                                      "down")
        try:
            rr = await self._timed(method, address, value, device_id=self.device_id)
        except ModbusException as exc:
            raise DeviceFault(DEVICE, f"no answer writing {what} ({exc})") from exc
        if rr.isError():
            raise DeviceFault(DEVICE, f"writing {what} refused: {_exception_text(rr)}")
