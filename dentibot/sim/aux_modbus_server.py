"""Auxiliary I/O PLC simulator: a pymodbus TCP server serving the DentiBot map over a World.

The datastore is a live view of the World, not a copy kept in sync: pymodbus 3.16's
``SimDevice(action=...)`` calls :meth:`AuxModbusServer._on_access` on every request before it
touches its registers; on a read the action writes the World's current state into the block
(so a response is never older than the request), on a write it decodes the block as it will be
after the write and applies it to the World (or refuses it). Nothing runs between requests and
the server never steps the World: a RealTimeStepper (or a lock-step owner) does.

What it mirrors (addresses in :mod:`dentibot.io.aux_registers`):

- discrete inputs / IR 3: ``world.pedal``, ``world.estop``;
- coils: ``world.indicators[name]`` for the names of the coil points (others are not mapped);
- holding registers: ``world.platform_mm`` (the commanded platform offset);
- IR 5..10, the platform's actual position: what the World applies to the phantom,
  ``world.platform_mm`` plus the patient-motion offset at ``world.t`` (see
  ``World.phantom_origin_0``);
- IR 2, heartbeat: ``world.steps`` modulo 65536, i.e. it advances as the World is stepped
  (500 per simulated second) and freezes when nobody steps the World, as a hung PLC's would.
- IR 4 bit 0 (moving): the motion offset differs between ``world.t - ts`` and ``world.t``;
  bit 1 (fault): the test hook :meth:`set_platform_fault`; bit 2 (setpoint rejected): latched
  by a refused setpoint write, cleared by the next accepted one; bit 3 (host lost): the host
  watchdog (HR 6-7, map 1.1) expired.

The host watchdog is the one thing that runs between requests: a task checks it every 10 ms
(real time, as a PLC's scan cycle would). Its time is the scan's: when this process's event
loop stalls (a garbage collection, a compilation, a starved CPU), the scan wakes late, and
the time beyond two scans is not counted, because a PLC on its own CPU would have gone on
reading the host's frames meanwhile; the host's feeds, held up by the same stall, would
otherwise trip a watchdog the real device would never trip. A host that stays silent while
the scan runs on time trips it within the watchdog time as ever. Once armed
(``watchdog_ms`` > 0), no new ``host_watchdog`` value for that long sets ``host_lost``,
switches the DRILLING lamp off and the FAULT lamp on, and holds the platform setpoint where it
is; the next new value clears ``host_lost`` (the lamps stay as they are until the host writes them). ``host_lost`` is also
a relay output: the callables in :attr:`AuxModbusServer.host_lost_outputs` are called with
True when it is set and False when it clears. In ``dentibot sim serve`` it opens the
handpiece drive's safe-torque-off input, in series with the emergency stop (the clinic's
safety relay chain), so that a dead host stops the file within the watchdog time even when
nothing else does (``docs/device-liveness.md``).

Unpleasant parts, as a real PLC: a setpoint outside the limits (or a half-written int32 that
decodes outside them) is refused with exception 3 (illegal data value) and leaves the World
alone; addresses outside the map answer exception 2; writes to the reserved coil bits 4..15
answer exception 2 (reads of them return 0); a request for another unit id gets exception 11
(gateway target failed to respond);
a frozen World freezes the heartbeat; ``close()`` drops every client connection.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Self

import structlog
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from dentibot.errors import ConfigError
from dentibot.io.aux_registers import (
    AXES,
    FUNCTION_TABLE,
    INDICATORS,
    SETPOINT_WORDS,
    Table,
    check_watchdog_ms,
    decode_registers,
    decode_setpoint,
    encode_bits,
    encode_inputs,
    encode_registers,
    points,
    span,
)
from dentibot.sim.world import World

log = structlog.get_logger(__name__)

#: The simulated PLC's scan period (s): the host watchdog is checked once per scan.
SCAN_S = 0.010


def _pack_bits(bits: list[bool]) -> list[int]:
    """Bits (address 0 first) -> 16-bit words, bit 0 in the LSB of word 0 (pymodbus layout)."""
    words = [0] * ((len(bits) + 15) // 16)
    for i, b in enumerate(bits):
        if b:
            words[i >> 4] |= 1 << (i & 15)
    return words


class AuxModbusServer:
    """The clinic's auxiliary-I/O PLC (pedal, e-stop, lamps, platform) over a World.

    Args:
        world: the World to mirror (read and commanded at the moment a request arrives).
        host: interface to bind (loopback by default).
        port: TCP port; 0 picks a free one. The bound port is :attr:`port` after ``start()``.
        device_id: Modbus unit id served.

    Counters: ``requests`` (by function code), ``refused`` (writes answered with an exception).
    """

    def __init__(self, world: World, host: str = "127.0.0.1", port: int = 5020,
                 device_id: int = 1) -> None:
        self.world = world
        self.host = host
        self.port = port
        self.device_id = device_id
        self.requests: dict[int, int] = {}
        self.refused = 0
        self.platform_fault = False
        self.setpoint_rejected = False
        #: host watchdog (map 1.1): time (ms, 0 = off), last value, expired
        self.watchdog_ms = 0
        self.host_watchdog = 0
        self.host_lost = False
        self.watchdog_expiries = 0
        #: scan time lost to stalls of this process's loop, not counted by the watchdog (s)
        self.stalled_s = 0.0
        #: the host-lost relay output: called with True when the watchdog expires, False
        #: when the host comes back (a new host_watchdog value)
        self.host_lost_outputs: list[Callable[[bool], None]] = []
        self._fed_at = 0.0
        self._server: ModbusTcpServer | None = None
        self._watchdog: asyncio.Task | None = None

    # ------------------------------------------------------------------ life cycle
    async def start(self) -> None:
        if self._server is not None:
            return
        blocks = []
        for table in (Table.COIL, Table.DISCRETE_INPUT, Table.HOLDING_REGISTER,
                      Table.INPUT_REGISTER):
            first, n = span(table)
            if table in (Table.COIL, Table.DISCRETE_INPUT):
                blocks.append([SimData(first, values=[False] * n, datatype=DataType.BITS)])
            else:
                blocks.append([SimData(first, values=[0] * n, datatype=DataType.REGISTERS)])
        device = SimDevice(self.device_id, simdata=tuple(blocks), action=self._on_access)
        # unit id 0 = "every other id": answered with exception 11, as a TCP gateway would
        others = SimDevice(0, simdata=tuple(blocks), action=self._other_unit)
        server = ModbusTcpServer([device, others], address=(self.host, self.port))
        try:
            await server.serve_forever(background=True)
        except RuntimeError as exc:             # pymodbus: "Could not start listen"
            await server.shutdown()
            raise ConfigError("aux_modbus_server.port", self.port,
                              f"a free TCP port on {self.host}", str(exc)) from None
        self._server = server
        self._watchdog = asyncio.create_task(self._watch_host(), name="aux-modbus-watchdog")
        self.port = server.transport.sockets[0].getsockname()[1]
        log.info("aux_modbus_server.started", host=self.host, port=self.port,
                 device_id=self.device_id)

    async def close(self) -> None:
        """Stop listening and drop every client; idempotent."""
        server, self._server = self._server, None
        if server is None:
            return
        task, self._watchdog = self._watchdog, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        await server.shutdown()
        # let the transports' connection_lost callbacks close the sockets and any request
        # already scheduled finish (it finds its transport gone and sends nothing)
        for _ in range(3):
            await asyncio.sleep(0)
        log.info("aux_modbus_server.closed", port=self.port)

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    # ------------------------------------------------------------------ test hooks
    def press_pedal(self, pressed: bool = True) -> None:
        """The clinician presses (or releases) the foot pedal."""
        self.world.pedal = bool(pressed)

    def set_estop(self, active: bool = True) -> None:
        """The emergency-stop button is pressed (or released and reset)."""
        self.world.estop = bool(active)

    def set_platform_fault(self, fault: bool = True) -> None:
        """The platform's controller reports (or clears) a drive fault."""
        self.platform_fault = bool(fault)

    # ------------------------------------------------------------------ host watchdog
    async def _watch_host(self) -> None:
        loop = asyncio.get_running_loop()
        scanned = loop.time()
        while True:
            await asyncio.sleep(SCAN_S)
            now = loop.time()
            stalled = now - scanned - 2 * SCAN_S    # the scan did not run (see the docstring)
            scanned = now
            if stalled > 0.0:
                self._fed_at += stalled
                self.stalled_s += stalled
            if (self.watchdog_ms and not self.host_lost
                    and now - self._fed_at > self.watchdog_ms / 1000.0):
                self.watchdog_expiries += 1
                self.world.indicators["drilling"] = False
                self.world.indicators["fault"] = True
                log.warning("aux_modbus_server.host_lost", watchdog_ms=self.watchdog_ms,
                            platform_held_mm=self.world.platform_mm)
                self._set_host_lost(True)

    def _set_host_lost(self, lost: bool) -> None:
        if lost == self.host_lost:
            return
        self.host_lost = lost
        for output in self.host_lost_outputs:
            try:
                output(lost)
            except Exception:                 # a PLC output never stops the scan
                log.exception("aux_modbus_server.host_lost_output_failed")

    def _feed(self, value: int, watchdog_ms: int) -> None:
        """A holding-register write: a new watchdog time arms it from now; a new
        ``host_watchdog`` value feeds it and clears ``host_lost``."""
        now = asyncio.get_running_loop().time()
        if watchdog_ms != self.watchdog_ms:
            self.watchdog_ms = watchdog_ms
            self._fed_at = now                 # armed (or re-timed) from now
        if value != self.host_watchdog:
            self.host_watchdog = value
            self._fed_at = now
            self._set_host_lost(False)

    # ------------------------------------------------------------------ World <-> image
    def platform_actual_mm(self) -> tuple[float, float, float]:
        """What the World applies: commanded offset plus the patient-motion offset now."""
        w = self.world
        off = w.motion.offset_mm(w.t)
        return tuple(w.platform_mm[i] + off[i] for i in range(3))

    def _moving(self) -> bool:
        w = self.world
        return w.motion.offset_mm(w.t) != w.motion.offset_mm(w.t - w.ts)

    def _bits_now(self, table: Table) -> list[bool]:
        w = self.world
        if table is Table.COIL:
            return encode_bits(table, {n: w.indicators.get(n, False) for n in INDICATORS})
        return encode_bits(table, {"pedal": w.pedal, "estop": w.estop,
                                   "platform_moving": self._moving(),
                                   "platform_fault": self.platform_fault})

    def _registers_now(self, table: Table) -> list[int]:
        w = self.world
        if table is Table.HOLDING_REGISTER:
            return encode_registers(table, {
                **{f"setpoint_{a}": v for a, v in zip(AXES, w.platform_mm, strict=True)},
                "host_watchdog": self.host_watchdog, "watchdog_ms": self.watchdog_ms})
        return encode_inputs(heartbeat=w.steps, pedal=w.pedal, estop=w.estop,
                             platform_mm=self.platform_actual_mm(),
                             platform_moving=self._moving(), platform_fault=self.platform_fault,
                             setpoint_rejected=self.setpoint_rejected, host_lost=self.host_lost)

    async def _on_access(self, fc: int, start: int, address: int, count: int,
                         registers: list[int], set_values) -> ExcCodes | None:
        """pymodbus SimDevice action: refresh the block from the World (read) or apply a
        write to the World. ``start`` is the address of ``registers[0]`` (for bit tables a
        16-bit word index); ``count`` is in registers (words for bit tables)."""
        self.requests[fc] = self.requests.get(fc, 0) + 1
        table = FUNCTION_TABLE[fc]
        bits = table in (Table.COIL, Table.DISCRETE_INPUT)
        image_bits = self._bits_now(table) if bits else None
        image = _pack_bits(image_bits) if bits else self._registers_now(table)
        if set_values is None:
            registers[0:len(image)] = image      # every block starts at address 0
            return None
        # a write: the image as it will be once pymodbus has stored the values
        _, n = span(table)
        if bits:
            new = list(image_bits)
            if address < 0 or address + len(set_values) > n:
                return self._refuse(fc, address, set_values, ExcCodes.ILLEGAL_ADDRESS,
                                    f"coils {n}..15 are reserved")
            new[address:address + len(set_values)] = [bool(v) for v in set_values]
            for p in points(table)[address:address + len(set_values)]:   # only those written
                self.world.indicators[p.name] = new[p.address]
            registers[0:len(image)] = _pack_bits(new)
            return None
        new = list(image)
        if address < 0 or address + len(set_values) > len(new):
            return self._refuse(fc, address, set_values, ExcCodes.ILLEGAL_ADDRESS,
                                f"holding registers end at {len(new) - 1}")
        new[address:address + len(set_values)] = list(set_values)
        values = decode_registers(table, new)
        try:
            ms = check_watchdog_ms(values["watchdog_ms"])
        except ConfigError as exc:
            return self._refuse(fc, address, set_values, ExcCodes.ILLEGAL_VALUE, str(exc))
        if address < SETPOINT_WORDS:            # the write touches the setpoint
            try:
                mm = decode_setpoint(new)
            except ConfigError as exc:
                self.setpoint_rejected = True
                return self._refuse(fc, address, set_values, ExcCodes.ILLEGAL_VALUE, str(exc))
            self.world.platform_mm = mm
            self.setpoint_rejected = False
        self._feed(values["host_watchdog"], ms)
        registers[0:len(image)] = image
        return None

    async def _other_unit(self, fc: int, *_args) -> ExcCodes:
        self.requests[fc] = self.requests.get(fc, 0) + 1
        return ExcCodes.GATEWAY_NO_RESPONSE

    def _refuse(self, fc: int, address: int, values, code: ExcCodes, why: str) -> ExcCodes:
        self.refused += 1
        log.warning("aux_modbus_server.write_refused", function_code=fc, address=address,
                    values=list(values), exc_code=int(code), reason=why)
        return code
