"""ATI Net F/T driver: RDT over UDP, counts per unit from ``/netftapi2.xml`` (asyncio).

:class:`NetFTDriver` implements :class:`dentibot.io.ForceSensor`. At ``connect()`` it reads the
calibration page over HTTP (unless counts per unit are given), opens a UDP endpoint connected to
the box (so only the box's datagrams are received), and sends *start real-time streaming* with
sample_count 0 (until stopped).

Reception runs in the datagram protocol's callback, which is the background reader: every
datagram is decoded as it arrives and the newest record wins, so a control task slower than the
stream never accumulates lag. Lost rdt_sequence numbers (gaps), duplicates and out-of-order
records (ignored) and bad datagrams (wrong length, not a whole number of 36-byte records) are
counted; bad bytes never stop the reader.

``read()`` returns the newest wrench without waiting, or raises :class:`DeviceFault` when there
is none yet, the link is closed, the newest record is older than ``stale_after_s`` (a held
wrench is never returned as fresh) or its status word is non-zero (naming the status bits).
"""

from __future__ import annotations

import asyncio
import math
import socket
import time
from typing import Self

import structlog

from dentibot.errors import ConfigError, DeviceFault, ProtocolError
from dentibot.io.interfaces import ConnectTimeout, Wrench
from dentibot.io.netft_protocol import (
    CALIBRATION_PATH,
    DEVICE,
    HTTP_MAX_BYTES,
    RDT_PORT,
    Command,
    NetFTCalibration,
    RdtRecord,
    SequenceTracker,
    counts_to_si,
    decode_datagram,
    describe_status,
    encode_request,
    http_get_request,
    parse_calibration_xml,
    parse_http_response,
    wrench_status_from_rdt,
)

log = structlog.get_logger(__name__)

#: Socket receive buffer asked for (bytes); the kernel may cap it (net.core.rmem_max). Big
#: enough for ~0.1 s of the fastest stream (7000 records/s x 36 bytes + overhead).
RECEIVE_BUFFER_BYTES = 1 << 20
#: Bad datagrams logged one by one before logging only every ``_LOG_EVERY``-th.
_LOG_FIRST, _LOG_EVERY = 10, 1000


class _RdtReceiver(asyncio.DatagramProtocol):
    def __init__(self, driver: NetFTDriver) -> None:
        self.driver = driver
        self.closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def datagram_received(self, data: bytes, addr) -> None:
        self.driver._on_datagram(data, time.monotonic())

    def error_received(self, exc: Exception) -> None:
        self.driver._on_error(exc)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)


class NetFTDriver:
    """ATI Net F/T box streaming RDT (implements ``dentibot.io.ForceSensor``).

    Args:
        host: the box's address; ``"192.168.1.1"`` is ATI's factory default.
        port: RDT UDP port (49152).
        http_port: port of the box's web server, for ``/netftapi2.xml`` (80).
        counts_per_force: counts per N; ``None`` (default) reads ``cfgcpf``/``scfgfu`` from the
            calibration page at connect. Give both factors or neither.
        counts_per_torque: counts per N*m; ``None`` reads ``cfgcpt``/``scfgtu``.
        stale_after_s: ``read()`` faults if the newest record is older than this (s). Default
            0.02 s: ten 500 Hz control periods, many records at any RDT rate >= 500 Hz.
        http_timeout_s: limit for the whole calibration-page exchange (s): TCP connection,
            request, the whole answer; a box that accepts and never (or too slowly) answers
            is a :class:`~dentibot.io.interfaces.ConnectTimeout` naming the address.
        name: device name in errors and logs.
    """

    def __init__(self, host: str = "192.168.1.1", port: int = RDT_PORT, http_port: int = 80,
                 counts_per_force: float | None = None, counts_per_torque: float | None = None,
                 stale_after_s: float = 0.02, http_timeout_s: float = 2.0,
                 name: str = DEVICE) -> None:
        if (counts_per_force is None) != (counts_per_torque is None):
            raise ConfigError("netft.counts_per_torque" if counts_per_torque is None
                              else "netft.counts_per_force", None,
                              "give both counts_per_force and counts_per_torque, or neither "
                              "(read from /netftapi2.xml)")
        for field, v in (("netft.counts_per_force", counts_per_force),
                         ("netft.counts_per_torque", counts_per_torque)):
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ConfigError(field, v, "a positive number of counts per unit")
        if not (math.isfinite(stale_after_s) and stale_after_s > 0):
            raise ConfigError("netft.stale_after_s", stale_after_s, "> 0 s")
        self.host = host
        self.port = port
        self.http_port = http_port
        self.stale_after_s = float(stale_after_s)
        self.http_timeout_s = float(http_timeout_s)
        self.name = name
        self.calibration: NetFTCalibration | None = None
        if counts_per_force is not None:
            self.calibration = NetFTCalibration(float(counts_per_force),
                                                float(counts_per_torque), "N", "Nm")
        self._given_calibration = self.calibration is not None
        self._cpf = self._cpt = 1.0
        # counters
        self.received = 0          # records accepted (new)
        self.lost = 0              # rdt_sequence numbers skipped (gaps)
        self.out_of_order = 0      # duplicate or older records, ignored
        self.bad_datagrams = 0     # undecodable datagrams
        self.datagrams = 0         # datagrams received, good or bad
        self.errors = 0            # socket errors reported by the OS (e.g. ICMP unreachable)
        self._tracker = SequenceTracker()
        self._latest: Wrench | None = None
        self._latest_status = 0
        self._transport: asyncio.DatagramTransport | None = None
        self._receiver: _RdtReceiver | None = None
        self._connected = False

    # ------------------------------------------------------------------ lifecycle
    @property
    def restarts(self) -> int:
        """Streams restarted by the box (rdt_sequence back to 1)."""
        return self._tracker.restarts

    @property
    def connected(self) -> bool:
        return self._connected

    @property
    def local_address(self) -> tuple | None:
        """(host, port) of this client's UDP socket while connected (the box streams there)."""
        t = self._transport
        return None if t is None else t.get_extra_info("sockname")

    async def connect(self) -> None:
        """Read the calibration (unless given), open the UDP endpoint, start streaming."""
        if self._connected:
            return
        if not self._given_calibration:
            self.calibration = await self.fetch_calibration()
        cal = self.calibration
        assert cal is not None
        self._cpf, self._cpt = cal.counts_per_newton, cal.counts_per_newton_metre
        loop = asyncio.get_running_loop()
        try:
            transport, receiver = await loop.create_datagram_endpoint(
                lambda: _RdtReceiver(self), remote_addr=(self.host, self.port))
        except OSError as exc:
            raise DeviceFault(self.name, f"cannot open UDP to {self.host}:{self.port}: "
                                         f"{exc}") from exc
        sock = transport.get_extra_info("socket")
        if sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
            except OSError:        # pragma: no cover - platform refuses: keep the default
                pass
        self._transport, self._receiver = transport, receiver
        self._tracker.reset()
        self._latest = None
        self._connected = True
        self._send(Command.START_REALTIME, 0)
        log.info("netft.connected", device=self.name, host=self.host, port=self.port,
                 counts_per_n=self._cpf, counts_per_nm=self._cpt,
                 rdt_rate_hz=cal.rdt_rate_hz)

    async def close(self) -> None:
        """Send STOP (the box keeps streaming otherwise), then close the socket. Idempotent."""
        transport, receiver = self._transport, self._receiver
        self._transport = self._receiver = None
        was = self._connected
        self._connected = False
        if transport is None:
            return
        if was:
            try:
                transport.sendto(encode_request(Command.STOP, 0))
            except OSError as exc:   # pragma: no cover - the box is gone: nothing to stop
                log.warning("netft.stop_failed", device=self.name, error=str(exc))
        transport.close()
        if receiver is not None:
            await receiver.closed
        log.info("netft.closed", device=self.name, received=self.received, lost=self.lost,
                 out_of_order=self.out_of_order, bad_datagrams=self.bad_datagrams)

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    # ------------------------------------------------------------------ ForceSensor
    async def read(self) -> Wrench:
        """Newest wrench (N, N*m), ``seq`` = rdt_sequence, ``t`` = reception time (monotonic).

        DeviceFault if not connected, no record yet, the stream is stale or the box reports a
        non-zero status.
        """
        if not self._connected:
            raise DeviceFault(self.name, "not connected")
        w = self._latest
        if w is None:
            raise DeviceFault(self.name, f"no RDT record received yet from "
                                         f"{self.host}:{self.port}")
        age = time.monotonic() - w.t
        if age > self.stale_after_s:
            raise DeviceFault(self.name, f"stream stale: newest record (rdt_sequence {w.seq}) "
                                         f"is {age * 1e3:.1f} ms old, limit "
                                         f"{self.stale_after_s * 1e3:.1f} ms")
        if self._latest_status:
            raise DeviceFault(self.name, f"status {describe_status(self._latest_status)} in "
                                         f"record rdt_sequence {w.seq}")
        return w

    async def bias(self) -> None:
        """Software bias in the box (command 0x0042): the current load reads zero from now on."""
        if not self._connected:
            raise DeviceFault(self.name, "not connected")
        self._send(Command.SET_BIAS, 0)

    # ------------------------------------------------------------------ HTTP
    async def fetch_calibration(self) -> NetFTCalibration:
        """GET ``/netftapi2.xml`` from the box and parse it.

        DeviceFault if the page cannot be fetched; ProtocolError if it is not a calibration
        document.
        """
        url = f"http://{self.host}:{self.http_port}{CALIBRATION_PATH}"
        try:
            data = await asyncio.wait_for(self._http_get(), self.http_timeout_s)
        except TimeoutError:
            raise ConnectTimeout(self.name, f"{self.host}:{self.http_port}",
                                 f"complete answer to GET {CALIBRATION_PATH}",
                                 self.http_timeout_s) from None
        except OSError as exc:
            raise DeviceFault(self.name, f"{url}: {exc}") from exc
        status, body = parse_http_response(data)
        if status != 200:
            raise DeviceFault(self.name, f"{url}: HTTP {status}")
        cal = parse_calibration_xml(body)
        log.info("netft.calibration", device=self.name, url=url, cfgcpf=cal.counts_per_force,
                 cfgcpt=cal.counts_per_torque, scfgfu=cal.force_unit, scfgtu=cal.torque_unit,
                 comrdtrate=cal.rdt_rate_hz)
        return cal

    async def _http_get(self) -> bytes:
        reader, writer = await asyncio.open_connection(self.host, self.http_port)
        try:
            writer.write(http_get_request(self.host, CALIBRATION_PATH))
            await writer.drain()
            data = await reader.read(HTTP_MAX_BYTES + 1)
            chunks = [data]
            total = len(data)
            while data and total <= HTTP_MAX_BYTES:
                data = await reader.read(HTTP_MAX_BYTES + 1 - total)
                chunks.append(data)
                total += len(data)
            if total > HTTP_MAX_BYTES:
                raise ProtocolError(self.name, f"{CALIBRATION_PATH} answer exceeds "
                                               f"{HTTP_MAX_BYTES} bytes")
            return b"".join(chunks)
        finally:
            writer.close()
            try:
                await writer.wait_closed()
            except OSError:        # pragma: no cover - reset by peer while closing
                pass

    # ------------------------------------------------------------------ reception
    def _send(self, command: Command, count: int) -> None:
        assert self._transport is not None
        self._transport.sendto(encode_request(command, count))

    def _on_datagram(self, data: bytes, t: float) -> None:
        self.datagrams += 1
        try:
            records = decode_datagram(data)
        except ProtocolError as exc:
            self.bad_datagrams += 1
            n = self.bad_datagrams
            if n <= _LOG_FIRST or n % _LOG_EVERY == 0:
                log.warning("netft.bad_datagram", device=self.name, size=len(data),
                            count=n, error=str(exc))
            return
        newest: RdtRecord | None = None
        tracker = self._tracker
        for rec in records:
            lost = tracker.accept(rec.rdt_sequence, rec.ft_sequence)
            if lost < 0:
                self.out_of_order += 1
                continue
            self.received += 1
            if lost:
                self.lost += lost
            newest = rec
        if newest is None:
            return
        force, torque = counts_to_si(newest.counts, self._cpf, self._cpt)
        self._latest_status = newest.status
        self._latest = Wrench(t, newest.rdt_sequence, force, torque,
                              wrench_status_from_rdt(newest.status))

    def _on_error(self, exc: Exception) -> None:
        self.errors += 1
        if self.errors <= _LOG_FIRST or self.errors % _LOG_EVERY == 0:
            log.warning("netft.socket_error", device=self.name, error=repr(exc),
                        count=self.errors)
