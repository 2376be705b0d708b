from dentibot.cli import main


def test_fk_prints_the_home_pose(capsys):
    assert main(["fk", "0", "0", "0", "0", "0", "0"]) == 0
    out = capsys.readouterr().out
    assert "x=190.000" in out and "z=308.000" in out and "beta=90.000" in out
