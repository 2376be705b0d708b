"""NetFTDriver against the simulated Net F/T box over real UDP/HTTP on 127.0.0.1.

The World is stepped in real time by a RealTimeStepper while the server streams it.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import socket
import struct
import threading
import time

import numpy as np
import pytest

from dentibot.errors import ConfigError, DeviceFault, ProtocolError
from dentibot.io import ForceSensor
from dentibot.io.interfaces import ConnectTimeout
from dentibot.io.netft import NetFTDriver
from dentibot.io.netft_protocol import Command, RdtRecord, encode_record, encode_records
from dentibot.sim import FTSensorParams, RealTimeStepper, SimForceSensor, World, WorldConfig
from dentibot.sim.netft_server import NetFTServer

pytestmark = [pytest.mark.wire, pytest.mark.timeout(30)]

G = 9.80665
#: Mini40 resolution in the World's sensor model: (Fx, Fy, Fz) N and torques N*m.
RES = (0.01, 0.01, 0.02, 1 / 4000, 1 / 4000, 1 / 4000)
#: A noise-free, offset-free sensor: its reading is the physics alone.
CLEAN = {"offset_sigma_n": 0.0, "offset_sigma_nm": 0.0, "noise_n": (0.0, 0.0, 0.0),
         "noise_nm": 0.0}


def clean_world(**sensor) -> World:
    return World(WorldConfig(seed=3, sensor=FTSensorParams(**{**CLEAN, **sensor})))


@contextlib.asynccontextmanager
async def rig(world: World | None = None, **server_kw):
    """A World stepped in real time and a NetFTServer (ephemeral ports) over it."""
    world = world or World(WorldConfig(seed=1))
    stop = asyncio.Event()
    stepper = asyncio.create_task(RealTimeStepper(world).run(stop))
    server = NetFTServer(world, port=0, http_port=server_kw.pop("http_port", 0), **server_kw)
    try:
        await server.start()
        yield world, server
    finally:
        await server.close()
        stop.set()
        await stepper


def driver_for(server: NetFTServer, **kw) -> NetFTDriver:
    kw.setdefault("stale_after_s", 0.5)       # generous: the test machine may be loaded
    return NetFTDriver("127.0.0.1", server.port, server.http_port, **kw)


async def wait_for(cond, timeout: float = 3.0) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.005)


async def first_read(drv: NetFTDriver):
    await wait_for(lambda: drv.received > 0)
    return await drv.read()


# --------------------------------------------------------------------------- HTTP calibration
async def test_counts_per_unit_are_read_over_http_and_a_known_load_reads_back_in_si():
    # a massless tool on a clean sensor reads exactly zero, so the load is the injected one
    async with rig(clean_world(mass_kg=0.0), counts_per_force=250_000,
                   counts_per_torque=4_000_000) as (_, srv):
        force, torque = (1.234567, -2.5, 17.125), (0.123456, -0.5, 0.0625)
        srv.inject_offset(force, torque)
        async with driver_for(srv) as drv:
            assert drv.calibration.counts_per_force == 250_000
            assert drv.calibration.counts_per_torque == 4_000_000
            assert drv.calibration.rdt_rate_hz == srv.rate_hz
            w = await first_read(drv)
    # within one count: 1/250000 N and 1/4000000 N*m
    assert w.force_n == pytest.approx(force, abs=1 / 250_000)
    assert w.torque_nm == pytest.approx(torque, abs=1 / 4_000_000)
    assert w.status == 0


async def test_calibration_page_404_and_split_request():
    async with rig() as (_, srv):
        for request in (b"GET /other HTTP/1.0\r\n\r\n", b"POST /netftapi2.xml HTTP/1.0\r\n\r\n"):
            reader, writer = await asyncio.open_connection("127.0.0.1", srv.http_port)
            writer.write(request)
            answer = await reader.read()
            writer.close()
            await writer.wait_closed()
            assert answer.startswith(b"HTTP/1.0 404")
        # the request arriving one byte at a time (split reads on the server side)
        reader, writer = await asyncio.open_connection("127.0.0.1", srv.http_port)
        for b in b"GET /netftapi2.xml HTTP/1.1\r\nHost: x\r\n\r\n":
            writer.write(bytes([b]))
            await writer.drain()
        answer = await reader.read()
        writer.close()
        await writer.wait_closed()
        assert answer.startswith(b"HTTP/1.0 200") and b"<cfgcpf>1000000</cfgcpf>" in answer


async def _fake_http(respond):
    """A one-off HTTP server whose handler is ``respond(writer)``; returns (server, port)."""
    async def handle(reader, writer):
        await reader.readuntil(b"\r\n\r\n")
        try:
            await respond(writer)
        finally:
            writer.close()
    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    return server, server.sockets[0].getsockname()[1]


async def test_driver_reads_a_calibration_answer_split_into_small_pieces():
    body = (b'<?xml version="1.0"?><netft><cfgcpf>2000000</cfgcpf><cfgcpt>500000</cfgcpt>'
            b"<scfgfu>N</scfgfu><scfgtu>Nm</scfgtu></netft>")
    answer = b"HTTP/1.1 200 OK\r\nContent-Type: text/xml\r\n\r\n" + body

    async def dribble(writer):
        for i in range(0, len(answer), 7):
            writer.write(answer[i:i + 7])
            await writer.drain()
            await asyncio.sleep(0.001)

    server, port = await _fake_http(dribble)
    async with server:
        cal = await NetFTDriver("127.0.0.1", 9, port).fetch_calibration()
    await server.wait_closed()
    assert (cal.counts_per_newton, cal.counts_per_newton_metre) == (2_000_000, 500_000)


@pytest.mark.parametrize(("answer", "error", "match"), [
    (b"HTTP/1.0 404 Not Found\r\n\r\n", DeviceFault, "HTTP 404"),
    (b"HTTP/1.0 200 OK\r\n\r\n<html>hello</html>", ProtocolError, "cfgcpf"),
    (b"garbage without headers", ProtocolError, "HTTP"),
])
async def test_bad_calibration_answers_are_typed_errors(answer, error, match):
    async def respond(writer):
        writer.write(answer)
        await writer.drain()

    server, port = await _fake_http(respond)
    async with server:
        drv = NetFTDriver("127.0.0.1", 9, port)
        with pytest.raises(error, match=match):
            await drv.connect()
        assert not drv.connected
    await server.wait_closed()


async def test_no_web_server_is_a_device_fault():
    with socket.socket() as s:      # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(DeviceFault, match="netftapi2.xml"):
        await NetFTDriver("127.0.0.1", 9, port).connect()


async def test_a_web_server_that_never_answers_is_a_typed_timeout():
    """Accepts the connection, reads the request, says nothing (or dribbles a byte now and
    then): the whole exchange is bounded by http_timeout_s."""
    accepted: list[asyncio.StreamWriter] = []
    handlers: list[asyncio.Task] = []

    async def silent(reader, writer):
        accepted.append(writer)
        handlers.append(asyncio.current_task())
        await reader.read(1024)
        for _ in range(100):
            writer.write(b"H")                   # never a complete answer
            await asyncio.sleep(0.05)

    server = await asyncio.start_server(silent, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        drv = NetFTDriver("127.0.0.1", 9, port, http_timeout_s=0.3)
        t0 = time.monotonic()
        with pytest.raises(ConnectTimeout) as e:
            await drv.connect()
        assert 0.3 <= time.monotonic() - t0 <= 0.3 + 0.5
        assert e.value.device == "netft" and f"127.0.0.1:{port}" in str(e.value)
        assert "netftapi2.xml" in str(e.value) and not drv.connected
    finally:
        for task in handlers:
            task.cancel()
        await asyncio.gather(*handlers, return_exceptions=True)
        for w in accepted:
            w.close()
        server.close()
        await server.wait_closed()


# --------------------------------------------------------------------------- streaming
async def test_500_hz_for_two_seconds_loses_no_sequence_number():
    async with rig(rate_hz=500) as (_, srv), driver_for(srv) as drv:
        await first_read(drv)
        t0 = time.monotonic()
        seqs = set()
        while time.monotonic() - t0 < 2.0:      # a 500 Hz reader, as the control task
            seqs.add((await drv.read()).seq)
            await asyncio.sleep(0.002)
        srv.stop_stream()
        elapsed = time.monotonic() - t0
        sent = srv.stream_records_sent
        await wait_for(lambda: drv.received == sent, timeout=1.0)
        assert drv.lost == 0 and drv.out_of_order == 0 and drv.bad_datagrams == 0
        # the newest record is the last one sent, its rdt_sequence = records in this stream
        assert (await drv.read()).seq == sent
        assert len(seqs) > 100
    # the schedule is 500 records per second (slips only if the loop stalled > max_lag_s = 0.1 s)
    assert sent + srv.schedule_slips >= 0.95 * 500 * elapsed
    assert sent <= 500 * (elapsed + 0.5)


async def test_stop_is_sent_on_close_and_the_server_stops_sending():
    async with rig() as (_, srv):
        drv = driver_for(srv)
        await drv.connect()
        await first_read(drv)
        addr = srv.owner
        await drv.close()
        await drv.close()                       # idempotent
        await wait_for(lambda: not srv.streaming)
        assert srv.requests[-1] == (addr, Command.STOP, 0)
        sent = srv.records_sent
        await asyncio.sleep(0.05)
        assert srv.records_sent == sent
        with pytest.raises(DeviceFault, match="not connected"):
            await drv.read()


async def test_second_requester_takes_the_stream_over():
    async with rig() as (_, srv):
        a = driver_for(srv, stale_after_s=0.1)
        b = driver_for(srv, stale_after_s=0.5)
        await a.connect()
        await first_read(a)
        await b.connect()
        await first_read(b)
        assert srv.owner[1] == b.local_address[1] != a.local_address[1]
        await asyncio.sleep(0.05)                # let datagrams already queued for A drain
        received_a = a.received
        await asyncio.sleep(0.15)
        assert a.received == received_a          # nothing more for the first client
        with pytest.raises(DeviceFault, match="stale"):
            await a.read()
        w = await b.read()
        assert w.seq >= 1 and b.lost == 0
        await b.close()
        await a.close()


async def test_bias_tares_the_current_load_in_the_box():
    world = clean_world()
    async with rig(world) as (_, srv), driver_for(srv) as drv:
        w = await first_read(drv)
        assert np.linalg.norm(w.force_n) == pytest.approx(0.139 * G, abs=0.03)
        await drv.bias()
        await wait_for(lambda: srv.requests[-1][1] == Command.SET_BIAS)
        await asyncio.sleep(0.05)
        w = await drv.read()
        assert np.abs(w.as_array()).max() < 1e-9
        # the in-process sensor over the same world sees the same tare (one box)
        assert np.abs((await SimForceSensor(world).read()).as_array()).max() < 1e-9
        assert srv.streaming                   # bias does not interrupt the stream


async def test_gravity_on_the_tool_reads_back_from_world_physics():
    world = clean_world()
    async with rig(world) as (_, srv), driver_for(srv) as drv:
        await first_read(drv)
        await asyncio.sleep(0.02)
        w = await drv.read()
    # independent physics: f_S = Rz(15 deg)^T 0R6^T (0, 0, -m g); tau = r x f_S
    m, th = 0.139, math.radians(15.0)
    rz = np.array([[math.cos(th), -math.sin(th), 0], [math.sin(th), math.cos(th), 0], [0, 0, 1]])
    f = rz.T @ world.flange_rotation.T @ np.array([0.0, 0.0, -m * G])
    tau = np.cross(np.array([3.0, -2.0, 45.0]) * 1e-3, f)
    np.testing.assert_array_less(np.abs(w.as_array() - np.concatenate([f, tau])),
                                 np.array(RES) / 2 + 2e-6)


async def test_stale_stream_is_a_fault_never_a_held_wrench():
    async with rig() as (_, srv), driver_for(srv, stale_after_s=0.1) as drv:
        held = await first_read(drv)
        srv.stop_stream()                      # the box goes quiet
        await asyncio.sleep(0.2)
        with pytest.raises(DeviceFault, match="stale") as e:
            await drv.read()
        assert "100.0 ms" in str(e.value) and e.value.device == "netft"
        assert held.seq <= drv.received


async def test_saturation_in_the_world_is_a_status_fault():
    # a 0.5 N range: the tool's 1.36 N weight saturates at least one force channel
    async with rig(clean_world(range_n=(0.5, 0.5, 0.5))) as (world, srv):
        assert world.sensor.status
        async with driver_for(srv) as drv:
            await wait_for(lambda: drv.received > 0)
            with pytest.raises(DeviceFault, match="0x80020000") as e:
                await drv.read()
            assert "saturation" in str(e.value)
            srv.status_override = 0x80000004       # any other status bit faults as well
            await asyncio.sleep(0.05)
            with pytest.raises(DeviceFault, match="internal temperature"):
                await drv.read()


async def test_bad_truncated_and_garbage_datagrams_are_counted_and_reading_goes_on():
    async with rig() as (_, srv), driver_for(srv) as drv:
        await first_read(drv)
        good = encode_record(RdtRecord(1, 0, 0, (0,) * 6))
        # (an empty datagram is covered byte-level: asyncio does not send empty ones)
        junk = [b"\x12\x34", good[:35], good + b"\x00", good * 2 + good[:20],
                bytes(range(100)), b"\xff" * (41 * 36)]
        for j in junk:
            srv.send_raw(j)
        srv.send_raw(good)                     # an old record: rdt 1, ft_sequence 0
        await wait_for(lambda: drv.bad_datagrams == len(junk) and drv.out_of_order == 1)
        before = drv.received
        await wait_for(lambda: drv.received > before + 5)
        assert (await drv.read()).seq > before
        assert drv.lost == 0


async def test_reader_counts_gaps_and_reordering_from_a_scripted_box():
    """A hand-scripted box: checks the bytes the driver sends and its sequence accounting."""
    loop = asyncio.get_running_loop()
    got: asyncio.Queue = asyncio.Queue()

    class Box(asyncio.DatagramProtocol):
        def datagram_received(self, data, addr):
            got.put_nowait((data, addr))

    box, _ = await loop.create_datagram_endpoint(Box, local_addr=("127.0.0.1", 0))
    try:
        port = box.get_extra_info("sockname")[1]
        drv = NetFTDriver("127.0.0.1", port, counts_per_force=1e6, counts_per_torque=1e6)
        assert isinstance(drv, ForceSensor)
        with pytest.raises(DeviceFault, match="not connected"):
            await drv.read()
        await drv.connect()
        data, peer = await asyncio.wait_for(got.get(), 2)
        assert data == bytes.fromhex("1234 0002 00000000")      # start real-time, count 0
        with pytest.raises(DeviceFault, match="no RDT record"):
            await drv.read()
        for seq in (1, 2, 5, 4, 5, 6):         # 3 lost, 4 late, 5 duplicated
            box.sendto(encode_record(RdtRecord(seq, 14 * seq, 0, (seq, 0, 0, 0, 0, -seq))), peer)
        # buffered-style datagram: 7 and 8 back to back
        box.sendto(encode_records([RdtRecord(s, 14 * s, 0, (s,) * 6) for s in (7, 8)]), peer)
        await wait_for(lambda: drv.received == 6)
        assert (drv.lost, drv.out_of_order) == (2, 2)
        w = await drv.read()
        assert w.seq == 8 and w.force_n == (8e-6, 8e-6, 8e-6)
        await drv.bias()
        assert (await asyncio.wait_for(got.get(), 2))[0] == bytes.fromhex("1234 0042 00000000")
        await drv.close()
        assert (await asyncio.wait_for(got.get(), 2))[0] == bytes.fromhex("1234 0000 00000000")
    finally:
        box.close()
        await asyncio.sleep(0)


def test_constructor_validates_its_configuration():
    with pytest.raises(ConfigError):
        NetFTDriver(counts_per_force=1e6)
    with pytest.raises(ConfigError):
        NetFTDriver(counts_per_force=0, counts_per_torque=1e6)
    with pytest.raises(ConfigError):
        NetFTDriver(stale_after_s=0)
    with pytest.raises(ConfigError):
        NetFTServer(World(WorldConfig()), rate_hz=10_000)


# --------------------------------------------------------------------------- simulator alone
def _plain_rdt_client(port: int, out: dict) -> None:
    """What a third-party RDT client does: plain socket + struct, no DentiBot code."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(2.0)
        s.sendto(struct.pack(">HHI", 0x1234, 0x0003, 25), ("127.0.0.1", port))  # buffered, 25
        sizes, recs = [], []
        while sum(sizes) < 25:
            data = s.recv(2048)
            sizes.append(len(data) // 36)
            recs += [struct.unpack_from(">III6i", data, o) for o in range(0, len(data), 36)]
        s.sendto(struct.pack(">HHI", 0x1234, 0x0002, 5), ("127.0.0.1", port))   # real-time, 5
        rt = [struct.unpack(">III6i", s.recv(2048)) for _ in range(5)]
        s.settimeout(0.1)
        try:
            extra = s.recv(2048)
        except TimeoutError:
            extra = None
        s.sendto(struct.pack(">HHI", 0x1234, 0x0000, 0), ("127.0.0.1", port))
    out.update(sizes=sizes, recs=recs, rt=rt, extra=extra)


async def test_a_plain_socket_struct_client_reads_the_simulator():
    async with rig(clean_world(mass_kg=0.0), buffer_size=10, http_port=None) as (_, srv):
        srv.inject_offset((1.0, -2.0, 3.0), (0.25, -0.5, 0.125))
        out: dict = {}
        th = threading.Thread(target=_plain_rdt_client, args=(srv.port, out))
        th.start()
        while th.is_alive():
            await asyncio.sleep(0.01)
        th.join()
        srv.send_raw(b"\x00" * 8, ("127.0.0.1", 9))      # harmless: nobody listens there
        bad = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        with bad:
            bad.sendto(b"\x12\x34\x00", ("127.0.0.1", srv.port))   # malformed request
            await wait_for(lambda: srv.bad_requests == 1)
    assert out["sizes"] == [10, 10, 5]                 # comrdtbsiz 10, sample_count 25
    assert [r[0] for r in out["recs"]] == list(range(1, 26))
    ft = [r[1] for r in out["recs"]]
    assert all(b > a for a, b in itertools.pairwise(ft))   # ft_sequence counts on
    assert {r[3:] for r in out["recs"]} == {(1_000_000, -2_000_000, 3_000_000,
                                             250_000, -500_000, 125_000)}
    assert {r[2] for r in out["recs"]} == {0}
    assert [r[0] for r in out["rt"]] == [1, 2, 3, 4, 5]  # restarts at 1 per request
    assert out["rt"][0][1] > ft[-1]                      # ft_sequence keeps counting
    assert out["extra"] is None                          # sample_count honoured


async def test_server_start_close_are_idempotent_and_release_everything():
    world = World(WorldConfig())
    srv = NetFTServer(world, port=0, http_port=0)
    await srv.start()
    await srv.start()
    port = srv.port
    assert port != 0 and srv.http_port != 0
    await srv.close()
    await srv.close()
    # the port is free again
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", port))
