"""One logging pipeline: DentiBot's structlog lines and the libraries' standard-library
logging (pymodbus above all) at one level, in one format, on stderr only."""

from __future__ import annotations

import json
import logging

import pytest
import structlog

from dentibot.logs import configure_logging


@pytest.fixture(autouse=True)
def _restore():
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)
    structlog.reset_defaults()


def test_pymodbus_lines_come_through_structlog_at_the_chosen_level(capsys):
    configure_logging("warning")
    logging.getLogger("pymodbus.logging").warning("received pdu without a request")
    logging.getLogger("pymodbus.logging").info("connected")        # below the level
    structlog.get_logger("dentibot.io").warning("aux.poll_failed", port=5020)
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.splitlines()
    assert len(lines) == 2
    assert "[warning" in lines[0] and "received pdu without a request" in lines[0]
    assert "[pymodbus.logging]" in lines[0]                   # the console names the logger
    assert "aux.poll_failed" in lines[1] and "port=5020" in lines[1]


def test_json_lines_for_every_source(capsys):
    configure_logging("info", json=True)
    logging.getLogger("pymodbus.logging").info("connected")
    structlog.get_logger().info("run.started", steps=4)
    records = [json.loads(line) for line in capsys.readouterr().err.splitlines()]
    assert [(r["event"], r["level"]) for r in records] == [("connected", "info"),
                                                           ("run.started", "info")]
    assert records[0]["logger"] == "pymodbus.logging" and records[1]["steps"] == 4


def test_configuring_twice_leaves_one_route(capsys):
    configure_logging("warning")
    configure_logging("warning")
    logging.getLogger("can").error("bus error")
    assert len(capsys.readouterr().err.splitlines()) == 1


def test_an_unknown_level_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="debug, info, warning, error, critical"):
        configure_logging("verbose")
