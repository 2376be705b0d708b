"""LoopReader: a bus's frames reach the event loop in order, in batches when the loop is busy,
and a broken link is told once."""

import asyncio
import time
import uuid

import can
import pytest

from dentibot.io.can_reader import LoopReader


def _pair():
    channel = f"reader-{uuid.uuid4().hex}"
    return (can.Bus(interface="virtual", channel=channel),
            can.Bus(interface="virtual", channel=channel))


async def _until(cond, timeout_s=2.0):
    t_end = time.monotonic() + timeout_s
    while not cond() and time.monotonic() < t_end:
        await asyncio.sleep(0.002)


async def test_frames_in_order_and_batched_while_the_loop_is_busy():
    tx, rx = _pair()
    got: list[int] = []
    reader = LoopReader(rx, lambda m: got.append(int.from_bytes(m.data, "little")),
                        loop=asyncio.get_running_loop())
    try:
        n = 600
        for i in range(n):
            tx.send(can.Message(arbitration_id=0x181, data=i.to_bytes(2, "little"),
                                is_extended_id=False))
        time.sleep(0.05)          # the loop busy: the frames wait in the reader's queue
        await _until(lambda: len(got) == n)
        assert got == list(range(n))
        # one hand-over per frame would be 600 deliveries; a busy loop gets them in a few
        # (at most MAX_BATCH = 512 per hand-over: at least two here)
        assert 2 <= reader.batches <= 20, reader.batches
        assert reader.frames == n
    finally:
        reader.stop()
        tx.shutdown()
        rx.shutdown()


class _Broken(can.BusABC):
    def __init__(self):
        super().__init__(channel="broken")
        self.calls = 0

    def send(self, msg, timeout=None):
        raise can.CanOperationError("no link")

    def _recv_internal(self, timeout):
        self.calls += 1
        raise can.CanOperationError("the server closed the connection")


async def test_a_receive_error_ends_the_reader_and_is_told_once():
    bus = _Broken()
    errors: list[Exception] = []
    reader = LoopReader(bus, lambda m: None, on_error=errors.append,
                        loop=asyncio.get_running_loop())
    await _until(lambda: bool(errors))
    await asyncio.sleep(0.05)
    assert len(errors) == 1 and "closed the connection" in str(errors[0])
    assert bus.calls == 1 and reader.exception is errors[0]
    reader.stop()
    bus.shutdown()


async def test_nothing_is_delivered_after_stop():
    tx, rx = _pair()
    got: list[can.Message] = []
    reader = LoopReader(rx, got.append, loop=asyncio.get_running_loop())
    try:
        reader.stop()
        assert reader.stopped
        tx.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
        await asyncio.sleep(0.1)
        assert got == []
    finally:
        tx.shutdown()
        rx.shutdown()


async def test_a_failing_handler_does_not_drop_the_rest_of_the_batch():
    tx, rx = _pair()
    got: list[int] = []
    loop = asyncio.get_running_loop()
    seen: list[dict] = []
    loop.set_exception_handler(lambda _loop, ctx: seen.append(ctx))

    def handler(m: can.Message) -> None:
        if m.data[0] == 3:
            raise ValueError("bad frame")
        got.append(m.data[0])

    reader = LoopReader(rx, handler, loop=loop)
    try:
        for i in range(6):
            tx.send(can.Message(arbitration_id=0x181, data=bytes([i]), is_extended_id=False))
        time.sleep(0.02)
        await _until(lambda: len(got) == 5)
        assert got == [0, 1, 2, 4, 5]
        assert len(seen) == 1 and isinstance(seen[0]["exception"], ValueError)
    finally:
        loop.set_exception_handler(None)
        reader.stop()
        tx.shutdown()
        rx.shutdown()


@pytest.mark.parametrize("timeout", [0.01, 0.05])
async def test_stop_joins_within_the_receive_timeout(timeout):
    tx, rx = _pair()
    reader = LoopReader(rx, lambda m: None, loop=asyncio.get_running_loop(), timeout=timeout)
    t0 = time.monotonic()
    reader.stop(timeout=1.0)
    assert time.monotonic() - t0 < timeout + 0.5
    assert not reader._thread.is_alive()
    tx.shutdown()
    rx.shutdown()


# ---------------------------------------------------------------- a bus with a descriptor
async def _socketcand_peer():
    """A socketcand server on loopback that greets, accepts the handshake and then writes
    what the test puts in its queue (None: close the connection)."""
    out: asyncio.Queue = asyncio.Queue()

    async def serve(reader, writer):
        writer.write(b"< hi >")
        for _ in range(2):                          # < open vcan0 >, < rawmode >
            await reader.readuntil(b">")
            writer.write(b"< ok >")
        while (chunk := await out.get()) is not None:
            writer.write(chunk)
            await writer.drain()
            await asyncio.sleep(0.01)               # each chunk in a read of its own
        writer.close()

    server = await asyncio.start_server(serve, "127.0.0.1", 0)
    return server, server.sockets[0].getsockname()[1], out


async def _open_socketcand(port: int):
    """Our socketcand client (its handshake blocks: in a short-lived thread)."""
    from dentibot.io.canopen_master import SocketcandBus, in_thread

    return await in_thread(lambda: SocketcandBus("vcan0", "127.0.0.1", port), "open-bus")


async def test_a_bus_with_a_descriptor_is_read_on_the_loop_in_order_across_split_reads():
    server, port, out = await _socketcand_peer()
    bus = await _open_socketcand(port)
    got: list[tuple[int, bytes]] = []
    errors: list[Exception] = []
    loop = asyncio.get_running_loop()
    reader = LoopReader(bus, lambda m: got.append((m.arbitration_id, bytes(m.data))),
                        on_error=errors.append, loop=loop)
    try:
        assert not reader.threaded            # the loop watches the socket: no thread
        # three frames: glued together, one split in the middle of its data, an empty one
        await out.put(b"< frame 181 1.000001 0102 >< frame 281 1.000002 A")
        await out.put(b"ABBCC >< frame 701 1.000003  >")
        await _until(lambda: len(got) == 3)
        assert got == [(0x181, b"\x01\x02"), (0x281, b"\xAA\xBB\xCC"), (0x701, b"")]
        assert reader.frames == 3
        await out.put(None)                   # the server closes: told once, then silence
        await _until(lambda: bool(errors))
        await asyncio.sleep(0.05)
        assert len(errors) == 1 and "closed the connection" in str(errors[0])
        assert reader.exception is errors[0]
        assert not loop.remove_reader(bus.fileno())    # no longer watched
    finally:
        reader.stop()
        bus.shutdown()
        server.close()
        await server.wait_closed()


async def test_stop_unwatches_a_bus_with_a_descriptor():
    server, port, out = await _socketcand_peer()
    bus = await _open_socketcand(port)
    got: list[can.Message] = []
    loop = asyncio.get_running_loop()
    reader = LoopReader(bus, got.append, loop=loop)
    try:
        reader.stop()
        assert reader.stopped and not loop.remove_reader(bus.fileno())
        await out.put(b"< frame 181 1.000001 01 >")
        await asyncio.sleep(0.1)
        assert got == []
    finally:
        await out.put(None)
        bus.shutdown()
        await asyncio.sleep(0.05)             # the server's side closes
        server.close()
        await server.wait_closed()
