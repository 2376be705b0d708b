"""The simulator's compiled feeding ticks give the control task's outcome, number for
number: trial procedures run with them and without them (reversals, patient motion, faults,
a fracture in a compiled world step)."""

from __future__ import annotations

import asyncio

import pytest

import dentibot.app.drill_loop as dl
from dentibot.app import drill_kernels as dk
from dentibot.trials import runner as rn
from dentibot.trials.spec import parse_trial

#: Acrylic canals, the patient swaying: regulated feed at a low tau_d (reversals), no
#: regulation (the torque limit reverses), the PD alone.
MIXED = """name: mixed
seed: 5
n: 1
rounds_s: [20]
population:
  patient:
    motion: {dist: choice, values: [head]}
  anatomy:
    material: {dist: choice, values: [acrylic]}
arms:
  - {name: low, tau_d_mnm: 15}
  - {name: none, strategy: none}
  - {name: fr, strategy: feedrate, tau_d_mnm: 30}
"""
#: Severe curves, no regulation and the limit at the file's strength: files break.
BREAKING = """name: breaking
seed: 9
n: 3
rounds_s: [15]
population:
  anatomy:
    material: {dist: choice, values: [acrylic]}
    curvature_class: {dist: choice, values: [severe]}
arms:
  - {name: none, strategy: none, torque_limit_share: 1.0}
"""


def _run(spec_text: str, monkeypatch, compiled: bool) -> tuple[list[dict], dict]:
    """Every procedure's row (wall time aside), and what the compiled loop did."""
    seen = {"ticks": 0, "codes": []}
    call, ticks = dl.DrillLoop.__call__, dk.drill_ticks

    async def counted(self, rt):
        n = await call(self, rt)
        seen["ticks"] += n
        return n

    def kernel(*args):
        out = ticks(*args)
        seen["codes"].append(out[2])
        return out

    monkeypatch.setattr(dl.DrillLoop, "__call__", counted)
    monkeypatch.setattr(dl.dk, "drill_ticks", kernel)
    spec = parse_trial(spec_text)
    rows = [rn.run_procedure(p, compiled_ticks=compiled) for a in range(len(spec.arms))
            for p in rn.procedures_of(spec, a, range(spec.n))]
    monkeypatch.undo()
    if not compiled:
        assert seen["ticks"] == 0
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in rows], seen


def test_compiled_feeding_ticks_give_the_same_procedures(monkeypatch):
    fast, seen = _run(MIXED, monkeypatch, compiled=True)
    slow, _ = _run(MIXED, monkeypatch, compiled=False)
    assert fast == slow
    ticks = sum(r["simulated_s"] for r in fast) / 0.002
    assert seen["ticks"] > 0.5 * ticks                 # most of the run was compiled
    assert sum(r["reversals"] for r in fast) >= 5      # stopped and resumed around events
    assert {r["status"] for r in fast} == {"ok", "fault"}


@pytest.mark.slow
def test_a_file_that_breaks_in_a_compiled_step(monkeypatch):
    fast, seen = _run(BREAKING, monkeypatch, compiled=True)
    slow, _ = _run(BREAKING, monkeypatch, compiled=False)
    assert fast == slow
    assert all(r["status"] == "fracture" for r in fast)
    assert any(c != 0 for c in seen["codes"])          # one broke inside the compiled loop


#: The main job shortened, with reversals (a low tau_d in acrylic).
#: on the thesis's world, whose file reverses within the round (the compiled reversals are
#: part of what is compared); the bench-fitted world's compiled ticks are held to the
#: tick-by-tick ones by the lateral schedule's tests
RECORDED = """name: recorded
seed: 4
world: thesis
file: {size: 25, taper: 0.06, length_mm: 25}
phantom: {working_length_mm: 16.0, orifice_gap_mm: 2.0, material: acrylic}
patient: {motion: static}
steps:
  - calibrate_load: {}
  - align: {duration_s: 0.2, fz_n: 1.0}
  - drill: {strategy: automated, tau_d_mnm: 20, rpm: 60, rounds: [{duration_s: 6}]}
"""


def _recorded(tmp_path, compiled: bool, monkeypatch) -> tuple:
    """A recorded run of :data:`RECORDED`: its summary, progress, the recording's messages
    (each /tick without its compute time), how many ticks each block of rows held, the
    compiled calls' largest number of ticks with the blocks handed over as it runs, and the
    most ticks the recorder had at risk."""
    import orjson
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from dentibot.app.runner import ProtocolRunner
    from dentibot.protocol.loader import load_protocol
    from dentibot.telemetry.cdr import TICK_CODEC

    in_blocks, relayed = [], [0]
    ticks = dk.drill_ticks

    def counted(n_max, *args):
        relay = args[17]
        if relay[0]:
            relayed[0] = max(relayed[0], n_max)
        return ticks(n_max, *args)
    monkeypatch.setattr(dk, "drill_ticks", counted)
    block = ProtocolRunner._block_read
    monkeypatch.setattr(ProtocolRunner, "_block_read",
                        lambda self, b, *rec: (in_blocks.append(len(b)), block(self, b, *rec)))
    progress: list[dict] = []
    spec = tmp_path / "recorded.yaml"
    spec.write_text(RECORDED)
    path = tmp_path / f"run-{compiled}.mcap"
    runner = ProtocolRunner(load_protocol(spec), recording=path, progress=progress.append,
                            compiled_ticks=compiled)
    result = asyncio.run(runner.run())
    at_risk = runner.recorder.at_risk_max
    messages = []                  # after /run, at their log time from the run's start
    ros2, start = DecoderFactory(), 0
    with open(path, "rb") as f:
        schemas = make_reader(f).get_summary().schemas
        for _, channel, message in make_reader(f).iter_messages():
            if channel.topic == "/tick":
                obj = TICK_CODEC.decode(message.data)
            elif channel.message_encoding == "cdr":          # /tf, by Foxglove's codec
                tf = ros2.decoder_for("cdr", schemas[channel.schema_id])(message.data)
                obj = [(t.header.frame_id, t.child_frame_id,
                        t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec - start,
                        *(getattr(t.transform.translation, a) for a in "xyz"),
                        *(getattr(t.transform.rotation, a) for a in "xyzw"))
                       for t in tf.transforms]
            else:
                obj = orjson.loads(message.data)
            if channel.topic == "/run":
                start = message.log_time
                continue
            if channel.topic == "/tick":
                obj.pop("compute_us")
            messages.append((channel.topic, message.log_time - start, _relative(obj, start)))
    return result.summary, progress, messages, in_blocks, relayed[0], at_risk


def _relative(obj, start_ns: int):
    """``obj`` with its Foxglove timestamps as ns from ``start_ns``."""
    if isinstance(obj, dict):
        return {k: v["sec"] * 1_000_000_000 + v["nsec"] - start_ns if k == "timestamp"
                else _relative(v, start_ns) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_relative(v, start_ns) for v in obj]
    return obj


@pytest.mark.parametrize("budget", [None, 50])
def test_a_recorded_run_hands_its_drilling_rows_over_in_blocks(tmp_path, monkeypatch, budget):
    """The CLI's run (recording, live summary, progress) with the drilling ticks compiled and
    their rows in blocks records what the tick-by-tick run records: every /tick row (its
    compute time aside), /tf, /scene and /events message, the same summary and progress.
    With the recorder's default budget (2,000 ticks) each call's rows leave after it, in
    blocks of up to 256 ticks; with a budget of 50 the calls send blocks of 25 as they run."""
    from dentibot.app import runner as runner_module
    from dentibot.control import kinematics_kernels as kk
    from dentibot.sim import canal_kernels as ck

    if budget is not None:
        opened = runner_module.open_recorder
        monkeypatch.setattr(runner_module, "open_recorder",
                            lambda *a, **kw: opened(*a, max_queue=budget, **kw))

    # the kernels the rows' numbers take, compiled at import for the types the runs pass
    kernels = (kk.tool_euler_deg, kk.euler_xyz_deg, ck.red_area)
    before = [list(k.signatures) for k in kernels]
    summary, progress, messages, blocks, relayed, at_risk = _recorded(tmp_path, True,
                                                                      monkeypatch)
    again, progress_again, messages_again, none, _, _ = _recorded(tmp_path, False, monkeypatch)
    assert [list(k.signatures) for k in kernels] == before
    assert not none and sum(blocks) > 2000          # most of the drilling went in blocks
    assert max(blocks) > 25
    if budget is None:
        assert relayed == 0 and 25 < at_risk <= 2000
    else:
        # calls of more ticks than half the recorder's budget (25), whose blocks reached
        # the recorder as they were computed: never more than its budget out of the file
        assert relayed > 25 and at_risk <= budget
    assert summary.reversals > 0 and summary == again
    assert progress == progress_again
    assert {"/tick", "/tf", "/scene", "/events"} <= {topic for topic, _, _ in messages}
    assert len(messages) == len(messages_again)
    for message, message_again in zip(messages, messages_again):
        assert message == message_again


def test_a_recorder_process_that_dies_while_the_compiled_ticks_drill_faults_the_run(tmp_path):
    """The recorder's process killed while the drilling ticks send it their blocks: the run
    stops the file and the arm and ends in a fault that names the recording, and what was
    flushed before stays readable."""
    import os
    import signal

    from dentibot.app.runner import ProtocolRunner
    from dentibot.protocol.loader import load_protocol
    from dentibot.telemetry.reader import read_recording

    spec = tmp_path / "recorded.yaml"
    spec.write_text(RECORDED)
    path = tmp_path / "killed.mcap"
    killed = []

    def progress(figures):
        if figures["step"].endswith(":drill") and figures["depth_mm"] > 1.0 and not killed:
            killed.append(figures["t"])
            os.kill(runner.recorder.pid, signal.SIGKILL)
    runner = ProtocolRunner(load_protocol(spec), recording=path, progress=progress)
    result = asyncio.run(runner.run())
    assert killed
    assert result.summary.status == "fault"
    assert "record" in result.summary.reason
    assert runner.world.handpiece.cmd_rpm == 0.0 and not runner.world.arm._vel_cmd.any()
    rec = read_recording(path)
    assert not rec.complete and rec.rows                  # cut short, readable up to then
