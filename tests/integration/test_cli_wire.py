"""Across processes: `dentibot sim serve` in one process, `dentibot run --devices` in another,
talking over loopback TCP/UDP (Meca500, Net F/T, Modbus) and socketcand (the EPOS4)."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.wire

ROOT = Path(__file__).resolve().parents[2]


def _free_ports(n: int, kind=socket.SOCK_STREAM) -> list[int]:
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, kind)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _wait_listening(port: int, deadline: float) -> None:
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise AssertionError(f"nothing listens on {port}")


@pytest.mark.timeout(200)
def test_protocol_runs_against_the_wire_simulators_in_another_process(tmp_path):
    meca, http, modbus, can = _free_ports(4)
    meca_mon = meca + 1
    (netft,) = _free_ports(1, socket.SOCK_DGRAM)
    serve = subprocess.Popen(
        [sys.executable, "-m", "dentibot.cli", "sim", "serve", "--meca-port", str(meca),
         "--netft-port", str(netft), "--netft-http-port", str(http), "--modbus-port",
         str(modbus), "--can-port", str(can), "--duration", "180"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        for port in (meca, http, modbus, can):
            _wait_listening(port, deadline)
        devices = tmp_path / "devices.yaml"
        devices.write_text(
            f"arm: {{host: 127.0.0.1, control_port: {meca}, monitor_port: {meca_mon}}}\n"
            f"ft: {{host: 127.0.0.1, port: {netft}, http_port: {http}, "
            "stale_after_ms: 100}\n"
            f"handpiece: {{interface: socketcand, host: 127.0.0.1, port: {can}, "
            "channel: vcan0, consumer_ms: 150}\n"
            f"aux: {{host: 127.0.0.1, port: {modbus}}}\n")
        protocol = tmp_path / "p.yaml"
        # a loaded CI machine delays loopback samples: looser freshness bounds than hardware,
        # the F/T driver's own (100 ms in the device file above) as loose as the protocol's;
        # the drive's heartbeat consumer (150 ms above, 30 by default) too, as either
        # process may stall past 30 ms there
        protocol.write_text(
            "name: wire\nlimits: {stale_periods: {arm: 50, ft: 50, motor: 50, aux: 200}}\n"
            "steps:\n  - calibrate_load: {}\n  - drag: {duration_s: 0.5}\n")
        # two runs in a row against the same simulators: the first parks the arm on its
        # way out, the second activates and homes it again without any resume
        for run in ("first", "second"):
            out = subprocess.run(
                [sys.executable, "-m", "dentibot.cli", "run", str(protocol), "--devices",
                 str(devices), "--json", "--quiet", "--out", str(tmp_path / f"{run}.mcap")],
                cwd=ROOT, capture_output=True, text=True, timeout=90, check=False)
            assert out.returncode == 0, run + out.stdout[-2000:] + out.stderr[-3000:]
            result = json.loads(out.stdout)
            assert result["status"] == "ok"
            assert [s["name"] for s in result["steps"]] == ["1:calibrate_load", "2:drag"]
            # the load identified over the wire is the simulated handpiece (rests at ~0 N)
            assert result["peak_force_N"] < 0.3
    finally:
        serve.terminate()
        serve.communicate(timeout=20)
