"""Running trials: overrides reaching the world, a procedure the same in any batch, resuming
after an interruption, the command line, and Ray."""

from __future__ import annotations

import json
import subprocess
import sys

import pyarrow.parquet as pq
import pytest
import structlog

from dentibot.cli import main
from dentibot.errors import ConfigError
from dentibot.trials import runner as rn
from dentibot.trials.spec import parse_trial

TINY = """name: tiny
seed: 3
n: 2
batch_size: 1
rounds_s: [1]
arms: [{name: a, tau_d_mnm: 40}]
"""


@pytest.fixture
def logging_restored():
    """The command configures logging for the process: put it back afterwards."""
    saved = structlog.get_config()
    yield
    structlog.configure(**saved)


def _rows(table):
    """Rows without the wall time (the only field that may differ between runs)."""
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in table.to_pylist()]


def test_yaml_overrides_reach_the_simulated_world():
    spec = parse_trial(TINY + """population:
  anatomy:
    working_length_mm: {dist: fixed, value: 13.25}
    apical_diameter_mm: {dist: fixed, value: 0.1}
    canal_taper: {dist: fixed, value: 0.03}
    curvature_class: {dist: choice, values: [severe]}
    angle_severe_deg: {dist: fixed, value: 31}
    curve_radius_mm: {dist: fixed, value: 7.5}
    material: {dist: choice, values: [acrylic]}
  file:
    torsional_strength_mnm: {dist: fixed, value: 58.5}
    rated_strength_mnm: {dist: fixed, value: 60}
  patient:
    motion: {dist: choice, values: [head]}
    sway_mm: {dist: fixed, value: 0.5}
""")
    (proc,) = rn.procedures_of(spec, 0, [1])
    runner = rn.build_runner(proc)
    w = runner.world
    p = w.canal.p
    assert p.working_length_mm == 13.25
    assert (p.initial_apical_mm, p.initial_taper) == (0.1, 0.03)
    assert w.canal.R0[-1] == pytest.approx(0.05)          # the apical radius, from 0.1 mm
    assert (p.curve_angle_deg, p.curve_radius_mm) == (31.0, 7.5)
    assert p.cutting_energy_mj_mm3 == 3000.0              # acrylic's
    assert w.file.torsional_strength_mnm == 58.5          # the file breaks at its own strength
    assert runner.p.file.torsional_strength_mnm == 60.0   # the protocol states the rated one
    assert runner.p.limits.torque_limit_mnm == pytest.approx(54.0)   # 90 % of it
    # the sway: half the default amplitude, the same phases (the world's own stream)
    default = rn.build_runner(rn.procedures_of(parse_trial(
        TINY + "population: {patient: {motion: {dist: choice, values: [head]}}}\n"), 0,
        [1])[0]).world.motion
    assert w.motion.amp == pytest.approx(0.5 * default.amp)
    assert (w.motion.phase == default.phase).all()


def test_an_interrupted_trial_keeps_its_finished_batches_and_goes_on(tmp_path):
    spec = parse_trial(TINY)
    out = tmp_path / "t"
    seen = []

    def interrupt(batch):
        seen.append(batch.filename)
        raise KeyboardInterrupt      # Ctrl-C right after the first batch is on disk

    with pytest.raises(KeyboardInterrupt):
        rn.run_trial(spec, out, advance=interrupt)
    (first,) = seen
    path = out / "batches" / first
    before = (path.stat().st_mtime_ns, path.read_bytes())
    assert sorted(p.name for p in (out / "batches").iterdir()) == [first]
    assert not (out / rn.PROCEDURES).exists()

    run = rn.run_trial(spec, out)
    assert (run.ran, run.kept) == (1, 1)
    assert (path.stat().st_mtime_ns, path.read_bytes()) == before     # kept, not redone
    table = pq.read_table(out / rn.PROCEDURES)
    assert [r["index"] for r in table.to_pylist()] == [0, 1]
    # a third run has nothing left to do
    assert (rn.run_trial(spec, out).ran, rn.run_trial(spec, out).kept) == (0, 2)


def test_another_spec_in_the_same_directory_is_refused(tmp_path):
    rn.open_out(tmp_path, parse_trial(TINY))
    with pytest.raises(ConfigError) as exc:
        rn.open_out(tmp_path, parse_trial(TINY.replace("seed: 3", "seed: 4")))
    assert exc.value.field == "--out" and "another trial spec" in exc.value.limit


def test_ray_without_ray_is_a_clear_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)          # import ray fails
    with pytest.raises(ConfigError) as exc:
        rn.run_trial(parse_trial(TINY), tmp_path, ray_address="auto")
    assert exc.value.field == "--ray" and "ray installed" in exc.value.limit


def test_the_command_prints_the_summary_and_writes_the_outputs(tmp_path, capsys,
                                                              logging_restored):
    spec = tmp_path / "tiny.yaml"
    spec.write_text(TINY.replace("n: 2", "n: 1"))
    out = tmp_path / "out"
    assert main(["trial", str(spec), "--out", str(out), "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    (arm,) = summary["arms"]
    assert arm["name"] == "a" and arm["n"] == 1
    assert {"fracture_rate", "fracture_rate_ci", "completeness_median"} <= set(arm)
    assert pq.read_table(out / "procedures.parquet").num_rows == 1
    assert json.loads((out / "summary.json").read_text())["arms"][0]["n"] == 1
    assert all((out / f).is_file() for f in ("fracture_rate.png", "completeness.png",
                                             "file_life.png"))


def test_a_bad_trial_file_exits_2(tmp_path, capsys, logging_restored):
    spec = tmp_path / "bad.yaml"
    spec.write_text(TINY.replace("n: 2", "n: -1"))
    assert main(["trial", str(spec), "--out", str(tmp_path / "o")]) == 2
    assert "n: value -1 is out of range: must be >= 1" in capsys.readouterr().err


@pytest.mark.slow
def test_procedure_i_gives_the_same_row_in_a_batch_of_five_and_alone_and_its_fatigue():
    # resin cuts fast; a severe curve starting a fifth down: the file bends within 10 s
    spec = parse_trial("""name: five
seed: 8
n: 5
rounds_s: [10]
population:
  anatomy:
    curvature_class: {dist: choice, values: [severe]}
    curve_start_frac: {dist: fixed, value: 0.2}
arms: [{name: a}]
""")
    procs = rn.procedures_of(spec, 0, range(5))
    five = _rows(rn.run_batch(procs))
    alone = _rows(rn.run_batch([procs[3]]))
    assert alone == five[3:4]
    for r in five:
        # the meter's Miner sum under the simulator's constants is the world's own
        assert r["fatigue_damage_sim"] > 0.0
        assert r["fatigue_damage"] == pytest.approx(r["fatigue_damage_sim"], rel=1e-6)
        assert r["curvature"] == "severe"


RAY_RUN = """
import sys
import ray
from dentibot.trials import runner as rn
from dentibot.trials.spec import parse_trial
ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
try:
    run = rn.run_trial(parse_trial(sys.argv[1]), sys.argv[2], ray_address="local")
finally:
    ray.shutdown()
print(run.ran, run.kept)
"""


@pytest.mark.slow
def test_a_ray_run_gives_the_local_table(tmp_path):
    pytest.importorskip("ray")
    spec = parse_trial(TINY)
    local = rn.run_trial(spec, tmp_path / "local")
    # a local Ray instance (one CPU), in its own process: Ray's driver keeps sockets open
    done = subprocess.run([sys.executable, "-c", RAY_RUN, TINY, str(tmp_path / "ray")],
                          capture_output=True, text=True, timeout=240, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split() == ["2", "0"]                # both batches ran on Ray
    remote = pq.read_table(tmp_path / "ray" / rn.PROCEDURES)
    assert _rows(remote) == _rows(local.table)
