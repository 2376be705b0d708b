"""The procedure keeps its figures when its code is reorganised: a shortened main job (seeded,
lock-step) against the summary it produced before (``golden/``). A change of behaviour on
purpose regenerates the file and says why in its commit."""

from __future__ import annotations

import json
import math
from pathlib import Path

from dentibot.cli import main

GOLDEN = Path(__file__).resolve().parent / "golden"


def _same(old, new, path="") -> list[str]:
    if isinstance(old, dict) and isinstance(new, dict):
        return [d for k in sorted(set(old) | set(new))
                for d in _same(old.get(k), new.get(k), f"{path}.{k}")]
    if isinstance(old, list) and isinstance(new, list) and len(old) == len(new):
        return [d for i, (a, b) in enumerate(zip(old, new)) for d in _same(a, b, f"{path}[{i}]")]
    if isinstance(old, float) and isinstance(new, float):
        return [] if math.isclose(old, new, rel_tol=1e-9, abs_tol=1e-12) else [
            f"{path}: {old!r} -> {new!r}"]
    return [] if old == new else [f"{path}: {old!r} -> {new!r}"]


def test_the_short_main_job_reproduces_its_golden_summary(capsys):
    code = main(["run", str(GOLDEN / "short-root-canal.yaml"), "--json", "--no-record",
                 "--quiet"])
    assert code == 0
    new = json.loads(capsys.readouterr().out)
    old = json.loads((GOLDEN / "short-root-canal.summary.json").read_text())
    assert old["depth_reached_mm"] > 10.0 and old["completeness"] > 0.5   # it drilled
    diffs = _same(old, new)
    assert not diffs, diffs
