"""`dentibot run` as a user runs it: bad input starts nothing; Ctrl-C stops safely and still
writes the recording and the summary."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dentibot.cli import main
from dentibot.telemetry.reader import MessageStream, read_recording
from dentibot.telemetry.schema import TelemetryError

ROOT = Path(__file__).resolve().parents[2]


def test_a_broken_protocol_is_refused_before_anything_starts(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: t\nsteps:\n  - drill: {tau_d_mnm: 500, rmp: 60}\n")
    out = tmp_path / "never.mcap"
    assert main(["run", str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{bad}:3: steps.0.drill.tau_d_mnm: value 500 is out of range: must be <= 200" in err
    assert "steps.0.drill.rmp: unknown key" in err
    assert not out.exists()


LONG_DRILL = """\
name: long-drill
seed: 3
steps:
  - calibrate_load: {}
  - align: {duration_s: 0.2, fz_n: 1.0}
  - drill: {strategy: automated, tau_d_mnm: 40, rounds: [{duration_s: 400}]}
"""


def _drilling(path) -> bool:
    """Whether the recording at ``path``, still being written, holds a drilling tick: read
    from the start up to the first one (the file grows faster than a whole read)."""
    try:
        return any(topic == "/tick" and obj["state"].startswith("treating.drilling")
                   for topic, obj in MessageStream(path))
    except TelemetryError:                    # not there yet
        return False


@pytest.mark.timeout(120)
@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)],
                         ids=["SIGINT", "SIGTERM"])
def test_a_signal_stops_safely_and_keeps_the_recording(tmp_path, sig, code):
    rec = tmp_path / "run.mcap"
    protocol = tmp_path / "long-drill.yaml"
    protocol.write_text(LONG_DRILL)
    proc = subprocess.Popen(
        [sys.executable, "-m", "dentibot.cli", "run", str(protocol), "--out", str(rec),
         "--quiet", "--json"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    # press Ctrl-C as soon as the recording (readable as written) holds a drilling tick: the
    # drilling then has about a minute of simulated time to go, seconds of wall time even at
    # the compiled ticks' pace, so the file is in the canal whatever the machine's load
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None and not _drilling(rec):
        time.sleep(0.02)
    assert proc.poll() is None, "the run ended before the signal"
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == code, stderr[-2000:]
    summary = json.loads(stdout)
    assert summary["status"] == "aborted" and summary["recording"] == str(rec)
    r = read_recording(rec)
    assert r.complete and r.status == "aborted"
    assert any(row["state"].startswith("treating") for row in r.rows)
    assert max(row["true_depth_mm"] for row in r.rows) > 2.0     # the file was in the canal
    last = r.rows[-1]
    # the file was withdrawn from the canal and stopped, the arm came to rest
    assert last["state"] == "idle" and last["true_depth_mm"] < 0.0
    assert abs(last["motor_rpm"]) < 5.0
    assert max(abs(x) for x in last["qdot_cmd_deg_s"]) == 0.0
    ticks = [row["tick"] for row in r.rows]
    assert ticks == list(range(len(ticks)))
    # once withdrawing, never back to drilling (the treatment ends with the safe stop)
    states = [row["state"] for row in r.rows]
    first_out = states.index("treating.retracting", max(i for i, st in enumerate(states)
                                                         if st.startswith("treating.drilling")))
    assert not any(st.startswith("treating.drilling") for st in states[first_out:])
