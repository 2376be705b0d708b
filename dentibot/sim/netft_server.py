"""A simulated ATI Net F/T box on the wire: RDT over UDP plus the ``/netftapi2.xml`` page.

It streams ``world.sensor.last`` (N, N*m in {S}) converted to counts, so any RDT client (the
:class:`dentibot.io.netft.NetFTDriver`, ATI's demo, a plain ``socket`` + ``struct`` reader) can
read the simulated world. It never steps the World: a record reads the sensor model at the moment
it is due, while a :class:`dentibot.sim.timing.RealTimeStepper` (or nobody) steps the world.

Behaviour of the box that clients must cope with, reproduced here:

- one stream owner: the box answers whoever sent the last start; a second client's start takes
  the stream over and the first simply stops receiving. A STOP from any address stops it.
- rdt_sequence restarts at 1 on every start request; ft_sequence is the box's internal sample
  counter (``internal_rate_hz``, 7000 Hz by default), derived from the clock, so it keeps
  counting across requests and while idle.
- sample_count is honoured (that many records, then the stream ends; 0 = until stopped).
  In buffered mode it counts records too and the last datagram may be short (*assumption*).
- buffered mode sends ``buffer_size`` records per datagram (``comrdtbsiz``).
- a client that vanishes without STOP keeps receiving datagrams until someone stops the box.
- malformed requests are ignored (counted in ``bad_requests``).

Timing: records are due at absolute deadlines ``t_start + k / rate_hz``; a wake-up sends every
record that is due, so the long-run rate is exact and does not drift even though the event loop
wakes up to ~1 ms late (records may leave in small bursts). After a stall longer than
``max_lag_s`` the schedule is moved on instead of replayed (``schedule_slips`` records).

Bias (0x0042) calls ``world.sensor.bias()``: the tare lives in the sensor model, like the real
box's software bias lives in the box, so the wire sensor and the in-process
:class:`dentibot.sim.devices.SimForceSensor` behave alike (and share one tare, as one box
would).

Status: ``world.sensor.status`` (``Wrench.status`` bits) is mapped to the RDT status word with
:data:`dentibot.io.netft_protocol.WRENCH_TO_RDT_STATUS` (saturation -> 0x80020000: summary bit 31
plus "transducer saturation or A/D error", bit 17; the bit numbers are *unconfirmed*).

Test hooks: :meth:`inject_offset` adds a known wrench to what is streamed; ``status_override``
forces a status word; :meth:`stop_stream` stops the box; :meth:`send_raw` sends arbitrary bytes.
"""

from __future__ import annotations

import asyncio
import collections
import math
from typing import Self

import structlog

from dentibot.errors import ConfigError, ProtocolError
from dentibot.io.netft_protocol import (
    CALIBRATION_PATH,
    RDT_PORT,
    Command,
    NetFTCalibration,
    RdtRecord,
    decode_request,
    encode_records,
    http_response,
    parse_http_request_line,
    rdt_status_from_wrench,
    render_calibration_xml,
    si_to_counts,
)
from dentibot.sim.world import World

log = structlog.get_logger(__name__)

_U32 = 1 << 32
#: Seconds an HTTP client gets to send its request head.
HTTP_REQUEST_TIMEOUT_S = 2.0
_HTTP_MAX_HEAD = 8192


class _RdtServerProtocol(asyncio.DatagramProtocol):
    def __init__(self, server: NetFTServer) -> None:
        self.server = server
        self.closed: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def datagram_received(self, data: bytes, addr) -> None:
        self.server._on_request(data, addr)

    def error_received(self, exc: Exception) -> None:
        # e.g. ICMP port unreachable after the owner vanished without STOP: the box keeps going
        self.server.send_errors += 1

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)


class NetFTServer:
    """Simulated Net F/T box serving ``world``'s F/T sensor over RDT (and HTTP).

    Args:
        world: the World whose ``sensor`` is streamed.
        host: address to bind (loopback by default).
        port: RDT UDP port; 0 = ephemeral (the bound port is in ``self.port`` after start).
        http_port: calibration web server port; 0 = ephemeral, None = no HTTP server.
        rate_hz: RDT output rate (``comrdtrate``), records per second.
        counts_per_force: counts per N (``cfgcpf``; units N).
        counts_per_torque: counts per N*m (``cfgcpt``; units Nm).
        buffer_size: records per datagram in buffered mode (``comrdtbsiz``, 1..40).
        internal_rate_hz: the box's internal sample rate driving ft_sequence.
        max_lag_s: most lateness (s) caught up at one wake-up; beyond that the schedule slips.
    """

    def __init__(self, world: World, host: str = "127.0.0.1", port: int = RDT_PORT,
                 http_port: int | None = None, rate_hz: float = 500,
                 counts_per_force: float = 1_000_000, counts_per_torque: float = 1_000_000,
                 buffer_size: int = 10, internal_rate_hz: float = 7000,
                 max_lag_s: float = 0.1) -> None:
        if not (math.isfinite(rate_hz) and 1 <= rate_hz <= 7000):
            raise ConfigError("netft_server.rate_hz", rate_hz, "1..7000 Hz (Net F/T range)")
        if not 1 <= buffer_size <= 40:
            raise ConfigError("netft_server.buffer_size", buffer_size, "1..40 records")
        for field, v in (("netft_server.counts_per_force", counts_per_force),
                         ("netft_server.counts_per_torque", counts_per_torque)):
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(field, v, "a positive number of counts per unit")
        self.world = world
        self.host = host
        self.port = port
        self.http_port = http_port
        self.rate_hz = float(rate_hz)
        self.buffer_size = int(buffer_size)
        self.internal_rate_hz = float(internal_rate_hz)
        self.max_lag_s = float(max_lag_s)
        self.max_burst = max(1, round(self.rate_hz * self.max_lag_s))
        self.calibration = NetFTCalibration(float(counts_per_force), float(counts_per_torque),
                                            "N", "Nm", self.rate_hz, self.buffer_size)
        self._cpf, self._cpt = float(counts_per_force), float(counts_per_torque)
        # test hooks
        self.offset_n = (0.0, 0.0, 0.0)
        self.offset_nm = (0.0, 0.0, 0.0)
        self.status_override: int | None = None
        # observable state and counters
        self.owner: tuple | None = None       # address the stream goes to
        self.mode: int | None = None          # Command.START_REALTIME / START_BUFFERED / None
        #: recent requests, newest last: (addr, command, sample_count)
        self.requests: collections.deque[tuple[tuple, int, int]] = collections.deque(maxlen=1000)
        self.bad_requests = 0
        self.records_sent = 0                 # in total
        self.datagrams_sent = 0
        self.stream_records_sent = 0          # in the current/last stream
        self.streams_started = 0
        self.schedule_slips = 0
        self.send_errors = 0
        self.http_requests = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._transport: asyncio.DatagramTransport | None = None
        self._proto: _RdtServerProtocol | None = None
        self._http: asyncio.Server | None = None
        self._http_tasks: set[asyncio.Task] = set()
        self._timer: asyncio.TimerHandle | None = None
        self._epoch = 0.0
        self._t_start = 0.0
        self._k = 0                           # next record index in the stream schedule
        self._remaining: int | None = None
        self._buffer: list[RdtRecord] = []
        self._rdt_seq = 0

    # ------------------------------------------------------------------ lifecycle
    @property
    def streaming(self) -> bool:
        return self.mode is not None

    async def start(self) -> None:
        if self._transport is not None:
            return
        loop = self._loop = asyncio.get_running_loop()
        self._epoch = loop.time()
        transport, proto = await loop.create_datagram_endpoint(
            lambda: _RdtServerProtocol(self), local_addr=(self.host, self.port))
        self._transport, self._proto = transport, proto
        self.port = transport.get_extra_info("sockname")[1]
        if self.http_port is not None:
            try:
                self._http = await asyncio.start_server(self._serve_http, self.host,
                                                        self.http_port)
            except OSError:
                await self.close()
                raise
            self.http_port = self._http.sockets[0].getsockname()[1]
        log.info("netft_server.started", host=self.host, port=self.port,
                 http_port=self.http_port, rate_hz=self.rate_hz)

    async def close(self) -> None:
        """Stop streaming, close the UDP socket, the HTTP server and its connections."""
        self._stop_stream()
        transport, proto, http = self._transport, self._proto, self._http
        self._transport = self._proto = self._http = None
        if http is not None:
            http.close()
            for task in list(self._http_tasks):
                task.cancel()
            if self._http_tasks:
                await asyncio.gather(*self._http_tasks, return_exceptions=True)
            await http.wait_closed()
        if transport is not None:
            transport.close()
            if proto is not None:
                await proto.closed
            log.info("netft_server.closed", records_sent=self.records_sent,
                     bad_requests=self.bad_requests)

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    # ------------------------------------------------------------------ test hooks
    def inject_offset(self, force_n=(0.0, 0.0, 0.0), torque_nm=(0.0, 0.0, 0.0)) -> None:
        """Add a known wrench (N, N*m) to every record from now on (a test load)."""
        self.offset_n = tuple(float(x) for x in force_n)
        self.offset_nm = tuple(float(x) for x in torque_nm)

    def stop_stream(self) -> None:
        """The box stops streaming now (as on a STOP from any client; a partly filled
        buffered datagram is sent first)."""
        self._stop_stream()

    def send_raw(self, data: bytes, addr=None) -> None:
        """Send arbitrary bytes from the RDT port to ``addr`` (default: the stream owner):
        line noise or a misbehaving box, for tests."""
        addr = addr if addr is not None else self.owner
        if self._transport is None or addr is None:
            raise ConfigError("netft_server.send_raw", addr, "a started server and a peer")
        self._transport.sendto(bytes(data), addr)

    def ft_sequence_at(self, t: float) -> int:
        """The box's internal sample counter at loop time ``t``."""
        return int((t - self._epoch) * self.internal_rate_hz) % _U32

    # ------------------------------------------------------------------ RDT requests
    def _on_request(self, data: bytes, addr) -> None:
        try:
            req = decode_request(data)
        except ProtocolError as exc:
            self.bad_requests += 1
            log.warning("netft_server.bad_request", size=len(data), peer=addr, error=str(exc))
            return
        self.requests.append((addr, req.command, req.sample_count))
        if req.command == Command.STOP:
            self._stop_stream()
        elif req.command == Command.SET_BIAS:
            self.world.sensor.bias()
        else:
            self._start_stream(addr, req.command, req.sample_count)

    def _start_stream(self, addr, mode: int, count: int) -> None:
        self._stop_stream()
        assert self._loop is not None
        self.owner, self.mode = addr, mode
        self._remaining = count or None
        self._rdt_seq = 0
        self._buffer = []
        self.stream_records_sent = 0
        self.streams_started += 1
        self._t_start = self._loop.time()
        self._k = 0
        self._tick()

    def _stop_stream(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self._buffer:
            self._flush()
        self.mode = None
        self._remaining = None

    # ------------------------------------------------------------------ streaming
    def _tick(self) -> None:
        self._timer = None
        loop = self._loop
        if self.mode is None or loop is None or self._transport is None:
            return
        now = loop.time()
        period = 1.0 / self.rate_hz
        due = math.floor((now - self._t_start) * self.rate_hz) + 1   # records due by now
        if due - self._k > self.max_burst:
            self.schedule_slips += due - self._k - self.max_burst
            self._t_start += (due - self._k - self.max_burst) * period
            due = self._k + self.max_burst
        buffered = self.mode == Command.START_BUFFERED
        while self._k < due:
            t_rec = self._t_start + self._k * period
            self._k += 1
            self._buffer.append(self._record(t_rec))
            if self._remaining is not None:
                self._remaining -= 1
            if not buffered or len(self._buffer) >= self.buffer_size:
                self._flush()
            if self._remaining == 0:
                self._stop_stream()
                return
        self._timer = loop.call_at(self._t_start + self._k * period, self._tick)

    def _record(self, t_rec: float) -> RdtRecord:
        s = self.world.sensor
        v = s.last
        of, ot = self.offset_n, self.offset_nm
        counts = si_to_counts((v[0] + of[0], v[1] + of[1], v[2] + of[2]),
                              (v[3] + ot[0], v[4] + ot[1], v[5] + ot[2]), self._cpf, self._cpt)
        status = (self.status_override if self.status_override is not None
                  else rdt_status_from_wrench(s.status))
        self._rdt_seq = (self._rdt_seq + 1) % _U32
        return RdtRecord(self._rdt_seq, self.ft_sequence_at(t_rec), status, counts)

    def _flush(self) -> None:
        records, self._buffer = self._buffer, []
        if not records or self._transport is None or self.owner is None:
            return
        self._transport.sendto(encode_records(records), self.owner)
        self.records_sent += len(records)
        self.stream_records_sent += len(records)
        self.datagrams_sent += 1

    # ------------------------------------------------------------------ HTTP
    async def _serve_http(self, reader: asyncio.StreamReader,
                          writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._http_tasks.add(task)
        self.http_requests += 1
        try:
            writer.write(await self._http_answer(reader))
            await writer.drain()
        except ConnectionError:
            pass
        finally:
            writer.close()
            self._http_tasks.discard(task)

    async def _http_answer(self, reader: asyncio.StreamReader) -> bytes:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"),
                                          HTTP_REQUEST_TIMEOUT_S)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError):
            return http_response(400, b"bad request\n", "text/plain")
        if len(head) > _HTTP_MAX_HEAD:
            return http_response(400, b"request head too long\n", "text/plain")
        try:
            method, path = parse_http_request_line(head.split(b"\r\n", 1)[0])
        except ProtocolError:
            return http_response(400, b"bad request line\n", "text/plain")
        if method == "GET" and path.split("?", 1)[0] == CALIBRATION_PATH:
            body = render_calibration_xml(self.calibration, runrate=int(self.internal_rate_hz),
                                          runstat="0x00000000", prodname="DentiBot sim Net F/T")
            return http_response(200, body)
        return http_response(404, b"not found\n", "text/plain")
