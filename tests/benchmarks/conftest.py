"""The benchmarks' instruments imported as the benchmark scripts import them (their folder on
``sys.path``), and forgotten after each test."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks"


@pytest.fixture
def bench_module(monkeypatch):
    """``bench_module(name)``: the module ``benchmarks/<name>.py``."""
    loaded: list[str] = []

    def load(name: str):
        monkeypatch.syspath_prepend(str(BENCH))
        loaded.append(name)
        return importlib.import_module(name)

    yield load
    for name in loaded:
        sys.modules.pop(name, None)
