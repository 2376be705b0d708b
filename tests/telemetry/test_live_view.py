"""LiveView: a viewer on 127.0.0.1 speaking the Foxglove WebSocket protocol receives the run's
channels as a recording holds them."""

from __future__ import annotations

import json
import socket
import time

import pytest
from foxglove_schema_rules import problems
from telemetry_helpers import ramp_row
from ws_client import FoxgloveWsClient, MessageData

from dentibot.errors import ConfigError
from dentibot.telemetry import TelemetryError, json_schema
from dentibot.telemetry.foxglove import FOXGLOVE_TOPICS
from dentibot.telemetry.live import LiveView

pytestmark = pytest.mark.timeout(60)

START_NS = 1_700_000_000_000_000_000
META = {"protocol": "demo", "seed": 7, "rate_hz": 500, "start_wall_ns": START_NS}
TOPICS = {"/run", "/tick", "/events", "/run/end", "/tf", "/scene"}


@pytest.fixture(scope="module", autouse=True)
def _sdk_runtime():
    """The Foxglove SDK starts its I/O runtime with the first server of the process and keeps
    it (with a few sockets of its own) until the process exits: start it once here, before
    the suite's per-test guard takes its count of open sockets, so that a LiveView is judged
    on what it leaves itself."""
    LiveView(META, port=0).close()


def _subscribe(client: FoxgloveWsClient, channels: dict, topics: list[str]) -> dict[int, str]:
    """Subscribe to ``topics``; subscription id -> topic."""
    subs = {i + 1: topic for i, topic in enumerate(topics)}
    client.send_json({"op": "subscribe", "subscriptions": [
        {"id": i, "channelId": channels[topic]["id"]} for i, topic in subs.items()]})
    return subs


def _collect(client: FoxgloveWsClient, subs: dict[int, str], until, timeout: float = 10.0):
    """Message Data received, as (topic, log time, decoded JSON), until ``until(got)``."""
    got: list[tuple[str, int, dict]] = []
    deadline = time.monotonic() + timeout
    while not until(got):
        assert time.monotonic() < deadline, f"not received in time: {[g[0] for g in got]}"
        msg = client.receive()
        if isinstance(msg, MessageData):
            got.append((subs[msg.subscription_id], msg.log_time_ns, json.loads(msg.payload)))
    return got


def test_a_viewer_on_localhost_receives_ticks_transforms_and_the_run():
    live = LiveView(META, port=0)
    client = None
    try:
        assert live.url == f"ws://127.0.0.1:{live.port}" and live.port > 0
        client = FoxgloveWsClient("127.0.0.1", live.port)
        info = client.receive()
        assert info["op"] == "serverInfo" and info["name"] == "DentiBot"
        channels = client.advertised(TOPICS)
        for topic, channel in channels.items():
            assert channel["encoding"] == "json"
            assert channel["schemaEncoding"] == "jsonschema"
            schema = json.loads(channel["schema"])
            expected = FOXGLOVE_TOPICS.get(topic) or json_schema(topic)
            assert schema == expected and channel["schemaName"] == expected["title"]
            assert problems(schema) == [], topic          # parses in the open-source viewers
        subs = _subscribe(client, channels, ["/run", "/tick", "/tf", "/events", "/run/end"])
        # the run is sent again to a viewer that subscribes to it
        (run,) = _collect(client, subs, lambda got: any(t == "/run" for t, _l, _m in got))
        assert run[1] == START_NS and run[2]["protocol"] == "demo"
        assert run[2]["start_wall_ns"] == START_NS
        rows = [ramp_row(i, phantom_pose=None) for i in range(5)]
        for row in rows:
            live.record(row)
        live.event("note", "hello", t=0.004, tick=2)
        got = _collect(client, subs, lambda got: sum(t == "/tick" for t, _l, _m in got) == 5
                       and any(t == "/events" for t, _l, _m in got)
                       and sum(t == "/tf" for t, _l, _m in got) == 5)
        ticks = [(lt, m) for t, lt, m in got if t == "/tick"]
        assert [lt for lt, _m in ticks] == [START_NS + round(r["t"] * 1e9) for r in rows]
        for row, (_lt, msg) in zip(rows, ticks, strict=True):
            # as in a recording: unknown values left out, everything else as handed over
            assert msg == {k: v for k, v in row.items() if v is not None}
            assert "phantom_pose" not in msg
        tf = next(m for t, _l, m in got if t == "/tf")
        (tip,) = tf["transforms"]
        assert (tip["parent_frame_id"], tip["child_frame_id"]) == ("base", "file_tip")
        assert [tip["translation"][k] for k in "xyz"] == pytest.approx([0.19, 0.0, 0.308])
        event = next((lt, m) for t, lt, m in got if t == "/events")
        assert event == (START_NS + 4_000_000, {"t": 0.004, "tick": 2, "kind": "note",
                                                "detail": "hello"})
        assert live.close("ok") == {"status": "ok", "reason": "", "duration_s": rows[-1]["t"]}
        end = _collect(client, subs, lambda got: any(t == "/run/end" for t, _l, _m in got))
        assert end[-1][2]["status"] == "ok"
    finally:
        if client is not None:
            client.close()
        live.close()
    assert live.closed and live.close("fault") == live.end        # idempotent
    live.record(ramp_row(9))                                       # counted, never raised
    assert live.items_dropped == 1


def test_nothing_is_encoded_for_channels_nobody_watches():
    with LiveView(META, port=0) as live:
        for i in range(50):
            live.record(ramp_row(i))
        deadline = time.monotonic() + 5
        while live.queue_depth and time.monotonic() < deadline:
            time.sleep(0.01)
        assert live.rows_queued == 50 and live.messages_sent == 1        # the first /run


def test_a_block_nobody_watches_is_counted_not_queued_and_a_watched_one_is_sent():
    """A lock-step run hands rows over faster than the publisher takes them: with no viewer
    on the rows' topics a block is only counted (nothing would be sent); a viewer on /tick
    receives each row of the block."""
    import numpy as np

    from dentibot.telemetry.blocks import WIDTH, TickBlock

    block = TickBlock(np.arange(8 * WIDTH, dtype=float).reshape(8, WIDTH), 100, 0.002,
                      "4:drill", "treating.drilling.feeding", 16.0, 0, (180.0, 0.0, 90.0))
    live = LiveView(META, port=0, poll_s=5.0)
    client = None
    try:
        time.sleep(0.05)                          # the publisher asleep: the queue shows all
        live.record_block(block)
        assert live.rows_queued == 8 and live.queue_depth == 0
        live.event("note", "after the block")
        assert live._queue[-1][1]["tick"] == 107 and live._queue[-1][1]["t"] == 107 * 0.002
        client = FoxgloveWsClient("127.0.0.1", live.port)
        client.receive()
        subs = _subscribe(client, client.advertised(TOPICS), ["/tick"])
        deadline = time.monotonic() + 10
        while not live._channels["/tick"].has_sinks():
            assert time.monotonic() < deadline
            time.sleep(0.01)
        live.record_block(block.part(0, 3))
        assert live.rows_queued == 11
        live._wake.set()
        got = _collect(client, subs, lambda got: len(got) == 3)
        assert [m["tick"] for _t, _l, m in got] == [100, 101, 102]
        assert [m["q_deg"] for _t, _l, m in got] == [r["q_deg"] for r in block.rows(0, 3)]
    finally:
        if client is not None:
            client.close()
        live.close()


def test_a_full_queue_drops_the_oldest_and_counts():
    with LiveView(META, port=0, max_queue=10, poll_s=5.0) as live:
        client = FoxgloveWsClient("127.0.0.1", live.port)      # a viewer: rows are queued
        try:
            client.receive()
            _subscribe(client, client.advertised(TOPICS), ["/tick"])
            deadline = time.monotonic() + 10
            while not live._channels["/tick"].has_sinks():
                assert time.monotonic() < deadline
                time.sleep(0.01)
            # the publisher sleeps up to poll_s between drains: fill the queue meanwhile
            time.sleep(0.05)
            for i in range(25):
                live.record(ramp_row(i))
            assert live.items_dropped >= 10 and live.queue_depth <= 10
        finally:
            client.close()


def test_a_taken_port_is_a_typed_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(TelemetryError, match="cannot serve the live view"):
            LiveView(META, port=port)
    with pytest.raises(ConfigError, match="port"):
        LiveView(META, port=70000)
