import pytest

from dentibot.cli import main

pytestmark = pytest.mark.wire


def test_fk_prints_the_home_pose(capsys):
    assert main(["fk", "0", "0", "0", "0", "0", "0"]) == 0
    out = capsys.readouterr().out
    assert "x=190.000" in out and "z=308.000" in out and "beta=90.000" in out


def test_selftest_faults_json_lists_every_fault_with_the_required_keys(capsys):
    import json

    from dentibot.sim.faults import FAULTS

    code = main(["selftest", "faults", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert [r["fault"] for r in out] == list(FAULTS)
    for r in out:
        assert {"fault", "detected_ms", "final_state", "samples_lost"} <= set(r)
        assert r["samples_lost"] == 0


def test_sim_serve_passes_the_node_id_to_the_epos4_simulator(monkeypatch, capsys):
    import dentibot.cli.sim as cli_sim

    seen = {}

    class FakeBot:
        def __init__(self, world_config, ports):
            seen["ports"], seen["world"] = ports, world_config
            self.ports = {"host": ports.host, "meca_port": 1, "meca_monitor_port": 2,
                          "netft_port": 3, "netft_http_port": 4, "modbus_port": 5,
                          "can_port": 6, "can_channel": "vcan0"}

        async def __aenter__(self):
            return self

        async def __aexit__(self, *exc):
            return False

    monkeypatch.setattr(cli_sim, "VirtualDentiBot", FakeBot)
    assert main(["sim", "serve", "--node-id", "7", "--duration", "0"]) == 0
    assert seen["ports"].node_id == 7
    assert "EPOS4 node 7" in capsys.readouterr().out
    # the served physics is the protocols' default world's: the bench-fitted arm and drag
    world = seen["world"]
    assert (world.arm.vel_dead_time_s, world.arm.vel_gain) == (0.016, 0.804)
    assert world.canal.drag_n_s_per_mm == 0.21
    assert main(["sim", "serve", "--world", "thesis", "--duration", "0"]) == 0
    assert seen["world"].arm.vel_gain == 1.0 and seen["world"].canal.drag_n_s_per_mm == 0.0


@pytest.mark.parametrize("argv, level, as_json", [
    (["--log-level", "error", "report", "x.mcap"], "error", False),
    (["report", "x.mcap", "--log-level", "debug"], "debug", False),
    (["--log-level", "error", "report", "x.mcap", "--log-level", "info"], "info", False),
    (["sim", "serve", "--log-json"], "warning", True),
    (["report", "x.mcap"], "warning", False),
])
def test_logging_options_anywhere(argv, level, as_json):
    from dentibot.cli import build_parser

    args = build_parser().parse_args(argv)
    assert (args.log_level, args.log_json) == (level, as_json)


def test_sim_serve_help_shows_its_port_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["sim", "serve", "--help"])
    out = capsys.readouterr().out
    assert "default: 10000" in out and "default: 49152" in out and "default: 5020" in out


def test_fk_json_gives_the_home_pose_in_mm_and_deg(capsys):
    import json

    assert main(["fk", "0", "0", "0", "0", "0", "0", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    # the Meca500's zero pose (maker's documentation): flange at (190, 0, 308) mm, beta 90 deg
    assert d["flange_pose"] == pytest.approx({"x_mm": 190.0, "y_mm": 0.0, "z_mm": 308.0,
                                              "alpha_deg": 0.0, "beta_deg": 90.0,
                                              "gamma_deg": 0.0}, abs=1e-9)
    assert d["joints_deg"] == [0.0] * 6
