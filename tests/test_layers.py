"""The import graph of ``dentibot/`` against the layer rules of docs/architecture.md.

Every ``import`` and ``from ... import`` of a dentibot module is an edge, at module level or
inside a function (a lazy import is a dependency all the same). The rules: each layer imports
only the layers below it (:data:`MAY_IMPORT`), nothing imports the CLI, and no module imports
itself through others (no cycles). There are no listed exceptions.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "dentibot"

#: Modules every layer may use: the version, the typed errors, the strict YAML reader, the
#: logging set-up and JSON-safe values.
BASE = {"dentibot", "dentibot.errors", "dentibot.yamlfile", "dentibot.logs", "dentibot.jsonsafe"}

_BELOW_APP = {"runtime", "states", "control", "io", "protocol", "telemetry"}
#: layer -> the layers it may import (its own always).
MAY_IMPORT: dict[str, set[str]] = {
    "control": set(),
    "io": set(),
    "telemetry": set(),
    "protocol": {"control"},
    "sim": {"io", "control"},
    "states": {"io", "control"},
    "runtime": {"states", "control", "io", "telemetry", "protocol"},
    "app": _BELOW_APP | {"sim"},
    "session": _BELOW_APP | {"app"},
    "experiments": _BELOW_APP | {"app"},
    "trials": _BELOW_APP | {"app"},
    "testing": _BELOW_APP | {"app"},
    "cli": _BELOW_APP | {"app", "sim", "session", "experiments", "trials"},
    # the Python API for notebooks and scripts: the same reach as the command line
    "api": _BELOW_APP | {"app", "sim", "experiments"},
}


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path) -> set[str]:
    """The dentibot modules ``path`` imports (absolute and relative, any depth)."""
    name = module_name(path)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join([*base, *([node.module] if node.module else [])])
            else:
                target = node.module or ""
            found.add(target)
            # ``from dentibot.cli import run``: ``run`` may be a module of the package
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                if _exists(sub):
                    found.add(sub)
    found.discard(name)         # a package's __init__ naming its own submodules
    return {m for m in found if m == "dentibot" or m.startswith("dentibot.")}


def _exists(module: str) -> bool:
    rel = Path(*module.split(".")[1:])
    return (PACKAGE / rel).with_suffix(".py").is_file() or (PACKAGE / rel / "__init__.py").is_file()


def layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def graph() -> dict[str, set[str]]:
    return {module_name(p): imports_of(p) for p in sorted(PACKAGE.rglob("*.py"))}


def test_the_rules_name_every_layer_of_the_package():
    layers = {layer(m) for m in graph()} - {"", *(m.rsplit(".", 1)[-1] for m in BASE)}
    assert layers <= set(MAY_IMPORT), sorted(layers - set(MAY_IMPORT))


def test_each_layer_imports_only_the_layers_below_it():
    broken = []
    for module, targets in graph().items():
        own = layer(module)
        if module in BASE:
            allowed: set[str] = set()
        else:
            allowed = MAY_IMPORT[own] | {own}
        for t in sorted(targets):
            if t in BASE or layer(t) in allowed:
                continue
            broken.append(f"{module} -> {t}")
    assert not broken, "layer rules broken:\n" + "\n".join(broken)


def test_nothing_imports_the_cli():
    users = [f"{m} -> {t}" for m, ts in graph().items() for t in ts
             if layer(t) == "cli" and layer(m) != "cli"]
    assert not users, users


def test_there_are_no_import_cycles():
    g = graph()
    # Tarjan's strongly connected components over modules
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in g.get(v, ()):
            if w not in g:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in g.get(v, ()):
                cycles.append(sorted(comp))

    for v in g:
        if v not in index:
            visit(v)
    assert not cycles, cycles


@pytest.mark.parametrize("source, expected", [
    ("from dentibot.sim.world import World\n", {"dentibot.sim.world"}),
    ("def f():\n    import dentibot.sim.canal\n", {"dentibot.sim.canal"}),
    ("from ..sim import world\n", {"dentibot.sim", "dentibot.sim.world"}),
    ("import numpy\n", set()),
])
def test_the_checker_sees_absolute_lazy_and_relative_imports(tmp_path, monkeypatch, source,
                                                            expected):
    fake = tmp_path / "dentibot"
    (fake / "runtime").mkdir(parents=True)
    (fake / "sim").mkdir()
    (fake / "sim" / "__init__.py").write_text("")
    (fake / "sim" / "world.py").write_text("")
    (fake / "sim" / "canal.py").write_text("")
    probe = fake / "runtime" / "probe.py"
    probe.write_text(source)
    monkeypatch.setattr(sys.modules[__name__], "PACKAGE", fake)
    assert imports_of(probe) == expected


def test_only_the_app_layer_constructs_the_runtime():
    builders = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) \
                    and node.func.id == "Runtime":
                builders.append(module_name(path))
    assert builders, "no construction of the runtime found: the check reads nothing"
    assert {layer(m) for m in builders} == {"app"}, builders
    # and within it, one place: the procedure (devices, clock, gate, one control loop)
    assert set(builders) == {"dentibot.app.procedure"}, builders


def test_two_clocks_and_a_short_control_task():
    """Time is real time or lock step (paced and held are options of lock step), and the
    control task is a short loop: read, tick, behaviour, send, record."""
    clocks = set()
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ClassDef) and any(
                    isinstance(b, ast.Name) and b.id == "Clock" for b in node.bases):
                clocks.add(node.name)
    assert clocks == {"RealTimeClock", "LockStepClock"}
    lines = (PACKAGE / "runtime" / "control_task.py").read_text().count("\n")
    assert lines < 300, lines
