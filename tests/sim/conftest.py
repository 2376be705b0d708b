"""Fixtures of the simulator tests (their helpers: world_drive)."""

from __future__ import annotations

import pytest

from dentibot.sim import World, WorldConfig


@pytest.fixture
def world() -> World:
    return World(WorldConfig(seed=1))
