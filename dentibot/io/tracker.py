"""Patient tracker driver: six CiA 406 draw-wire encoders over CANopen, asyncio.

:class:`TrackerDriver` implements :class:`dentibot.io.interfaces.PatientTracker` on any
python-can bus, opened by :class:`~dentibot.io.canopen_master.CanOpenMaster`: kernel
SocketCAN, a socketcand server (the bounded client
:class:`~dentibot.io.canopen_master.SocketcandBus`), python-can's ``virtual`` bus, or a
factory. It gives string lengths; the pose is :func:`dentibot.control.strings.forward`'s
business.

Start-up (``connect()``), per encoder node, SDOs with ``sdo_timeout_s`` each:

1. NMT *enter pre-operational*.
2. Identity: device type 0x1000 (low word 406, else :class:`DeviceFault`), vendor id,
   product code, revision and serial number 0x1018; an expected vendor id or product code
   that differs is an :class:`IdentityMismatch`. No answer to the first SDO is a
   :class:`~dentibot.io.interfaces.ConnectTimeout` naming the node.
3. Configuration (``configure=True``): operating parameters 0x6000 (scaling on), measuring
   units per revolution 0x6001, total measuring range 0x6002, producer heartbeat 0x1017,
   TPDO1 = position value 0x6004 with transmission type ``transmission_type`` (COB-ID
   invalid -> type -> count 0 -> entry -> count 1 -> COB-ID valid). Everything is read
   back; a difference is a :class:`~dentibot.io.canopen_master.ConfigurationMismatch`
   (``configure=False``: only the comparison).
4. NMT *start*.

SYNC: with ``sync_producer=True`` the driver sends SYNC every ``sync_period_s`` (its own
task); otherwise another master does (in a DentiBot run, the handpiece driver at 500 Hz)
and the driver only listens. The encoders answer every ``transmission_type``-th SYNC.

Samples: each SYNC heard after at least one TPDO closes a sample (``seq`` + 1) from the
newest position value of every node. ``read()`` never waits; per string
(:data:`~dentibot.io.interfaces.STRING_OK` ...): ``no_data`` before its first TPDO,
``fault`` when the node's heartbeat is older than ``heartbeat_timeout_s``, its NMT state is
not OPERATIONAL, it rebooted, or an EMCY reports an error; ``stale`` when its newest TPDO is
older than ``stale_after_s``; ``slack`` below ``min_length_mm``; ``over_range`` above
``max_length_mm`` or at the end of the encoder's range. ``read()`` raises only when the
driver is not connected or the link is down.

Length of string i: ``l_i = zero_length_mm[i] + counts_i * resolution_mm``, where
``resolution_mm = drum_mm_per_rev / units_per_revolution`` is the measuring step.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import can
import structlog

from dentibot.errors import ConfigError, DeviceFault, ProtocolError
from dentibot.io import canopen_protocol as co
from dentibot.io import cia406
from dentibot.io.canopen_master import CanOpenMaster, ConfigurationMismatch
from dentibot.io.canopen_protocol import NmtCommand, NmtState, OdObject
from dentibot.io.interfaces import (
    STRING_FAULT,
    STRING_NO_DATA,
    STRING_OK,
    STRING_OVER_RANGE,
    STRING_SLACK,
    STRING_STALE,
    ConnectTimeout,
    StringSample,
)
from dentibot.io.tasks import cancel_until_done

log = structlog.get_logger(__name__)

#: Default node ids of strings 1..6.
DEFAULT_NODE_IDS = (0x21, 0x22, 0x23, 0x24, 0x25, 0x26)
#: Measuring step (mm): the 0.01 mm resolution class of draw-wire encoders with a CANopen
#: interface (assumption: the encoder chosen reaches it with its drum and counts per turn).
DEFAULT_RESOLUTION_MM = 0.01
#: Wire drawn per drum turn (mm; assumption, a 100 mm drum circumference).
DEFAULT_DRUM_MM_PER_REV = 100.0
#: Measuring range (mm; assumption, the smallest common range class of draw-wire encoders).
DEFAULT_RANGE_MM = 300.0
#: String length at position value 0 (mm; wire fully in, from the exit to the clamp hook).
DEFAULT_ZERO_LENGTH_MM = 20.0
#: Every SYNC: the lengths at the control rate (500 Hz with the handpiece driver's SYNC), so
#: that a jerk of the patient is seen within a tick; six encoders then take about 24 % of a
#: 1 Mbit/s bus (every 5th SYNC: 100 Hz, about 5 %).
DEFAULT_TRANSMISSION_TYPE = 1
#: How often a start waiting for its nodes' heartbeats looks at them (s).
_CONFIRM_POLL_S = 0.002


class IdentityMismatch(DeviceFault):
    """An encoder's identity 0x1018 is not the one configured."""


class _Node:
    """What the driver knows of one encoder."""

    def __init__(self, node_id: int) -> None:
        self.node_id = node_id
        self.counts: int | None = None
        self.t = -math.inf               # newest TPDO
        self.hb_t = -math.inf            # newest heartbeat
        self.nmt: NmtState | None = None
        self.rebooted = False
        self.emcy: co.Emcy | None = None
        self.identity: dict[str, int] = {}
        self.tpdos = 0


class TrackerDriver(CanOpenMaster):
    """Six (or three or more) CiA 406 draw-wire encoders (``dentibot.io.PatientTracker``).

    Args:
        bus_factory, interface, channel, host, port, bus_kwargs, connect_timeout_s: the bus,
            as for :class:`~dentibot.io.canopen_master.CanOpenMaster`.
        node_ids: node ids of strings 1..n (default 0x21..0x26).
        resolution_mm, drum_mm_per_rev, range_mm: measuring step, wire per drum turn and
            range (0x6001 = drum / step, 0x6002 = range / step).
        zero_length_mm: string length at position value 0 (one value, or one per string).
        min_length_mm, max_length_mm: readings outside are ``slack`` / ``over_range``.
        transmission_type: TPDO1 sent every n-th SYNC (1..240).
        sync_producer: send SYNC every ``sync_period_s`` (True), or listen to another
            master's (False).
        heartbeat_ms: the encoders' producer heartbeat 0x1017 (ms);
            heartbeat_timeout_s: silence that makes a string ``fault``.
        stale_after_s: a string whose newest TPDO is older is ``stale``.
        sdo_timeout_s: per SDO request. configure: write the configuration (True) or only
            verify it.
        vendor_id, product_code: expected identity (None: any, logged).
    """

    log_name = "tracker"

    def __init__(self, bus_factory: Callable[[], can.BusABC] | None = None, *,
                 interface: str = "socketcan", channel: str = "can0",
                 host: str = "127.0.0.1", port: int = 29536,
                 bus_kwargs: dict[str, Any] | None = None,
                 node_ids: Sequence[int] = DEFAULT_NODE_IDS,
                 resolution_mm: float = DEFAULT_RESOLUTION_MM,
                 drum_mm_per_rev: float = DEFAULT_DRUM_MM_PER_REV,
                 range_mm: float = DEFAULT_RANGE_MM,
                 zero_length_mm: float | Sequence[float] = DEFAULT_ZERO_LENGTH_MM,
                 min_length_mm: float = 30.0, max_length_mm: float = 300.0,
                 transmission_type: int = DEFAULT_TRANSMISSION_TYPE,
                 sync_producer: bool = False, sync_period_s: float = 0.002,
                 heartbeat_ms: int = 100, heartbeat_timeout_s: float = 0.35,
                 stale_after_s: float = 0.1, sdo_timeout_s: float = 0.5,
                 connect_timeout_s: float = 2.0, configure: bool = True,
                 vendor_id: int | None = None, product_code: int | None = None,
                 name: str = cia406.DEVICE) -> None:
        ids = [co.check_node_id(n) for n in node_ids]
        if len(ids) < 3 or len(set(ids)) != len(ids):
            raise ConfigError("tracker.node_ids", list(node_ids), "3 or more distinct node ids")
        for fld, v in (("resolution_mm", resolution_mm), ("drum_mm_per_rev", drum_mm_per_rev),
                       ("range_mm", range_mm), ("sync_period_s", sync_period_s),
                       ("heartbeat_timeout_s", heartbeat_timeout_s),
                       ("stale_after_s", stale_after_s), ("sdo_timeout_s", sdo_timeout_s),
                       ("connect_timeout_s", connect_timeout_s),
                       ("max_length_mm", max_length_mm)):
            if isinstance(v, bool) or not (isinstance(v, int | float) and math.isfinite(v)
                                           and v > 0):
                raise ConfigError(f"tracker.{fld}", v, "a finite number > 0")
        if not (isinstance(transmission_type, int) and 1 <= transmission_type <= 240):
            raise ConfigError("tracker.transmission_type", transmission_type,
                              "1..240 (synchronous: every n-th SYNC, CiA 301)")
        if not (isinstance(heartbeat_ms, int) and 1 <= heartbeat_ms <= 0xFFFF):
            raise ConfigError("tracker.heartbeat_ms", heartbeat_ms, "1..65535 ms")
        if heartbeat_timeout_s * 1000.0 < 2 * heartbeat_ms:
            raise ConfigError("tracker.heartbeat_timeout_s", heartbeat_timeout_s,
                              f"at least two heartbeat periods ({2 * heartbeat_ms} ms)")
        zl = ([float(zero_length_mm)] * len(ids) if isinstance(zero_length_mm, int | float)
              else [float(z) for z in zero_length_mm])
        if len(zl) != len(ids) or not all(math.isfinite(z) and z >= 0 for z in zl):
            raise ConfigError("tracker.zero_length_mm", zero_length_mm,
                              f"one length >= 0 mm, or {len(ids)} of them")
        if not 0 <= min_length_mm < max_length_mm:
            raise ConfigError("tracker.min_length_mm", min_length_mm,
                              f"0 <= min < max_length_mm ({max_length_mm})")
        self.units_per_revolution = round(drum_mm_per_rev / resolution_mm)
        self.total_range_units = round(range_mm / resolution_mm)
        if not (1 <= self.units_per_revolution <= 0xFFFF_FFFF
                and 1 <= self.total_range_units <= 0xFFFF_FFFF):
            raise ConfigError("tracker.resolution_mm", resolution_mm,
                              "a step giving 1..2^32-1 units per turn and per range")
        super().__init__(bus_factory, interface=interface, channel=channel, host=host,
                         port=port, bus_kwargs=bus_kwargs, sdo_timeout_s=sdo_timeout_s,
                         connect_timeout_s=connect_timeout_s, sync_period_s=sync_period_s,
                         heartbeat_ms=heartbeat_ms, heartbeat_timeout_s=heartbeat_timeout_s,
                         name=name)
        self.node_ids = tuple(ids)
        self.resolution_mm = float(resolution_mm)
        self.zero_length_mm = tuple(zl)
        self.min_length_mm, self.max_length_mm = float(min_length_mm), float(max_length_mm)
        self.transmission_type = transmission_type
        self.sync_producer = bool(sync_producer)
        self.stale_after_s = float(stale_after_s)
        self.configure = bool(configure)
        self.expected_vendor_id, self.expected_product_code = vendor_id, product_code
        self.nodes = {n: _Node(n) for n in ids}
        self._handlers[co.COB_BASE["SYNC"]] = lambda data, now: self._on_sync(now)
        for n in ids:
            self._handlers[co.cob_id("TPDO1", n)] = partial(self._on_tpdo, n)
            self._handlers[co.cob_id("SDO_TX", n)] = partial(self._on_sdo, n)
            self._handlers[co.cob_id("EMCY", n)] = partial(self._on_emcy, n)
            self._handlers[co.cob_id("HEARTBEAT", n)] = partial(self._on_heartbeat, n)
        # counters
        self.syncs_sent = 0
        self.syncs_heard = 0
        self.samples = 0
        # state
        self._fresh = False          # a TPDO since the last sample was closed
        self._sample: StringSample | None = None
        self._sync_task: asyncio.Task | None = None

    # ================================================================== lifecycle

    async def connect(self) -> None:
        """Open the bus, identify and configure every encoder, start them (and the own SYNC
        when ``sync_producer``). A failure closes what was opened, then raises."""
        if self._connected:
            return
        if self._closed:
            raise DeviceFault(self.name, "driver closed; create a new one to reconnect")
        loop = asyncio.get_running_loop()
        await self._open_bus()
        try:
            for nid in self.node_ids:
                await self._start_node(nid)
            await self._await_operational(self.node_ids)
            self._started = True
            if self.sync_producer:
                self._sync_task = loop.create_task(self._sync_loop(), name=f"{self.name}-sync")
        except BaseException:
            await self.close()
            raise
        log.info("tracker started", device=self.name, nodes=[hex(n) for n in self.node_ids],
                 sync_producer=self.sync_producer, transmission_type=self.transmission_type)

    async def _start_node(self, nid: int) -> None:
        node = self.nodes[nid]
        self._send_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, nid)
        try:
            dtype = await self.sdo_read(nid, "device_type")
        except _SdoTimeout:
            raise ConnectTimeout(self.name, f"node 0x{nid:02X} on {self._bus_description()}",
                                 "SDO answer to the device type 0x1000",
                                 self.sdo_timeout_s) from None
        if dtype & 0xFFFF != cia406.PROFILE:
            raise DeviceFault(self.name, f"node 0x{nid:02X}: device type 0x{dtype:08X} is not "
                                         f"a CiA 406 encoder (low word must be 406 = 0x0196)")
        ident = {k: await self.sdo_read(nid, k) for k in
                 ("vendor_id", "product_code", "revision_number", "serial_number")}
        ident["device_type"] = dtype
        node.identity = ident
        for key, want in (("vendor_id", self.expected_vendor_id),
                          ("product_code", self.expected_product_code)):
            if want is not None and ident[key] != want:
                raise IdentityMismatch(self.name, f"node 0x{nid:02X}: {key} "
                                                  f"0x{ident[key]:08X}, expected 0x{want:08X}")
        await self._configure_node(nid)
        node.rebooted, node.emcy = False, None
        node.hb_t = time.monotonic()        # the heartbeat is watched from the start on
        node.nmt = None                      # unknown until a heartbeat after the start
        self._send_nmt(NmtCommand.START, nid)
        log.info("tracker encoder", device=self.name, node=hex(nid),
                 **{k: hex(v) for k, v in ident.items()})

    async def _configure_node(self, nid: int) -> None:
        o = cia406.obj
        cob = co.cob_id("TPDO1", nid) | co.PDO_COB_NO_RTR
        want: list[tuple[OdObject, int]] = [
            (o("operating_parameters"), cia406.OPERATING_SCALING),
            (o("measuring_units_per_revolution"), self.units_per_revolution),
            (o("total_measuring_range"), self.total_range_units),
            (o("producer_heartbeat_time"), self.heartbeat_ms),
            (o("tpdo1_transmission_type"), self.transmission_type),
            (o("tpdo1_mapped_count"), 1),
            (o("tpdo1_mapping_1"), cia406.POSITION_MAPPING_WORD),
            (o("tpdo1_cob_id"), cob),
        ]
        if self.configure:
            for ob, v in want[:4]:
                await self.sdo_write(nid, ob, v)
            await self.sdo_write(nid, o("tpdo1_cob_id"), cob | co.PDO_COB_INVALID)
            await self.sdo_write(nid, o("tpdo1_transmission_type"), self.transmission_type)
            await self.sdo_write(nid, o("tpdo1_mapped_count"), 0)
            await self.sdo_write(nid, o("tpdo1_mapping_1"), cia406.POSITION_MAPPING_WORD)
            await self.sdo_write(nid, o("tpdo1_mapped_count"), 1)
            await self.sdo_write(nid, o("tpdo1_cob_id"), cob)
        for ob, v in want:
            got = await self.sdo_read(nid, ob)
            if ob.name == "tpdo1_cob_id":
                mask = co.PDO_COB_INVALID | 0x7FF
                got_cmp, v_cmp = got & mask, v & mask
            elif ob.name == "operating_parameters":
                got_cmp, v_cmp = got & cia406.OPERATING_SCALING, v
            else:
                got_cmp, v_cmp = got, v
            if got_cmp != v_cmp:
                raise ConfigurationMismatch(self.name, ob, v, got,
                                            f"node 0x{nid:02X} would not report the string "
                                            "length as configured")

    async def close(self) -> None:
        """Stop the own SYNC, send the encoders to pre-operational (PDOs off), stop the
        reader and shut the bus down. Idempotent."""
        if self._closed:
            return
        self._closed = True
        task, self._sync_task = self._sync_task, None
        await cancel_until_done(task)
        if self._started and self._link_error is None:
            for nid in self.node_ids:
                try:
                    self._send_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, nid)
                except DeviceFault:
                    break
        await self._teardown()
        log.info("tracker closed", device=self.name, samples=self.samples, errors=self.errors)

    async def recover(self) -> None:
        """Restart every encoder that is not healthy (rebooted, not OPERATIONAL, EMCY,
        heartbeat lost): identify, configure and start it again."""
        if not self._started:
            raise DeviceFault(self.name, "not connected")
        now = time.monotonic()
        restarted = [nid for nid, node in self.nodes.items()
                     if self._node_fault(node, now) is not None]
        for nid in restarted:
            await self._start_node(nid)
        await self._await_operational(restarted)

    async def _await_operational(self, node_ids) -> None:
        """Until the heartbeat of each node of ``node_ids`` reports OPERATIONAL after its NMT
        start, at most ``heartbeat_timeout_s``: the start is confirmed, not assumed. A
        heartbeat the node sent before the start reached it still reports the state it left
        (PRE-OPERATIONAL); taken for the node's state after the start, it would fault a running
        node's string until the next heartbeat."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.heartbeat_timeout_s
        while waiting := [n for n in node_ids if self.nodes[n].nmt is not NmtState.OPERATIONAL]:
            if loop.time() >= deadline:
                states = ", ".join(
                    f"node 0x{n:02X} ({getattr(self.nodes[n].nmt, 'name', 'no heartbeat')})"
                    for n in waiting)
                raise ConnectTimeout(self.name, f"{states} on {self._bus_description()}",
                                     "heartbeat reporting OPERATIONAL after the NMT start",
                                     self.heartbeat_timeout_s)
            await asyncio.sleep(_CONFIRM_POLL_S)

    # ================================================================== SDO client
    async def sdo_read(self, node_id: int, obj: str | OdObject) -> int:
        """Read an encoder object by expedited SDO (start-up and diagnostics only)."""
        o = cia406.obj(obj) if isinstance(obj, str) else obj
        frame = await self._sdo(node_id, o, co.encode_sdo_upload(o.index, o.sub), "upload")
        if frame.kind != "upload":
            raise ProtocolError(self.name, f"SDO upload {o} from node 0x{node_id:02X}: "
                                           f"unexpected answer '{frame.kind}'")
        return o.dtype.decode(frame.payload, f"SDO upload {o}")

    async def sdo_write(self, node_id: int, obj: str | OdObject, value: int) -> None:
        """Write an encoder object by expedited SDO."""
        o = cia406.obj(obj) if isinstance(obj, str) else obj
        payload = o.dtype.encode(value, f"{self.name}.{o.name}")
        frame = await self._sdo(node_id, o, co.encode_sdo_download(o.index, o.sub, payload),
                                "download")
        if frame.kind != "download_ack":
            raise ProtocolError(self.name, f"SDO download {o} to node 0x{node_id:02X}: "
                                           f"unexpected answer '{frame.kind}'")

    async def _sdo(self, nid: int, o: OdObject, request: bytes, verb: str) -> co.SdoFrame:
        timeout = _SdoTimeout(self.name, f"SDO {verb} {o} to node 0x{nid:02X} not answered "
                                         f"within {self.sdo_timeout_s} s")
        return await self._sdo_transfer(nid, o.index, o.sub, request, verb,
                                        timeout_error=timeout,
                                        abort_device=f"{self.name} node 0x{nid:02X}")

    # ================================================================== SYNC, reception
    async def _sync_loop(self) -> None:
        await self._cyclic(self._send_sync)

    async def _send_sync(self) -> None:
        self._send(co.COB_BASE["SYNC"], co.encode_sync())
        self.syncs_sent += 1
        self._on_sync(time.monotonic())     # our own SYNC is not received back

    def _on_sync(self, now: float) -> None:
        self.syncs_heard += 1
        if self._fresh:
            self._fresh = False
            self.samples += 1
            self._sample = self._build(now, self.samples)

    def _on_tpdo(self, nid: int, data: bytes, now: float) -> None:
        (counts,) = cia406.POSITION_TPDO.unpack(data, f"TPDO1 of node 0x{nid:02X}")
        node = self.nodes[nid]
        node.counts, node.t = counts, now
        node.tpdos += 1
        self._fresh = True

    def _on_sdo(self, nid: int, data: bytes, now: float) -> None:
        self._on_sdo_response(nid, data, "SDO response of node {node} for {index}:{sub} that "
                                         "nobody asked for")

    def _on_emcy(self, nid: int, data: bytes, now: float) -> None:
        emcy = co.decode_emcy(data)
        node = self.nodes[nid]
        node.emcy = None if emcy.is_reset else emcy
        if not emcy.is_reset:
            log.warning("tracker EMCY", device=self.name, node=hex(nid),
                        code=f"0x{emcy.code:04X}", meaning=emcy.meaning)

    def _on_heartbeat(self, nid: int, data: bytes, now: float) -> None:
        state = co.decode_heartbeat(data)
        node = self.nodes[nid]
        node.hb_t = now
        if state is NmtState.BOOT_UP and self._started:
            node.rebooted = True
            log.error("tracker encoder rebooted", device=self.name, node=hex(nid))
        node.nmt = state

    # ================================================================== samples
    def _node_fault(self, node: _Node, now: float) -> str | None:
        """Why the node's string cannot be trusted (None: no fault)."""
        if node.rebooted:
            return "rebooted (configuration lost): recover()"
        if now - node.hb_t > self.heartbeat_timeout_s:
            return f"heartbeat lost for {(now - node.hb_t) * 1e3:.0f} ms"
        if node.nmt is not NmtState.OPERATIONAL:
            return f"NMT {node.nmt.name if node.nmt else 'unknown'}"
        if node.emcy is not None:
            return node.emcy.describe()
        return None

    def _status(self, node: _Node, length: float, now: float) -> str:
        if node.counts is None:
            return STRING_NO_DATA
        if self._node_fault(node, now) is not None:
            return STRING_FAULT
        if now - node.t > self.stale_after_s:
            return STRING_STALE
        if length < self.min_length_mm:
            return STRING_SLACK
        if length > self.max_length_mm or node.counts >= self.total_range_units - 1:
            return STRING_OVER_RANGE
        return STRING_OK

    def _build(self, t: float, seq: int) -> StringSample:
        counts, lens = [], []
        for i, nid in enumerate(self.node_ids):
            c = self.nodes[nid].counts
            counts.append(-1 if c is None else c)
            lens.append(math.nan if c is None else self.zero_length_mm[i] + c * self.resolution_mm)
        return StringSample(t, seq, tuple(lens), tuple(counts), ())

    async def read(self) -> StringSample:
        """Newest lengths with the status of every string as of now (never waits).
        :class:`DeviceFault` only when not connected or the CAN link is down."""
        if not self._started:
            raise DeviceFault(self.name, "closed" if self._closed else "not connected")
        if self._link_error is not None:
            raise DeviceFault(self.name, f"CAN link down ({self._bus_description()}): "
                                         f"{self._link_error}")
        now = time.monotonic()
        s = self._sample or self._build(now, 0)
        status = tuple(self._status(self.nodes[nid], s.lengths_mm[i], now)
                       for i, nid in enumerate(self.node_ids))
        return StringSample(s.t, s.seq, s.lengths_mm, s.counts, status)

    def diagnose(self) -> dict[int, str | None]:
        """Per node id: why it is faulted now (None: healthy)."""
        now = time.monotonic()
        return {nid: self._node_fault(n, now) for nid, n in self.nodes.items()}

    @property
    def connected(self) -> bool:
        return self._started


class _SdoTimeout(DeviceFault):
    """An SDO request was not answered in time."""


__all__ = ["DEFAULT_DRUM_MM_PER_REV", "DEFAULT_NODE_IDS", "DEFAULT_RANGE_MM",
           "DEFAULT_RESOLUTION_MM", "DEFAULT_TRANSMISSION_TYPE", "DEFAULT_ZERO_LENGTH_MM",
           "IdentityMismatch", "TrackerDriver"]
