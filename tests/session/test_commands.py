"""The command language: parsing, parameter validation by the protocol schema, completion."""

from __future__ import annotations

import pytest

from dentibot.control.feedrate import FILE_STRENGTH_MNM
from dentibot.protocol.loader import ProtocolFileError, parse_protocol
from dentibot.session.commands import (
    COMMANDS,
    CommandError,
    completions,
    help_text,
    parse,
    validate_step,
)


def test_words_subcommands_and_typed_parameters():
    c = parse("drill tau_d=40 rpm=60.5 strategy=automated rounds=[60,40]")
    assert (c.name, c.sub, c.args) == ("drill", None, ())
    assert c.params == {"tau_d": 40, "rpm": 60.5, "strategy": "automated", "rounds": [60, 40]}
    c = parse("Calibrate LOAD")
    assert (c.name, c.sub) == ("calibrate", "load")
    c = parse("step drag duration_s=2 hand_force_n=0,0,-1")
    assert c.args == ("drag",) and c.params["hand_force_n"] == [0, 0, -1]
    c = parse("record start 'runs/a b.mcap'")
    assert (c.sub, c.args) == ("start", ("runs/a b.mcap",))
    assert parse("   ") is None and parse("# a comment") is None
    assert parse("exit").name == "quit" and parse("e-stop").name == "estop"


@pytest.mark.parametrize("line, words", [
    ("frobnicate", ["unknown command 'frobnicate'", "connect", "drill"]),
    ("calibrate", ["needs one of load | tcp", "got nothing"]),
    ("record pause", ["needs one of start | stop", "'pause'"]),
    ("drill tau_d=1 tau_d=2", ["given twice"]),
    ("drill 'unbalanced", ["cannot read the line"]),
])
def test_bad_lines_say_what_is_wrong(line, words):
    with pytest.raises(CommandError) as e:
        parse(line)
    for w in words:
        assert w in str(e.value)


def test_parameters_are_the_protocol_step_fields_with_or_without_units():
    spec = validate_step("drill", {"tau_d": 50, "fz_min": -0.2, "rounds": [300, 200]})
    assert spec.tau_d_mnm == 50 and spec.fz_min_n == -0.2
    assert [r.duration_s for r in spec.rounds] == [300, 200]       # thesis experiment 2
    spec = validate_step("align", {"config": "C", "duration": 3})
    assert spec.config == "C" and spec.duration_s == 3
    assert validate_step("drag", {"hand_force_n": [0, 0, -1]}).hand_force_n == (0, 0, -1)


def _loader_message(kind: str, field: str, value) -> str:
    with pytest.raises(ProtocolFileError) as e:
        parse_protocol(f"name: x\nsteps:\n  - {kind}: {{{field}: {value}}}\n")
    return str(e.value).rsplit(f"{field}: ", 1)[1]


@pytest.mark.parametrize("kind, field, value", [
    ("drill", "tau_d_mnm", FILE_STRENGTH_MNM + 18),   # above the file's 62 mNm strength
    ("drill", "tau_d_mnm", 0.05),                          # N m for mNm
    ("drill", "strategy", "fastest"),
    ("drag", "duration_s", -1),
    ("align", "config", "D"),
    ("drill", "torque", 3),
])
def test_invalid_values_get_the_protocol_files_wording(kind, field, value):
    with pytest.raises(CommandError) as e:
        validate_step(kind, {field: value})
    text = str(e.value)
    assert text.startswith(f"{kind}.{field}: ")
    assert text.split(": ", 1)[1] == _loader_message(kind, field, value)


def test_tau_d_must_stay_below_the_torque_limit_of_the_thesis_file():
    # the hard limit defaults to 90 % of the thesis file's 62 mNm strength: 55.8 mNm
    with pytest.raises(CommandError) as e:
        validate_step("drill", {"tau_d": 56})
    assert str(e.value) == ("drill.tau_d_mnm: 56 mNm is not below the torque limit "
                            "(limits.torque_limit_mnm = 55.8 mNm)")
    assert validate_step("drill", {"tau_d": 55}).tau_d_mnm == 55.0


def test_completion_of_commands_subcommands_and_parameters():
    assert completions("dr") == ["drag", "drill"]
    assert completions("calibrate l") == ["calibrate load"]
    assert completions("drill tau") == ["drill tau_d_mnm="]
    assert completions("drill tau_d_mnm=40 f") == ["drill tau_d_mnm=40 fz_min_n=",
                                                   "drill tau_d_mnm=40 fz_max_n="]
    assert completions("step al") == ["step align"]
    assert completions("step align con") == ["step align config="]
    assert completions("drill rpm=6") == []                 # a value: nothing to offer
    assert completions("connect") == []


def test_help_lists_every_command_and_the_keys():
    text = help_text()
    for name in COMMANDS:
        assert name in text
    assert "space" in text and "Esc" in text
    assert "tau_d_mnm" in help_text("drill") and "calibrate_load" in help_text("step")
    with pytest.raises(CommandError):
        help_text("nope")
