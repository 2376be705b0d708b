"""Where DentiBot's log lines go: stderr, through structlog, for the command line and the
Python API alike.

:func:`configure_logging` sets the level and the format (console or JSON lines) and sends the
standard-library loggers of the libraries underneath (pymodbus, python-can, asyncio ...)
through the same structlog pipeline, so that one level and one format cover every line.
Nothing is written to stdout: stdout belongs to results (``--json``, tables, notebooks).
"""

from __future__ import annotations

import logging
import sys
from typing import Any

import structlog

__all__ = ["LOG_LEVELS", "configure_logging", "configure_default"]

#: The levels a user may choose, least severe first.
LOG_LEVELS = ("debug", "info", "warning", "error", "critical")


class _Stderr:
    """Whatever ``sys.stderr`` is when a line is logged (not when logging was configured):
    pytest's capture, a notebook's redirected stream."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


class _ToStructlog(logging.Handler):
    """A standard-library record re-emitted through structlog (logger name, level, message,
    and the exception text when there is one)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            kw: dict[str, Any] = {"logger": record.name}
            if record.exc_info:
                kw["exc_info"] = record.exc_info
            structlog.get_logger(record.name).log(record.levelno, record.getMessage(), **kw)
        except Exception:  # noqa: BLE001 - logging must never raise into the caller
            self.handleError(record)


_SETTINGS: tuple[str, bool] | None = None


def configure_logging(level: str = "warning", *, json: bool = False) -> None:
    """Log lines of ``level`` and above to stderr with a timestamp (``json``: one JSON object
    per line); the libraries' standard-library logging follows the same level and format.
    Raises ValueError naming the allowed levels."""
    global _SETTINGS
    if level not in LOG_LEVELS:
        raise ValueError(f"log level {level!r}: one of {', '.join(LOG_LEVELS)}")
    _SETTINGS = (level, json)
    number = getattr(logging, level.upper())
    processors: list[Any] = [structlog.processors.add_log_level,
                             structlog.processors.TimeStamper("iso")]
    if json:
        processors += [structlog.processors.format_exc_info, structlog.processors.JSONRenderer()]
    else:
        processors.append(structlog.dev.ConsoleRenderer(colors=False))
    structlog.configure(processors=processors,
                        wrapper_class=structlog.make_filtering_bound_logger(number),
                        logger_factory=structlog.PrintLoggerFactory(_Stderr()),
                        cache_logger_on_first_use=False)
    root = logging.getLogger()
    for h in [h for h in root.handlers if isinstance(h, _ToStructlog)]:
        root.removeHandler(h)
    root.addHandler(_ToStructlog())
    root.setLevel(number)
    # pymodbus sets up its own logger ("pymodbus.logging"): no handler of its own, so that its
    # lines reach the root handler above, once
    pm = logging.getLogger("pymodbus")
    for h in list(pm.handlers):
        pm.removeHandler(h)
    pm.propagate = True
    pm.setLevel(logging.NOTSET)


def logging_settings() -> tuple[str, bool] | None:
    """``(level, json)`` of the last :func:`configure_logging`, or None: what a helper process
    (the recorder's) needs to log the same way."""
    return _SETTINGS


def configure_default() -> None:
    """Warnings and errors only, on stderr, unless logging was configured already (by
    :func:`configure_logging` or by the user's own structlog set-up)."""
    if not structlog.is_configured():
        configure_logging("warning")
