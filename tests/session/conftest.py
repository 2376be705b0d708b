"""Session tests: quiet logs; a controller on the built-in simulator in stepped lock-step
time (simulated time advances only when the test says, so that the terminal UI and the
simulation are driven separately and deterministically)."""

from __future__ import annotations

import logging

import pytest
import structlog

from dentibot.session.controller import SessionController, SessionOptions


@pytest.fixture(autouse=True)
def _quiet_logs():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))


@pytest.fixture
async def stepped(tmp_path):
    """A session on the built-in simulator, stepped clock, load not yet calibrated."""
    c = SessionController(SessionOptions(clock="stepped", record_dir=tmp_path))
    yield c
    if not c.closed:                 # a failed test must not leave the control task running
        await c.shutdown()
