"""DentiBot from Python: scripts and notebooks.

- :func:`run_protocol`: a protocol run, as ``dentibot run`` does it (built-in simulator in
  lock-step time, or devices in real time), with its recording and summary;
- :func:`run_experiment`: a thesis experiment, the result ``dentibot experiment NAME --json``
  prints, as a dict;
- :func:`open_recording`: a recording as typed Arrow tables (``.to_pandas()`` with the
  ``dentibot[notebook]`` extra);
- :func:`configure_logging`: DentiBot's log lines, on stderr.

The functions are synchronous and work in a plain script as well as inside a running event
loop (Jupyter): there the work runs in a worker thread with its own event loop while the
caller waits. The ``*_async`` variants are coroutines for code that prefers ``await``.

Logging: unless structlog was configured (by :func:`configure_logging` or by the user), the
first call here configures warnings and errors only, on stderr; nothing goes to stdout.

Interrupting a call (Ctrl-C, the notebook's interrupt) stops a procedure safely (file stopped
and withdrawn, arm stopped, recording finished), then raises KeyboardInterrupt.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import threading
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from dentibot.logs import configure_default, configure_logging

if TYPE_CHECKING:
    from dentibot.app.runner import RunResult
    from dentibot.io.devices import DevicesConfig
    from dentibot.protocol.schema import Protocol
    from dentibot.telemetry.reader import RecordingTables

__all__ = ["RecordingTables", "RunResult", "configure_logging", "open_recording",
           "run_experiment", "run_experiment_async", "run_protocol", "run_protocol_async"]

T = TypeVar("T")



# ---------------------------------------------------------------------------- logging
def _default_logging() -> None:
    configure_default()


# ---------------------------------------------------------------------------- event loops
def _run(coro: Coroutine[Any, Any, T]) -> T:
    """``asyncio.run(coro)``; inside a running event loop, in a worker thread with its own."""
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return asyncio.run(coro)
    return _run_in_thread(coro)


def _run_in_thread(coro: Coroutine[Any, Any, T]) -> T:
    started = threading.Event()
    box: dict[str, Any] = {}

    async def main() -> T:
        box["loop"], box["task"] = asyncio.get_running_loop(), asyncio.current_task()
        started.set()
        return await coro

    def target() -> None:
        try:
            box["result"] = asyncio.run(main())
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            box["error"] = exc
        finally:
            started.set()

    thread = threading.Thread(target=target, name="dentibot-api", daemon=True)
    thread.start()
    try:
        while thread.is_alive():
            thread.join(0.1)
    except KeyboardInterrupt:
        # the notebook's interrupt: cancel the run (its safe stop runs), then re-raise
        started.wait()
        if "task" in box:
            try:
                box["loop"].call_soon_threadsafe(box["task"].cancel)
            except RuntimeError:             # the loop has just finished
                pass
        thread.join()
        raise
    if "error" in box:
        raise box["error"]
    return box["result"]


# ---------------------------------------------------------------------------- protocols
async def run_protocol_async(protocol: str | os.PathLike[str] | Protocol, *,
                             devices: str | os.PathLike[str] | DevicesConfig | None = None,
                             out: str | os.PathLike[str] | None = None, record: bool = True,
                             overwrite: bool = False, live: int | None = None,
                             progress: Callable[[dict], None] | None = None) -> RunResult:
    """Coroutine of :func:`run_protocol`."""
    from dentibot.app.runner import ProtocolRunner
    from dentibot.io.devices import DevicesConfig, load_devices_config
    from dentibot.protocol.loader import load_protocol
    from dentibot.protocol.schema import Protocol

    _default_logging()
    if not isinstance(protocol, Protocol):
        protocol = load_protocol(protocol)
    if devices is not None and not isinstance(devices, DevicesConfig):
        devices = load_devices_config(devices)
    runner = ProtocolRunner(protocol, recording=out, no_record=not record, devices=devices,
                            overwrite=overwrite, live=live, progress=progress)
    return await runner.run()


def run_protocol(protocol: str | os.PathLike[str] | Protocol, *,
                 devices: str | os.PathLike[str] | DevicesConfig | None = None,
                 out: str | os.PathLike[str] | None = None, record: bool = True,
                 overwrite: bool = False, live: int | None = None,
                 progress: Callable[[dict], None] | None = None) -> RunResult:
    """Run a protocol end to end, as ``dentibot run`` does; returns its
    :class:`~dentibot.app.runner.RunResult` (``summary``, ``recording``, ``exit_code``).

    ``protocol``: a protocol file (YAML) or a :class:`~dentibot.protocol.schema.Protocol`
    (e.g. from :func:`~dentibot.protocol.loader.parse_protocol`). ``devices``: a device
    configuration file or :class:`~dentibot.io.devices.DevicesConfig` (real time); None: the
    built-in simulator (lock-step time). ``out``: the recording (MCAP); default the
    protocol's ``recording.path`` or ``runs/<name>-<seed>.mcap``; an existing file is
    replaced only with ``overwrite``. ``record=False``: no recording. ``live``: serve the run
    to Foxglove on this port of 127.0.0.1 (0: a free port). ``progress(figures)``: called every
    250 ticks, in the thread that runs the procedure, with the live key figures (step, state,
    t, depth_mm, file_torque_mnm...).

    Inside a running event loop (Jupyter) the run goes to a worker thread with its own loop.
    Raises :class:`~dentibot.errors.DentibotError` subclasses on bad input (nothing started).
    """
    return _run(run_protocol_async(protocol, devices=devices, out=out, record=record,
                                   overwrite=overwrite, live=live, progress=progress))


# ---------------------------------------------------------------------------- experiments
async def run_experiment_async(name: str, *, progress: Callable[[str], None] | None = None,
                               **options: Any) -> dict[str, Any]:
    """Coroutine of :func:`run_experiment`."""
    from dentibot.experiments.results import options_of, run_experiment

    _default_logging()
    options = dict(options)
    options.pop("json", None)                # the result is always the JSON one
    if options.pop("quiet", False):
        progress = None
    options_of(name)                         # an unknown experiment: before anything starts
    loop = asyncio.get_running_loop()
    cancel = threading.Event()
    done: asyncio.Future = loop.create_future()

    def line(text: str) -> None:             # from the experiment's thread to this loop's
        loop.call_soon_threadsafe(progress, text)

    def settle(result: Any = None, error: BaseException | None = None) -> None:
        if not done.done():
            if error is None:
                done.set_result(result)
            else:
                done.set_exception(error)

    def work() -> None:
        try:
            result = run_experiment(name, progress=None if progress is None else line,
                                    cancel=cancel, **options)
        except BaseException as exc:  # noqa: BLE001 - handed to the awaiting task
            loop.call_soon_threadsafe(settle, None, exc)
        else:
            loop.call_soon_threadsafe(settle, result)

    threading.Thread(target=work, name="dentibot-experiment", daemon=True).start()
    try:
        result = await asyncio.shield(done)
    except asyncio.CancelledError:
        # the notebook's interrupt or Ctrl-C: the run in progress stops safely, then this ends
        cancel.set()
        with contextlib.suppress(BaseException):
            await done
        raise
    return result.to_dict()


def run_experiment(name: str, *, progress: Callable[[str], None] | None = None,
                   **options: Any) -> dict[str, Any]:
    """Run a thesis experiment (``"alignment"`` or ``"preclinical"``) on the built-in
    simulator; returns what ``dentibot experiment NAME --json`` prints.

    ``options`` are the command's long options, ``_`` for ``-``: ``config="A"``,
    ``speeds=(3, 4)``, ``seeds=8``, ``workers=2``, ``no_figures=True``, ``out="figs"``,
    ``strategy="all"``, ``rounds=(300, 200)``... (``dentibot experiment NAME --help``).
    ``progress(line)`` gets each progress line (one per finished run), in the thread of the
    event loop that awaits the run. The experiment runs in this process, in a worker thread
    (its runs in ``workers`` local processes when more than one), so it works inside a running
    event loop too. Whether the thesis's claims were shown is in ``result["checks"]``. Raises
    :class:`~dentibot.errors.ConfigError` (a ValueError) for an unknown experiment or option,
    or a bad value, before anything runs.
    """
    return _run(run_experiment_async(name, progress=progress, **options))


# ---------------------------------------------------------------------------- recordings
def open_recording(path: str | os.PathLike[str]) -> RecordingTables:
    """A recording as typed Arrow tables: ``.ticks`` (one column per ``/tick`` field),
    ``.events``, ``.metadata`` (the ``/run`` record), ``.end``, ``.complete``,
    ``.to_pandas()``. See :func:`~dentibot.telemetry.reader.read_table`."""
    from dentibot.telemetry.reader import read_table

    _default_logging()
    return read_table(Path(path))


def __getattr__(name: str) -> Any:
    """``RunResult`` and ``RecordingTables``, imported when first asked for (so that importing
    this module stays cheap)."""
    if name == "RunResult":
        from dentibot.app.runner import RunResult

        return RunResult
    if name == "RecordingTables":
        from dentibot.telemetry.reader import RecordingTables

        return RecordingTables
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
