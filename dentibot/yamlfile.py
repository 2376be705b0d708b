"""Every YAML file the product reads (protocols, device configurations), read strictly.

A file a user hands to a robot is refused, before anything starts, unless it is plainly what it
says. The checks, in order, each with the file, the line, the field, the value and the limit:

- bytes: at most :data:`MAX_BYTES`, UTF-8 text (a binary or mis-encoded file is named as such,
  with the offset of the first bad byte), no control characters;
- structure, from the parser's event stream (which does not recurse, so a 5,000-deep nesting
  cannot exhaust the stack): nesting at most :data:`MAX_DEPTH`, at most :data:`MAX_NODES`
  values, and no aliases (``*name``: a 470-byte alias bomb would otherwise expand to millions
  of values; write repeated values out);
- keys: a mapping that names a key twice is refused (YAML keeps the last one silently: a
  ``tau_d_mnm`` given as 40 and then 61 would run at 61);
- values, against the pydantic model (:class:`StrictModel`): unknown keys, types, ranges;
  booleans are not numbers (``rpm: true`` is not 1 rpm), NaN and infinities are refused
  everywhere.

Messages quote values shortened to :data:`MAX_ECHO` characters: an error never echoes
unbounded input.
"""

from __future__ import annotations

import math
import typing
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from dentibot.errors import ConfigError

#: Largest file accepted (bytes): a protocol or device file is a page or two of text.
MAX_BYTES = 256 * 1024
#: Deepest nesting of mappings and sequences accepted.
MAX_DEPTH = 16
#: Most values (scalars, mappings, sequences) in one file.
MAX_NODES = 20_000
#: Longest quotation of a value in a message (characters).
MAX_ECHO = 60

Problem = tuple[int | None, str, str]   # (line, dotted field, what is wrong)


def echo(value: Any) -> str:
    """``repr(value)``, shortened to :data:`MAX_ECHO` characters."""
    try:
        text = repr(value)
    except Exception:  # noqa: BLE001 - a value that cannot even be shown
        text = f"<{type(value).__name__}>"
    if len(text) > MAX_ECHO:
        text = text[:MAX_ECHO - 12] + f"... ({len(text)} chars)"
    return text


class YamlFileError(ConfigError):
    """A file is malformed or invalid; ``problems`` lists every (line, field, text)."""

    kind = "file"

    def __init__(self, path: str, problems: list[Problem]) -> None:
        self.path = path
        self.problems = problems
        lines = [f"{path}:{line if line else '?'}: {fld}: {text}" for line, fld, text in problems]
        _, first_field, first_text = problems[0]
        super().__init__(first_field, None, first_text)
        self.args = (f"invalid {self.kind}\n" + "\n".join(lines),)

    def __str__(self) -> str:
        return self.args[0]


# ---------------------------------------------------------------------------- bytes
def read_text(path: str | Path, error: type[YamlFileError] = YamlFileError) -> str:
    """The file's text, if it is bounded UTF-8 text."""
    p = Path(path)
    try:
        with p.open("rb") as f:
            data = f.read(MAX_BYTES + 1)
    except OSError as exc:
        raise error(str(p), [(None, "file", f"cannot read: {exc.strerror}")]) from None
    return decode(data, str(p), error)


def decode(data: bytes, path: str, error: type[YamlFileError] = YamlFileError) -> str:
    if len(data) > MAX_BYTES:
        raise error(path, [(None, "file", f"larger than {MAX_BYTES} bytes: not a "
                                          "protocol or configuration file")])
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise error(path, [(line, "file", f"not UTF-8 text: byte 0x{data[exc.start]:02x} at "
                                          f"offset {exc.start} (a binary file, or another "
                                          "encoding: save it as UTF-8)")]) from None
    for i, ch in enumerate(text):
        if ch < " " and ch not in "\t\n\r" or ch == "\x7f":
            line = text.count("\n", 0, i) + 1
            raise error(path, [(line, "file", f"control character {ch!r} at offset {i}: "
                                              "not a text file")])
    return text


# ---------------------------------------------------------------------------- structure
def _check_structure(text: str, path: str, error: type[YamlFileError]) -> None:
    depth = nodes = 0
    try:
        for ev in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(ev, yaml.AliasEvent):
                raise error(path, [(ev.start_mark.line + 1, "yaml",
                                    f"alias *{echo(ev.anchor)[1:-1]}: aliases are not "
                                    "accepted (write the value out)")])
            if isinstance(ev, (yaml.ScalarEvent, yaml.MappingStartEvent,
                               yaml.SequenceStartEvent)):
                nodes += 1
                if nodes > MAX_NODES:
                    raise error(path, [(ev.start_mark.line + 1, "yaml",
                                        f"more than {MAX_NODES} values")])
            if isinstance(ev, (yaml.MappingStartEvent, yaml.SequenceStartEvent)):
                depth += 1
                if depth > MAX_DEPTH:
                    raise error(path, [(ev.start_mark.line + 1, "yaml",
                                        f"nested deeper than {MAX_DEPTH} levels")])
            elif isinstance(ev, (yaml.MappingEndEvent, yaml.SequenceEndEvent)):
                depth -= 1
    except yaml.YAMLError as exc:
        raise error(path, [_yaml_problem(exc)]) from None


def _yaml_problem(exc: yaml.YAMLError) -> Problem:
    mark = getattr(exc, "problem_mark", None)
    line = mark.line + 1 if mark is not None else None
    return (line, "yaml", f"not valid YAML: {getattr(exc, 'problem', None) or exc}")


def _check_keys(node, path: str, where: str, problems: list[Problem]) -> None:
    if isinstance(node, yaml.MappingNode):
        seen: dict[str, int] = {}
        for k, v in node.value:
            key = k.value if isinstance(k, yaml.ScalarNode) else echo(k.value)
            name = f"{where}.{key}" if where else str(key)
            if key in seen:
                problems.append((k.start_mark.line + 1, name,
                                 f"given twice (lines {seen[key]} and "
                                 f"{k.start_mark.line + 1}): keep one"))
            else:
                seen[key] = k.start_mark.line + 1
            _check_keys(v, path, name, problems)
    elif isinstance(node, yaml.SequenceNode):
        for i, v in enumerate(node.value):
            _check_keys(v, path, f"{where}.{i}" if where else str(i), problems)


def parse(text: str, path: str, error: type[YamlFileError] = YamlFileError):
    """``(data, root node)`` of ``text`` after the structural checks."""
    _check_structure(text, path, error)
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
        data = yaml.load(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError as exc:
        raise error(path, [_yaml_problem(exc)]) from None
    problems: list[Problem] = []
    _check_keys(root, path, "", problems)
    if problems:
        raise error(path, problems)
    return data, root


# ---------------------------------------------------------------------------- values
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
    value = echo(err.get("input"))
    kind = err["type"]
    limits = {"greater_than_equal": ">= {ge}", "greater_than": "> {gt}",
              "less_than_equal": "<= {le}", "less_than": "< {lt}"}
    if kind in limits:
        return f"value {value} is out of range: must be {limits[kind].format(**ctx)}"
    if kind == "literal_error":
        return f"value {value} is not one of {ctx.get('expected')}"
    if kind == "extra_forbidden":
        return "unknown key (not in the schema; check its spelling)"
    if kind == "missing":
        return "required field is missing"
    if kind == "finite_number":
        return f"value {value} is not a finite number (NaN and infinities are refused)"
    if kind == "value_error":
        return str(ctx.get("error", err["msg"]))
    return f"{err['msg']} (got {value})"


def validate(model: type[BaseModel], data: Any, root, path: str,
             error: type[YamlFileError] = YamlFileError):
    """``model`` validated from ``data``; every problem with its line."""
    try:
        obj = model.model_validate(data)
    except ValidationError as exc:
        problems = []
        for err in exc.errors():
            loc = tuple(x for x in err["loc"] if not (isinstance(x, str) and "[" in x))
            field = ".".join(str(x) for x in loc) or error.kind
            problems.append((_line_of(root, loc), field, describe_error(err)))
        raise error(path, problems) from None
    cross = getattr(obj, "cross_checks", None)
    if cross is not None:
        problems = [(_line_of(root, loc), ".".join(map(str, loc)) or error.kind, text)
                    for loc, text in cross()]
        if problems:
            raise error(path, problems)
    return obj


def load(path: str | Path, model: type[BaseModel], error: type[YamlFileError] = YamlFileError):
    """Read, check and validate ``path`` as ``model``."""
    text = read_text(path, error)
    return loads(text, model, str(path), error)


def loads(text: str, model: type[BaseModel], path: str,
          error: type[YamlFileError] = YamlFileError):
    data, root = parse(text, path, error)
    if not isinstance(data, dict):
        raise error(path, [(1, error.kind,
                            "the file must be a mapping of keys to values" if data is not None
                            else "the file is empty")])
    return validate(model, data, root, path, error)


# ---------------------------------------------------------------------------- models
def _takes_bool(annotation) -> bool:
    if annotation is bool:
        return True
    return any(_takes_bool(a) for a in typing.get_args(annotation))


def _refuse(value) -> None:
    if isinstance(value, bool):
        raise ValueError(f"{echo(value)} is a boolean, not a number: write the number")
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{echo(value)} is not a finite number (NaN and infinities are "
                         "refused)")
    if isinstance(value, (list, tuple)):
        for v in value:
            _refuse(v)


class StrictModel(BaseModel):
    """A section of a file: unknown keys are errors, values are frozen, NaN and infinities
    are refused, and a boolean is accepted only where the field is one.

    A file's top model may define ``cross_checks()`` -> ``[(location, text)]``: checks between
    fields, run after validation, each reported at the line of its location (a tuple of keys
    and indices, as pydantic's)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_for_numbers(cls, value, info):
        ann = cls.model_fields[info.field_name].annotation
        if not _takes_bool(ann) and not isinstance(value, dict):
            _refuse(value)
        return value


__all__ = ["MAX_BYTES", "MAX_DEPTH", "MAX_ECHO", "MAX_NODES", "StrictModel", "YamlFileError",
           "decode", "describe_error", "echo", "load", "loads", "parse", "read_text",
           "validate"]
