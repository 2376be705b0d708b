"""Where the device configuration comes from: ``--devices FILE``, a bare ``--devices``
(environment, working directory, user's configuration directory), ``$DENTIBOT_DEVICES``."""

from __future__ import annotations

from pathlib import Path

import pytest

from dentibot.cli import main
from dentibot.errors import ConfigError
from dentibot.io.devices import devices_yaml, find_devices_file, loopback_config


@pytest.fixture
def places(tmp_path):
    cwd, config = tmp_path / "work", tmp_path / "config"
    cwd.mkdir()
    (config / "dentibot").mkdir(parents=True)
    return cwd, config


def _write(path: Path) -> Path:
    path.write_text(devices_yaml(loopback_config()))
    return path


def test_no_flag_and_no_environment_is_the_built_in_simulator(places):
    cwd, config = places
    _write(cwd / "devices.yaml")               # lying there does not send a run to hardware
    assert find_devices_file(None, env={"XDG_CONFIG_HOME": str(config)}, cwd=cwd) is None


def test_the_environment_variable_is_taken_without_the_flag(places, tmp_path):
    cwd, _ = places
    env = {"DENTIBOT_DEVICES": str(tmp_path / "bench.yaml")}
    assert find_devices_file(None, env=env, cwd=cwd) == (tmp_path / "bench.yaml",
                                                          "$DENTIBOT_DEVICES")


def test_an_explicit_file_wins_over_everything(places, tmp_path):
    cwd, config = places
    env = {"DENTIBOT_DEVICES": str(_write(tmp_path / "env.yaml")),
           "XDG_CONFIG_HOME": str(config)}
    assert find_devices_file("mine.yaml", env=env, cwd=cwd) == (Path("mine.yaml"), "--devices")


def test_a_bare_flag_looks_in_order(places, tmp_path):
    cwd, config = places
    env = {"XDG_CONFIG_HOME": str(config)}
    user = _write(config / "dentibot" / "devices.yaml")
    assert find_devices_file("", env=env, cwd=cwd) == (user, "the user's configuration directory")
    here = _write(cwd / "devices.yaml")
    assert find_devices_file("", env=env, cwd=cwd) == (here, "the working directory")
    env["DENTIBOT_DEVICES"] = str(_write(tmp_path / "env.yaml"))
    assert find_devices_file("", env=env, cwd=cwd) == (tmp_path / "env.yaml",
                                                        "$DENTIBOT_DEVICES")


def test_the_config_directory_defaults_to_dot_config_under_home(tmp_path):
    home = tmp_path / "home"
    (home / ".config" / "dentibot").mkdir(parents=True)
    user = _write(home / ".config" / "dentibot" / "devices.yaml")
    cwd = tmp_path / "empty"
    cwd.mkdir()
    assert find_devices_file("", env={"HOME": str(home)}, cwd=cwd)[0] == user


def test_a_bare_flag_with_nothing_to_find_names_every_place(places):
    cwd, config = places
    with pytest.raises(ConfigError) as err:
        find_devices_file("", env={"XDG_CONFIG_HOME": str(config)}, cwd=cwd)
    text = str(err.value)
    assert "--devices" in text
    assert str(cwd / "devices.yaml") in text
    assert str(config / "dentibot" / "devices.yaml") in text


def test_cli_bare_devices_with_nothing_found_is_bad_input(places, monkeypatch, capsys):
    cwd, config = places
    monkeypatch.chdir(cwd)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(config))
    root = Path(__file__).resolve().parents[2]
    assert main(["run", str(root / "protocols/root-canal.yaml"), "--devices"]) == 2
    err = capsys.readouterr().err
    assert "--devices" in err and str(cwd / "devices.yaml") in err


def test_cli_environment_file_is_named_and_validated_before_anything_connects(
        tmp_path, monkeypatch, capsys):
    bad = tmp_path / "bench.yaml"
    bad.write_text("arm: {host: 127.0.0.1}\n")            # the F/T sensor and the rest missing
    monkeypatch.setenv("DENTIBOT_DEVICES", str(bad))
    root = Path(__file__).resolve().parents[2]
    assert main(["run", str(root / "protocols/root-canal.yaml"), "--no-record"]) == 2
    err = capsys.readouterr().err
    assert f"devices from {bad} ($DENTIBOT_DEVICES)" in err
    assert "invalid" in err and "ft" in err


def test_cli_sim_and_devices_exclude_each_other(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["run", "x.yaml", "--sim", "--devices", "d.yaml"])
    assert stop.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err
