"""Load a protocol file: YAML -> :class:`~dentibot.protocol.schema.Protocol`, with errors that
name the file, the line, the field, the value and the allowed range or choices.

Errors are collected (all of them, not only the first) into one :class:`ProtocolFileError`
before anything starts.
"""

from __future__ import annotations

from pathlib import Path

import yaml
from pydantic import ValidationError

from dentibot.errors import ConfigError
from dentibot.protocol.schema import Protocol


class ProtocolFileError(ConfigError):
    """A protocol file is malformed or invalid; ``problems`` lists every (line, field, text)."""

    def __init__(self, path: str, problems: list[tuple[int | None, str, str]]) -> None:
        self.path = path
        self.problems = problems
        lines = [f"{path}:{line if line else '?'}: {fld}: {text}" for line, fld, text in problems]
        _, first_field, first_text = problems[0]
        super().__init__(first_field, None, first_text)
        self.args = ("invalid protocol\n" + "\n".join(lines),)

    def __str__(self) -> str:
        return self.args[0]


def _line_of(node, loc: tuple) -> int | None:
    """1-based line of the YAML node at ``loc`` (the deepest existing parent otherwise)."""
    line = node.start_mark.line + 1 if node is not None else None
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            nxt = None
            for k, v in node.value:
                if k.value == key:
                    nxt = v
                    line = k.start_mark.line + 1
                    break
            if nxt is None:
                return line
            node = nxt
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int):
            if key >= len(node.value):
                return line
            node = node.value[key]
            line = node.start_mark.line + 1
        else:
            return line
    return line


def describe_error(err: dict) -> str:
    """One pydantic error as text: the value and the allowed range, choices or type."""
    ctx = err.get("ctx") or {}
    value = err.get("input")
    kind = err["type"]
    limits = {"greater_than_equal": ">= {ge}", "greater_than": "> {gt}",
              "less_than_equal": "<= {le}", "less_than": "< {lt}"}
    if kind in limits:
        return f"value {value!r} is out of range: must be {limits[kind].format(**ctx)}"
    if kind == "literal_error":
        return f"value {value!r} is not one of {ctx.get('expected')}"
    if kind == "extra_forbidden":
        return "unknown key (not in the schema; check its spelling)"
    if kind == "missing":
        return "required field is missing"
    return f"{err['msg']} (got {value!r})"


def parse_protocol(text: str, path: str = "<protocol>") -> Protocol:
    """Validate protocol ``text``; raises :class:`ProtocolFileError`."""
    try:
        root = yaml.compose(text)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        what = f"not valid YAML: {getattr(exc, 'problem', exc)}"
        raise ProtocolFileError(path, [(line, "yaml", what)]) from None
    if not isinstance(data, dict):
        what = "the file must be a mapping (name: ..., steps: [...])"
        raise ProtocolFileError(path, [(1, "protocol", what)])
    try:
        return Protocol.model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            loc = tuple(x for x in err["loc"] if not (isinstance(x, str) and "[" in x))
            field = ".".join(str(x) for x in loc) or "protocol"
            problems.append((_line_of(root, loc), field, describe_error(err)))
        raise ProtocolFileError(path, problems) from None


def load_protocol(path: str | Path) -> Protocol:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ProtocolFileError(str(p), [(None, "file", f"cannot read: {exc.strerror}")]) from None
    return parse_protocol(text, str(p))
