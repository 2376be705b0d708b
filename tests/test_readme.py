"""The README's two set-up commands: the main job (a protocol on the built-in simulator) and
the test command that CI runs."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _first_block() -> list[str]:
    readme = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```sh\n(.*?)\n```", readme, flags=re.DOTALL)
    assert blocks, "README must open with its set-up commands in a sh block"
    return blocks[0].splitlines()


def test_readme_opens_with_exactly_the_two_setup_commands():
    lines = _first_block()
    assert len(lines) == 2
    assert "dentibot run protocols/" in lines[0] and "pytest" in lines[1]


def test_ci_runs_the_readme_test_command():
    test_cmd = [line for line in _first_block() if "pytest" in line]
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert test_cmd[0] in ci


@pytest.mark.timeout(300)
def test_the_main_job_runs_to_completion():
    """The README's first command, minus the install: the protocol runs and ends ok."""
    cmd = _first_block()[0].split("&&")[-1].split()
    protocol = cmd[cmd.index("run") + 1]
    out = subprocess.run(
        [sys.executable, "-m", "dentibot.cli", "run", protocol, "--no-record", "--json",
         "--quiet"], cwd=ROOT, capture_output=True, text=True, timeout=280, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    import json

    result = json.loads(out.stdout)
    assert result["status"] == "ok" and result["fractures"] == 0
    assert result["completeness"] > 0.8


def test_the_layout_table_names_every_package_of_the_tree_and_no_other():
    readme = (ROOT / "README.md").read_text()
    layout = readme.split("## Layout", 1)[1].split("\n## ", 1)[0]
    listed = set(re.findall(r"^\| `dentibot/(\w+)/` \|", layout, flags=re.MULTILINE))
    packages = {p.parent.name for p in (ROOT / "dentibot").glob("*/__init__.py")}
    assert listed == packages, (sorted(listed - packages), sorted(packages - listed))
    for package, row in re.findall(r"^\| `dentibot/(\w+)/` \|(.*)$", layout, flags=re.MULTILINE):
        for module in re.findall(r"`(\w+)` \(", row):
            assert (ROOT / "dentibot" / package / f"{module}.py").is_file(), (package, module)
    for module in re.findall(r"^\| `dentibot/(\w+)\.py` \|", layout, flags=re.MULTILINE):
        assert (ROOT / "dentibot" / f"{module}.py").is_file(), module
