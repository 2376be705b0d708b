"""Every shipped protocol runs to a good end on the built-in simulator (the main job,
protocols/root-canal.yaml, runs through the README's command in tests/test_readme.py).

The runs are independent and long (phantom D drills 500 simulated seconds): they run in two
worker processes at once, the longest first, and each test checks its own run's summary."""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import pytest
import structlog

from dentibot.app.runner import ProtocolRunner
from dentibot.protocol.loader import load_protocol

DIR = Path(__file__).parents[2] / "protocols"
SHIPPED = sorted(p for p in DIR.glob("*.yaml") if p.name != "root-canal.yaml")


def _planned_s(path: Path) -> float:
    """The protocol's planned seconds (what orders the runs: the longest first)."""
    steps = load_protocol(path).steps
    total = 0.0
    for st in steps:
        total += getattr(st.spec, "duration_s", 0.0) or 0.0
        total += sum(getattr(r, "duration_s", 0.0) for r in getattr(st.spec, "rounds", ()) or ())
    return total


def _run(path: str):
    """One shipped protocol, run as ``dentibot run --no-record`` runs it (in a worker)."""
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    return asyncio.run(ProtocolRunner(load_protocol(Path(path)), no_record=True).run()).summary


@pytest.fixture(scope="module")
def shipped_runs(worker_runs):
    return worker_runs({p.stem: (_run, str(p)) for p in sorted(SHIPPED, key=_planned_s,
                                                               reverse=True)})


@pytest.mark.timeout(300)
@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_protocol_succeeds(path, shipped_runs):
    protocol = load_protocol(path)
    s = shipped_runs[path.stem].result(timeout=280)
    assert s.status == "ok", s.reason
    assert s.fractures == 0
    assert s.duration_s >= sum(getattr(st.spec, "duration_s", 0.0) for st in protocol.steps)
    if any(st.kind == "drill" for st in protocol.steps):
        assert s.completeness > 0.8 and s.peak_file_torque_mNm < 62.0
    if protocol.patient.motion == "square":   # thesis experiment 1: forces stay small
        assert s.peak_force_N < 5.0
