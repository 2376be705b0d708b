"""A simulated Maxon EPOS4 CANopen node on a python-can bus, over a World's handpiece.

:class:`Epos4Node` is a CANopen slave (CiA 301 + CiA 402) that exposes
``world.handpiece`` over the real protocol, so that :class:`dentibot.io.epos4.Epos4Driver` (or
any CANopen master) can drive it on python-can's ``virtual`` bus, or through
:class:`dentibot.sim.socketcand.SocketcandServer` from another process.

What it does (all framing from :mod:`dentibot.io.canopen_protocol`):

- NMT: boot-up message (heartbeat byte 0x00) at ``start()`` and after a reset, then
  PRE-OPERATIONAL; START / STOP / ENTER PRE-OPERATIONAL / RESET NODE / RESET COMMUNICATION.
  SDOs are served in PRE-OPERATIONAL and OPERATIONAL; PDOs (and SYNC answers) only in
  OPERATIONAL; EMCY in PRE-OPERATIONAL and OPERATIONAL. Leaving OPERATIONAL while the drive is
  enabled applies the abort connection option code 0x6007 (default 3: quick stop).
- Heartbeat producer: every 0x1017 ms (constructor ``heartbeat_period_s``; 0 = off).
- Heartbeat consumer (CiA 301, object 1016h): entry 0x1016:01 = producer node id << 16 |
  consumer time ms (power-on 0: off). Monitoring starts at the first heartbeat received from
  that node and restarts with each one; when none comes for the consumer time the node
  signals a heartbeat error -- error code 0x8130, error register bit "communication", EMCY
  -- and applies 0x6007 (CiA 402): 0 nothing more, 1 the fault reaction (the quick-stop ramp,
  then FAULT), 2 disable voltage at once, 3 quick stop (the quick-stop ramp, then 0x605A). The
  consumer watches again from the next heartbeat. Consumer time and node id are read back as
  written.
- Quick stop and fault reaction (CiA 402): the motor decelerates from its actual speed to 0
  on a ramp of 0x6085 (motor rpm/s, updated every millisecond), the power stage staying on;
  then FAULT (fault reaction) or what 0x605A says (quick stop: 6 stay in QUICK STOP ACTIVE,
  the power-on value, 2 switch on disabled). The World's handpiece follows the ramp through
  its own speed loop. Errors where the power stage cannot brake (STO) switch it off at once.
- Object dictionary: exactly :data:`~dentibot.io.canopen_protocol.OBJECTS` -- the CiA 301
  mandatory objects (device type 0x1000, error register 0x1001, identity 0x1018 with maxon's
  vendor id), heartbeat 0x1016/0x1017, PDO parameters 0x1400-0x1BFF, the EPOS4 objects the
  project uses and the CiA 402 objects python-canopen's ``BaseNode402`` uses, among them
  supported drive modes 0x6502 (bits of the modes implemented: profile position and profile
  velocity). Its electronic data sheet (CiA 306), :data:`EDS_PATH` (``dentibot/io/epos4.eds``),
  is rendered from the same table and power-on values by :func:`render_eds`.
- Expedited SDO server over that dictionary (aborts: no object 0x06020000, no sub
  0x06090011, read-only 0x06010002, length 0x06070010, bad value 0x06090030, segmented
  requests 0x05040001, PDO parameters while OPERATIONAL 0x08000022, mapping entries while
  sub 0 != 0 or the PDO is valid 0x06010000, unmappable 0x06040041, > 64 bits 0x06040042).
- PDOs per the configured mapping (0x1400/0x1600, 0x1800/0x1A00 ...): the node's *default*
  mapping differs from the project's, so a master has to configure it. TxPDOs with
  transmission type 0..240 are sent on every n-th SYNC with values read from the World at
  that moment; RxPDOs of type 0..240 take effect at the next SYNC, 254/255 at reception.
  RxPDOs of the wrong length: not processed, EMCY 0x8210 (CAN PDO length error) and FAULT
  (assumption: the EPOS4 treats its listed errors as device errors).
- CiA 402 state machine driven by the controlword exactly per
  :func:`~dentibot.io.canopen_protocol.apply_controlword` (illegal transitions ignored);
  profile velocity (3) -> ``handpiece.set_velocity(target / gear)``, profile position (1) ->
  ``handpiece.move_relative`` on the rising edge of controlword bit 4 (bit 6 relative, else
  absolute), set-point acknowledge in statusword bit 12 until bit 4 drops, target reached
  bit 10; halt (bit 8) stops. Only in OPERATION ENABLED; leaving it stops the handpiece
  (the world model has no coasting).
- Faults: EMCY + FAULT on :meth:`Epos4Node.inject_emcy`, on a lost host heartbeat (above),
  or when the safe torque off opens while the power stage is on (0x8A88 STO error;
  assumption). The STO input is open while the World's emergency stop is pressed or any
  source given to :meth:`Epos4Node.set_sto` holds it open (in ``dentibot sim serve``: the aux
  I/O's host-lost output, wired into the same safety chain). With STO open the drive refuses
  to switch on and stays in READY TO SWITCH ON (assumption). Fault reset (15) sends EMCY
  0x0000. The drive knows nothing of the file beyond its own motor: a fractured file is not
  a drive error (the controller detects it from torque and speed).

Scaling: velocity (rpm, motor side) = ``omega_rpm * gear``; position (inc) = ``pos_deg * gear
* counts_per_turn / 360`` wrapped into INTEGER32; current 0x30D1:01 (mA) = ``current_a *
1000``; torque actual 0x6077 (per mille of 0x6076) from the current and the torque constant.

Threading: frames are handed to the event loop (:class:`~dentibot.io.can_reader.LoopReader`),
so the World is only touched from the loop's thread, like
:class:`~dentibot.sim.timing.RealTimeStepper`. The node never steps the World. The bus is the
caller's: ``close()`` does not shut it down.
"""

from __future__ import annotations

import asyncio
import math
from fractions import Fraction
from pathlib import Path

import can
import structlog

from dentibot.errors import ConfigError, ProtocolError
from dentibot.io import canopen_protocol as co
from dentibot.io.canopen_protocol import (
    CW_FAULT_RESET,
    CW_HALT,
    CW_NEW_SETPOINT,
    CW_RELATIVE,
    HEARTBEAT_ERROR_CODE,
    PDO_COB_INVALID,
    QUICK_STOP_OPTIONS,
    SW_INTERNAL_LIMIT,
    SW_REMOTE,
    SW_SETPOINT_ACK,
    SW_SPEED_ZERO,
    SW_TARGET_REACHED,
    SW_VOLTAGE_ENABLED,
    AbortConnectionOption,
    Mode,
    NmtState,
    PdoLayout,
    State,
)
from dentibot.io.tasks import cancel_until_done
from dentibot.sim.canopen_node import BusAttached, SdoServerAbort, SimNode
from dentibot.sim.world import World

log = structlog.get_logger(__name__)

#: EMCY code when the safe torque off drops while the power stage is on (assumption).
STO_EMCY_CODE = 0x8A88
#: EMCY code of an RxPDO with the wrong length (CiA 301 "PDO not processed due to length").
PDO_LENGTH_EMCY_CODE = 0x8210
#: Device type 0x1000: profile 402 in the low word, 0x0002 (servo drive) in the high word, as
#: an EPOS4 reports it.
DEVICE_TYPE = 0x0002_0192
#: Identity object 0x1018 (CiA 301): maxon motor ag's CiA vendor id, and the product code and
#: revision number (high word: firmware version 0x0170) of an EPOS4 Module 50/15 as in maxon's
#: own device configuration file for it; the serial number is the simulator's own.
VENDOR_ID = 0x0000_00FB
PRODUCT_CODE = 0x6552_0000
REVISION_NUMBER = 0x0170_0000
SERIAL_NUMBER = 0x0000_0001
#: Constructor defaults: producer heartbeat time 0x1017 (ms) and main sensor resolution
#: 0x3000:05 (increments per motor turn: a 512-pulse quadrature encoder, an assumption for the
#: handpiece motor).
DEFAULT_HEARTBEAT_MS = 100
DEFAULT_COUNTS_PER_TURN = 2048
#: Velocity window for "target reached" in profile velocity mode, and the "speed zero"
#: threshold, both in motor rpm (assumptions; the EPOS4 has its own parameters).
VELOCITY_WINDOW_RPM = 20
SPEED_ZERO_RPM = 10
#: States in which the drive brakes the motor on the quick-stop ramp, power stage on.
_BRAKING = frozenset({State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE})
#: States in which the power stage is on (statusword bit 4, voltage enabled).
_POWERED = frozenset({State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED,
                      State.QUICK_STOP_ACTIVE, State.FAULT_REACTION_ACTIVE})
#: The modes of operation the node implements, and their bits in 0x6502 (CiA 402).
_SUPPORTED_MODES = frozenset({Mode.PROFILE_POSITION, Mode.PROFILE_VELOCITY})
SUPPORTED_DRIVE_MODES = sum(1 << co.SUPPORTED_DRIVE_MODE_BITS[m] for m in _SUPPORTED_MODES)
#: Objects whose writing (SDO or RxPDO) feeds the drive logic.
_DRIVE_OBJECTS = frozenset({"controlword", "modes_of_operation", "target_velocity",
                            "target_position", "profile_velocity"})
#: Quick-stop ramp update period (s): the drive's profile generator, as seen by the World.
RAMP_STEP_S = 0.001
#: Power-on values of the quick-stop / fault-reaction objects (CiA 402 / assumption):
#: 0x6007 3 quick stop, 0x605A 6 stay in QUICK STOP ACTIVE, 0x6085 10,000 motor rpm/s.
POWER_ON_ABORT_CONNECTION = int(AbortConnectionOption.QUICK_STOP)
POWER_ON_QUICK_STOP_OPTION = 6
POWER_ON_QUICK_STOP_DECEL = 10_000
#: Power-on values that do not depend on the World or the constructor (the EDS's
#: DefaultValue): application objects (reset node) ...
POWER_ON_APPLICATION: dict[str, int] = {
    "controlword": 0,
    "abort_connection_option_code": POWER_ON_ABORT_CONNECTION,
    "quick_stop_option_code": POWER_ON_QUICK_STOP_OPTION,
    "modes_of_operation": 0,
    "target_torque": 0,
    "target_position": 0,
    "profile_acceleration": 10_000,
    "profile_deceleration": 10_000,
    "quick_stop_deceleration": POWER_ON_QUICK_STOP_DECEL,
    "target_velocity": 0,
    "supported_drive_modes": SUPPORTED_DRIVE_MODES,
}
#: ... and communication objects (reset communication), PDO parameters aside.
POWER_ON_COMMUNICATION: dict[str, int] = {
    "device_type": DEVICE_TYPE,
    "consumer_heartbeat_time": 0,
    "vendor_id": VENDOR_ID,
    "product_code": PRODUCT_CODE,
    "revision_number": REVISION_NUMBER,
    "serial_number": SERIAL_NUMBER,
}
#: The default PDO mapping, as an EPOS4's (deliberately not the project's): RxPDO1 =
#: controlword, RxPDO2 = controlword + mode, TxPDO1 = statusword, TxPDO2 = statusword + mode
#: display; PDO 3 and 4 not valid and empty. RxPDOs asynchronous (255), TxPDOs synchronous (1).
DEFAULT_PDO_MAPPING: dict[tuple[str, int], tuple[str, ...]] = {
    ("rx", 1): ("controlword",),
    ("rx", 2): ("controlword", "modes_of_operation"),
    ("tx", 1): ("statusword",),
    ("tx", 2): ("statusword", "modes_of_operation_display"),
}
DEFAULT_TRANSMISSION_TYPE = {"rx": 255, "tx": 1}


def default_pdo_parameters(node_id: int) -> dict[tuple[int, int], int]:
    """Power-on values of the PDO communication and mapping parameters (0x1400-0x1BFF) of a
    node ``node_id`` (0: COB-IDs without the node id, as an EDS writes them relative to
    $NODEID)."""
    out: dict[tuple[int, int], int] = {}
    for direction, comm0 in (("rx", 0x1400), ("tx", 0x1800)):
        for n in range(1, 5):
            comm, mapping = comm0 + n - 1, comm0 + 0x200 + n - 1
            fn = f"{'RPDO' if direction == 'rx' else 'TPDO'}{n}"
            names = DEFAULT_PDO_MAPPING.get((direction, n), ())
            cob = co.COB_BASE[fn] + node_id | (0 if names else PDO_COB_INVALID)
            if direction == "tx":
                cob |= co.PDO_COB_NO_RTR
            out[(comm, 1)] = cob
            out[(comm, 2)] = DEFAULT_TRANSMISSION_TYPE[direction]
            if direction == "tx":
                out[(comm, 3)] = 0
                out[(comm, 5)] = 0
            out[(mapping, 0)] = len(names)
            for s in range(1, 9):
                out[(mapping, s)] = 0
            for s, nm in enumerate(names, 1):
                out[(mapping, s)] = co.obj(nm).mapping_word
    return out


class Epos4Node(SimNode, BusAttached):
    """A simulated EPOS4 (CANopen node ``node_id``) on ``bus`` over ``world.handpiece``.

    Args:
        world: the World whose handpiece the drive turns (never stepped here).
        bus: a python-can bus (e.g. ``virtual`` channel); owned by the caller.
        node_id: CANopen node id 1..127.
        heartbeat_period_s: default producer heartbeat time 0x1017 (s; 0 = off). 0.1 s.
            The consumer 0x1016:01 is off at power-on: the master configures it.
        encoder_counts_per_turn: main sensor resolution 0x3000:05 (increments per motor turn).
            2048 = a 512-pulse quadrature encoder (assumption for the handpiece motor).
        name: device name in logs.
    """

    def __init__(self, world: World, bus: can.BusABC, node_id: int = 1, *,
                 heartbeat_period_s: float = DEFAULT_HEARTBEAT_MS / 1000,
                 encoder_counts_per_turn: int = DEFAULT_COUNTS_PER_TURN,
                 name: str = "epos4-sim") -> None:
        super().__init__(node_id)
        if not (math.isfinite(heartbeat_period_s) and 0 <= heartbeat_period_s <= 65.535):
            raise ConfigError("epos4_node.heartbeat_period_s", heartbeat_period_s,
                              "0 (off) .. 65.535 s")
        if not (isinstance(encoder_counts_per_turn, int) and encoder_counts_per_turn > 0):
            raise ConfigError("epos4_node.encoder_counts_per_turn", encoder_counts_per_turn,
                              "a positive integer (increments per motor turn)")
        self.world = world
        self.bus = bus
        self.name = name
        self.heartbeat_period_s = float(heartbeat_period_s)
        self.counts_per_turn = encoder_counts_per_turn
        hp = world.handpiece.p
        self.gear_ratio = float(hp.gear_ratio)
        self._inc_per_file_deg = self.gear_ratio * self.counts_per_turn / 360.0
        #: set True to make the node deaf and mute (a cut cable): no answers, no heartbeat.
        self.muted = False
        #: set True (:meth:`lose_output`) for a power stage that lost its supply: the motor
        #: coasts, the drive still reports OPERATION ENABLED and sends no EMCY.
        self.output_lost = False
        # counters
        self.syncs_received = 0
        self.syncs_answered = 0      # SYNCs at which at least one TxPDO was sent
        self.tpdos_sent = 0
        self.rpdos_received = 0
        self.nmt_commands = 0
        self.emcy_sent = 0
        self.heartbeats_sent = 0
        self.errors = 0              # frames that broke the protocol (counted, not processed)
        self.pdo_length_errors = 0
        self.send_errors = 0
        self.ignored_modes = 0
        self.setpoints_accepted = 0  # profile position set-points taken (bit 4 edges)
        self.transitions: list[str] = []    # CiA 402 transition numbers taken, in order
        # state
        self.state = State.SWITCH_ON_DISABLED
        self._od: dict[tuple[int, int], int] = {}
        self._rx_layouts: dict[int, PdoLayout | None] = {}
        self._tx_layouts: dict[int, PdoLayout | None] = {}
        self._rx_cobs: dict[int, int] = {}
        self._pending_rpdo: dict[int, tuple[int, ...]] = {}
        self._sync_count = 0
        self._mode_display = 0
        self._sp_ack = False
        self._internal_limit = False
        self._error_code = 0
        self._error_register = 0
        self.heartbeats_consumed = 0     # heartbeats received from the watched producer
        self.heartbeat_errors = 0        # consumer time expired
        self._consumer: tuple[int, float] | None = None    # (producer node, seconds)
        self._consumer_timer: asyncio.TimerHandle | None = None
        self._sto_open: set[str] = set()
        self._ramp_task: asyncio.Task | None = None
        self._ramp_then: State | None = None
        self._hb_task: asyncio.Task | None = None
        self._started = False
        self._closed = False
        self._reset_application()
        self._reset_communication()
        self._getters = {
            "statusword": self._statusword,
            "velocity_actual": self._velocity_actual,
            "position_actual": self._position_actual,
            "current_actual_averaged": self._current_ma,
            "current_actual": self._current_ma,
            "torque_actual": self._torque_actual,
            "modes_of_operation_display": lambda: self._mode_display,
            "error_code": lambda: self._error_code,
            "error_register": lambda: self._error_register,
            "sto_inputs": lambda: 0x00 if self.sto_active else 0x03,
        }

    # ------------------------------------------------------------------ lifecycle
    async def start(self) -> None:
        """Attach to the bus (read in this event loop), send the boot-up message, enter
        PRE-OPERATIONAL and start the heartbeat producer."""
        if self._started:
            return
        if self._closed:
            raise ConfigError("epos4_node", "closed", "a node that has not been closed")
        loop = asyncio.get_running_loop()
        self._attach(self.bus, self._on_message)
        self._started = True
        self.boot()
        self._hb_task = loop.create_task(self._heartbeat_loop(), name=f"{self.name}-heartbeat")

    async def close(self) -> None:
        """Stop the heartbeat and detach from the bus (idempotent; the bus stays open)."""
        if self._closed:
            return
        self._closed = True
        self._disarm_consumer()
        await self._cancel_ramp()
        task, self._hb_task = self._hb_task, None
        await cancel_until_done(task)
        self._detach()

    # ------------------------------------------------------------------ public helpers
    def inject_emcy(self, code: int, register: int | None = None,
                    manufacturer: bytes = bytes(5)) -> None:
        """Raise a device error: EMCY ``code`` (register from the code's class unless given)
        and the drive goes to FAULT (through fault reaction active), stopping the motor."""
        if not 0 < code <= 0xFFFF:
            raise ConfigError("epos4_node.emcy_code", code, "1..0xFFFF (0 means no error)")
        self._fault(code, register, manufacturer)

    def lose_output(self, lost: bool = True) -> None:
        """The motor loses its power (a supply or motor cable fault the drive does not
        detect): it coasts to rest and follows no command, while the statusword still says
        operation enabled and no EMCY goes out. ``lose_output(False)`` restores it."""
        self.output_lost = lost
        if lost:
            self.world.handpiece.stop()

    def set_sto(self, source: str, open_: bool) -> None:
        """Open (or close) the safe-torque-off input on behalf of ``source`` (a name, e.g.
        the aux I/O's host-lost relay). The input is open while any source holds it open or
        the World's emergency stop is pressed; opening it while the power stage is on is an
        STO error (FAULT, the power stage off at once). Closing it again does not clear the
        fault: the master resets it."""
        if open_:
            self._sto_open.add(source)
            log.warning("epos4 sim STO open", node=self.node_id, source=source)
            self._poll_world()
        else:
            self._sto_open.discard(source)

    @property
    def sto_active(self) -> bool:
        """The STO input is open (the power stage cannot be switched on)."""
        return bool(self.world.estop or self._sto_open)

    @property
    def consumer(self) -> tuple[int, float] | None:
        """(watched node id, consumer time s) from 0x1016:01, or None when off."""
        return self._consumer

    def value(self, name: str) -> int:
        """Current value of object ``name`` as an SDO upload would return it."""
        return self._read(co.obj(name))

    @property
    def rx_layouts(self) -> dict[int, PdoLayout | None]:
        """Configured RxPDO layouts by PDO number (None: no entries mapped)."""
        return dict(self._rx_layouts)

    @property
    def tx_layouts(self) -> dict[int, PdoLayout | None]:
        return dict(self._tx_layouts)

    @property
    def error_code(self) -> int:
        return self._error_code

    @property
    def object_addresses(self) -> frozenset[tuple[int, int]]:
        """Every (index, sub) the node's SDO server answers (its object dictionary)."""
        return frozenset(self._od) | {co.obj(n).address for n in self._getters}

    # ------------------------------------------------------------------ object dictionary
    def _reset_application(self) -> None:
        """Power-on values of the application objects (0x2000-0x9FFF); drive disabled."""
        hp = self.world.handpiece
        p = hp.p
        gear = Fraction(self.gear_ratio).limit_denominator(1000)
        nominal_ma = round(p.current_limit_a * 1000)   # assumption: nominal = limit current
        km_unm = round(p.km_mnm_per_a * 1000)
        for name, value in {
            **POWER_ON_APPLICATION,
            "axis_main_sensor_resolution": self.counts_per_turn,
            "motor_nominal_current": nominal_ma,
            "motor_output_current_limit": nominal_ma,
            "motor_torque_constant": km_unm,
            "gear_reduction_numerator": gear.numerator,
            "gear_reduction_denominator": gear.denominator,
            "motor_rated_torque": round(km_unm * nominal_ma / 1000),
            "profile_velocity": round(p.move_rpm * self.gear_ratio),
        }.items():
            self._od[co.obj(name).address] = value
        for name in co.HIGHEST_SUB_OBJECTS:          # sub-index 0 of records and arrays
            o = co.obj(name)
            self._od[o.address] = co.HIGHEST_SUB_INDEX[o.index]
        self._mode_display = 0
        self._sp_ack = False
        self._internal_limit = False
        self._error_code = self._error_register = 0
        self._stop_ramp_now()
        if self.state is not State.SWITCH_ON_DISABLED:
            self._set_state(State.SWITCH_ON_DISABLED, "reset")
        hp.stop()
        hp.enabled = False
        hp.set_current_limit(nominal_ma / 1000.0)     # 0x3001:02 at its power-on value

    def _reset_communication(self) -> None:
        """Power-on values of the communication objects (0x1000-0x1FFF), the PDO parameters
        those of :data:`DEFAULT_PDO_MAPPING` (deliberately not the project's mapping)."""
        od = self._od
        for name, value in {
            **POWER_ON_COMMUNICATION,
            "producer_heartbeat_time": round(self.heartbeat_period_s * 1000),
        }.items():
            od[co.obj(name).address] = value
        od.update(default_pdo_parameters(self.node_id))
        for direction in ("rx", "tx"):
            for n in range(1, 5):
                self._rebuild_layout(direction, n)
        self._configure_consumer()
        self._pending_rpdo.clear()
        self._sync_count = 0

    def _rebuild_layout(self, direction: str, n: int) -> None:
        comm = (0x1400 if direction == "rx" else 0x1800) + n - 1
        mapping = comm + 0x200
        count = self._od[(mapping, 0)]
        words = [self._od[(mapping, s)] for s in range(1, count + 1)]
        layout = PdoLayout.from_words(words, direction) if words else None
        if direction == "rx":
            self._rx_layouts[n] = layout
            self._rx_cobs = {
                self._od[(0x1400 + k - 1, 1)] & 0x7FF: k for k in range(1, 5)
                if not self._od[(0x1400 + k - 1, 1)] & PDO_COB_INVALID
            }
        else:
            self._tx_layouts[n] = layout

    def _read(self, o: co.OdObject) -> int:
        getter = self._getters.get(o.name)
        if getter is not None:
            return int(getter())
        return self._od[o.address]

    # ------------------------------------------------------------------ World -> objects
    def _velocity_actual(self) -> int:
        return round(self.world.handpiece.omega_rpm * self.gear_ratio)

    def _position_actual(self) -> int:
        return co.wrap_i32(round(self.world.handpiece.pos_deg * self._inc_per_file_deg))

    def _current_ma(self) -> int:
        return round(self.world.handpiece.current_a * 1000.0)

    def _torque_actual(self) -> int:
        rated_unm = self._od[co.obj("motor_rated_torque").address] or 1
        km_unm = self._od[co.obj("motor_torque_constant").address]
        per_mille = self.world.handpiece.current_a * km_unm / rated_unm * 1000.0
        return max(-32768, min(32767, round(per_mille)))

    def _statusword(self) -> int:
        st = self.state
        sw = co.STATE_STATUSWORD[st] | SW_REMOTE
        if st in _POWERED:
            sw |= SW_VOLTAGE_ENABLED
        if self._internal_limit:
            sw |= SW_INTERNAL_LIMIT
        if st is State.OPERATION_ENABLED:
            hp = self.world.handpiece
            if self._mode_display == Mode.PROFILE_POSITION:
                if self._sp_ack:
                    sw |= SW_SETPOINT_ACK
                if hp.mode == "pos" and hp.move_done:
                    sw |= SW_TARGET_REACHED
            elif self._mode_display == Mode.PROFILE_VELOCITY:
                g = self.gear_ratio
                if abs(hp.omega_rpm - hp.cmd_rpm) * g <= VELOCITY_WINDOW_RPM:
                    sw |= SW_TARGET_REACHED
                if abs(hp.omega_rpm) * g <= SPEED_ZERO_RPM:
                    sw |= SW_SPEED_ZERO
        return sw

    # ------------------------------------------------------------------ bus I/O
    def _send(self, can_id: int, data: bytes) -> None:
        self._send_frame(can_id, data, "epos4 sim send failed", node=self.node_id)

    def _on_message(self, msg: can.Message) -> None:
        if self._closed or msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        if self.muted:
            return
        cid = msg.arbitration_id
        data = bytes(msg.data)
        try:
            consumer = self._consumer
            if consumer is not None and cid == co.COB_BASE["HEARTBEAT"] + consumer[0]:
                self._on_consumed_heartbeat(data)
            elif cid == co.COB_BASE["NMT"]:
                self._on_nmt(data)
            elif cid == co.COB_BASE["SYNC"]:
                self._on_sync(data)
            elif cid == co.COB_BASE["SDO_RX"] + self.node_id:
                self.on_sdo(data)
            elif cid in self._rx_cobs:
                self._on_rpdo(self._rx_cobs[cid], data)
        except ProtocolError as exc:
            self.errors += 1
            log.warning("epos4 sim bad frame", node=self.node_id, cob_id=hex(cid),
                        data=data.hex(), error=str(exc))

    # ------------------------------------------------------------------ NMT, heartbeat
    def boot(self) -> None:
        super().boot()
        log.info("epos4 sim boot-up", node=self.node_id)

    def _on_nmt(self, data: bytes) -> None:
        cmd, node = co.decode_nmt(data)
        if node not in (0, self.node_id):
            return
        self.nmt_commands += 1
        self.on_nmt(cmd)

    def _on_reset_node(self) -> None:
        self._reset_application()
        self._reset_communication()

    def _on_reset_communication(self) -> None:
        self._leave_operational()
        self._reset_communication()

    def _leave_operational(self) -> None:
        """NMT takes an enabled node out of OPERATIONAL: an abort connection event (CiA 402,
        0x6007); not an error in itself, so no EMCY unless the option is "fault"."""
        if self.nmt_state is not NmtState.OPERATIONAL:
            return
        if self.state not in (State.OPERATION_ENABLED, State.SWITCHED_ON):
            return
        self._abort_connection(None)

    def _abort_connection(self, error_code: int | None) -> None:
        """Apply the abort connection option code 0x6007 (CiA 402). ``error_code``: the
        communication error behind the event (0x8130 for a lost heartbeat), signalled by EMCY
        whatever the option; None for an NMT-commanded exit."""
        raw = self._od[co.obj("abort_connection_option_code").address]
        try:
            option = AbortConnectionOption(raw)
        except ValueError:                      # manufacturer-specific values: act as fault
            option = AbortConnectionOption.FAULT
        if option is AbortConnectionOption.FAULT:
            self._fault(error_code or HEARTBEAT_ERROR_CODE)
            return
        if error_code is not None:
            self._error_code = error_code
            self._error_register = co.error_register_for(error_code)
            self._send_emcy(error_code, self._error_register)
        st = self.state
        if option is AbortConnectionOption.DISABLE_VOLTAGE:
            if st in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE, State.SWITCHED_ON,
                      State.READY_TO_SWITCH_ON):
                self._power_off(State.SWITCH_ON_DISABLED, "9 (abort connection)")
        elif option is AbortConnectionOption.QUICK_STOP:
            if st is State.OPERATION_ENABLED:
                self._quick_stop("11 (abort connection)")
            elif st in (State.SWITCHED_ON, State.READY_TO_SWITCH_ON):
                self._set_state(State.SWITCH_ON_DISABLED, "10 (abort connection)")

    # ------------------------------------------------------------------ heartbeat consumer
    def _configure_consumer(self) -> None:
        """(Re)read 0x1016:01; monitoring of the producer starts at its next heartbeat."""
        self._disarm_consumer()
        word = self._od[co.obj("consumer_heartbeat_time").address]
        if co.consumer_entry_active(word):
            node, ms = co.decode_consumer_heartbeat(word)
            self._consumer = (node, ms / 1000.0)
            log.info("epos4 sim heartbeat consumer", node=self.node_id, producer=node,
                     consumer_ms=ms)
        else:
            self._consumer = None

    def _disarm_consumer(self) -> None:
        if self._consumer_timer is not None:
            self._consumer_timer.cancel()
            self._consumer_timer = None

    def _on_consumed_heartbeat(self, data: bytes) -> None:
        co.decode_heartbeat(data)               # a malformed frame is not a heartbeat
        if self._consumer is None or self.nmt_state is NmtState.BOOT_UP:
            return
        self.heartbeats_consumed += 1
        self._disarm_consumer()
        loop = asyncio.get_running_loop()
        self._consumer_timer = loop.call_later(self._consumer[1], self._consumer_expired)

    def _consumer_expired(self) -> None:
        """No heartbeat from the watched producer for the consumer time (CiA 301 heartbeat
        event): EMCY 0x8130 and the abort connection option code."""
        self._consumer_timer = None
        if self._closed or self._consumer is None or self.nmt_state is NmtState.BOOT_UP:
            return
        self.heartbeat_errors += 1
        log.warning("epos4 sim heartbeat lost", node=self.node_id, producer=self._consumer[0],
                    consumer_ms=round(self._consumer[1] * 1000), state=self.state.value)
        self._poll_world()
        self._abort_connection(HEARTBEAT_ERROR_CODE)

    async def _heartbeat_loop(self) -> None:
        while True:
            period = self._od[co.obj("producer_heartbeat_time").address] / 1000.0
            if period <= 0:
                await asyncio.sleep(0.05)
                continue
            await asyncio.sleep(period)
            self._poll_world()
            if not self.muted and self.nmt_state is not NmtState.BOOT_UP:
                self.send_heartbeat()
                self.heartbeats_sent += 1

    # ------------------------------------------------------------------ SDO server
    def _sdo_aborted(self, req: co.SdoFrame, code: int) -> None:
        log.info("epos4 sim SDO abort", node=self.node_id, index=hex(req.index),
                 sub=req.sub, code=hex(code), meaning=co.sdo_abort_meaning(code))

    def _lookup(self, index: int, sub: int) -> co.OdObject:
        o = co.OBJECTS_BY_ADDRESS.get((index, sub))
        if o is not None and (o.name in self._getters or o.address in self._od):
            return o
        if any(i == index for i, _ in self._od) or any(
                co.obj(n).index == index for n in self._getters):
            raise SdoServerAbort(0x0609_0011)
        raise SdoServerAbort(0x0602_0000)

    def _write_sdo(self, o: co.OdObject, value: int) -> None:
        if 0x1400 <= o.index <= 0x1BFF:
            self._write_pdo_parameter(o, value)
            return
        if o.name == "consumer_heartbeat_time":
            node, ms = co.decode_consumer_heartbeat(value)
            if ms and node == self.node_id:
                raise SdoServerAbort(0x0604_0043)  # watching itself: parameter incompatibility
            self._od[o.address] = value
            self._configure_consumer()
            return
        if o.name == "motor_output_current_limit":
            nominal = self._od[co.obj("motor_nominal_current").address]
            if not 0 < value <= nominal:
                raise SdoServerAbort(0x0609_0031 if value > nominal else 0x0609_0032)
            self._od[o.address] = value
            self.world.handpiece.set_current_limit(value / 1000.0)   # the current controller
            return
        if o.name == "abort_connection_option_code" and value not in (0, 1, 2, 3):
            raise SdoServerAbort(0x0609_0030)
        if o.name == "quick_stop_option_code" and value not in QUICK_STOP_OPTIONS:
            raise SdoServerAbort(0x0609_0030)
        prev_cw = self._od[co.obj("controlword").address]
        self._od[o.address] = value
        if o.name in _DRIVE_OBJECTS:
            self._drive_update(prev_cw)

    def _write_pdo_parameter(self, o: co.OdObject, value: int) -> None:
        if self.nmt_state is NmtState.OPERATIONAL:
            raise SdoServerAbort(0x0800_0022)  # configure PDOs in PRE-OPERATIONAL (EPOS4)
        index, sub = o.address
        is_map = index in range(0x1600, 0x1604) or index in range(0x1A00, 0x1A04)
        direction = "rx" if index < 0x1800 else "tx"
        comm = index - 0x200 if is_map else index
        n = comm - (0x1400 if direction == "rx" else 0x1800) + 1
        valid = not self._od[(comm, 1)] & PDO_COB_INVALID
        if not is_map:
            if sub == 1:
                old = self._od[(comm, 1)]
                if valid and not value & PDO_COB_INVALID and (value & 0x7FF) != (old & 0x7FF):
                    raise SdoServerAbort(0x0609_0030)  # change the COB-ID only while invalid
                if value & 0x7FF == 0:
                    raise SdoServerAbort(0x0609_0030)
            elif sub == 2 and not (value <= 240 or value in (254, 255)):
                raise SdoServerAbort(0x0609_0030)
            self._od[o.address] = value
            self._rebuild_layout(direction, n)
            return
        if valid:
            raise SdoServerAbort(0x0601_0000)   # mapping only while the PDO is not valid
        if sub == 0:
            if value > 8:
                raise SdoServerAbort(0x0609_0031)
            words = [self._od[(index, s)] for s in range(1, value + 1)]
            try:
                PdoLayout.from_words(words, direction)
            except ConfigError as exc:
                raise SdoServerAbort(0x0604_0042 if "64 bits" in str(exc)
                                     else 0x0604_0041) from None
            self._od[o.address] = value
            self._rebuild_layout(direction, n)
            return
        if self._od[(index, 0)] != 0:
            raise SdoServerAbort(0x0601_0000)   # set sub 0 to 0 before changing entries
        try:
            PdoLayout.from_words([value], direction)
        except ConfigError:
            raise SdoServerAbort(0x0604_0041) from None
        self._od[o.address] = value

    # ------------------------------------------------------------------ PDO, SYNC
    def _on_rpdo(self, n: int, data: bytes) -> None:
        if self.nmt_state is not NmtState.OPERATIONAL:
            return
        layout = self._rx_layouts.get(n)
        if layout is None:
            return
        self.rpdos_received += 1
        if len(data) != layout.size:
            self.pdo_length_errors += 1
            self.errors += 1
            log.warning("epos4 sim RxPDO length error", node=self.node_id, pdo=n,
                        got=len(data), expected=layout.size)
            self._fault(PDO_LENGTH_EMCY_CODE)
            return
        values = layout.unpack(data, f"RxPDO{n}")
        if self._od[(0x1400 + n - 1, 2)] <= 240:
            self._pending_rpdo[n] = values      # synchronous: acts at the next SYNC
        else:
            self._apply_rpdo(layout, values)

    def _apply_rpdo(self, layout: PdoLayout, values: tuple[int, ...]) -> None:
        prev_cw = self._od[co.obj("controlword").address]
        for o, v in zip(layout.objects, values, strict=True):
            self._od[o.address] = v
        self._drive_update(prev_cw)

    def _on_sync(self, data: bytes) -> None:
        co.decode_sync(data)
        self.syncs_received += 1
        if self.nmt_state is not NmtState.OPERATIONAL:
            return
        self._poll_world()
        if self._pending_rpdo:
            pending, self._pending_rpdo = self._pending_rpdo, {}
            for n, values in sorted(pending.items()):
                layout = self._rx_layouts.get(n)
                if layout is not None and len(layout.objects) == len(values):
                    self._apply_rpdo(layout, values)
        self._sync_count += 1
        sent = False
        for n in range(1, 5):
            layout = self._tx_layouts.get(n)
            comm = 0x1800 + n - 1
            cob = self._od[(comm, 1)]
            ttype = self._od[(comm, 2)]
            if layout is None or cob & PDO_COB_INVALID or ttype > 240:
                continue
            if self._sync_count % max(ttype, 1):
                continue
            values = [self._read(o) for o in layout.objects]
            self._send(cob & 0x7FF, layout.pack(values, f"TxPDO{n}"))
            self.tpdos_sent += 1
            sent = True
        if sent:
            self.syncs_answered += 1

    # ------------------------------------------------------------------ CiA 402 drive
    def _set_state(self, new: State, transition: str | None, *,
                   braking: bool = False) -> None:
        """Enter ``new``. Leaving OPERATION ENABLED stops the motor at once and switches the
        power stage off, unless ``braking``: then a quick-stop ramp brings it to rest first
        (QUICK STOP ACTIVE, FAULT REACTION ACTIVE), and the power stage goes off when the
        drive leaves those states for one without power."""
        old = self.state
        if new is old:
            return
        self.state = new
        if transition:
            self.transitions.append(transition)
        hp = self.world.handpiece
        if new not in _BRAKING and self._ramp_task is not None:
            self._stop_ramp_now()                # left a braking state another way
        if old is State.OPERATION_ENABLED:
            self._sp_ack = False
            if not braking:
                hp.stop()
                hp.enabled = False
        elif old in _BRAKING and new is not State.OPERATION_ENABLED and new not in _BRAKING:
            hp.stop()
            hp.enabled = False
        if new is State.OPERATION_ENABLED:
            hp.enabled = True
            self._enter_mode()
        log.debug("epos4 sim state", node=self.node_id, old=old.value, new=new.value,
                  transition=transition)

    # ------------------------------------------------------------------ quick-stop ramp
    def _quick_stop(self, transition: str) -> None:
        """CiA 402 quick stop from OPERATION ENABLED: QUICK STOP ACTIVE, the ramp, then what
        0x605A says."""
        self._set_state(State.QUICK_STOP_ACTIVE, transition, braking=True)
        self._start_ramp()

    def _power_off(self, new: State, transition: str) -> None:
        """Disable voltage: the power stage off at once, no ramp."""
        self._stop_ramp_now()
        self._set_state(new, transition)
        self.world.handpiece.stop()
        self.world.handpiece.enabled = False

    def _decel_file_rpm_s(self) -> float:
        return self._od[co.obj("quick_stop_deceleration").address] / self.gear_ratio

    def _start_ramp(self) -> None:
        """Decelerate from the actual speed at 0x6085; a ramp already running goes on."""
        if self._ramp_task is not None and not self._ramp_task.done():
            return
        hp = self.world.handpiece
        decel = self._decel_file_rpm_s()
        v0 = hp.omega_rpm
        if decel <= 0 or abs(v0) * self.gear_ratio < SPEED_ZERO_RPM:
            hp.stop()
            self._ramp_done()
            return
        self._ramp_task = asyncio.get_running_loop().create_task(
            self._ramp(v0, decel), name=f"{self.name}-quick-stop-ramp")

    async def _ramp(self, v0: float, decel: float) -> None:
        loop = asyncio.get_running_loop()
        hp = self.world.handpiece
        t0 = loop.time()
        sign = 1.0 if v0 > 0 else -1.0
        limit = hp.p.max_rpm
        try:
            while (v := abs(v0) - decel * (loop.time() - t0)) > 0:
                hp.set_velocity(sign * min(v, limit))
                await asyncio.sleep(RAMP_STEP_S)
        except asyncio.CancelledError:
            return                               # stopped by _stop_ramp_now / close
        self._ramp_task = None
        hp.stop()
        self._ramp_done()

    def _ramp_done(self) -> None:
        """The motor is at rest: the fault reaction ends in FAULT; a quick stop stays or goes
        to switch on disabled per 0x605A."""
        if self.state is State.FAULT_REACTION_ACTIVE:
            self._set_state(State.FAULT, "14")
        elif self.state is State.QUICK_STOP_ACTIVE:
            then = QUICK_STOP_OPTIONS.get(
                self._od[co.obj("quick_stop_option_code").address], State.SWITCH_ON_DISABLED)
            if then is not None:
                self._set_state(then, "12 (quick stop done)")

    def _stop_ramp_now(self) -> None:
        task, self._ramp_task = self._ramp_task, None
        if task is not None and not task.done():
            task.cancel()
            self.world.handpiece.stop()

    async def _cancel_ramp(self) -> None:
        task, self._ramp_task = self._ramp_task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    def _drive_update(self, prev_cw: int) -> None:
        od = self._od
        cw = od[co.obj("controlword").address]
        self._poll_world()
        mode = od[co.obj("modes_of_operation").address]
        mode_changed = mode != self._mode_display
        if mode_changed:
            if mode in _SUPPORTED_MODES:
                self._mode_display = mode
            else:
                self.ignored_modes += 1
                mode_changed = False
        new, tr = co.apply_controlword(self.state, cw, prev_cw)
        if self.sto_active and new in (State.SWITCHED_ON, State.OPERATION_ENABLED) \
                and self.state not in (State.SWITCHED_ON, State.OPERATION_ENABLED):
            new, tr = self.state, None        # STO active: the power stage stays off
        reset_edge = bool(cw & CW_FAULT_RESET and not prev_cw & CW_FAULT_RESET)
        if tr == "15" or (reset_edge and self._error_code and self.state not in (
                State.FAULT, State.FAULT_REACTION_ACTIVE)):
            # transition 15; or an error signalled without FAULT (0x6007 = 0, 2, 3)
            self._error_code = self._error_register = 0
            self._send_emcy(0, 0)
        if tr is not None and tr.startswith("11"):
            self._quick_stop(tr)              # the quick-stop ramp, then 0x605A
        elif new is not self.state:
            self._set_state(new, tr)          # entering operation enabled enters the mode
        elif mode_changed and self.state is State.OPERATION_ENABLED:
            self._enter_mode()
        if self.state is State.OPERATION_ENABLED:
            self._run_mode(cw, prev_cw)

    def _enter_mode(self) -> None:
        """The handpiece's behaviour on entering operation enabled or a new mode: velocity
        mode follows the target velocity, position mode holds the current position."""
        hp = self.world.handpiece
        self._sp_ack = False
        if self._mode_display == Mode.PROFILE_POSITION:
            hp.move_relative(0.0)
        elif self._mode_display == Mode.PROFILE_VELOCITY:
            self._follow_velocity(self._od[co.obj("controlword").address])
        else:
            hp.stop()

    def _follow_velocity(self, cw: int) -> None:
        hp = self.world.handpiece
        if cw & CW_HALT or self.output_lost:
            hp.stop()
            return
        rpm = self._od[co.obj("target_velocity").address] / self.gear_ratio
        limit = hp.p.max_rpm
        self._internal_limit = abs(rpm) > limit
        hp.set_velocity(max(-limit, min(limit, rpm)))

    def _run_mode(self, cw: int, prev_cw: int) -> None:
        hp = self.world.handpiece
        if self.output_lost:
            hp.stop()                            # no power: the motor coasts
            return
        mode = self._mode_display
        if mode == Mode.PROFILE_VELOCITY:
            self._follow_velocity(cw)
        elif mode == Mode.PROFILE_POSITION:
            if cw & CW_NEW_SETPOINT and not prev_cw & CW_NEW_SETPOINT:
                target = self._od[co.obj("target_position").address]
                deg = target / self._inc_per_file_deg
                if not cw & CW_RELATIVE:
                    deg -= hp.pos_deg
                pv = self._od[co.obj("profile_velocity").address] / self.gear_ratio
                rpm = min(pv, hp.p.max_rpm) if pv > 0 else None
                self._internal_limit = pv > hp.p.max_rpm
                hp.move_relative(deg, rpm)
                self._sp_ack = True
                self.setpoints_accepted += 1
            elif not cw & CW_NEW_SETPOINT:
                self._sp_ack = False
            if cw & CW_HALT and not prev_cw & CW_HALT:
                hp.move_relative(0.0)

    # ------------------------------------------------------------------ faults
    def _poll_world(self) -> None:
        """Faults the World causes: the STO opening while the power stage is on."""
        if self.sto_active and self.state in (State.SWITCHED_ON, State.OPERATION_ENABLED,
                                              State.QUICK_STOP_ACTIVE,
                                              State.FAULT_REACTION_ACTIVE):
            self._fault(STO_EMCY_CODE, brake=False)

    def _fault(self, code: int, register: int | None = None,
               manufacturer: bytes = bytes(5), *, brake: bool = True) -> None:
        """A device error: error code and register, EMCY, FAULT. With ``brake`` (and the
        motor powered) the fault reaction first stops it on the quick-stop ramp; without
        (the STO took the power stage) it goes to FAULT at once."""
        self._error_code = code
        self._error_register = co.error_register_for(code) if register is None else register
        st = self.state
        if st is not State.FAULT:
            powered = st in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE,
                             State.FAULT_REACTION_ACTIVE)
            if brake and powered and self._decel_file_rpm_s() > 0:
                self._set_state(State.FAULT_REACTION_ACTIVE, "13", braking=True)
                self._start_ramp()
            else:
                self._set_state(State.FAULT_REACTION_ACTIVE, "13")
                self._stop_ramp_now()
                self.world.handpiece.stop()
                self._set_state(State.FAULT, "14")
        self._send_emcy(code, self._error_register, manufacturer)

    def _send_emcy(self, code: int, register: int, manufacturer: bytes = bytes(5)) -> None:
        if self.muted or self.nmt_state not in (NmtState.PRE_OPERATIONAL,
                                                NmtState.OPERATIONAL):
            return
        self._send(co.cob_id("EMCY", self.node_id), co.encode_emcy(code, register, manufacturer))
        self.emcy_sent += 1
        log.info("epos4 sim EMCY", node=self.node_id, code=hex(code),
                 meaning=co.error_meaning(code))


# ====================================================================== electronic data sheet
#: The node's electronic data sheet (CiA 306), shipped in the package beside the driver:
#: ``canopen.BaseNode402(node_id, EDS_PATH)``. Generated by :func:`render_eds`; a test keeps
#: the file and the object table in agreement.
EDS_PATH = Path(co.__file__).with_name("epos4.eds")
_EDS_HEX_NAMES = frozenset({"device_type", "vendor_id", "product_code", "revision_number",
                            "serial_number", "supported_drive_modes",
                            "consumer_heartbeat_time"})


def eds_default(o: co.OdObject) -> str | None:
    """An object's DefaultValue in the EDS: its power-on value where that does not depend on
    the World (motor data, gear and profile velocity do; live values have none); PDO COB-IDs
    relative to $NODEID."""
    pdo = default_pdo_parameters(0)
    if o.name in POWER_ON_APPLICATION:
        value = POWER_ON_APPLICATION[o.name]
    elif o.name in POWER_ON_COMMUNICATION:
        value = POWER_ON_COMMUNICATION[o.name]
    elif o.name in co.HIGHEST_SUB_OBJECTS:
        value = co.HIGHEST_SUB_INDEX[o.index]
    elif o.name == "producer_heartbeat_time":
        value = DEFAULT_HEARTBEAT_MS
    elif o.name == "axis_main_sensor_resolution":
        value = DEFAULT_COUNTS_PER_TURN
    elif o.address in pdo:
        value = pdo[o.address]
        if o.sub == 1 and (o.index < 0x1600 or 0x1800 <= o.index < 0x1A00):   # COB-IDs
            return f"$NODEID+0x{value:08X}"
        if o.dtype is co.U32:
            return f"0x{value:08X}"
        return str(value)
    else:
        return None
    if o.name in _EDS_HEX_NAMES:
        return f"0x{value:08X}"
    return str(value)


def render_eds() -> str:
    """The EDS (CiA 306, the INI-style text ``canopen.import_od`` reads) of the objects the
    node implements, from :data:`~dentibot.io.canopen_protocol.OBJECTS` and the power-on
    values above."""
    objs = sorted(co.OBJECTS.values(), key=lambda o: o.address)
    indices = sorted({o.index for o in objs})
    out: list[str] = [
        "; Electronic data sheet (CiA 306) of the DentiBot simulated EPOS4 CANopen node.",
        "; Generated by dentibot.sim.epos4_node.render_eds from the object table in",
        "; dentibot.io.canopen_protocol: regenerate it rather than edit it.",
        "",
        "[FileInfo]",
        "FileName=epos4.eds",
        "FileVersion=1",
        "FileRevision=0",
        "EDSVersion=4.0",
        "Description=Simulated maxon EPOS4: the subset of the EPOS4 objects DentiBot implements",
        "CreatedBy=DentiBot",
        "",
        "[DeviceInfo]",
        "VendorName=maxon motor ag",
        f"VendorNumber=0x{VENDOR_ID:08X}",
        "ProductName=EPOS4 (DentiBot simulated node)",
        f"ProductNumber=0x{PRODUCT_CODE:08X}",
        f"RevisionNumber=0x{REVISION_NUMBER:08X}",
        *(f"BaudRate_{r}={int(r != 10)}" for r in (10, 20, 50, 125, 250, 500, 800, 1000)),
        "SimpleBootUpMaster=0",
        "SimpleBootUpSlave=1",
        "Granularity=8",
        "DynamicChannelsSupported=0",
        "GroupMessaging=0",
        "NrOfRXPDO=4",
        "NrOfTXPDO=4",
        "LSS_Supported=0",
        "",
        "[DummyUsage]",
        *(f"Dummy{i:04d}=0" for i in range(1, 8)),
        "",
        "[Comments]",
        "Lines=3",
        "Line1=Modes of operation: profile position (1) and profile velocity (3), 0x6502.",
        "Line2=Expedited SDO only. TxPDOs are sent on SYNC (transmission types 0..240).",
        "Line3=Velocities in motor rpm, accelerations in motor rpm/s, positions in increments.",
        "",
    ]
    mandatory = [i for i in indices if i in (0x1000, 0x1001, 0x1018)]
    manufacturer = [i for i in indices if 0x2000 <= i < 0x6000]
    optional = [i for i in indices if i not in mandatory and i not in manufacturer]
    for title, group in (("MandatoryObjects", mandatory), ("OptionalObjects", optional),
                         ("ManufacturerObjects", manufacturer)):
        out += [f"[{title}]", f"SupportedObjects={len(group)}",
                *(f"{k}=0x{i:04X}" for k, i in enumerate(group, 1)), ""]

    def entry(section: str, o: co.OdObject) -> list[str]:
        lines = [f"[{section}]", f"ParameterName={o.parameter_name}", "ObjectType=0x7",
                 f"DataType=0x{o.dtype.code:04X}", f"AccessType={o.access}"]
        default = eds_default(o)
        if default is not None:
            lines.append(f"DefaultValue={default}")
        if o.name.endswith("_mapped_count"):
            lines += ["LowLimit=0", "HighLimit=8"]
        lines += [f"PDOMapping={int(o.pdo is not None)}", ""]
        return lines

    for index in indices:
        subs = [o for o in objs if o.index == index]
        if index not in co.OBJECT_GROUPS:
            (o,) = subs
            out += entry(f"{index:04X}", o)
            continue
        name, code = co.OBJECT_GROUPS[index]
        out += [f"[{index:04X}]", f"ParameterName={name}", f"ObjectType=0x{code:X}",
                f"SubNumber={len(subs)}", ""]
        for o in subs:
            out += entry(f"{index:04X}sub{o.sub:X}", o)
    return "\n".join(out)


def write_eds(path: Path | str = EDS_PATH) -> Path:
    """Write :func:`render_eds` to ``path`` (the shipped file by default)."""
    path = Path(path)
    path.write_text(render_eds(), encoding="utf-8")
    return path
