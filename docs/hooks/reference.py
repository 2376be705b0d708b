"""MkDocs hook: the reference sections of the site, generated from the code at every build.

A page asks for a section with a marker line (an HTML comment, so the page reads the same
without the hook):

- ``<!-- reference: dentibot.protocol.schema:Protocol -->``: every field of a pydantic model
  and of the sections inside it, one table per section: field, type, default, limits,
  description;
- ``<!-- signatures: dentibot.api -->``: the signature and docstring of each function and
  class in the module's ``__all__``;
- ``<!-- include: protocols/root-canal.yaml -->``: a file of the repository as a code block;
- ``<!-- value: dentibot.protocol.schema:MAX_TOOL_MM -->``, anywhere in a line: a constant of
  the code (a number, or a dict of numbers as ``key value, ...``).

A marker naming a missing module, object or file fails the build.
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
import inspect
import re
import sys
import types
import typing
from pathlib import Path

import annotated_types
from pydantic import AfterValidator, BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))           # the checkout's code, whatever else is installed

MARKER = re.compile(r"^<!-- (reference|signatures|include): (\S+) -->$", re.MULTILINE)
VALUE = re.compile(r"<!-- value: (\S+) -->")

_SCALARS = {float: "number", int: "integer", str: "string", bool: "boolean"}
_LIMITS = ((annotated_types.Ge, "ge", ">="), (annotated_types.Gt, "gt", ">"),
           (annotated_types.Le, "le", "<="), (annotated_types.Lt, "lt", "<"),
           (annotated_types.MinLen, "min_length", "length >="),
           (annotated_types.MaxLen, "max_length", "length <="))


def on_page_markdown(markdown: str, page, config, files) -> str:
    markdown = MARKER.sub(lambda m: _GENERATORS[m.group(1)](m.group(2)), markdown)
    return VALUE.sub(lambda m: value(m.group(1)), markdown)


def value(target: str) -> str:
    """The constant ``module:NAME`` as text."""
    module, _, name = target.partition(":")
    obj = getattr(importlib.import_module(module), name)
    if isinstance(obj, dict):
        return ", ".join(f"{k} {_num(v)}" for k, v in obj.items())
    return _num(obj)


# ---------------------------------------------------------------------------- models
def model_reference(target: str) -> str:
    """Tables of the model ``module:Class`` and of every model inside it."""
    module, _, name = target.partition(":")
    model = getattr(importlib.import_module(module), name)
    sections: list[tuple[str, type[BaseModel]]] = []
    _collect(model, "", sections)
    return "\n".join(_section(path, m, name.lower()) for path, m in sections)


def _models_in(annotation) -> list[tuple[str, type[BaseModel]]]:
    """The models a field holds: ``("", M)`` for a section, ``("[]", M)`` for a list of them."""
    origin = typing.get_origin(annotation)
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [("", annotation)]
    if origin is list:
        return [("[]" + s, m) for s, m in _models_in(typing.get_args(annotation)[0])]
    if origin in (typing.Union, types.UnionType, typing.Annotated):
        return [x for a in typing.get_args(annotation) for x in _models_in(a)]
    return []


def _collect(model: type[BaseModel], path: str, out: list) -> None:
    out.append((path, model))
    for name, info in model.model_fields.items():
        for suffix, inner in _models_in(info.annotation):
            _collect(inner, f"{path}{name}{suffix}.", out)


def _anchor(prefix: str, path: str) -> str:
    return f"{prefix}-" + (re.sub(r"[^a-z0-9]+", "-", path.lower()).strip("-") or "top")


def _section(path: str, model: type[BaseModel], prefix: str) -> str:
    title = f"`{path.rstrip('.')}`" if path else "Top level"
    lines = [f"### {title} {{#{_anchor(prefix, path)}}}", ""]
    doc = inspect.getdoc(model)
    own = model.__doc__ is not None and doc and not doc.startswith("A section of")
    if own and model.__doc__ not in (c.__doc__ for c in model.__mro__[1:]):
        lines += [_rst_to_md(doc), ""]
    if not model.model_fields:
        key = path.rstrip(".").rsplit(".", 1)[-1]
        return "\n".join(lines + [f"No settings: `{key}: {{}}`.", ""])
    lines += ["| field | type | default | limits | description |",
              "| --- | --- | --- | --- | --- |"]
    for name, info in model.model_fields.items():
        lines.append("| " + " | ".join([
            f"`{path}{name}`", _type(info.annotation, f"{path}{name}", prefix), _default(info),
            _limits(info.metadata, info.annotation), _cell(info.description or "")]) + " |")
    return "\n".join(lines) + "\n"


def _type(annotation, path: str, prefix: str) -> str:
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if annotation in _SCALARS:
        return _SCALARS[annotation]
    if annotation is type(None):
        return "null"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return f"[section](#{_anchor(prefix, path + '.')})"
    if origin is typing.Annotated:
        return _type(args[0], path, prefix)
    if origin is typing.Literal:
        return "one of " + ", ".join(f"`{a}`" for a in args)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type(a, path, prefix) for a in args)
    if origin is tuple:
        return f"list of {len(args)}: " + ", ".join(_type(a, path, prefix) for a in args) \
            if len(set(args)) > 1 else f"list of {len(args)} {_type(args[0], path, prefix)}s"
    if origin is list:
        inner = args[0]
        if isinstance(inner, type) and issubclass(inner, BaseModel):
            return f"list of [sections](#{_anchor(prefix, path + '[].')})"
        return f"list of {_type(inner, path, prefix)}"
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return "one of " + ", ".join(f"`{e.value}`" for e in annotation)
    return _cell(getattr(annotation, "__name__", str(annotation)))


def _default(info) -> str:
    if info.is_required():
        return "required"
    value = info.default
    if value is PydanticUndefined:
        return ""
    if isinstance(value, BaseModel):
        return "its defaults"
    if value is None:
        return "`null`"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, (int, float)):
        return f"`{_num(value)}`"
    if isinstance(value, tuple):
        return "`[" + ", ".join(_num(v) for v in value) + "]`"
    if value == "":
        return '`""`'
    return f"`{value}`"


def _num(value) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


def _limits(metadata, annotation) -> str:
    found = []
    for item in metadata:
        if isinstance(item, FieldInfo):                  # Annotated[float, Field(ge=...)]
            found.append(_limits(item.metadata, None))
        elif isinstance(item, AfterValidator):           # a check of its own: its docstring
            text = _cell(inspect.getdoc(item.func) or "").rstrip(".")
            found.append(text[:1].lower() + text[1:])
        for kind, attr, sign in _LIMITS:
            if isinstance(item, kind):
                found.append(f"{sign} {_num(getattr(item, attr))}")
    if typing.get_origin(annotation) is tuple:           # limits of each item
        items = {_limits(typing.get_args(a)[1:], None)
                 for a in typing.get_args(annotation)
                 if typing.get_origin(a) is typing.Annotated}
        if len(items) == 1 and "" not in items:
            found.append("each " + items.pop())
    return ", ".join(f for f in found if f)


def _cell(text: str) -> str:
    return _rst_to_md(text).replace("|", "\\|").replace("\n", " ")


def _rst_to_md(text: str) -> str:
    text = re.sub(r":\w+:`~?([\w.]+)`", lambda m: f"`{m.group(1).rsplit('.', 1)[-1]}`", text)
    return text.replace("``", "`")


# ---------------------------------------------------------------------------- signatures
def signatures(module_name: str) -> str:
    """Each public function and class of ``module_name``: heading, signature, docstring; a
    class's fields (dataclass) and its public methods and properties."""
    module = importlib.import_module(module_name)
    out = []
    for name in module.__all__:
        obj = getattr(module, name)
        if inspect.isfunction(obj):
            out += [f"### `{name}`", "", "```python", _signature(obj, name), "```", "",
                    _rst_to_md(inspect.getdoc(obj) or ""), ""]
        elif inspect.isclass(obj):
            out += _class(name, obj)
    return "\n".join(out)


class _Raw:
    """An annotation written as it is in the source (``from __future__ import annotations``
    leaves them as text, which inspect would quote)."""

    def __init__(self, text) -> None:
        self.text = text if isinstance(text, str) else inspect.formatannotation(text)

    def __repr__(self) -> str:
        return self.text


def _signature(func, name: str) -> str:
    sig = inspect.signature(func)
    params = [p.replace(annotation=_Raw(p.annotation))
              if p.annotation is not inspect.Parameter.empty else p
              for p in sig.parameters.values()]
    ret = sig.return_annotation
    sig = sig.replace(parameters=params, return_annotation=(
        ret if ret is inspect.Signature.empty else _Raw(ret)))
    kind = "async def" if inspect.iscoroutinefunction(func) else "def"
    text = f"{kind} {name}{sig}"
    if len(text) <= 90:
        return text
    parts = [str(p) for p in params]
    if any(p.kind is inspect.Parameter.KEYWORD_ONLY for p in params):
        first = next(i for i, p in enumerate(params) if p.kind is inspect.Parameter.KEYWORD_ONLY)
        parts.insert(first, "*")
    tail = "" if sig.return_annotation is inspect.Signature.empty \
        else f" -> {sig.return_annotation!r}"
    return f"{kind} {name}(\n" + "".join(f"    {p},\n" for p in parts) + f"){tail}"


def _class(name: str, cls: type) -> list[str]:
    out = [f"### `{name}`", "", f"`{cls.__module__}.{cls.__qualname__}`", ""]
    doc = cls.__doc__ and inspect.getdoc(cls)
    if doc and not doc.startswith(f"{cls.__name__}("):       # not a dataclass's own
        out += [_rst_to_md(doc), ""]
    if dataclasses.is_dataclass(cls):
        out += ["| attribute | type |", "| --- | --- |"]
        out += [f"| `{f.name}` | `{_Raw(f.type)!r}` |".replace("|`", "| `")
                for f in dataclasses.fields(cls)]
        out.append("")
    for attr, member in vars(cls).items():
        if attr.startswith("_"):
            continue
        if isinstance(member, property):
            first = (inspect.getdoc(member) or "").split("\n\n")[0]
            out.append(f"- `{attr}` (property): {_rst_to_md(first)}".rstrip(": "))
        elif inspect.isfunction(member):
            first = (inspect.getdoc(member) or "").split("\n\n")[0]
            out.append(f"- `{attr}()`: {_rst_to_md(first)}".rstrip(": "))
    return [*out, ""]


# ---------------------------------------------------------------------------- files
def include(path: str) -> str:
    """A repository file as a fenced code block (YAML, Python or text)."""
    file = (ROOT / path).resolve()
    if ROOT not in file.parents:
        raise ValueError(f"include {path}: outside the repository")
    lang = {".yaml": "yaml", ".yml": "yaml", ".py": "python"}.get(file.suffix, "text")
    return f"```{lang}\n{file.read_text(encoding='utf-8').rstrip()}\n```"


_GENERATORS = {"reference": model_reference, "signatures": signatures, "include": include}


if __name__ == "__main__":           # print a reference: python docs/hooks/reference.py X:Y
    print(model_reference(sys.argv[1]))
