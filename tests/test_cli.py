from dentibot.cli import main


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
