"""Live view: the channels of a recording, streamed to Foxglove while the procedure runs.

:class:`LiveView` is a sink like :class:`~dentibot.telemetry.recorder.McapRecorder`: the control
task hands it each row (``record``) and each event (``event``), and :meth:`LiveView.close`
ends it. It serves the Foxglove WebSocket protocol (through the Foxglove SDK's server) on
``127.0.0.1`` by default, with the topics, schemas and encodings of a recording (``/run``,
``/tick``, ``/events``, ``/run/end``, and the 3D topics ``/tf`` and ``/scene``) and the same log
times (wall-clock start + ``t``): a layout made on a recording works live and back.

Not a record. The recording is the record of a procedure; the live view is a window on it, and
must never slow the control task or stop a run:

- ``record()``/``event()`` append to a bounded queue and return (no encoding, no I/O); a
  publisher thread encodes and hands the messages to the server. If the publisher falls
  behind (a lock-step run, many times faster than real time, with a viewer subscribed), the
  oldest items are dropped and counted (``items_dropped``): a live view shows the present.
- Nothing is encoded for a channel no viewer subscribes to, and rows no viewer watches (on
  ``/tick``, ``/tf`` or ``/scene``) are not even queued.
- A publisher that fails is logged and counted, never raised into the control task;
  :attr:`LiveView.error` tells why.

The ``/run`` message is sent again whenever a viewer subscribes to ``/run``, so a viewer that
connects in the middle of a run still learns what it is watching.

The server binds to ``host`` (``127.0.0.1``: this machine only; another address exposes the
procedure's data to the network, unauthenticated) and ``port`` (0: a free one, see
:attr:`LiveView.port`). The server speaks the protocol under the subprotocol name
``foxglove.sdk.v1`` (the SDK's name for ``foxglove.websocket.v1``): Foxglove connects to it, and
so do Lichtblick releases from the end of 2025 on.
"""

from __future__ import annotations

import collections
import threading
import time
from typing import Any

import foxglove
import orjson
import structlog

from dentibot.errors import ConfigError
from dentibot.telemetry.blocks import TickBlock
from dentibot.telemetry.foxglove import (
    FOXGLOVE_TOPICS,
    SCENE_TOPIC,
    TF_TOPIC,
    FoxgloveView,
    as_view,
)
from dentibot.telemetry.recorder import (
    _dentibot_version,
    _finite,
    _json_default,
    _log_time_ns,
    _nonfinite,
    _start_fields,
    _without_none,
    event_message,
)
from dentibot.telemetry.schema import END_STATUSES, TOPICS, TelemetryError, json_schema

__all__ = ["DEFAULT_PORT", "LiveView"]

log = structlog.get_logger("dentibot.telemetry")

DEFAULT_PORT = 8765          # Foxglove's default WebSocket port
_SLICE_S = 0.001             # longest stretch the publisher keeps the interpreter lock
_ORJSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY
#: the topics a row is sent on
_ROW_TOPICS = ("/tick", TF_TOPIC, SCENE_TOPIC)


class _Listener:
    """Server callbacks (called from the server's own thread): only flags for the publisher."""

    def __init__(self, live: LiveView) -> None:
        self._live = live

    def on_subscribe(self, client: Any, channel: Any) -> None:
        if channel.topic == "/run":
            self._live._resend_run = True
            self._live._wake.set()

    def on_unsubscribe(self, client: Any, channel: Any) -> None:
        """Nothing to do: the channel stops being encoded when no viewer is left."""


class LiveView:
    """Serve a run live over the Foxglove WebSocket protocol (see the module docstring).

    Parameters (defaults in brackets):

    - ``metadata``: the run's ``/run`` message, as given to the recorder (pass the recorder's
      ``metadata`` to share its ``start_wall_ns``, so that live and recorded log times agree);
      ``dentibot_version``, ``start_wall_ns`` and ``start_time`` are filled in when absent.
    - ``host`` ["127.0.0.1"], ``port`` [8765; 0 for a free port].
    - ``view`` [True]: the 3D channels, as for the recorder (a
      :class:`~dentibot.telemetry.foxglove.FoxgloveView`, True, or False/None).
    - ``name`` ["DentiBot"]: the server name viewers show.
    - ``max_queue`` [2000]: items waiting for the publisher before the oldest are dropped.
    - ``poll_s`` [0.01]: the publisher's sleep when the queue is empty.

    Raises TelemetryError if the server cannot listen (port taken...), ConfigError on bad
    parameters. Counters: ``rows_queued``, ``items_dropped``, ``messages_sent``,
    ``rows_rejected`` (not serialisable), ``view_errors``.
    """

    def __init__(self, metadata: dict[str, Any] | None = None, *, host: str = "127.0.0.1",
                 port: int = DEFAULT_PORT, view: FoxgloveView | bool | None = True,
                 name: str = "DentiBot", max_queue: int = 2000, poll_s: float = 0.01) -> None:
        if not (isinstance(port, int) and not isinstance(port, bool) and 0 <= port <= 65535):
            raise ConfigError("live.port", port, "an integer 0..65535 (0: a free port)")
        if not (isinstance(max_queue, int) and max_queue > 0):
            raise ConfigError("live.max_queue", max_queue, "an integer > 0")
        if not (isinstance(poll_s, (int, float)) and poll_s > 0):
            raise ConfigError("live.poll_s", poll_s, "> 0 s")
        meta = dict(metadata or {})
        meta.setdefault("dentibot_version", _dentibot_version())
        _start_fields(meta)
        view = as_view(view, "live.view")
        try:
            self._run_json = orjson.dumps(_without_none(meta), default=_json_default,
                                          option=_ORJSON_OPTIONS)
        except TypeError as exc:
            raise ConfigError("metadata", meta, "JSON-serialisable values", str(exc)) from exc
        self.metadata = meta
        self.start_wall_ns: int = meta["start_wall_ns"]
        self.view: FoxgloveView | None = view
        self.host = host
        self.poll_s = float(poll_s)

        self.rows_queued = 0
        self.items_dropped = 0
        self.messages_sent = 0
        self.rows_rejected = 0
        self.view_errors = 0
        self.end: dict[str, Any] | None = None
        self._queue: collections.deque[tuple[str, Any]] = collections.deque(maxlen=max_queue)
        self._max_queue = max_queue
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._closed = False
        self._error: BaseException | None = None
        self._resend_run = False
        self._last_t = 0.0
        self._last_tick = 0
        self._last_log_ns = self.start_wall_ns
        self._last_scene_t: float | None = None

        self._context = foxglove.Context()
        schemas = {topic: json_schema(topic) for topic in TOPICS}
        if view is not None:
            schemas.update(FOXGLOVE_TOPICS)
        self._channels = {topic: foxglove.Channel(topic, schema=schema, context=self._context)
                          for topic, schema in schemas.items()}
        try:
            self._server = foxglove.start_server(
                name=name, host=host, port=port, context=self._context,
                server_listener=_Listener(self))
        except Exception as exc:  # noqa: BLE001 - the SDK's error types are not public
            for channel in self._channels.values():
                channel.close()
            raise TelemetryError(f"ws://{host}:{port}", f"cannot serve the live view: {exc}; "
                                 "choose another port (0: any free one)") from exc
        self.port: int = self._server.port
        self._log("/run", self._run_json, self.start_wall_ns)
        self._thread = threading.Thread(target=self._publish, name=f"live-view:{self.port}",
                                        daemon=True)
        self._thread.start()
        log.info("telemetry.live", url=self.url)

    @property
    def url(self) -> str:
        """Where a viewer connects: ``ws://host:port``."""
        return f"ws://{self.host}:{self.port}"

    @property
    def error(self) -> BaseException | None:
        """What stopped the publisher, or None."""
        return self._error

    @property
    def queue_depth(self) -> int:
        """Items waiting for the publisher now."""
        return len(self._queue)

    @property
    def closed(self) -> bool:
        return self._closed

    # -- caller side (the control task) -------------------------------------------------------

    def _put(self, item: tuple[str, Any]) -> None:
        q = self._queue
        if len(q) == self._max_queue:          # the deque drops the oldest: count it
            self.items_dropped += 1
        q.append(item)

    def record(self, row: dict[str, Any]) -> None:
        """Queue one tick row (the row is encoded later: do not mutate it). Returns at once;
        after :meth:`close`, or if the publisher stopped, the row is only counted as dropped;
        when no viewer watches the rows' topics, only counted as queued (nothing of it would
        be sent, and a lock-step run hands rows over faster than the publisher takes them)."""
        if self._closed or self._error is not None:
            self.items_dropped += 1
            return
        if self._watched():
            self._put(("tick", row))
        self.rows_queued += 1
        t = row.get("t")
        if isinstance(t, (int, float)):
            self._last_t = t
        tick = row.get("tick")
        if isinstance(tick, int):
            self._last_tick = tick

    def _watched(self) -> bool:
        """Whether a viewer subscribes to a topic rows are sent on."""
        channels = self._channels
        return any(channels[t].has_sinks() for t in _ROW_TOPICS if t in channels)

    def record_block(self, block: TickBlock) -> None:
        """A block of rows (:class:`~dentibot.telemetry.blocks.TickBlock`): :meth:`record` of
        each, looking once whether a viewer watches them."""
        n = len(block)
        if self._closed or self._error is not None:
            self.items_dropped += n
            return
        if not n:
            return
        if self._watched():
            for row in block.rows():
                self._put(("tick", row))
        self.rows_queued += n
        self._last_t = (block.k0 + n - 1) * block.ts
        self._last_tick = block.k0 + n - 1

    def event(self, kind: str, detail: str = "", *, t: float | None = None,
              tick: int | None = None) -> None:
        """Queue an ``/events`` message; ``t``/``tick`` default to the last row's."""
        if self._closed or self._error is not None:
            self.items_dropped += 1
            return
        self._put(("event", event_message(kind, detail, t, tick, self._last_t,
                                          self._last_tick)))

    def close(self, status: str = "ok", reason: str = "",
              duration_s: float | None = None) -> dict[str, Any] | None:
        """Send ``/run/end`` {status, reason, duration_s (default: the last row's t)}, let
        the publisher finish the queue, stop the server. Idempotent; returns the end record."""
        if self._closed:
            return self.end
        if status not in END_STATUSES:
            raise ConfigError("run.status", status, f"one of {list(END_STATUSES)}")
        self.end = {"status": status, "reason": reason,
                    "duration_s": float(self._last_t) if duration_s is None else duration_s}
        self._put(("end", self.end))
        self._closed = True
        self._stop.set()
        self._wake.set()
        self._thread.join()
        if self._channels["/run/end"].has_sinks():
            time.sleep(0.05)                   # let the server's sender write the end out
        self._server.stop()
        for channel in self._channels.values():
            channel.close()
        log.info("telemetry.live_closed", url=self.url, status=status,
                 rows_queued=self.rows_queued, items_dropped=self.items_dropped,
                 messages_sent=self.messages_sent)
        return self.end

    def __enter__(self) -> LiveView:  # noqa: PYI034
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close("ok")
        else:
            self.close("aborted", f"{exc_type.__name__}: {exc}")

    # -- publisher thread ---------------------------------------------------------------------

    def _publish(self) -> None:
        try:
            while True:
                stopping = self._stop.is_set()     # read before draining: nothing follows
                if self._resend_run:
                    self._resend_run = False
                    self._log("/run", self._run_json, self.start_wall_ns)
                self._drain()
                if stopping:
                    break
                self._wake.wait(self.poll_s)
                self._wake.clear()
        except BaseException as exc:  # noqa: BLE001 - a live view never stops the run
            self._error = exc
            log.error("telemetry.live_failed", url=self.url, error=repr(exc))

    def _drain(self) -> None:
        q = self._queue
        clock = time.monotonic
        slice_end = clock() + _SLICE_S
        while q:
            try:
                kind, payload = q.popleft()
            except IndexError:                     # emptied by a concurrent drop
                break
            if kind == "tick":
                self._send_tick(payload)
            elif kind == "event":
                self._send("/events", payload, payload["t"])
            else:
                self._send("/run/end", payload, self._last_t)
            if clock() >= slice_end:
                time.sleep(0)                      # hand the interpreter lock back
                slice_end = clock() + _SLICE_S

    def _log(self, topic: str, data: bytes, log_ns: int) -> None:
        self._channels[topic].log(data, log_time=log_ns)
        self.messages_sent += 1

    def _encode(self, obj: Any) -> bytes | None:
        try:
            data = orjson.dumps(_without_none(obj), default=_json_default,
                                option=_ORJSON_OPTIONS)
        except TypeError:
            self.rows_rejected += 1
            return None
        if _nonfinite(obj):                        # as the recorder: leave NaN fields out
            data = orjson.dumps(_without_none(_finite(obj)), default=_json_default,
                                option=_ORJSON_OPTIONS)
        return data

    def _send(self, topic: str, obj: dict[str, Any], t: Any) -> None:
        log_ns = _log_time_ns(self.start_wall_ns, t, self._last_log_ns)
        self._last_log_ns = log_ns
        if self._channels[topic].has_sinks():
            data = self._encode(obj)
            if data is not None:
                self._log(topic, data, log_ns)

    def _send_tick(self, row: Any) -> None:
        if not isinstance(row, dict):
            self.rows_rejected += 1
            return
        t = row.get("t")
        self._send("/tick", row, t)
        view = self.view
        if view is None:
            return
        log_ns = self._last_log_ns
        try:
            if self._channels[TF_TOPIC].has_sinks():
                tf = view.transforms_json(row, log_ns)
                if tf is not None:
                    self._log(TF_TOPIC, tf, log_ns)
            if view.scene_due(t, self._last_scene_t):
                self._last_scene_t = float(t)
                if self._channels[SCENE_TOPIC].has_sinks():
                    self._log(SCENE_TOPIC, orjson.dumps(view.scene(row, log_ns)), log_ns)
        except Exception as exc:  # noqa: BLE001 - a drawing problem costs the drawing only
            self.view_errors += 1
            if self.view_errors <= 5:
                log.warning("telemetry.live_view_failed", tick=row.get("tick"),
                            error=repr(exc), view_errors=self.view_errors)
