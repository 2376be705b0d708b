"""Maxon EPOS4 driver: the handpiece motor over CANopen (CiA 301 / CiA 402), asyncio.

:class:`Epos4Driver` implements :class:`dentibot.io.Handpiece` on any python-can bus: kernel
SocketCAN (``interface="socketcan"``, the default, channel ``"can0"``), a socketcand server
(``interface="socketcand"``, host/port: the driver's own client, :class:`SocketcandBus`, whose
connection, handshake and sends are bounded in time), python-can's in-process ``virtual`` bus,
or a bus factory of your own.

Start-up (``connect()``; SDOs only here, never in the cyclic exchange):

1. NMT *enter pre-operational* (PDOs stop, SDOs keep working).
2. Read the device type 0x1000 (low word must be 402), vendor id, error code 0x603F and
   register 0x1001, motor data (0x3001:01 nominal current mA, 0x3001:05 torque constant
   uNm/A), rated torque 0x6076 (uNm), gear 0x3003:01/02, main sensor resolution 0x3000:05
   (increments per motor turn), statusword 0x6041.
3. Write the producer heartbeat time 0x1017 (``heartbeat_ms``).
4. Configure the project's PDO mapping (:data:`~dentibot.io.canopen_protocol.PROJECT_PDOS`):
   per PDO, COB-ID invalid -> transmission type -> mapping count 0 -> entries -> count ->
   COB-ID valid; then read everything back and compare (``configure_pdos=False``: only
   compare, for a drive configured by other means).
5. Liveness (see below): write the quick-stop deceleration 0x6085, the abort connection
   option code 0x6007 and the heartbeat consumer entry 0x1016:01 (the host's node id and the
   consumer time), then read all three back; a drive that does not hold what was written is a
   :class:`ConfigurationMismatch` and the connection fails.
6. NMT *start*; the cyclic exchange begins (own task with ``sync=True``, else the caller's
   ``exchange()``) and with it the host's heartbeat; the node's own heartbeat confirms
   OPERATIONAL (within three of its periods: one sent before it took the start may still be
   on its way); a FAULT found at start-up is reset; then
   the CiA 402 enable sequence (shutdown -> switch on -> enable operation), each step waiting
   for the statusword in TxPDO1, ``state_timeout_s`` in all -> :class:`DeviceFault` naming the
   state it got stuck in.

Liveness: the drive stops the file by itself when the host dies, freezes or loses the bus.
CiA 301 heartbeat consumer: 0x1016:01 = (``host_node_id`` << 16) | ``consumer_ms``; the host
produces NMT error-control frames 0x700 + ``host_node_id`` (state byte 0x05, operational)
every ``host_heartbeat_period_s``; monitoring starts at the first one the drive receives
(CiA 301). When none arrives for ``consumer_ms`` the drive signals a heartbeat error (EMCY
0x8130, error register bit "communication") and applies the abort connection option code
0x6007 (CiA 402). The default, 1 "fault signal", runs the fault reaction (a stop on the
quick-stop ramp 0x6085 written here) and latches FAULT: the file stays still until the host is
back and calls :meth:`fault_reset` and :meth:`enable`. Option 3 "quick stop" would end in
QUICK STOP ACTIVE, which "enable operation" alone leaves; that is why 1 is the default.
The objects and their layout are CiA 301/402 (the heartbeat's COB-ID 0x700 + node id); the
reaction is the EPOS4's documented use of 0x6007, read back at start-up because it is not
confirmed against every EPOS4 firmware.

Where the heartbeat comes from decides what it covers. It is produced by the cyclic exchange
(the own SYNC task, or the caller's ``exchange()``), so it stops with the process (kill,
crash), with a frozen process (SIGSTOP, a debugger), with a blocked event loop and with a dead
link (bus-off, a cut cable, a dead socketcand). A thread of its own would keep beating through
a blocked event loop; a task of the event loop keeps beating through a control task that is
stuck in an ``await`` while the loop itself runs. So the heartbeat is also gated by the
control path: the control task feeds the driver every tick (``read()`` does, or
:meth:`feed`), and while the file is commanded to turn (a non-zero velocity, a move not
finished) the heartbeat is withheld once the last feed is older than ``feed_timeout_s``. A
control task that stops ticking while the file turns therefore stops the file within
``feed_timeout_s + consumer_ms``; a file at rest keeps the heartbeat going from the cyclic
exchange alone (nothing moves unless the control path commands it, which feeds). Supervision
by feed starts with the first feed, so start-up and the time before the first tick are covered
by the process-level liveness only. No SYNC/RPDO timeout is configured: the EPOS4's
communication profile documents none.

Cyclic exchange (every ``sync_period_s``): RxPDO2 (target position, profile velocity), RxPDO1
(controlword, target velocity, mode), then SYNC; the drive answers with TxPDO1 (statusword,
velocity actual, mode display) and TxPDO2 (position actual, current actual averaged).
RxPDO2 goes first so that a new position set-point is in place when the controlword's
new-set-point edge arrives (both RxPDOs are asynchronous, type 255). A real-time control task
paces the cycle (``cycle_soon()`` after each tick): the RxPDOs carry that tick's commands and
the SYNC keeps the tick's timing; when its ticks stop the cycle keeps its own period. Frames
are received on this event loop (:class:`~dentibot.io.can_reader.LoopReader`); nothing
blocks. One complete TxPDO1+TxPDO2 pair is one sample (``seq`` +1); answers are matched to
SYNCs in order, a SYNC unanswered after ``answer_timeout_s`` counts as lost.

``read()`` -> :class:`MotorState` at the *file*: ``velocity_rpm = velocity actual / gear``,
``position_deg = increments / counts_per_turn * 360 / gear`` (unwrapped across the INTEGER32
overflow), ``current_a = 0x30D1:01 / 1000``. It raises :class:`DeviceFault` when there is no
sample, the newest is older than ``stale_after_s``, the heartbeat is silent beyond
``heartbeat_timeout_s``, an EMCY reported an error (naming the code and its meaning), the
drive is in FAULT, the node rebooted, or the link is down.

Commands: ``set_velocity`` (profile velocity mode 3, file rpm * gear -> 0x60FF),
``move_relative`` (profile position mode 1, relative bit 6, new-set-point bit 4 handshake
with the set-point acknowledge bit 12; ``wait_move_done()`` waits for target reached),
``stop()`` = profile velocity 0 rpm: the drive ramps down and stays enabled, holding zero speed
(use ``quick_stop()`` for the CiA 402 quick stop, after which ``enable()`` is needed),
``fault_reset()`` (rising edge of controlword bit 7, once the fault reaction has ended) and
``enable()``.

``close()`` commands 0 rpm and *shutdown* (power stage off), switches the heartbeat consumer
off (0x1016:01 = 0) while the host still beats, stops the cycle, sends NMT *enter
pre-operational*, stops the Notifier and shuts the bus down.

Assumptions (unconfirmed, read from the drive where possible): velocity unit rpm (0x60A9
default), torque constant in uNm/A and rated torque in uNm, encoder 2048 increments per motor
turn (a 512-pulse encoder, x4) unless the drive reports 0x3000:05.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import can
import structlog

from dentibot.errors import ConfigError, DeviceFault, ProtocolError
from dentibot.io import canopen_protocol as co
from dentibot.io.canopen_master import (
    SOCKETCAND_PORT,  # noqa: F401 - importable from here as before
    CanOpenMaster,
    ConfigurationMismatch,
    SdoAbort,
    SocketcandBus,
)
from dentibot.io.canopen_protocol import (
    ABORT_CONNECTION_OPTIONS,
    CONTROLWORD,
    CW_CHANGE_SET_IMMEDIATELY,
    CW_NEW_SETPOINT,
    CW_RELATIVE,
    ENABLE_STEP,
    PDO_COB_INVALID,
    PDO_COB_NO_RTR,
    PROJECT_PDOS,
    RXPDO1,
    RXPDO2,
    SW_SETPOINT_ACK,
    SW_TARGET_REACHED,
    TXPDO1,
    TXPDO2,
    AbortConnectionOption,
    Command,
    Emcy,
    Mode,
    NmtCommand,
    NmtState,
    OdObject,
    SdoFrame,
    State,
)
from dentibot.io.interfaces import ConnectTimeout, MotorState
from dentibot.io.tasks import cancel_until_done

log = structlog.get_logger(__name__)

#: Increments per motor turn used when the drive does not report 0x3000:05: a 512-pulse
#: quadrature encoder counted x4 (assumption for the handpiece motor).
DEFAULT_COUNTS_PER_TURN = 2048
#: The host's node id in the drive's heartbeat consumer entry. CiA 301 gives the NMT master
#: no fixed id; 127, the top of the range, is the usual choice (configurable).
DEFAULT_HOST_NODE_ID = 127
#: Heartbeat consumer time (ms). With the host beating every 5 ms, a beat may come 25 ms late
#: (measured on loopback through socketcand on a loaded machine: gaps up to 17 ms) before the
#: drive stops the file. The budget it fits: a file at 60 rpm must be
#: still (< 1 rpm) within 100 ms of the host's death; the handpiece's speed loop (a first
#: order, 10 ms, see ``dentibot.sim.handpiece``) needs 10 ms * ln(60) = 41 ms to come down
#: from 60 rpm even on an instant ramp, the quick-stop ramp at
#: :data:`DEFAULT_QUICK_STOP_FILE_RPM_S` another 10 ms, scheduling a few ms: 30 ms is left
#: for detection. A host on a real-time system may use less; a host whose event loop may
#: stall longer than about 25 ms needs more, and then stops the file later.
DEFAULT_CONSUMER_MS = 30
#: The host's heartbeat period (s): a sixth of the consumer time, every other cycle at 500 Hz
#: (one 1-byte frame, about 13 kbit/s on the bus: 1.3 % of 1 Mbit/s).
DEFAULT_HOST_HEARTBEAT_PERIOD_S = 0.005
#: Control-path silence (s) after which a turning file loses its heartbeat: 50 periods at
#: 500 Hz, so a few late ticks never withhold it, a dead or stuck control task always does.
DEFAULT_FEED_TIMEOUT_S = 0.1
#: Quick-stop deceleration at the file (rpm/s): 60 rpm to rest in 10 ms, 402,000 rpm/s at
#: the motor through the 67:1 gear. Assumption: within what a small maxon DC motor's peak
#: torque gives its own rotor (the file's inertia is negligible behind the gear); the drive
#: limits the current anyway.
DEFAULT_QUICK_STOP_FILE_RPM_S = 6000.0
#: Unanswered SYNCs logged one by one before logging only every ``_LOG_EVERY``-th.
_LOG_FIRST, _LOG_EVERY = 10, 1000
#: Longest ``close()`` waits for the drive to confirm the shutdown (s).
_CLOSE_WAIT_S = 0.2

_TX1, _TX2 = TXPDO1.layout, TXPDO2.layout
_RX1, _RX2 = RXPDO1.layout, RXPDO2.layout
_I32_MIN, _I32_MAX = co.I32.range


class Epos4Driver(CanOpenMaster):
    """Maxon EPOS4 handpiece drive over CANopen (implements ``dentibot.io.Handpiece``).

    Args:
        bus_factory, interface, channel, host, port, bus_kwargs: the bus, as for
            :class:`~dentibot.io.canopen_master.CanOpenMaster` (default: kernel SocketCAN
            ``can0``).
        node_id: CANopen node id of the drive (1).
        gear_ratio: handpiece gear, motor turns per file turn (67, thesis 5.1). The drive's
            0x3003 is read and a mismatch logged; this value is used.
        encoder_counts_per_turn: increments per motor turn if the drive does not report
            0x3000:05 (2048: 512-pulse encoder x4, assumption).
        sync_period_s: cycle of the own SYNC task (0.002 s = 500 Hz).
        max_file_rpm: largest |speed| accepted at the file (200 rpm, thesis 5.1).
        move_rpm: file speed of ``move_relative`` moves (100 rpm).
        heartbeat_ms: producer heartbeat time written to 0x1017 (100 ms; None: keep the
            drive's); heartbeat_timeout_s: silence that faults ``read()`` (0.5 s).
        stale_after_s: newest TxPDO older than this faults ``read()`` (0.1 s = 50 cycles).
        answer_timeout_s: a SYNC unanswered for this long counts as lost (0.1 s).
        sdo_timeout_s: per SDO request (0.5 s); state_timeout_s: for enable / fault reset
            (1.0 s).
        configure_pdos: write the PDO mapping at start-up (True) or only verify it.
        connect_timeout_s: opening the bus, for socketcand the TCP connection and the whole
            handshake (2.0 s): a silent peer is a :class:`ConnectTimeout`.
        host_node_id: the node id whose heartbeat the drive consumes, the host's (127);
            it produces 0x700 + host_node_id.
        consumer_ms: heartbeat consumer time written to 0x1016:01 (ms; see
            :data:`DEFAULT_CONSUMER_MS`); 0 writes the entry off, None leaves the drive's
            entry as it is.
        host_heartbeat_period_s: the host's heartbeat period (0.005 s), at most a third of
            the consumer time.
        feed_timeout_s: while the file is commanded to turn, the heartbeat is withheld once
            the control path has not fed the driver (``read()``/:meth:`feed`) for this long
            (0.1 s = 50 control periods); None: no supervision by feed.
        abort_connection_option: 0x6007 written at start-up (1, fault signal; see
            :class:`~dentibot.io.canopen_protocol.AbortConnectionOption`); None: keep.
        quick_stop_file_rpm_s: quick-stop deceleration at the file (rpm/s), written to
            0x6085 as motor rpm/s (x gear); None: keep the drive's. Default
            :data:`DEFAULT_QUICK_STOP_FILE_RPM_S`.
        name: device name in errors and logs.
    """

    log_name = "epos4"
    factory_description = "from the bus factory"
    count_error_frames = True

    def __init__(self, bus_factory: Callable[[], can.BusABC] | None = None, *,
                 interface: str = "socketcan", channel: str = "can0",
                 host: str = "127.0.0.1", port: int = 29536,
                 bus_kwargs: dict[str, Any] | None = None, node_id: int = 1,
                 gear_ratio: float = 67.0,
                 encoder_counts_per_turn: int = DEFAULT_COUNTS_PER_TURN,
                 sync_period_s: float = 0.002, max_file_rpm: float = 200.0,
                 move_rpm: float = 100.0, heartbeat_ms: int | None = 100,
                 heartbeat_timeout_s: float = 0.5, stale_after_s: float = 0.1,
                 answer_timeout_s: float = 0.1, sdo_timeout_s: float = 0.5,
                 state_timeout_s: float = 1.0, configure_pdos: bool = True,
                 connect_timeout_s: float = 2.0, host_node_id: int = DEFAULT_HOST_NODE_ID,
                 consumer_ms: int | None = DEFAULT_CONSUMER_MS,
                 host_heartbeat_period_s: float = DEFAULT_HOST_HEARTBEAT_PERIOD_S,
                 feed_timeout_s: float | None = DEFAULT_FEED_TIMEOUT_S,
                 abort_connection_option: int | None = AbortConnectionOption.FAULT,
                 quick_stop_file_rpm_s: float | None = DEFAULT_QUICK_STOP_FILE_RPM_S,
                 name: str = co.DEVICE) -> None:
        self.node_id = co.check_node_id(node_id)
        self.host_node_id = co.check_node_id(host_node_id)
        if self.host_node_id == self.node_id:
            raise ConfigError("epos4.host_node_id", host_node_id,
                              f"a node id other than the drive's ({node_id})")
        for field, v, lo in (("epos4.gear_ratio", gear_ratio, 0.0),
                             ("epos4.sync_period_s", sync_period_s, 0.0),
                             ("epos4.max_file_rpm", max_file_rpm, 0.0),
                             ("epos4.heartbeat_timeout_s", heartbeat_timeout_s, 0.0),
                             ("epos4.stale_after_s", stale_after_s, 0.0),
                             ("epos4.answer_timeout_s", answer_timeout_s, 0.0),
                             ("epos4.sdo_timeout_s", sdo_timeout_s, 0.0),
                             ("epos4.state_timeout_s", state_timeout_s, 0.0),
                             ("epos4.connect_timeout_s", connect_timeout_s, 0.0),
                             ("epos4.host_heartbeat_period_s", host_heartbeat_period_s, 0.0),
                             ("epos4.feed_timeout_s",
                              1.0 if feed_timeout_s is None else feed_timeout_s, 0.0),
                             ("epos4.quick_stop_file_rpm_s",
                              1.0 if quick_stop_file_rpm_s is None else quick_stop_file_rpm_s,
                              0.0)):
            if isinstance(v, bool) or not (isinstance(v, int | float) and math.isfinite(v)
                                           and v > lo):
                raise ConfigError(field, v, f"a finite number > {lo}")
        if consumer_ms is not None:
            co.encode_consumer_heartbeat(self.host_node_id, consumer_ms)   # range check
            if consumer_ms and host_heartbeat_period_s * 3000.0 > consumer_ms:
                raise ConfigError("epos4.host_heartbeat_period_s", host_heartbeat_period_s,
                                  f"at most a third of the consumer time ({consumer_ms} ms), "
                                  "so that a late beat or two do not fault the drive")
        if abort_connection_option is not None:
            try:
                abort_connection_option = AbortConnectionOption(abort_connection_option)
            except ValueError:
                raise ConfigError("epos4.abort_connection_option", abort_connection_option,
                                  "0..3 (CiA 402 0x6007)") from None
        if not 0 < move_rpm <= max_file_rpm:
            raise ConfigError("epos4.move_rpm", move_rpm, f"0 < rpm <= {max_file_rpm}")
        if not (isinstance(encoder_counts_per_turn, int) and encoder_counts_per_turn > 0):
            raise ConfigError("epos4.encoder_counts_per_turn", encoder_counts_per_turn,
                              "a positive integer (increments per motor turn)")
        if heartbeat_ms is not None and not (isinstance(heartbeat_ms, int)
                                             and 0 <= heartbeat_ms <= 0xFFFF):
            raise ConfigError("epos4.heartbeat_ms", heartbeat_ms, "None or 0..65535 ms")
        super().__init__(bus_factory, interface=interface, channel=channel, host=host,
                         port=port, bus_kwargs=bus_kwargs, sdo_timeout_s=sdo_timeout_s,
                         connect_timeout_s=connect_timeout_s, sync_period_s=sync_period_s,
                         heartbeat_ms=heartbeat_ms, heartbeat_timeout_s=heartbeat_timeout_s,
                         name=name)
        self.gear_ratio = float(gear_ratio)
        self.counts_per_turn = encoder_counts_per_turn
        self.max_file_rpm = float(max_file_rpm)
        self.move_rpm = float(move_rpm)
        self.stale_after_s = float(stale_after_s)
        self.answer_timeout_s = float(answer_timeout_s)
        self.state_timeout_s = float(state_timeout_s)
        self.configure_pdos = bool(configure_pdos)
        self.consumer_ms = consumer_ms
        self.host_heartbeat_period_s = float(host_heartbeat_period_s)
        self.feed_timeout_s = None if feed_timeout_s is None else float(feed_timeout_s)
        self.abort_connection_option = abort_connection_option
        self.quick_stop_file_rpm_s = (None if quick_stop_file_rpm_s is None
                                      else float(quick_stop_file_rpm_s))
        nid = self.node_id
        self._host_hb_cob = co.cob_id("HEARTBEAT", self.host_node_id)
        self._cob = {fn: co.cob_id(fn, nid) for fn in
                     ("RPDO1", "RPDO2", "TPDO1", "TPDO2", "SDO_RX", "SDO_TX", "EMCY",
                      "HEARTBEAT")}
        self._handlers = {
            self._cob["TPDO1"]: self._on_tpdo1,
            self._cob["TPDO2"]: self._on_tpdo2,
            self._cob["SDO_TX"]: self._on_sdo,
            self._cob["EMCY"]: self._on_emcy,
            self._cob["HEARTBEAT"]: self._on_heartbeat,
        }
        # counters
        self.syncs_sent = 0
        self.received = 0           # complete TxPDO1+TxPDO2 samples (= seq of the newest)
        self.lost = 0               # SYNCs not answered within answer_timeout_s
        self.unsolicited = 0        # samples with no SYNC waiting (answers after "lost")
        self.incomplete = 0         # a TxPDO1 or TxPDO2 without its partner
        self.emcy_count = 0
        self.heartbeats = 0
        self.host_heartbeats = 0    # heartbeats this host produced for the drive's consumer
        self.withheld = 0           # host heartbeats withheld: the control path went silent
        #: the longest time between two heartbeats this host produced (s): how close the host
        #: came to the drive's consumer time (a stalled event loop, a loaded machine); the
        #: caller may reset it to 0 to watch a stretch of its own
        self.host_heartbeat_gap_max_s = 0.0
        self.feeds = 0
        self.latency_last_s = 0.0   # SYNC sent -> TxPDO2 received
        self.latency_max_s = 0.0
        self._latency_sum = 0.0
        # drive data (read at start-up)
        self.device_type = 0
        self.vendor_id = 0
        self.km_mnm_per_a = 0.0
        self.nominal_current_a = 0.0
        self.rated_torque_mnm = 0.0
        self.device_gear: tuple[int, int] = (0, 0)
        self.startup_error_code = 0
        # live state
        self.statusword: int | None = None
        self.state: State | None = None
        self.mode_display: int | None = None
        self.nmt_state: NmtState | None = None
        self.last_emcy: Emcy | None = None
        self._emcy_fault: Emcy | None = None     # the first EMCY since the last reset
        self._emcy_later = 0                       # EMCYs received after it
        self._rebooted = False
        self._sample: MotorState | None = None
        self._tx1: tuple[int, State, int, int] | None = None
        self._pos_raw: int | None = None
        self._pos_inc = 0
        self._outstanding: deque[float] = deque()
        self._matched = 0
        self._hb_t = 0.0
        self._host_hb_t = -math.inf      # when the host's last heartbeat went out
        self._fed_t: float | None = None  # last feed from the control path (None: never)
        self._withholding = False
        # command image sent every cycle
        self._cw = CONTROLWORD[Command.DISABLE_VOLTAGE]
        self._mode = int(Mode.PROFILE_VELOCITY)
        self._target_vel = 0
        self._target_pos = 0
        self._profile_vel = round(self.move_rpm * self.gear_ratio)
        self._cycle_key: tuple | None = None     # the image the cycle's frames were packed from
        self._cycle_frames: tuple = ()
        self._sp = "idle"           # new set-point handshake: idle, request, sent, acked
        self._sp_sync = 0           # number of the SYNC that carried the set-point edge
        self._last_bit4 = False     # bit 4 of the last controlword sent
        # plumbing
        self._sync_task: asyncio.Task | None = None
        self._rx_event: asyncio.Event | None = None
        self._consumer_set = False  # 0x1016:01 written (switched off again on close)
        #: what the drive holds after start-up: 0x6085 (motor rpm/s), 0x6007, 0x1016:01
        #: as (host node id, consumer ms)
        self.liveness: dict[str, Any] = {}

    # ================================================================== lifecycle
    def _open_timeout(self, exc: TimeoutError) -> ConnectTimeout:
        if self.interface == "socketcand":
            return ConnectTimeout(self.name, f"{self.host}:{self.port}",
                                  f"socketcand {exc} (channel {self.channel})",
                                  self.connect_timeout_s)
        return ConnectTimeout(self.name, self._bus_description(), "answer opening the bus",
                              self.connect_timeout_s)

    async def connect(self, sync: bool = True) -> None:
        """Open the bus, configure the drive over SDO, start it and enable operation.

        ``sync=True`` starts the own cyclic task (RxPDOs + SYNC every ``sync_period_s``);
        with ``sync=False`` the caller drives the cycle with :meth:`exchange` (the start-up
        waits then run their own exchanges)."""
        if self._connected:
            return
        if self._closed:
            raise DeviceFault(self.name, "driver closed; create a new one to reconnect")
        self._rx_event = asyncio.Event()
        await self._open_bus()
        try:
            await self._start_up(sync)
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        """Stop the cycle, leave the drive disabled (0 rpm, shutdown) and pre-operational,
        stop the reader and shut the bus down. Idempotent."""
        if self._closed:
            return
        self._closed = True
        healthy = self._started and self._link_error is None
        if healthy:
            self._target_vel = 0
            self._mode = int(Mode.PROFILE_VELOCITY)
            self._sp = "idle"
            self._cw = CONTROLWORD[Command.SHUTDOWN]
            self._fed_t = None              # leaving: beat unconditionally until the end
            # the power stage off, confirmed by the statusword (bounded: a silent drive
            # does not hold the close up)
            try:
                await self._drive_cycles_until(
                    lambda: self.state is not State.OPERATION_ENABLED,
                    time.monotonic() + min(self.state_timeout_s, _CLOSE_WAIT_S))
            except DeviceFault:
                pass
            if self.consumer_ms and self._consumer_set:
                # the drive stops watching before the host stops beating (the cycle, and so
                # the heartbeat, runs on meanwhile): a clean close is not a lost host
                try:
                    await self._sdo_write_at(*co.obj("consumer_heartbeat_time").address, 0)
                except DeviceFault as exc:
                    log.warning("epos4 consumer not switched off", device=self.name,
                                error=str(exc))
        await self.stop_sync()
        if healthy:
            try:
                self._send_cycle()
                self._send_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, self.node_id)
            except DeviceFault:
                pass
        await self._teardown()
        log.info("epos4 closed", device=self.name, syncs=self.syncs_sent,
                 received=self.received, lost=self.lost, errors=self.errors,
                 host_heartbeat_gap_max_ms=round(self.host_heartbeat_gap_max_s * 1e3, 1),
                 consumer_ms=self.consumer_ms)

    async def _start_up(self, sync: bool) -> None:
        nid = self.node_id
        self._send_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, nid)
        self.device_type = await self.sdo_read("device_type")
        if self.device_type & 0xFFFF != 402:
            raise DeviceFault(self.name, f"node {nid}: device type 0x{self.device_type:08X} is "
                                         "not a CiA 402 drive (low word must be 402 = 0x0192)")
        self.vendor_id = await self.sdo_read("vendor_id")
        self.startup_error_code = await self.sdo_read("error_code")
        register = await self.sdo_read("error_register")
        self.km_mnm_per_a = await self.sdo_read("motor_torque_constant") / 1000.0
        self.nominal_current_a = await self.sdo_read("motor_nominal_current") / 1000.0
        self.rated_torque_mnm = await self.sdo_read("motor_rated_torque") / 1000.0
        self.device_gear = (await self.sdo_read("gear_reduction_numerator"),
                            await self.sdo_read("gear_reduction_denominator"))
        num, den = self.device_gear
        if den and abs(num / den - self.gear_ratio) > 1e-6:
            log.warning("epos4 gear configuration differs", device=self.name,
                        drive_gear=f"{num}/{den}", used=self.gear_ratio)
        resolution = await self.sdo_read("axis_main_sensor_resolution")
        if resolution > 0 and resolution != self.counts_per_turn:
            log.warning("epos4 sensor resolution from the drive", device=self.name,
                        drive=resolution, configured=self.counts_per_turn)
            self.counts_per_turn = resolution
        if self.heartbeat_ms is not None:
            await self.sdo_write("producer_heartbeat_time", self.heartbeat_ms)
        else:
            self.heartbeat_ms = await self.sdo_read("producer_heartbeat_time")
        self.statusword = await self.sdo_read("statusword")
        self.state = co.state_from_statusword(self.statusword)
        log.info("epos4 drive", device=self.name, node=nid, vendor=hex(self.vendor_id),
                 km_mnm_per_a=self.km_mnm_per_a, rated_torque_mnm=self.rated_torque_mnm,
                 counts_per_turn=self.counts_per_turn, error_code=hex(self.startup_error_code),
                 error_register=hex(register), state=self.state.value)
        await self._setup_pdos()
        await self._configure_liveness()
        self._profile_vel = round(self.move_rpm * self.gear_ratio)
        self._cw = CONTROLWORD[Command.DISABLE_VOLTAGE]
        beats = self.heartbeats
        self._send_nmt(NmtCommand.START, nid)
        self.nmt_state = NmtState.OPERATIONAL
        self._hb_t = time.monotonic()
        self._started = True
        if sync:
            self.start_sync()
        await self._confirm_operational(beats)
        if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE) or self.startup_error_code:
            await self.fault_reset()
        await self.enable()

    async def _confirm_operational(self, beats: int) -> None:
        """Wait, the cycle running, for a heartbeat of the node saying OPERATIONAL after the
        NMT start (``beats``: the heartbeats counted before it). A heartbeat the node sent
        before it took the start, still PRE-OPERATIONAL, can arrive after it: without this
        the first read could find that state and fault. Within three heartbeat periods (one
        in flight, one to come, margin), else :class:`DeviceFault` naming the state the node
        reports. Nothing to wait for when the node produces no heartbeat."""
        if not self.heartbeat_ms:
            return
        limit_s = 3 * self.heartbeat_ms / 1000.0
        if not await self._drive_cycles_until(
                lambda: self.heartbeats > beats and self.nmt_state is NmtState.OPERATIONAL,
                time.monotonic() + limit_s):
            seen = "no heartbeat" if self.heartbeats == beats else \
                f"NMT {self.nmt_state.name if self.nmt_state else 'unknown'}"
            raise DeviceFault(self.name, f"node {self.node_id} did not report OPERATIONAL "
                                         f"within {limit_s * 1e3:.0f} ms of the NMT start "
                                         f"({seen})")

    async def _configure_liveness(self) -> None:
        """Quick-stop deceleration 0x6085, abort connection option 0x6007 and the heartbeat
        consumer 0x1016:01, each written (unless configured None) and read back. The consumer
        goes last: the drive starts watching at the first heartbeat it receives (CiA 301),
        which the cyclic exchange sends right after NMT start."""
        writes: list[tuple[str, int, str]] = []
        if self.quick_stop_file_rpm_s is not None:
            writes.append(("quick_stop_deceleration",
                           round(self.quick_stop_file_rpm_s * self.gear_ratio),
                           "the drive would not stop on the configured quick-stop ramp"))
        if self.abort_connection_option is not None:
            reaction = ABORT_CONNECTION_OPTIONS[self.abort_connection_option]
            writes.append(("abort_connection_option_code", int(self.abort_connection_option),
                           f"the drive would not react as configured to a lost host ({reaction})"))
        if self.consumer_ms is not None:
            writes.append(("consumer_heartbeat_time",
                           co.encode_consumer_heartbeat(self.host_node_id, self.consumer_ms)
                           if self.consumer_ms else 0,
                           "the drive would not watch the host's heartbeat as configured"))
        for name, value, why in writes:
            o = co.obj(name)
            await self.sdo_write(o, value)
            got = await self.sdo_read(o)
            if got != value:
                raise ConfigurationMismatch(self.name, o, value, got, why)
            if name == "consumer_heartbeat_time":
                self._consumer_set = True
        self.liveness = {
            "quick_stop_deceleration_rpm_s": await self.sdo_read("quick_stop_deceleration"),
            "abort_connection_option": await self.sdo_read("abort_connection_option_code"),
            "consumer": co.decode_consumer_heartbeat(
                await self.sdo_read("consumer_heartbeat_time")),
        }
        log.info("epos4 liveness", device=self.name, host_node=self.host_node_id,
                 **self.liveness)

    async def _setup_pdos(self) -> None:
        for pdo in PROJECT_PDOS:
            cob = pdo.cob_id(self.node_id)
            cob_word = cob | (PDO_COB_NO_RTR if pdo.direction == "tx" else 0)
            words = pdo.layout.words
            comm, mp = pdo.comm_index, pdo.map_index
            if self.configure_pdos:
                await self._sdo_write_at(comm, 1, cob_word | PDO_COB_INVALID)
                await self._sdo_write_at(comm, 2, pdo.transmission_type)
                await self._sdo_write_at(mp, 0, 0)
                for i, w in enumerate(words, 1):
                    await self._sdo_write_at(mp, i, w)
                await self._sdo_write_at(mp, 0, len(words))
                await self._sdo_write_at(comm, 1, cob_word)
            got_cob = await self._sdo_read_at(comm, 1)
            got_type = await self._sdo_read_at(comm, 2)
            n = await self._sdo_read_at(mp, 0)
            got_words = tuple([await self._sdo_read_at(mp, i)
                               for i in range(1, min(n, 8) + 1)])
            if (got_cob & PDO_COB_INVALID or got_cob & 0x7FF != cob or got_words != words
                    or got_type != pdo.transmission_type):
                raise DeviceFault(self.name, (
                    f"{pdo.name} reads back COB-ID 0x{got_cob:08X}, type {got_type}, mapping "
                    f"{[f'0x{w:08X}' for w in got_words]}; expected COB-ID 0x{cob:03X} valid, "
                    f"type {pdo.transmission_type}, mapping {[f'0x{w:08X}' for w in words]}"))

    # ================================================================== SDO client
    def _resolve(self, obj: str | OdObject) -> OdObject:
        return co.obj(obj) if isinstance(obj, str) else obj

    async def sdo_read(self, obj: str | OdObject) -> int:
        """Read object ``obj`` (a name in ``canopen_protocol.OBJECTS`` or an OdObject) by an
        expedited SDO upload. Start-up and diagnostics only: never in the control loop."""
        o = self._resolve(obj)
        frame = await self._sdo(o.index, o.sub, co.encode_sdo_upload(o.index, o.sub), "upload")
        if frame.kind == "upload":
            return o.dtype.decode(frame.payload, f"SDO upload {o}")
        if frame.kind == "upload_segmented":
            raise DeviceFault(self.name, f"SDO upload {o}: the drive answered with a segmented "
                                         "transfer (not supported here)")
        raise ProtocolError(self.name, f"SDO upload {o}: unexpected answer '{frame.kind}'")

    async def sdo_write(self, obj: str | OdObject, value: int) -> None:
        """Write ``value`` to object ``obj`` by an expedited SDO download."""
        o = self._resolve(obj)
        payload = o.dtype.encode(value, f"{self.name}.{o.name}")
        frame = await self._sdo(o.index, o.sub, co.encode_sdo_download(o.index, o.sub, payload),
                                "download")
        if frame.kind != "download_ack":
            raise ProtocolError(self.name, f"SDO download {o}: unexpected answer '{frame.kind}'")

    async def _sdo_read_at(self, index: int, sub: int) -> int:
        return await self.sdo_read(co.OBJECTS_BY_ADDRESS[(index, sub)])

    async def _sdo_write_at(self, index: int, sub: int, value: int) -> None:
        await self.sdo_write(co.OBJECTS_BY_ADDRESS[(index, sub)], value)

    async def _sdo(self, index: int, sub: int, request: bytes, verb: str) -> SdoFrame:
        timeout = DeviceFault(self.name, (
            f"SDO {verb} 0x{index:04X}:{sub:02X} not answered within "
            f"{self.sdo_timeout_s} s (node {self.node_id} absent, or not in "
            "PRE-OPERATIONAL/OPERATIONAL)"))
        return await self._sdo_transfer(self.node_id, index, sub, request, verb,
                                        timeout_error=timeout, abort_device=self.name)

    # ================================================================== cyclic exchange
    def _controlword(self) -> int:
        """The controlword of the cycle about to be sent. Profile position set-point
        handshake: bit 4 rises only after a cycle with bit 4 low and with the drive's
        acknowledge (statusword bit 12) low; it stays high until an answer to a SYNC sent
        with it acknowledges, then drops."""
        cw = self._cw
        if self._mode == Mode.PROFILE_POSITION and cw == CONTROLWORD[Command.ENABLE_OPERATION]:
            cw |= CW_CHANGE_SET_IMMEDIATELY | CW_RELATIVE
            # bit 12 means "speed zero" in profile velocity mode: only an acknowledge in
            # profile position mode holds the next edge back
            ack = (self.mode_display == Mode.PROFILE_POSITION
                   and (self.statusword or 0) & SW_SETPOINT_ACK)
            if self._sp == "request" and not self._last_bit4 and not ack:
                self._sp = "sent"
                self._sp_sync = self.syncs_sent + 1          # the SYNC that follows
            if self._sp == "sent":
                cw |= CW_NEW_SETPOINT
        self._last_bit4 = bool(cw & CW_NEW_SETPOINT)
        return cw

    def _send_cycle(self) -> None:
        """RxPDO2, RxPDO1, SYNC (one cycle's frames, in one write where the bus allows). The
        commands change seldom: the frames are packed again only when they do."""
        key = (self._controlword(), self._target_vel, self._mode, self._target_pos,
               self._profile_vel)
        if key != self._cycle_key:
            rx1 = _RX1.pack(key[:3], "RxPDO1")
            rx2 = _RX2.pack(key[3:], "RxPDO2")
            self._cycle_frames = ((self._cob["RPDO2"], rx2), (self._cob["RPDO1"], rx1),
                                  (co.COB_BASE["SYNC"], co.encode_sync()))
            self._cycle_key = key
        self._send_frames(self._cycle_frames)

    async def exchange(self, wait: bool = False) -> None:
        """One cycle: send the RxPDOs and a SYNC. The TxPDO answers arrive in the background
        (``read()`` returns them); ``wait=True`` returns once this SYNC is answered (or after
        ``answer_timeout_s``). For a control task that owns the cycle (``connect(sync=False)``).
        """
        if not self._started:
            raise DeviceFault(self.name, "not connected")
        now = time.monotonic()
        out = self._outstanding
        while out and now - out[0] > self.answer_timeout_s:
            out.popleft()
            self.lost += 1
            if self.lost <= _LOG_FIRST or self.lost % _LOG_EVERY == 0:
                log.warning("epos4 SYNC unanswered", device=self.name, lost=self.lost,
                            timeout_s=self.answer_timeout_s)
        self._send_cycle()
        self.syncs_sent += 1
        out.append(now)
        self._heartbeat(now)
        if wait:
            await self._wait_answered(self.syncs_sent, now + self.answer_timeout_s)

    # ================================================================== host heartbeat
    def feed(self) -> None:
        """The control path is alive: call it every control tick (``read()`` does). While the
        file is commanded to turn, a feed older than ``feed_timeout_s`` withholds the host's
        heartbeat, and the drive stops the file ``consumer_ms`` later. Cheap: a clock read."""
        self._fed_t = time.monotonic()
        self.feeds += 1

    def _file_commanded(self) -> bool:
        """The drive is told to turn the file: a non-zero velocity, or a move not done."""
        if self._mode == Mode.PROFILE_VELOCITY:
            return self._target_vel != 0
        return self._sp != "idle" and not self.move_done

    def _heartbeat(self, now: float) -> None:
        """Send the host's heartbeat when it is due, unless the control path went silent
        while the file turns (see the module docstring)."""
        if now - self._host_hb_t < self.host_heartbeat_period_s:
            return
        fed = self._fed_t
        if (self.feed_timeout_s is not None and fed is not None
                and now - fed > self.feed_timeout_s and self._file_commanded()):
            self.withheld += 1
            if not self._withholding:
                self._withholding = True
                log.error("epos4 host heartbeat withheld: the control path is silent while "
                          "the file turns", device=self.name,
                          silent_ms=round((now - fed) * 1e3),
                          limit_ms=round(self.feed_timeout_s * 1e3),
                          drive_stops_after_ms=self.consumer_ms)
            return
        if self._withholding:
            self._withholding = False
            log.warning("epos4 host heartbeat resumed", device=self.name)
        gap = now - self._host_hb_t
        if gap > self.host_heartbeat_gap_max_s and self.host_heartbeats:
            self.host_heartbeat_gap_max_s = gap
        self._host_hb_t = now
        self.host_heartbeats += 1
        self._send(self._host_hb_cob, co.encode_heartbeat(NmtState.OPERATIONAL))

    async def _wait_answered(self, n_syncs: int, deadline: float) -> bool:
        """Wait until SYNC number ``n_syncs`` is answered (or expired as lost)."""
        ev = self._rx_event
        while self._matched + self.lost < n_syncs:
            left = deadline - time.monotonic()
            if left <= 0 or ev is None:
                return False
            ev.clear()
            try:
                await asyncio.wait_for(ev.wait(), left)
            except TimeoutError:
                return False
        return True

    async def _sync_loop(self) -> None:
        await self._cyclic(self.exchange)   # a failed send: counted, logged, read() reports it

    def start_sync(self) -> None:
        """Start the own cyclic task (RxPDOs + SYNC every ``sync_period_s``); no-op if it
        runs. ``connect(sync=True)`` does this."""
        if not self._started:
            raise DeviceFault(self.name, "not connected")
        if self._sync_task is None or self._sync_task.done():
            self._sync_task = asyncio.get_running_loop().create_task(
                self._sync_loop(), name=f"{self.name}-sync")

    async def stop_sync(self) -> None:
        """Stop the own cyclic task (hand the cycle over to :meth:`exchange`). The drive keeps
        its last commands; ``read()`` turns stale unless someone exchanges."""
        task, self._sync_task = self._sync_task, None
        await cancel_until_done(task)

    async def _drive_cycles_until(self, pred: Callable[[], bool], deadline: float) -> bool:
        """Wait for ``pred`` while cycles run (the own task's, or exchanges made here)."""
        while not pred():
            if time.monotonic() > deadline:
                return False
            if self._sync_task is None or self._sync_task.done():
                await self.exchange(wait=True)
                if not pred():
                    await asyncio.sleep(self.sync_period_s)
            else:
                await asyncio.sleep(self.sync_period_s)
        return True

    async def _cycles(self, n: int, deadline: float) -> bool:
        target = self.syncs_sent + n
        return await self._drive_cycles_until(lambda: self._matched + self.lost >= target,
                                              deadline)

    # ================================================================== reception
    def _on_tpdo1(self, data: bytes, now: float) -> None:
        sw, vel, mode = _TX1.unpack(data, "TxPDO1")
        state = co.state_from_statusword(sw)
        if self._tx1 is not None:
            self.incomplete += 1
        self._tx1 = (sw, state, vel, mode)
        self.statusword, self.state, self.mode_display = sw, state, mode
        # answers come in SYNC order: this one answers SYNC number matched + lost + 1
        if (self._sp == "sent" and mode == Mode.PROFILE_POSITION and sw & SW_SETPOINT_ACK
                and self._matched + self.lost + 1 >= self._sp_sync):
            self._sp = "acked"

    def _on_tpdo2(self, data: bytes, now: float) -> None:
        pos, current_ma = _TX2.unpack(data, "TxPDO2")
        tx1, self._tx1 = self._tx1, None
        if tx1 is None:
            self.incomplete += 1
            return
        sw, state, vel, _mode = tx1
        if self._pos_raw is not None:
            self._pos_inc += co.unwrap_i32_delta(pos, self._pos_raw)
        else:
            self._pos_inc = pos
        self._pos_raw = pos
        self.received += 1
        if self._outstanding:
            lat = now - self._outstanding.popleft()
            self._matched += 1
            self.latency_last_s = lat
            self._latency_sum += lat
            self.latency_max_s = max(self.latency_max_s, lat)
        else:
            self.unsolicited += 1
        g = self.gear_ratio
        fault = None
        if self._emcy_fault is not None:
            fault = self._emcy_cause()
        elif state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            fault = f"drive in {state.value} (statusword 0x{sw:04X})"
        self._sample = MotorState(
            t=now, seq=self.received, velocity_rpm=vel / g,
            position_deg=self._pos_inc * 360.0 / (self.counts_per_turn * g),
            current_a=current_ma / 1000.0, enabled=state is State.OPERATION_ENABLED,
            fault=fault)
        if self._rx_event is not None:
            self._rx_event.set()

    def _on_sdo(self, data: bytes, now: float) -> None:
        self._on_sdo_response(self.node_id, data,
                              "SDO response for {index}:{sub} that nobody asked for")

    def _on_emcy(self, data: bytes, now: float) -> None:
        emcy = co.decode_emcy(data)
        self.emcy_count += 1
        self.last_emcy = emcy
        if emcy.is_reset:
            self._emcy_fault = None
            self._emcy_later = 0
            log.info("epos4 EMCY error reset", device=self.name)
        else:
            # the first error of an episode is its cause: the ones that follow (an
            # under-voltage after an over-current, a following error after either) are
            # consequences, counted but not reported in its place
            if self._emcy_fault is None:
                self._emcy_fault = emcy
            else:
                self._emcy_later += 1
            log.warning("epos4 EMCY", device=self.name, code=f"0x{emcy.code:04X}",
                        meaning=emcy.meaning, register=f"0x{emcy.register:02X}")

    def _on_heartbeat(self, data: bytes, now: float) -> None:
        state = co.decode_heartbeat(data)
        self.heartbeats += 1
        self._hb_t = now
        if state is NmtState.BOOT_UP and self._started:
            self._rebooted = True
            log.error("epos4 node rebooted", device=self.name, node=self.node_id)
        self.nmt_state = state

    # ================================================================== health
    def _emcy_cause(self) -> str:
        """The first EMCY of the episode, and how many came after it."""
        text = self._emcy_fault.describe()
        if self._emcy_later:
            text += f" (first of {self._emcy_later + 1} EMCYs; last {self.last_emcy.describe()})"
        return text

    def _fault_message(self) -> str | None:
        if self._link_error is not None:
            return f"CAN link down ({self._bus_description()}): {self._link_error}"
        if self._rebooted:
            return (f"node {self.node_id} sent a boot-up message: it was reset and lost its "
                    "PDO configuration; reconnect")
        if self._emcy_fault is not None:
            return f"{self._emcy_cause()}; drive in FAULT: call fault_reset(), then enable()"
        if self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            return (f"drive in {self.state.value} (statusword "
                    f"{co.describe_statusword(self.statusword or 0)}): call fault_reset()")
        return None

    def _check_link(self) -> None:
        if not self._started:
            raise DeviceFault(self.name, "closed" if self._closed else "not connected")
        msg = self._fault_message()
        if msg is not None:
            raise DeviceFault(self.name, msg)

    async def read(self) -> MotorState:
        """Newest motor state at the file, without waiting; :class:`DeviceFault` if there is
        none, it is stale, the heartbeat stopped, or the drive/link is faulted. Feeds the
        control-path watchdog (:meth:`feed`): the control task reads every tick. Diagnostics
        that must not count as the control path use :attr:`last`."""
        self.feed()
        self._check_link()
        s = self._sample
        if s is None:
            raise DeviceFault(self.name, "no sample yet: no TxPDO pair has answered a SYNC")
        now = time.monotonic()
        age = now - s.t
        if age > self.stale_after_s:
            raise DeviceFault(self.name, f"stale: newest TxPDO is {age * 1e3:.1f} ms old "
                                         f"(limit {self.stale_after_s * 1e3:.0f} ms)")
        if self.heartbeat_ms:
            hb_age = now - self._hb_t
            if hb_age > self.heartbeat_timeout_s:
                raise DeviceFault(self.name, f"heartbeat lost: none for {hb_age * 1e3:.0f} ms "
                                             f"(limit {self.heartbeat_timeout_s * 1e3:.0f} ms, "
                                             f"period {self.heartbeat_ms} ms)")
        if self.nmt_state is not NmtState.OPERATIONAL:
            name = self.nmt_state.name if self.nmt_state is not None else "unknown"
            raise DeviceFault(self.name, f"node {self.node_id} is NMT {name}, not OPERATIONAL")
        return s

    @property
    def last(self) -> MotorState | None:
        """Newest sample whatever the health (None before the first); for diagnostics."""
        return self._sample

    @property
    def connected(self) -> bool:
        return self._started

    @property
    def latency_mean_s(self) -> float:
        return self._latency_sum / self._matched if self._matched else 0.0

    def file_torque_mnm(self, current_a: float | None = None, efficiency: float = 1.0) -> float:
        """File torque (mNm) from a motor current (A; default the newest sample's):
        ``I * Km * gear * efficiency`` with Km read from 0x3001:05 (thesis eq 5.4-5.5)."""
        if current_a is None:
            if self._sample is None:
                raise DeviceFault(self.name, "no sample yet")
            current_a = self._sample.current_a
        return current_a * self.km_mnm_per_a * self.gear_ratio * efficiency

    # ================================================================== CiA 402 commands
    def _check_enabled(self, what: str) -> None:
        self._check_link()
        if self.state is not State.OPERATION_ENABLED:
            st = self.state.value if self.state is not None else "unknown"
            raise DeviceFault(self.name, f"{what}: drive not enabled (state {st}); "
                                         "call enable()")

    async def enable(self, timeout_s: float | None = None) -> None:
        """CiA 402 enable sequence to OPERATION ENABLED (shutdown -> switch on -> enable
        operation, from wherever the drive is), each step confirmed by the statusword.
        :class:`DeviceFault` naming the state if it gets stuck, or if the drive is in FAULT
        (call :meth:`fault_reset` first)."""
        if not self._started:
            raise DeviceFault(self.name, "not connected")
        timeout = self.state_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        while self.state is not State.OPERATION_ENABLED:
            st = self.state
            if st in (State.FAULT, State.FAULT_REACTION_ACTIVE) or self._emcy_fault:
                raise DeviceFault(self.name, f"enable: {self._fault_message()}")
            step = ENABLE_STEP.get(st) if st is not None else None
            if step is not None:
                self._cw = CONTROLWORD[step]
            if not await self._drive_cycles_until(lambda st=st: self.state is not st,
                                                  deadline):
                sent = f"0x{self._cw:04X} ({step.value})" if step else "nothing (waiting)"
                raise DeviceFault(self.name, (
                    f"enable: stuck in {st.name if st else 'unknown'} (statusword "
                    f"{co.describe_statusword(self.statusword or 0)}) for {timeout} s; "
                    f"controlword sent {sent}"))
        self._cw = CONTROLWORD[Command.ENABLE_OPERATION]
        log.info("epos4 operation enabled", device=self.name)

    async def recover(self) -> None:
        """After a fault, on the operator's reset: clear a latched drive fault, then enable
        the output (the velocity setpoint is 0: the file stays still until commanded)."""
        await self.fault_reset()
        await self.enable()

    async def fault_reset(self, timeout_s: float | None = None) -> None:
        """Clear a FAULT: controlword bit 7 low for a cycle, then high (rising edge); wait for
        SWITCH ON DISABLED. The drive stays disabled: call :meth:`enable` afterwards. No-op
        when there is no fault."""
        if not self._started:
            raise DeviceFault(self.name, "not connected")
        if self.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE) \
                and self._emcy_fault is None:
            return
        timeout = self.state_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        self._mode, self._target_vel, self._sp = int(Mode.PROFILE_VELOCITY), 0, "idle"
        self._cw = CONTROLWORD[Command.DISABLE_VOLTAGE]            # bit 7 low first
        await self._cycles(2, deadline)
        # a drive takes the fault reset (transition 15) in FAULT only: let the fault reaction
        # (a stop on the quick-stop ramp) end first
        await self._drive_cycles_until(
            lambda: self.state is not State.FAULT_REACTION_ACTIVE, deadline)
        self._cw = CONTROLWORD[Command.FAULT_RESET]
        ok = await self._drive_cycles_until(
            lambda: self.state not in (State.FAULT, State.FAULT_REACTION_ACTIVE), deadline)
        self._cw = CONTROLWORD[Command.DISABLE_VOLTAGE]
        if not ok:
            raise DeviceFault(self.name, (
                f"fault reset: still in FAULT after {timeout} s (statusword "
                f"{co.describe_statusword(self.statusword or 0)}; last "
                f"{self.last_emcy.describe() if self.last_emcy else 'EMCY: none'})"))
        self._emcy_fault = None
        self._emcy_later = 0
        log.info("epos4 fault reset", device=self.name)

    async def set_velocity(self, rpm: float) -> None:
        """Turn the file at ``rpm`` (profile velocity mode; motor target = rpm * gear)."""
        rpm = float(rpm)
        if not (math.isfinite(rpm) and abs(rpm) <= self.max_file_rpm):
            raise ConfigError("epos4.velocity_rpm", rpm,
                              f"|rpm| <= {self.max_file_rpm} at the file")
        self._check_enabled("set_velocity")
        self._target_vel = round(rpm * self.gear_ratio)
        self._mode = int(Mode.PROFILE_VELOCITY)
        self._sp = "idle"

    async def move_relative(self, deg: float, rpm: float | None = None) -> None:
        """Turn the file by ``deg`` at ``rpm`` (default ``move_rpm``), then hold (profile
        position mode, relative). Returns at once; see :meth:`wait_move_done`."""
        deg = float(deg)
        rpm = self.move_rpm if rpm is None else float(rpm)
        if not (math.isfinite(rpm) and 0 < rpm <= self.max_file_rpm):
            raise ConfigError("epos4.move_rpm", rpm, f"0 < rpm <= {self.max_file_rpm}")
        inc = round(deg * self.gear_ratio * self.counts_per_turn / 360.0) \
            if math.isfinite(deg) else None
        if inc is None or not _I32_MIN <= inc <= _I32_MAX:
            raise ConfigError("epos4.move_deg", deg, "a finite angle within the INTEGER32 "
                                                     "target position range")
        self._check_enabled("move_relative")
        self._target_pos = inc
        self._profile_vel = round(rpm * self.gear_ratio)
        self._mode = int(Mode.PROFILE_POSITION)
        self._sp = "request"

    @property
    def move_done(self) -> bool:
        """The last ``move_relative`` was acknowledged and its target reached."""
        return (self._mode == Mode.PROFILE_POSITION and self._sp == "acked"
                and self.mode_display == Mode.PROFILE_POSITION
                and bool((self.statusword or 0) & SW_TARGET_REACHED))

    async def wait_move_done(self, timeout_s: float = 5.0) -> None:
        """Wait for the end of the move; :class:`DeviceFault` on fault or timeout."""
        deadline = time.monotonic() + timeout_s
        ok = await self._drive_cycles_until(
            lambda: self.move_done or self._fault_message() is not None, deadline)
        self._check_link()
        if not ok:
            raise DeviceFault(self.name, f"move not finished within {timeout_s} s (statusword "
                                         f"{co.describe_statusword(self.statusword or 0)})")

    async def stop(self) -> None:
        """Stop turning: profile velocity mode with target 0 rpm. The drive ramps down and
        stays enabled, holding zero speed. Never raises for a disabled or faulted drive."""
        self._target_vel = 0
        self._mode = int(Mode.PROFILE_VELOCITY)
        self._sp = "idle"

    async def quick_stop(self) -> None:
        """CiA 402 quick stop (controlword 0x02): the drive stops on its quick-stop ramp and
        goes to QUICK STOP ACTIVE; :meth:`enable` brings it back."""
        self._target_vel = 0
        self._sp = "idle"
        self._cw = CONTROLWORD[Command.QUICK_STOP]

    async def set_current_limit(self, amps: float) -> None:
        """Limit the motor current to ``amps`` (A): the output current limit 0x3001:02 (mA),
        above which the drive's current controller clamps, so the torque at the file cannot
        exceed ``amps x Km x gear x efficiency``. At most the motor's nominal current read at
        start-up (0x3001:01). An SDO write read back (:class:`ConfigurationMismatch` if the
        drive holds another value): call it before the control loop's first tick, never
        inside the loop (SDOs belong to start-up: an SDO round trip does not fit in a tick)."""
        amps = float(amps)
        top = self.nominal_current_a or math.inf
        if not (math.isfinite(amps) and 0.0 < amps <= top):
            raise ConfigError("epos4.current_limit_a", amps,
                              f"0 < A <= {top:g} (the motor's nominal current 0x3001:01)")
        if not self._started:
            raise DeviceFault(self.name, "set_current_limit: not connected")
        o = co.obj("motor_output_current_limit")
        value = max(1, round(amps * 1000.0))
        await self.sdo_write(o, value)
        got = await self.sdo_read(o)
        if got != value:
            raise ConfigurationMismatch(self.name, o, value, got,
                                        "the drive would not limit the current as configured")
        log.info("epos4 current limit", device=self.name, limit_ma=got)

    async def nmt(self, command: NmtCommand) -> None:
        """Send an NMT command to the drive (diagnostics; the start-up does what is needed)."""
        self._send_nmt(command, self.node_id)


__all__ = ["DEFAULT_CONSUMER_MS", "DEFAULT_COUNTS_PER_TURN", "DEFAULT_FEED_TIMEOUT_S",
           "DEFAULT_HOST_HEARTBEAT_PERIOD_S", "DEFAULT_HOST_NODE_ID",
           "DEFAULT_QUICK_STOP_FILE_RPM_S", "ConfigurationMismatch", "Epos4Driver", "SdoAbort",
           "SocketcandBus"]
