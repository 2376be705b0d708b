"""Plumbing of a simulated CANopen node (CiA 301), shared by the simulated devices.

:class:`SimNode` holds what every simulated slave does the same way: the NMT state machine
(boot-up message, START, STOP, ENTER PRE-OPERATIONAL, the two resets), the heartbeat frame,
and an expedited SDO server over the node's object dictionary, whose objects (type, access)
come from the project's tables (:mod:`dentibot.io.canopen_protocol`,
:mod:`dentibot.io.cia406`). Aborts (CiA 301 codes): write-only on upload 0x06010001, not
writable 0x06010002, length 0x06070010, segmented or unknown requests 0x05040001; the node
adds its own through :class:`SdoServerAbort`. :class:`BusAttached` attaches a frame
callback to the simulator's bus (:class:`~dentibot.io.can_reader.LoopReader`, frames handed
to this event loop in batches; the bus stays the caller's).
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Self

import can
import structlog

from dentibot.io import canopen_protocol as co
from dentibot.io.can_reader import LoopReader
from dentibot.io.canopen_protocol import NmtCommand, NmtState, OdObject, SdoFrame

log = structlog.get_logger(__name__)

#: Reader receive timeout (s): how long ``close()`` may wait for the reader thread.
_READER_TIMEOUT_S = 0.05


class SdoServerAbort(Exception):
    """An SDO request the node refuses, with its CiA 301 abort ``code``."""

    def __init__(self, code: int) -> None:
        self.code = code
        super().__init__(f"SDO abort 0x{code:08X} ({co.sdo_abort_meaning(code)})")


class BusAttached:
    """Something on a python-can bus ``bus`` it does not own: :meth:`start` / :meth:`close`
    (or ``async with``)."""

    bus: can.BusABC
    send_errors: int
    _reader: LoopReader | None = None

    def _send_frame(self, can_id: int, data: bytes, failed: str, **fields: object) -> None:
        """Send a standard data frame; a failure is counted in ``send_errors`` and logged
        as ``failed`` (with ``fields``), never raised (a node does not stop on it)."""
        try:
            self.bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
        except (can.CanError, OSError) as exc:
            self.send_errors += 1
            log.warning(failed, **fields, cob_id=hex(can_id), error=str(exc))

    def _attach(self, bus: can.BusABC, callback: Callable[[can.Message], None]) -> None:
        """Hand the bus's frames to ``callback`` in the running event loop."""
        self._reader = LoopReader(bus, callback, timeout=_READER_TIMEOUT_S,
                                  loop=asyncio.get_running_loop())

    def _detach(self) -> None:
        """Stop listening (the bus stays open)."""
        if self._reader is not None:
            self._reader.stop(timeout=1.0)
            self._reader = None

    async def start(self) -> None:
        raise NotImplementedError

    async def close(self) -> None:
        raise NotImplementedError

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()


class SimNode:
    """NMT state, heartbeat frame and expedited SDO server of one simulated node.

    A subclass sends frames with :meth:`_send` and gives its object dictionary through
    :meth:`_lookup`, :meth:`_read`, :meth:`_write_sdo` (raising
    :class:`SdoServerAbort` to refuse), optionally :meth:`_sdo_writable` and the NMT hooks
    :meth:`_leave_operational`, :meth:`_on_reset_node`, :meth:`_on_reset_communication`.
    """

    def __init__(self, node_id: int) -> None:
        self.node_id = co.check_node_id(node_id)
        self.nmt_state = NmtState.BOOT_UP
        self.sdo_requests = 0
        self.sdo_aborts = 0

    def _send(self, can_id: int, data: bytes) -> None:
        raise NotImplementedError

    # ------------------------------------------------------------------ NMT (CiA 301)
    def boot(self) -> None:
        """The boot-up message (heartbeat COB-ID, state 0), then PRE-OPERATIONAL."""
        self.nmt_state = NmtState.BOOT_UP
        self._send(co.cob_id("HEARTBEAT", self.node_id), co.encode_heartbeat(NmtState.BOOT_UP))
        self.nmt_state = NmtState.PRE_OPERATIONAL

    def send_heartbeat(self) -> None:
        """One heartbeat frame with the node's NMT state."""
        self._send(co.cob_id("HEARTBEAT", self.node_id), co.encode_heartbeat(self.nmt_state))

    def on_nmt(self, cmd: NmtCommand) -> None:
        """Apply an NMT command addressed to this node."""
        if cmd is NmtCommand.START:
            self.nmt_state = NmtState.OPERATIONAL
        elif cmd is NmtCommand.STOP:
            self._leave_operational()
            self.nmt_state = NmtState.STOPPED
        elif cmd is NmtCommand.ENTER_PRE_OPERATIONAL:
            self._leave_operational()
            self.nmt_state = NmtState.PRE_OPERATIONAL
        elif cmd is NmtCommand.RESET_NODE:
            self._on_reset_node()
            self.boot()
        else:
            self._on_reset_communication()
            self.boot()

    def _leave_operational(self) -> None:
        """Called before STOP and ENTER PRE-OPERATIONAL take effect."""

    def _on_reset_node(self) -> None:
        """Power-on values of the whole dictionary (before the boot-up message)."""

    def _on_reset_communication(self) -> None:
        """Power-on values of the communication objects (before the boot-up message)."""

    # ------------------------------------------------------------------ SDO server
    def _lookup(self, index: int, sub: int) -> OdObject:
        """The object at ``index``:``sub`` (:class:`SdoServerAbort` 0x06020000 / 0x06090011
        when there is none)."""
        raise NotImplementedError

    def _read(self, o: OdObject) -> int:
        raise NotImplementedError

    def _write_sdo(self, o: OdObject, value: int) -> None:
        raise NotImplementedError

    def _sdo_writable(self, o: OdObject) -> bool:
        return o.access not in ("ro", "const")

    def _sdo_aborted(self, req: SdoFrame, code: int) -> None:
        """Called for every abort the node answers."""

    def on_sdo(self, data: bytes) -> None:
        """Answer an SDO request (client -> server frame), in PRE-OPERATIONAL and
        OPERATIONAL only; expedited transfers only."""
        if self.nmt_state not in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL):
            return
        req = co.decode_sdo_request(data)
        self.sdo_requests += 1
        if req.kind == "abort":
            return
        try:
            if req.kind == "upload":
                o = self._lookup(req.index, req.sub)
                if o.access == "wo":
                    raise SdoServerAbort(0x0601_0001)
                reply = co.encode_sdo_upload_ack(req.index, req.sub,
                                                 o.dtype.encode(self._read(o), o.name))
            elif req.kind == "download" and req.expedited:
                o = self._lookup(req.index, req.sub)
                if not self._sdo_writable(o):
                    raise SdoServerAbort(0x0601_0002)
                payload = req.payload
                if req.size is None:              # size not indicated: 4 bytes sent
                    payload = payload[:o.dtype.size]
                if len(payload) != o.dtype.size:
                    raise SdoServerAbort(0x0607_0010)
                self._write_sdo(o, o.dtype.decode(payload, o.name))
                reply = co.encode_sdo_download_ack(req.index, req.sub)
            else:
                raise SdoServerAbort(0x0504_0001)
        except SdoServerAbort as ab:
            self.sdo_aborts += 1
            self._sdo_aborted(req, ab.code)
            reply = co.encode_sdo_abort(req.index, req.sub, ab.code)
        self._send(co.cob_id("SDO_TX", self.node_id), reply)


__all__ = ["BusAttached", "SdoServerAbort", "SimNode"]
