"""A protocol's ``control.cpus``: the CPUs its control process is kept to in real time. It
reaches the runtime's configuration, and a CPU the process may not use is refused before
anything starts, naming the key, the value and the CPUs there are."""

from __future__ import annotations

import os

import pytest

from dentibot.app.runner import runtime_config
from dentibot.cli import main
from dentibot.protocol.loader import ProtocolFileError, parse_protocol

CPUS = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
pytestmark = pytest.mark.skipif(not CPUS, reason="no CPU affinity on this system")

BASE = """\
name: t
seed: 1
steps:
  - drill: {strategy: automated, tau_d_mnm: 40, rounds: [{duration_s: 1}]}
"""


def test_the_cpus_reach_the_runtime_and_none_by_default():
    assert runtime_config(parse_protocol(BASE)).cpus is None
    p = parse_protocol(BASE + f"control: {{cpus: [{CPUS[-1]}]}}\n")
    assert runtime_config(p).cpus == (CPUS[-1],)


def test_an_empty_list_is_refused_by_the_schema():
    with pytest.raises(ProtocolFileError, match=r"control\.cpus"):
        parse_protocol(BASE + "control: {cpus: []}\n")


def test_a_cpu_the_process_may_not_use_starts_nothing(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    missing = max(CPUS) + 1
    bad.write_text(BASE + f"control: {{cpus: [{missing}]}}\n")
    out = tmp_path / "never.mcap"
    assert main(["run", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "control.cpus" in err and f"[{missing}]" in err and str(CPUS) in err, err
    assert not out.exists()
