"""Runtime tests: quiet logs (faults are asserted, not printed)."""

from __future__ import annotations

import logging

import pytest
import structlog


@pytest.fixture(autouse=True, scope="session")
def _quiet_logs():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))


@pytest.fixture(autouse=True)
async def _stop_procedures():
    from sim_runs import MADE

    yield
    while MADE:
        await MADE.pop().stop()
