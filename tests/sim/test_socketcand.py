"""SocketcandServer: the ASCII codec (checked against python-can's own socketcand codec), the
server over loopback TCP, python-can's socketcand client through it, and the EPOS4 driver
reaching the simulated node through it."""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
import threading
import time
import uuid

import can
import pytest
from can.interfaces.socketcand.socketcand import (
    convert_ascii_message_to_can_message,
    convert_can_message_to_ascii_message,
)
from hypothesis import given
from hypothesis import strategies as st

from dentibot.app.selftest_wire import LoopStalls
from dentibot.errors import DeviceFault, ProtocolError
from dentibot.io.canopen_protocol import State
from dentibot.io.epos4 import Epos4Driver, SocketcandBus
from dentibot.sim import RealTimeStepper, World, WorldConfig
from dentibot.sim.epos4_node import Epos4Node
from dentibot.sim.socketcand import (
    CommandBuffer,
    SocketcandServer,
    encode_frame,
    parse_command,
    parse_send,
)

pytestmark = [pytest.mark.wire, pytest.mark.timeout(30)]


def channel() -> str:
    return f"socketcand-test-{uuid.uuid4().hex}"


# ---------------------------------------------------------------- codec

STREAM = b"< hi >< open vcan0 >< send 601 8 40 0 10 0 0 0 0 0 >< send 080 0  >< echo >"
COMMANDS = ["< hi >", "< open vcan0 >", "< send 601 8 40 0 10 0 0 0 0 0 >", "< send 080 0  >",
            "< echo >"]


def test_command_buffer_survives_any_split():
    for size in (1, 2, 3, 7, len(STREAM)):
        buf = CommandBuffer()
        got = []
        for i in range(0, len(STREAM), size):
            got += buf.feed(STREAM[i:i + size])
        assert got == COMMANDS
        assert buf.discarded == 0


def test_command_buffer_skips_garbage():
    buf = CommandBuffer(max_chars=64)
    assert buf.feed(b"junk\r\n< echo >more") == ["< echo >"]
    assert buf.discarded == len("junk\r\nmore")        # text outside < > is skipped
    assert buf.feed(b" < a < echo >") == ["< echo >"]                 # keep the last "<"
    assert buf.feed(b"<" + b"x" * 100) == []                          # over-long: dropped
    assert buf.feed(b"< echo >") == ["< echo >"]
    assert buf.feed(b"< \xff\xfe >< echo >") == ["< echo >"]          # not ASCII: dropped


@given(st.lists(st.integers(1, 20), min_size=1, max_size=40))
def test_command_buffer_split_fuzz(cuts):
    buf, got, i = CommandBuffer(), [], 0
    for n in cuts:
        got += buf.feed(STREAM[i:i + n])
        i += n
    got += buf.feed(STREAM[i:])
    assert got == COMMANDS


@given(st.binary(max_size=300))
def test_command_buffer_and_parsers_never_crash_untyped(data):
    for text in CommandBuffer().feed(data):
        assert text.startswith("<") and text.endswith(">")
        try:
            verb, args = parse_command(text)
            if verb == "send":
                parse_send(args)
        except ProtocolError as exc:
            assert exc.device == "socketcand"


@given(st.booleans(), st.integers(0, 0x1FFF_FFFF), st.binary(max_size=8))
def test_python_cans_send_command_parses_back(ext, can_id, data):
    can_id = can_id if ext else can_id & 0x7FF
    msg = can.Message(arbitration_id=can_id, is_extended_id=ext, data=data)
    verb, args = parse_command(convert_can_message_to_ascii_message(msg))
    assert verb == "send"
    assert parse_send(args) == (can_id, ext, data)


@given(st.booleans(), st.integers(0, 0x1FFF_FFFF), st.binary(max_size=8),
       st.floats(0, 2e9, allow_nan=False))
def test_our_frame_line_parses_in_python_cans_client(ext, can_id, data, ts):
    can_id = can_id if ext else can_id & 0x7FF
    msg = convert_ascii_message_to_can_message(encode_frame(can_id, ext, data, ts))
    assert (msg.arbitration_id, msg.is_extended_id, bytes(msg.data)) == (can_id, ext, data)
    assert msg.timestamp == pytest.approx(ts, abs=1e-6)


def test_frame_line_format():
    assert encode_frame(0x181, False, b"\x37\x06", 12.5) == "< frame 181 12.500000 3706 >"
    assert encode_frame(0x80, False, b"", 1.0) == "< frame 080 1.000000  >"
    assert encode_frame(0x1234567, True, b"\xab", 0.9999996) == \
        "< frame 01234567 1.000000 AB >"


@pytest.mark.parametrize("args, why", [
    (["601"], "needs an id and a length"), (["6G1", "0"], "not hexadecimal"),
    (["800", "0"], "0..7FF"), (["1234", "0"], "3 hex digits"), (["601", "9"], "0..8"),
    (["601", "2", "1"], "length 2 but 1 data bytes"), (["601", "1", "100"], "at most 2"),
    (["601", "1", "-1"], "hex number"),
])
def test_malformed_send_is_a_protocol_error(args, why):
    with pytest.raises(ProtocolError, match=why):
        parse_send(args)


# ---------------------------------------------------------------- server over TCP


@contextlib.asynccontextmanager
async def server_on(ch: str, **kw):
    bus = can.Bus(interface="virtual", channel=ch)
    server = SocketcandServer(bus, port=0, **kw)
    try:
        await server.start()
        yield server
    finally:
        await server.close()
        bus.shutdown()


class Line:
    """A raw TCP client speaking socketcand by hand."""

    def __init__(self, reader, writer):
        self.reader, self.writer, self.buf = reader, writer, CommandBuffer()
        self.pending: list[str] = []

    @classmethod
    async def open(cls, port: int) -> Line:
        return cls(*await asyncio.open_connection("127.0.0.1", port))

    async def expect(self, timeout: float = 2.0) -> str:
        deadline = time.monotonic() + timeout
        while not self.pending:
            data = await asyncio.wait_for(self.reader.read(4096),
                                          max(0.01, deadline - time.monotonic()))
            assert data, "connection closed"
            self.pending += self.buf.feed(data)
        return self.pending.pop(0)

    def say(self, text: str) -> None:
        self.writer.write(text.encode())

    async def close(self) -> None:
        self.writer.close()
        with contextlib.suppress(ConnectionError):
            await self.writer.wait_closed()


async def handshake(port: int, ch: str = "vcan0") -> Line:
    line = await Line.open(port)
    assert await line.expect() == "< hi >"
    line.say(f"< open {ch} >")
    assert await line.expect() == "< ok >"
    line.say("< rawmode >")
    assert await line.expect() == "< ok >"
    return line


async def test_server_handshake_and_bridging():
    ch = channel()
    watch = can.Bus(interface="virtual", channel=ch)
    try:
        async with server_on(ch) as server:
            line = await Line.open(server.port)
            assert await line.expect() == "< hi >"
            line.say("< rawmode >")
            assert (await line.expect()).startswith("< error")           # no bus open yet
            line.say("< open can7 >")
            assert await line.expect() == "< error could not open bus >"
            line.say("< open vcan0 >")
            assert await line.expect() == "< ok >"
            line.say("< rawmode >")
            assert await line.expect() == "< ok >"
            line.say("< echo >")
            assert await line.expect() == "< echo >"
            # client -> bus, split over several writes with garbage between commands
            for part in ("xx< send 6", "01 8 40 41 60 0 0 0 0 0", " >\n< send 08", "0 0  >"):
                line.say(part)
                await asyncio.sleep(0.01)
            got = []
            deadline = time.monotonic() + 2
            while len(got) < 2 and time.monotonic() < deadline:
                if (m := watch.recv(0)) is not None:
                    got.append(m)
                await asyncio.sleep(0.005)
            assert [(m.arbitration_id, bytes(m.data)) for m in got] == \
                [(0x601, bytes.fromhex("4041600000000000")), (0x080, b"")]
            # bus -> client
            watch.send(can.Message(arbitration_id=0x581, is_extended_id=False,
                                   data=bytes.fromhex("4B41600040020000")))
            text = await line.expect()
            assert text.startswith("< frame 581 ") and text.endswith(" 4B41600040020000 >")
            # a malformed send is answered with an error; the connection stays usable
            line.say("< send 601 2 1 >")
            assert (await line.expect()).startswith("< error length 2 but 1")
            line.say("< bogus >")
            assert (await line.expect()).startswith("< error unknown")
            line.say("< echo >")
            assert await line.expect() == "< echo >"
            assert server.errors == 4 and server.frames_from_clients == 2
            await line.close()
    finally:
        watch.shutdown()


async def test_frames_wait_until_the_handshake_is_over():
    """python-can's client compares each handshake answer to one recv(): a frame glued to
    the last "< ok >" would break it. Frames flow before, during and after the handshake."""
    ch = channel()
    pump = can.Bus(interface="virtual", channel=ch)
    stop = asyncio.Event()

    async def flood():
        k = 0
        while not stop.is_set():
            pump.send(can.Message(arbitration_id=0x181, is_extended_id=False,
                                  data=k.to_bytes(2, "little")))
            k = (k + 1) & 0xFFFF
            await asyncio.sleep(0.0005)

    try:
        async with server_on(ch, handshake_grace_s=5.0) as server:
            task = asyncio.create_task(flood())
            try:
                line = await Line.open(server.port)
                raw = await asyncio.wait_for(line.reader.read(256), 2)
                assert raw == b"< hi >"
                line.say("< open vcan0 >")
                assert await asyncio.wait_for(line.reader.read(256), 2) == b"< ok >"
                line.say("< rawmode >")
                assert await asyncio.wait_for(line.reader.read(256), 2) == b"< ok >"
                await asyncio.sleep(0.05)           # frames are held back meanwhile
                line.say("< echo >")                # the client speaks: frames may flow
                texts = [await line.expect() for _ in range(20)]
                assert texts[0] == "< echo >" or texts[0].startswith("< frame 181 ")
                assert sum(t.startswith("< frame 181 ") for t in texts) >= 19
                await line.close()
            finally:
                stop.set()
                await task
    finally:
        pump.shutdown()


async def test_clients_see_each_others_frames_but_not_their_own():
    ch = channel()
    async with server_on(ch) as server:
        a = await handshake(server.port)
        b = await handshake(server.port)
        a.say("< echo >")
        b.say("< echo >")
        assert await a.expect() == "< echo >" and await b.expect() == "< echo >"
        a.say("< send 123 1 aa >")
        assert (await b.expect()).endswith(" AA >")
        a.say("< echo >")
        assert await a.expect() == "< echo >"       # nothing of its own came first
        assert server.clients == 2
        await a.close()
        await b.close()


async def _in_thread(fn):
    """Run blocking ``fn`` in a thread while the loop keeps serving; return its result."""
    box: dict = {}

    def run():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001
            box["error"] = exc

    th = threading.Thread(target=run)
    th.start()
    while th.is_alive():
        await asyncio.sleep(0.005)
    th.join()
    if "error" in box:
        raise box["error"]
    return box.get("value")


async def test_python_can_socketcand_client_through_the_server():
    ch = channel()
    watch = can.Bus(interface="virtual", channel=ch)
    try:
        async with server_on(ch) as server:
            client = await _in_thread(lambda: can.Bus(
                interface="socketcand", host="127.0.0.1", port=server.port, channel="vcan0"))
            try:
                client.send(can.Message(arbitration_id=0x12345, is_extended_id=True,
                                        data=b"\x01\x02"))
                got: list[can.Message] = []
                assert await _until(lambda: _drain(watch, got) >= 1)
                assert [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in got] == \
                    [(0x12345, True, b"\x01\x02")]
                watch.send(can.Message(arbitration_id=0x701, is_extended_id=False,
                                       data=b"\x05"))
                msg = await _in_thread(lambda: client.recv(2.0))
                assert (msg.arbitration_id, msg.is_extended_id, bytes(msg.data)) == \
                    (0x701, False, b"\x05")
            finally:
                client.shutdown()
    finally:
        watch.shutdown()


def _drain(bus: can.BusABC, out: list) -> int:
    while (m := bus.recv(0)) is not None:
        out.append(m)
    return len(out)


async def _until(pred, timeout: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(0.005)
    return True


# ---------------------------------------------------------------- the driver through it


class _Writes:
    """A socket stand-in that keeps each write."""

    def __init__(self):
        self.writes: list[bytes] = []

    def sendall(self, data: bytes) -> None:
        self.writes.append(bytes(data))


def test_a_drive_cycle_is_one_write_and_packed_again_only_when_its_commands_change():
    drv = Epos4Driver(interface="socketcand", channel="vcan0", node_id=1)
    bus = SocketcandBus.__new__(SocketcandBus)      # no server: its socket is the spy
    bus._sock, bus.channel_info = _Writes(), "spy"
    drv._bus = bus
    drv._send_cycle()
    drv._send_cycle()
    drv._target_vel = 4020                           # 60 rpm x 67: a new command
    drv._send_cycle()
    writes = bus._sock.writes
    assert len(writes) == 3                          # one write per cycle
    assert writes[0] == writes[1] != writes[2]
    buf = CommandBuffer()
    frames = [parse_send(parse_command(line)[1]) for line in buf.feed(writes[2])]
    # RxPDO2 (target position, profile velocity), RxPDO1 (controlword, target velocity,
    # mode of operation), SYNC: the cycle's order, each line as the server parses it
    assert [f[0] for f in frames] == [0x301, 0x201, 0x080]
    assert frames[1][2][2:6] == (4020).to_bytes(4, "little", signed=True)
    assert frames[2][2] == b""
    # the same lines python-can's own client would send, frame by frame
    assert [parse_send(parse_command(convert_can_message_to_ascii_message(
        can.Message(arbitration_id=c, data=d, is_extended_id=False)))[1]) for c, _, d in frames] \
        == frames


async def test_epos4_driver_through_socketcand():
    ch = channel()
    world = World(WorldConfig(seed=1))
    stop = asyncio.Event()
    stepper = asyncio.create_task(RealTimeStepper(world).run(stop))
    node_bus = can.Bus(interface="virtual", channel=ch)
    node = Epos4Node(world, node_bus)
    server_bus = can.Bus(interface="virtual", channel=ch)
    server = SocketcandServer(server_bus, port=0, channel="vcan0")
    drv = None
    try:
        await node.start()
        await server.start()
        # host and drive share this loop: a longer consumer time than the product's 30 ms,
        # so that a stall of the test process is not a lost host (tests/io/test_epos4.py)
        drv = Epos4Driver(interface="socketcand", host="127.0.0.1", port=server.port,
                          channel="vcan0", stale_after_s=0.5, answer_timeout_s=0.5,
                          consumer_ms=250)
        await drv.connect()
        assert drv.state is State.OPERATION_ENABLED and node.state is State.OPERATION_ENABLED
        await drv.set_velocity(60.0)
        n0 = drv.syncs_sent
        assert await _until(lambda: drv.syncs_sent - n0 >= 300, timeout=10.0)
        s = await drv.read()
        assert s.velocity_rpm == pytest.approx(60.0, abs=1 / 67)
        await drv.stop_sync()
        await asyncio.sleep(0.1)
        assert node.syncs_received == drv.syncs_sent
        assert drv.received == node.syncs_answered == drv.syncs_sent
        assert drv.lost == 0 and drv.errors == 0
        # the close waits for the server's end of the stream (up to 0.1 s) off the loop: the
        # server answering it runs on this very loop, which a close that waited in it held
        # for the whole 0.1 s
        probe = LoopStalls()
        probe.start()
        await asyncio.sleep(0.01)                     # the probe is waiting
        closing, drv = drv, None
        await closing.close()
        worst_ms = await probe.stop()
        assert worst_ms < 50.0, worst_ms
    finally:
        if drv is not None:
            await drv.close()
        await server.close()
        await node.close()
        stop.set()
        await stepper
        node_bus.shutdown()
        server_bus.shutdown()


CHILD = """
import asyncio, json, logging, sys
import structlog
structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.ERROR))
from dentibot.io.epos4 import Epos4Driver, SocketcandBus

async def main(port):
    drv = Epos4Driver(interface="socketcand", port=port, channel="vcan0",
                      stale_after_s=0.5, answer_timeout_s=0.5)
    async with drv:
        await drv.set_velocity(60.0)
        for _ in range(250):                     # a control loop reads (feeds) every tick
            s = await drv.read() if drv.received else None
            await asyncio.sleep(0.002)
        s = await drv.read()
        out = {"rpm": s.velocity_rpm, "enabled": s.enabled, "lost": drv.lost,
               "received": drv.received, "km": drv.km_mnm_per_a}
    sys.stdout.write("RESULT " + json.dumps(out) + "\\n")

asyncio.run(main(int(sys.argv[1])))
"""


async def test_driver_in_another_process_reaches_the_node():
    """What the endpoint is for: the virtual bus is per process, socketcand is not."""
    ch = channel()
    world = World(WorldConfig(seed=1))
    stop = asyncio.Event()
    stepper = asyncio.create_task(RealTimeStepper(world).run(stop))
    node_bus = can.Bus(interface="virtual", channel=ch)
    server_bus = can.Bus(interface="virtual", channel=ch)
    node = Epos4Node(world, node_bus)
    server = SocketcandServer(server_bus, port=0)
    try:
        await node.start()
        await server.start()
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-c", CHILD, str(server.port),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        out, err = await asyncio.wait_for(proc.communicate(), 25.0)
        assert proc.returncode == 0, err.decode()[-2000:]
        line = next(ln for ln in out.decode().splitlines() if ln.startswith("RESULT "))
        res = json.loads(line.removeprefix("RESULT "))
        assert res["enabled"] and res["lost"] == 0 and res["received"] > 50
        assert res["rpm"] == pytest.approx(60.0, abs=1 / 67)
        assert res["km"] == 16.0
        assert server.clients_served == 1
        # the driver left the drive disabled and pre-operational when it closed
        assert await _until(lambda: node.state is State.READY_TO_SWITCH_ON)
        assert node.nmt_state.name == "PRE_OPERATIONAL"
    finally:
        await server.close()
        await node.close()
        stop.set()
        await stepper
        node_bus.shutdown()
        server_bus.shutdown()


# ---------------------------------------------------------------- the driver's own client


@given(st.booleans(), st.integers(0, 0x1FFF_FFFF), st.binary(max_size=8))
def test_the_drivers_send_line_parses_in_the_server(ext, can_id, data):
    if not ext:
        can_id &= 0x7FF
    msg = can.Message(arbitration_id=can_id, is_extended_id=ext, data=data)
    verb, args = parse_command(SocketcandBus.send_line(msg))
    assert verb == "send" and parse_send(args) == (can_id, ext, data)


@given(st.booleans(), st.integers(0, 0x1FFF_FFFF), st.binary(max_size=8),
       st.floats(0, 2e9, allow_nan=False))
def test_the_servers_frame_line_parses_in_the_drivers_client(ext, can_id, data, ts):
    if not ext:
        can_id &= 0x7FF
    msg = SocketcandBus.parse_frame(encode_frame(can_id, ext, data, ts))
    assert (msg.arbitration_id, msg.is_extended_id, bytes(msg.data)) == (can_id, ext, data)


@contextlib.asynccontextmanager
async def scripted_server(script):
    """A TCP server whose handler is ``script(reader, writer)``."""
    tasks: list[asyncio.Task] = []
    writers: list[asyncio.StreamWriter] = []

    async def handle(reader, writer):
        tasks.append(asyncio.current_task())
        writers.append(writer)
        with contextlib.suppress(ConnectionError):
            await script(reader, writer)

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        for w in writers:
            w.close()
        server.close()
        await server.wait_closed()


async def test_the_drivers_client_survives_split_and_glued_handshake_answers():
    """The greeting split over two TCP writes, a frame glued to the last "< ok >": python-can's
    own client compares each answer to one recv(); the driver's buffers the stream."""
    async def script(reader, writer):
        writer.write(b"< h")
        await writer.drain()
        await asyncio.sleep(0.02)
        writer.write(b"i >")
        await reader.readuntil(b">")                                  # < open vcan0 >
        writer.write(b"< ok >")
        await reader.readuntil(b">")                                  # < rawmode >
        writer.write(b"< ok >< frame 701 1700000000.000001 05 >")
        await writer.drain()
        assert await reader.readuntil(b">") == b"< send 123 0 >"
        writer.write(b"< frame 181 1700000000.000002 0102 >")
        await writer.drain()
        await asyncio.sleep(1.0)

    async with scripted_server(script) as port:
        bus = await _in_thread(lambda: SocketcandBus("vcan0", "127.0.0.1", port,
                                                     timeout_s=2.0))
        try:
            msg = bus.recv(1.0)
            assert (msg.arbitration_id, bytes(msg.data)) == (0x701, b"\x05")
            bus.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b""))
            msg = await _in_thread(lambda: bus.recv(2.0))
            assert (msg.arbitration_id, bytes(msg.data)) == (0x181, b"\x01\x02")
        finally:
            bus.shutdown()


async def test_the_drivers_client_reports_refusals_and_a_closed_connection():
    async def refuse(reader, writer):
        writer.write(b"< hi >")
        await reader.readuntil(b">")
        writer.write(b"< error could not open bus >")
        await writer.drain()
        await asyncio.sleep(1.0)

    async with scripted_server(refuse) as port:
        drv = Epos4Driver(interface="socketcand", host="127.0.0.1", port=port, channel="can9")
        with pytest.raises(DeviceFault, match=r"could not open bus") as e:
            await drv.connect()
        assert f"127.0.0.1:{port}" in str(e.value)
        await drv.close()

    async def hang_up(reader, writer):
        writer.write(b"< hi >")
        await reader.readuntil(b">")
        writer.write(b"< ok >")
        await reader.readuntil(b">")
        writer.write(b"< ok >")
        await writer.drain()
        await asyncio.sleep(0.05)
        writer.close()

    async with scripted_server(hang_up) as port:
        bus = await _in_thread(lambda: SocketcandBus("vcan0", "127.0.0.1", port))
        try:
            with pytest.raises(can.CanOperationError, match="closed the connection"):
                await _in_thread(lambda: bus.recv(2.0))
        finally:
            bus.shutdown()


async def test_closing_the_client_delivers_its_last_frames_although_frames_were_unread():
    """Frames the server sent that the client has not read when it closes: a plain close
    sends a reset, and the reset makes the server's kernel drop what the server had not
    read yet, here the NMT command sent last (as a driver's close sends it)."""
    from dentibot.io.tasks import in_thread

    received: list[bytes] = []
    done = asyncio.Event()

    async def serve(reader, writer):
        writer.write(b"< hi >")
        for _ in range(2):                            # < open vcan0 >, < rawmode >
            await reader.readuntil(b">")
            writer.write(b"< ok >")
        writer.write(b"< frame 701 1.000000 05 >" * 200)  # the client will not read these
        await writer.drain()
        await asyncio.sleep(0.1)                      # busy: the client sends and closes
        try:
            received.append(await reader.read())      # up to the end of the stream
        except ConnectionResetError:
            received.append(b"(reset: unread bytes dropped)")
        writer.close()
        done.set()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        bus = await in_thread(lambda: SocketcandBus("vcan0", "127.0.0.1", port), "open")
        await asyncio.sleep(0.02)                      # the server's frames are in flight
        bus.send(can.Message(arbitration_id=0x000, data=b"\x80\x00", is_extended_id=False))
        await in_thread(bus.shutdown, "close")
        await asyncio.wait_for(done.wait(), 2.0)
        assert received and received[0].endswith(b"< send 000 2 80 00 >"), received
    finally:
        server.close()
        await server.wait_closed()
