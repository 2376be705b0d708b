"""Every shipped protocol runs to a good end on the built-in simulator (the main job,
protocols/root-canal.yaml, runs through the README's command in tests/test_readme.py)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
import structlog

from dentibot.protocol.loader import load_protocol
from dentibot.app.runner import ProtocolRunner

DIR = Path(__file__).parents[2] / "protocols"
SHIPPED = sorted(p for p in DIR.glob("*.yaml") if p.name != "root-canal.yaml")


@pytest.fixture(autouse=True)
def _quiet():
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))


@pytest.mark.timeout(300)
@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
async def test_shipped_protocol_succeeds(path):
    protocol = load_protocol(path)
    res = await ProtocolRunner(protocol, no_record=True).run()
    s = res.summary
    assert s.status == "ok", s.reason
    assert s.fractures == 0
    assert s.duration_s >= sum(getattr(st.spec, "duration_s", 0.0) for st in protocol.steps)
    if any(st.kind == "drill" for st in protocol.steps):
        assert s.completeness > 0.8 and s.peak_file_torque_mNm < 62.0
    if protocol.patient.motion == "square":   # thesis experiment 1: forces stay small
        assert s.peak_force_N < 5.0
