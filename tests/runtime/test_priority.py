"""The real-time loop's priority: raised where the system permits, restored after."""

from __future__ import annotations

import os

import pytest

from dentibot.runtime.clock import REALTIME_NICE, raised_priority, realtime_policy

pytestmark = pytest.mark.skipif(not hasattr(os, "getpriority"), reason="no priorities here")


def _may_raise() -> bool:
    """Whether this process may lower its nice value (CAP_SYS_NICE or RLIMIT_NICE)."""
    before = os.getpriority(os.PRIO_PROCESS, 0)
    try:
        os.setpriority(os.PRIO_PROCESS, 0, before - 1)
    except OSError:
        return False
    os.setpriority(os.PRIO_PROCESS, 0, before)
    return True


def test_raised_where_permitted_and_restored():
    before = os.getpriority(os.PRIO_PROCESS, 0)
    allowed = _may_raise()
    with raised_priority() as granted:
        inside = os.getpriority(os.PRIO_PROCESS, 0)
    assert os.getpriority(os.PRIO_PROCESS, 0) == before
    if allowed and before > REALTIME_NICE:
        assert granted and inside == REALTIME_NICE
    elif not allowed:
        assert not granted and inside == before


def test_an_unprivileged_thread_runs_as_it_is(monkeypatch):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "setpriority", refuse)
    before = os.getpriority(os.PRIO_PROCESS, 0)
    with raised_priority() as granted:
        assert os.getpriority(os.PRIO_PROCESS, 0) == before
    assert granted is (before <= REALTIME_NICE)


def test_lock_step_leaves_the_priority_alone():
    before = os.getpriority(os.PRIO_PROCESS, 0)
    with realtime_policy(False):
        assert os.getpriority(os.PRIO_PROCESS, 0) == before
