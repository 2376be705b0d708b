"""Simulated CiA 406 draw-wire encoders on a python-can bus, over a World.

:class:`TrackerNodes` puts one CANopen slave per string (default node ids 0x21..0x26) on a
bus, reading the string lengths of :class:`~dentibot.sim.tracker_device.StringModel`, so
that :class:`dentibot.io.tracker.TrackerDriver` (or any CANopen master) reads them on
python-can's ``virtual`` bus or through :class:`~dentibot.sim.socketcand.SocketcandServer`.

Per node (framing from :mod:`dentibot.io.canopen_protocol`, objects from
:mod:`dentibot.io.cia406`):

- NMT: boot-up message at ``start()`` and after a reset, then PRE-OPERATIONAL; START, STOP,
  ENTER PRE-OPERATIONAL, RESET NODE, RESET COMMUNICATION (both resets restore the power-on
  values here). SDOs in PRE-OPERATIONAL and OPERATIONAL, PDOs in OPERATIONAL only.
- Heartbeat producer every 0x1017 ms (power-on 0: off; the master sets it).
- Expedited SDO server over :data:`~dentibot.io.cia406.OBJECTS` (aborts: no object
  0x06020000, read-only 0x06010002, length 0x06070010, segmented 0x05040001, PDO parameters
  while OPERATIONAL 0x08000022, mapping while sub 0 != 0 or the PDO is valid 0x06010000,
  an unmappable entry 0x06040041).
- TPDO1 (power-on: position value, not valid until the master validates it; transmission
  type 1) sent on every n-th SYNC for types 0..240 (type 0 on every SYNC); the asynchronous
  types 254/255 are accepted but not transmitted.
- Position value 0x6004: with the scaling function on (0x6000 bit 2) ``round(extension /
  drum x 0x6001)`` wrapped at 0x6002, else in the physical resolution (0x6501 per turn);
  plus the preset offset (writing 0x6003 makes the position value equal to it now).

Test hooks: ``muted`` (a node that says nothing: cut cable or power loss) and the model's
``broken`` / ``held_mm`` (a snapped or caught wire). The node never steps the World; frames
are handled in the event loop (:class:`~dentibot.io.can_reader.LoopReader`). The bus is the
caller's.
"""

from __future__ import annotations

import asyncio
from collections.abc import Sequence

import can
import structlog

from dentibot.errors import ConfigError, ProtocolError
from dentibot.io import canopen_protocol as co
from dentibot.io import cia406
from dentibot.io.canopen_protocol import NmtState
from dentibot.io.tasks import cancel_until_done
from dentibot.io.tracker import DEFAULT_NODE_IDS
from dentibot.sim.canopen_node import BusAttached, SdoServerAbort, SimNode
from dentibot.sim.tracker_device import StringModel, TrackerSimParams
from dentibot.sim.world import World

log = structlog.get_logger(__name__)

#: Identity 0x1018 of the simulated encoders: no registered vendor (0), the simulator's own
#: product code; serial number = node id.
VENDOR_ID = 0x0000_0000
PRODUCT_CODE = 0x0406_0D01
REVISION_NUMBER = 0x0001_0000
#: Physical resolution of the drum's shaft (0x6501, counts per turn; assumption) and turns
#: (0x6502).
SINGLETURN_RESOLUTION = 10_000
REVOLUTIONS = 4
_HB_TICK_S = 0.005


class EncoderNode(SimNode):
    """One simulated draw-wire encoder: string ``index`` (0-based) of ``model``."""

    def __init__(self, nodes: TrackerNodes, node_id: int, index: int) -> None:
        super().__init__(node_id)
        self.nodes = nodes
        self.index = index
        self.muted = False
        self.od: dict[tuple[int, int], int] = {}
        self.tpdos_sent = 0
        self._sync_count = 0
        self._hb_due = 0.0
        self._offset = 0
        self.reset()

    # ------------------------------------------------------------------ object dictionary
    def reset(self) -> None:
        """Power-on values of every object."""
        o = cia406.OBJECTS
        u = SINGLETURN_RESOLUTION
        values = {
            "device_type": cia406.DEVICE_TYPE_MULTITURN, "error_register": 0,
            "producer_heartbeat_time": 0, "identity_count": 4, "vendor_id": VENDOR_ID,
            "product_code": PRODUCT_CODE, "revision_number": REVISION_NUMBER,
            "serial_number": self.node_id,
            "tpdo1_highest_sub": 5,
            "tpdo1_cob_id": co.cob_id("TPDO1", self.node_id) | co.PDO_COB_INVALID
            | co.PDO_COB_NO_RTR,
            "tpdo1_transmission_type": 1, "tpdo1_inhibit_time": 0, "tpdo1_event_timer": 0,
            "tpdo1_mapped_count": 1, "tpdo1_mapping_1": cia406.POSITION_MAPPING_WORD,
            "operating_parameters": 0, "measuring_units_per_revolution": u,
            "total_measuring_range": u * REVOLUTIONS, "preset_value": 0,
            "encoder_operating_status": 0, "singleturn_resolution": u,
            "number_of_revolutions": REVOLUTIONS, "encoder_alarms": 0, "encoder_warnings": 0,
            "encoder_serial_number": self.node_id,
        }
        for s in range(2, 9):
            values[f"tpdo1_mapping_{s}"] = 0
        self.od = {o[k].address: v for k, v in values.items() if k in o}
        self._offset = 0
        self._sync_count = 0

    def _scaled(self) -> tuple[int, int]:
        """(units per turn, wrap) in effect."""
        od, o = self.od, cia406.OBJECTS
        if od[o["operating_parameters"].address] & cia406.OPERATING_SCALING:
            return (od[o["measuring_units_per_revolution"].address],
                    od[o["total_measuring_range"].address])
        return SINGLETURN_RESOLUTION, SINGLETURN_RESOLUTION * REVOLUTIONS

    def raw_position(self) -> int:
        """Position before the preset offset, from the model's counts (model step = the
        configured scaling when it matches: 0.01 mm per unit by default)."""
        m = self.nodes.model
        ext_mm = self.nodes.nodes_counts()[self.index] * m.p.resolution_mm
        upr, _ = self._scaled()
        return round(ext_mm / m.p.drum_mm_per_rev * upr)

    def position_value(self) -> int:
        _, wrap = self._scaled()
        return (self.raw_position() + self._offset) % max(1, wrap)

    def _read(self, o: co.OdObject) -> int:
        if o.name == "position_value":
            return self.position_value()
        return self.od[o.address]

    # ------------------------------------------------------------------ frames
    def send(self, can_id: int, data: bytes) -> None:
        if not self.muted:
            self.nodes._send(can_id, data)

    _send = send

    def _on_reset_node(self) -> None:
        self.reset()                            # both resets restore the power-on values

    _on_reset_communication = _on_reset_node

    def on_sync(self) -> None:
        if self.nmt_state is not NmtState.OPERATIONAL:
            return
        o = cia406.OBJECTS
        cob = self.od[o["tpdo1_cob_id"].address]
        if cob & co.PDO_COB_INVALID or self.od[o["tpdo1_mapped_count"].address] != 1:
            return
        ttype = self.od[o["tpdo1_transmission_type"].address]
        if ttype > 240:
            return
        self._sync_count += 1
        if ttype and self._sync_count % ttype:
            return
        self.send(cob & 0x7FF, cia406.POSITION_TPDO.pack((self.position_value(),)))
        self.tpdos_sent += 1

    def _lookup(self, index: int, sub: int) -> co.OdObject:
        o = cia406.OBJECTS_BY_ADDRESS.get((index, sub))
        if o is None:
            raise SdoServerAbort(0x0602_0000 if index not in
                                 {i for i, _ in cia406.OBJECTS_BY_ADDRESS} else 0x0609_0011)
        return o

    def _sdo_writable(self, o: co.OdObject) -> bool:
        return not (o.access in ("ro", "const") or o.sub == 0 and o.name.endswith("highest_sub")
                    or o.name == "identity_count")

    def _write_sdo(self, o: co.OdObject, value: int) -> None:
        od, objs = self.od, cia406.OBJECTS
        if o.index in (0x1800, 0x1A00) and self.nmt_state is NmtState.OPERATIONAL:
            raise SdoServerAbort(0x0800_0022)
        if o.index == 0x1A00:
            valid = not od[objs["tpdo1_cob_id"].address] & co.PDO_COB_INVALID
            if o.sub == 0:
                if valid or value > 1 or (value == 1 and od[objs["tpdo1_mapping_1"].address]
                                          != cia406.POSITION_MAPPING_WORD):
                    raise SdoServerAbort(0x0604_0041 if value else 0x0601_0000)
            elif valid or od[objs["tpdo1_mapped_count"].address] != 0:
                raise SdoServerAbort(0x0601_0000)
            elif o.sub == 1 and value not in (0, cia406.POSITION_MAPPING_WORD):
                raise SdoServerAbort(0x0604_0041)
        if o.name == "tpdo1_cob_id" and (value & 0x7FF) != co.cob_id("TPDO1", self.node_id):
            raise SdoServerAbort(0x0609_0030)
        if o.name == "preset_value":
            _, wrap = self._scaled()
            if value >= wrap:
                raise SdoServerAbort(0x0609_0031)
            self._offset = value - self.raw_position()
        if o.name in ("measuring_units_per_revolution", "total_measuring_range") and value == 0:
            raise SdoServerAbort(0x0609_0032)
        od[o.address] = value


class TrackerNodes(BusAttached):
    """The tracker's encoders (one :class:`EncoderNode` per string) on ``bus`` over
    ``world``. ``start()``/``close()`` (or ``async with``); the bus stays the caller's."""

    def __init__(self, world: World, bus: can.BusABC,
                 params: TrackerSimParams | None = None, *,
                 node_ids: Sequence[int] = DEFAULT_NODE_IDS, name: str = "tracker-sim") -> None:
        self.model = StringModel(world, params)
        if len(node_ids) != self.model.n or len(set(node_ids)) != len(node_ids):
            raise ConfigError("tracker_sim.node_ids", list(node_ids),
                              f"{self.model.n} distinct node ids, one per string")
        self.world = world
        self.bus = bus
        self.name = name
        self.nodes = [EncoderNode(self, nid, i) for i, nid in enumerate(node_ids)]
        self.by_id = {n.node_id: n for n in self.nodes}
        self._sdo_cobs = {co.cob_id("SDO_RX", n.node_id): n for n in self.nodes}
        self.syncs_received = 0
        self.errors = 0
        self.send_errors = 0
        self._sync_counts: tuple[int, ...] | None = None
        self._hb_task: asyncio.Task | None = None
        self._started = self._closed = False

    def node(self, node_id: int) -> EncoderNode:
        return self.by_id[node_id]

    async def start(self) -> None:
        """Attach to the bus, send every node's boot-up message, start the heartbeats."""
        if self._started:
            return
        if self._closed:
            raise ConfigError("tracker_sim", "closed", "nodes that have not been closed")
        self._attach(self.bus, self._on_message)
        self._started = True
        for n in self.nodes:
            n.boot()
        self._hb_task = asyncio.get_running_loop().create_task(
            self._heartbeat_loop(), name=f"{self.name}-heartbeat")

    async def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        task, self._hb_task = self._hb_task, None
        await cancel_until_done(task)
        self._detach()

    def _send(self, can_id: int, data: bytes) -> None:
        self._send_frame(can_id, data, "tracker sim send failed")

    def _on_message(self, msg: can.Message) -> None:
        if self._closed or msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        cid, data = msg.arbitration_id, bytes(msg.data)
        try:
            if cid == co.COB_BASE["SYNC"]:
                co.decode_sync(data)
                self.syncs_received += 1
                self._sync_counts = None         # one model reading per SYNC for all nodes
                for n in self.nodes:
                    if not n.muted:
                        n.on_sync()
            elif cid == co.COB_BASE["NMT"]:
                cmd, target = co.decode_nmt(data)
                for n in self.nodes:
                    if target in (0, n.node_id) and not n.muted:
                        n.on_nmt(cmd)
            elif cid in self._sdo_cobs:
                node = self._sdo_cobs[cid]
                if not node.muted:
                    node.on_sdo(data)
        except ProtocolError as exc:
            self.errors += 1
            log.warning("tracker sim bad frame", cob_id=hex(cid), data=data.hex(),
                        error=str(exc))

    def nodes_counts(self) -> tuple[int, ...]:
        """The model's counts, read once per SYNC (all nodes sample together)."""
        if self._sync_counts is None:
            self._sync_counts = self.model.counts()
        return self._sync_counts

    async def _heartbeat_loop(self) -> None:
        loop = asyncio.get_running_loop()
        hb = cia406.OBJECTS["producer_heartbeat_time"].address
        while True:
            await asyncio.sleep(_HB_TICK_S)
            now = loop.time()
            for n in self.nodes:
                period = n.od[hb] / 1000.0
                if period <= 0 or n.muted or n.nmt_state is NmtState.BOOT_UP:
                    n._hb_due = now
                    continue
                if now >= n._hb_due + period:
                    n._hb_due = now
                    n.send_heartbeat()


__all__ = ["PRODUCT_CODE", "VENDOR_ID", "EncoderNode", "TrackerNodes"]
