"""Bad input never reaches the robot: a corpus of malformed protocol and device files, each
refused by ``dentibot run`` with exit status 2 and a message naming the file, the line and the
field, before anything is built or started and without touching any file; and the schema
fuzzed (hypothesis): whatever the YAML, the loader answers with a protocol or a clean error,
never anything else."""

from __future__ import annotations

import json
import math

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dentibot.cli import main
from dentibot.io.devices import DevicesFileError, load_devices_config
from dentibot.protocol.loader import ProtocolFileError, parse_protocol
from dentibot.yamlfile import MAX_BYTES, MAX_ECHO

GOOD = """\
name: t
seed: 1
file: {size: 25, taper: 0.06, length_mm: 25}
phantom: {working_length_mm: 16.0}
steps:
  - calibrate_load: {}
  - drag: {duration_s: 0.5, hand_force_n: [0.0, 0.0, -1.0]}
  - align: {duration_s: 0.2, fz_n: 1.0}
  - drill: {strategy: automated, tau_d_mnm: 40, rounds: [{duration_s: 10}]}
"""

NESTED = "name: t\nsteps:\n  - drill: {}\nx: " + "[" * 5000 + "]" * 5000 + "\n"
BOMB = ("name: &a [x, x, x, x, x, x, x, x, x]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
        "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
        "e: [*d, *d, *d, *d, *d, *d, *d, *d, *d]\nsteps:\n  - drill: {}\n")


def _sub(old: str, new: str) -> str:
    assert old in GOOD, old
    return GOOD.replace(old, new)


#: (id, file content, field named, words in the message)
PROTOCOL_CASES = [
    ("binary", b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR\x00\x00", "file", "not UTF-8"),
    ("latin1", "name: caf\xe9\nsteps:\n  - drill: {}\n".encode("latin-1"), "file", "not UTF-8"),
    ("nul", b"name: t\x00\nsteps:\n  - drill: {}\n", "file", "control character"),
    ("too_big", b"name: t\nsteps:\n  - drill: {}\n#" + b"x" * MAX_BYTES, "file", "larger than"),
    ("nested", NESTED, "yaml", "nested deeper than"),
    ("alias_bomb", BOMB, "yaml", "aliases are not accepted"),
    ("empty", "", "protocol", "empty"),
    ("list", "- drill: {}\n", "protocol", "mapping"),
    ("not_yaml", "name: t\nsteps: [\n", "yaml", "not valid YAML"),
    ("duplicate_key", _sub("tau_d_mnm: 40,", "tau_d_mnm: 40, tau_d_mnm: 61,"),
     "steps.3.drill.tau_d_mnm", "given twice"),
    ("bool_rpm", _sub("strategy: automated,", "strategy: automated, rpm: true,"),
     "steps.3.drill.rpm", "boolean, not a number"),
    ("bool_seed", _sub("seed: 1", "seed: yes"), "seed", "boolean"),
    ("nan_tip", _sub("seed: 1", "seed: 1\ntool: {tip_mm: [.nan, 0, 90]}"), "tool.tip_mm",
     "not a finite number"),
    ("inf_hand", _sub("[0.0, 0.0, -1.0]", "[.inf, 0, 0]"), "steps.1.drag.hand_force_n",
     "not a finite number"),
    ("nan_duration", _sub("duration_s: 0.5", "duration_s: .nan"), "steps.1.drag.duration_s",
     "finite"),
    ("wl_longer_than_file", _sub("length_mm: 25", "length_mm: 21").replace(
        "working_length_mm: 16.0", "working_length_mm: 29.0"), "phantom.working_length_mm",
     "does not fit the 21 mm file: at most 19 mm"),
    ("wl_does_not_fit", _sub("length_mm: 25", "length_mm: 21").replace(
        "working_length_mm: 16.0", "working_length_mm: 20.0"), "phantom.working_length_mm",
     "does not fit the 21 mm file"),
    ("tool_100m", _sub("seed: 1", "seed: 1\ntool: {tip_mm: [0, 0, 100000]}"), "tool.tip_mm.2",
     "out of range"),
    ("tool_out_of_reach", _sub("seed: 1", "seed: 1\ntool: {tip_mm: [200, 200, 90]}"),
     "tool.tip_mm", "from the flange"),
    ("rounds_20000", _sub("rounds: [{duration_s: 10}]",
                          "rounds: [" + ", ".join(["{duration_s: 3600}"] * 20000) + "]"),
     "file", "larger than"),
    ("rounds_2000", _sub("rounds: [{duration_s: 10}]",
                         "rounds: [" + ", ".join(["{duration_s: 3600}"] * 2000) + "]"),
     "steps.3.drill.rounds", "at most 100"),
    ("hours", _sub("rounds: [{duration_s: 10}]",
                   "rounds: [" + ", ".join(["{duration_s: 3600}"] * 3) + "]"),
     "steps", "planned in all"),
    ("tau_in_newton_metres", _sub("tau_d_mnm: 40", "tau_d_mnm: 0.04"),
     "steps.3.drill.tau_d_mnm", "N m"),
    ("tau_above_limit", _sub("tau_d_mnm: 40", "tau_d_mnm: 61"), "steps.3.drill.tau_d_mnm",
     "not below the torque limit"),
    ("limit_at_strength", _sub("seed: 1", "seed: 1\nlimits: {torque_limit_mnm: 62}"),
     "limits.torque_limit_mnm", "too close to the file's strength"),
    ("stale_10s", _sub("seed: 1", "seed: 1\nlimits: {stale_periods: {aux: 5000}}"),
     "limits.stale_periods.aux", "at most 500 ms"),
    ("drill_before_calibration", GOOD.replace("  - calibrate_load: {}\n", "") +
     "  - calibrate_load: {}\n", "steps.0.drag", "before the load calibration"),
    ("unknown_key", _sub("tau_d_mnm: 40,", "tau_d: 40,"), "steps.3.drill.tau_d",
     "unknown key"),
    ("two_actions", _sub("  - calibrate_load: {}\n", "  - {calibrate_load: {}, drag: {}}\n"),
     "steps.0", "exactly one of"),
    ("missing_name", GOOD.replace("name: t\n", ""), "name", "required field is missing"),
    ("description_flood", _sub("seed: 1", "seed: 1\ndescription: " + "x" * 5000),
     "description", "at most 4000"),
    ("curve_past_wl", _sub("working_length_mm: 16.0",
                           "working_length_mm: 16.0, curve: {start_mm: 18}"), "phantom",
     "must be below"),
]


@pytest.fixture
def nothing_starts(monkeypatch):
    """Fails the test if anything builds a procedure or opens a device."""
    from dentibot.app.procedure import Procedure
    from dentibot.io import devices

    def refuse(*a, **k):
        raise AssertionError("a procedure was built for bad input")

    monkeypatch.setattr(Procedure, "simulated", classmethod(refuse))
    monkeypatch.setattr(Procedure, "over", classmethod(refuse))
    monkeypatch.setattr(devices, "open_devices", refuse)


def _refused(tmp_path, capsys, argv: list[str], path, field: str, words: str) -> str:
    before = sorted(tmp_path.rglob("*"))
    out = tmp_path / "never.mcap"
    assert main([*argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert f"{path}:" in err and f": {field}: " in err and words in err, err[:2000]
    assert sorted(tmp_path.rglob("*")) == before        # nothing written
    assert max(len(line) for line in err.splitlines()) < 400   # no unbounded echo
    return err


@pytest.mark.timeout(20)
@pytest.mark.parametrize("name, content, field, words", PROTOCOL_CASES,
                         ids=[c[0] for c in PROTOCOL_CASES])
def test_a_bad_protocol_is_refused_before_anything_starts(tmp_path, capsys, nothing_starts,
                                                          name, content, field, words):
    path = tmp_path / f"{name}.yaml"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8")
    err = _refused(tmp_path, capsys, ["run", str(path)], path, field, words)
    if field not in ("file", "protocol", "yaml", "name"):
        assert f"{path}:?" not in err.split(f": {field}: ")[0].splitlines()[-1]  # has a line


def test_the_good_protocol_of_the_corpus_is_accepted():
    p = parse_protocol(GOOD)
    assert p.planned_s() == pytest.approx(10.7)


def test_an_existing_recording_is_never_replaced_without_force(tmp_path, capsys, monkeypatch):
    path = tmp_path / "p.yaml"
    path.write_text(GOOD.replace("rounds: [{duration_s: 10}]", "rounds: [{duration_s: 0.1}]"))
    out = tmp_path / "run.mcap"
    out.write_bytes(b"an earlier run")
    assert main(["run", str(path), "--out", str(out), "--quiet", "--json"]) == 2
    err = capsys.readouterr().err
    assert "recording.path" in err and "--force" in err
    assert out.read_bytes() == b"an earlier run"
    assert main(["run", str(path), "--out", str(out), "--quiet", "--json", "--force"]) == 0
    assert out.read_bytes()[:8] == b"\x89MCAP0\r\n"


# ---------------------------------------------------------------------------- devices
DEVICES = """\
arm: {host: 127.0.0.1, control_port: 10000, monitor_port: 10001}
ft: {host: 127.0.0.1, port: 49152, http_port: 8080}
handpiece: {interface: socketcand, host: 127.0.0.1, port: 29536, channel: vcan0, node_id: 1}
aux: {host: 127.0.0.1, port: 5020}
"""


def _dev(old: str, new: str) -> str:
    assert old in DEVICES, old
    return DEVICES.replace(old, new)


DEVICE_CASES = [
    ("empty", "", "device configuration", "empty"),
    ("only_comment", "# nothing here\n", "device configuration", "empty"),
    ("no_arm", DEVICES.split("\n", 1)[1], "arm", "required field is missing"),
    ("no_host", _dev("arm: {host: 127.0.0.1, ", "arm: {"), "arm.host", "required"),
    ("aux_null", _dev("aux: {host: 127.0.0.1, port: 5020}", "aux: null"), "aux",
     "estop_waiver"),
    ("vel_timeout_1s", _dev("monitor_port: 10001}", "monitor_port: 10001, vel_timeout_s: 1.0}"),
     "arm.vel_timeout_s", "<= 0.1"),
    ("watchdog_off", _dev("port: 5020}", "port: 5020, watchdog_ms: 0}"), "aux.watchdog_ms",
     ">= 50"),
    ("alias_bomb", "a: &a [x, x]\nb: [*a, *a]\n" + DEVICES, "yaml", "aliases"),
    ("duplicate", DEVICES + "arm: {host: 10.0.0.1}\n", "arm", "given twice"),
    ("port_range", _dev("port: 49152", "port: 70000"), "ft.port", "<= 65535"),
    ("bool_port", _dev("port: 49152", "port: true"), "ft.port", "boolean"),
    ("nan_counts", _dev("http_port: 8080}", "http_port: 8080, counts_per_force: .nan}"),
     "ft.counts_per_force", "finite"),
    ("binary", b"\xff\xfe\x00a\x00r\x00m", "file", "not UTF-8"),
]


@pytest.mark.timeout(20)
@pytest.mark.parametrize("name, content, field, words", DEVICE_CASES,
                         ids=[c[0] for c in DEVICE_CASES])
def test_a_bad_device_file_is_refused_before_anything_connects(tmp_path, capsys, nothing_starts,
                                                               name, content, field, words):
    protocol = tmp_path / "p.yaml"
    protocol.write_text(GOOD)
    path = tmp_path / f"{name}.yaml"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8")
    _refused(tmp_path, capsys, ["run", str(protocol), "--devices", str(path)], path, field,
             words)


def test_the_good_device_file_loads_and_a_waiver_replaces_the_aux(tmp_path):
    path = tmp_path / "d.yaml"
    path.write_text(DEVICES)
    cfg = load_devices_config(path)
    assert cfg.aux.watchdog_ms == 200 and cfg.arm.vel_timeout_s == 0.05
    path.write_text(_dev("aux: {host: 127.0.0.1, port: 5020}",
                         "estop_waiver: bench with a hardware e-stop in the arm's power"))
    assert load_devices_config(path).aux is None
    path.write_text(_dev("aux: {host: 127.0.0.1, port: 5020}", "estop_waiver: ok"))
    with pytest.raises(DevicesFileError, match="estop_waiver"):
        load_devices_config(path)


# ---------------------------------------------------------------------------- fuzzing
def _leaves(obj, path=()):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _leaves(v, (*path, k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _leaves(v, (*path, i))
    yield path


def _set(obj, path, value):
    if not path:
        return value
    obj[path[0]] = _set(obj[path[0]], path[1:], value)
    return obj


JUNK = st.one_of(
    st.none(), st.booleans(), st.integers(-10**12, 10**12),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=300),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=5),
    st.dictionaries(st.text(max_size=10), st.integers(), max_size=3),
    st.sampled_from(["1e400", "-0", "0x10", "NaN", ".inf", "true", "", "~"]))


def _check_outcome(text: str) -> None:
    try:
        p = parse_protocol(text, "fuzz.yaml")
    except ProtocolFileError as exc:
        assert exc.problems
        for line, field, message in exc.problems:
            assert field and message and len(message) < 300 + MAX_ECHO
            assert line is None or line >= 1
        return
    # accepted: then every number in it is finite and the cross-field rules hold
    data = json.loads(p.model_dump_json())
    for leaf in _leaves(data):
        v = data
        for k in leaf:
            v = v[k]
        if isinstance(v, float):
            assert math.isfinite(v)
    assert p.cross_checks() == []
    assert p.limits.torque_limit_mnm <= 0.9 * p.file.torsional_strength_mnm + 1e-9


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_fuzzed_values_give_a_protocol_or_a_clean_error(data):
    base = yaml.safe_load(GOOD)
    leaves = [p for p in _leaves(base) if p]
    where = data.draw(st.sampled_from(leaves))
    value = data.draw(JUNK)
    _check_outcome(yaml.safe_dump(_set(base, where, value)))


@settings(max_examples=150, deadline=None)
@given(st.text(max_size=400))
def test_fuzzed_text_gives_a_protocol_or_a_clean_error(text):
    _check_outcome(text)
