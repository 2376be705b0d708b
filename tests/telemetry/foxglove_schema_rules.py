"""The rules of the JSON-schema parser in the open-source Foxglove Studio and Lichtblick viewers
(``parseJsonSchema`` in their ``mcap-support`` package), ported as a checker.

The viewers turn a channel's JSON schema into message definitions before showing a single
message; a schema the parser throws on leaves the whole channel unreadable. What the parser
does, object by object, starting at the root:

- the schema's ``type`` must be the string ``"object"``;
- its ``properties`` must be an object (the parser walks its entries; without it, it throws);
- each property is read by its ``type``, which must be one string:
  ``boolean``; ``string`` (``contentEncoding`` absent or ``"base64"``); ``number`` and
  ``integer``; ``object`` (checked by the same rules, recursively); ``array`` whose ``items``
  is an object whose ``type`` is ``boolean``, ``string`` (without ``contentEncoding``),
  ``number``, ``integer`` or ``object`` (recursively);
- anything else throws: ``"null"``, a list of types (``["number", "null"]``), a missing
  ``type``, an array of arrays, an array without ``items``.

Foxglove Studio's later parser also takes a property declared as ``oneOf`` alternatives with
numeric ``const`` values (an enumeration); Lichtblick's does not. The checker follows the
stricter of the two, so that a schema it accepts opens in both.
"""

from __future__ import annotations

from typing import Any

_SCALARS = {"boolean", "number", "integer"}


def problems(schema: Any, path: str = "$") -> list[str]:
    """What the viewers' parser would throw on, with where (empty: the schema parses)."""
    if not isinstance(schema, dict) or schema.get("type") != "object":
        got = schema.get("type") if isinstance(schema, dict) else schema
        return [f'{path}: expected "type": "object", got {got!r}']
    props = schema.get("properties")
    if not isinstance(props, dict):
        return [f"{path}: no properties object"]
    found: list[str] = []
    for name, field in props.items():
        where = f"{path}.{name}"
        if not isinstance(field, dict):
            found.append(f"{where}: not a schema")
            continue
        if "oneOf" in field:
            found.append(f"{where}: oneOf (an enumeration) is not parsed by Lichtblick")
            continue
        kind = field.get("type")
        if not isinstance(kind, str):
            found.append(f"{where}: type must be one string, got {kind!r}")
        elif kind in _SCALARS:
            pass
        elif kind == "string":
            if field.get("contentEncoding") not in (None, "base64"):
                found.append(f"{where}: contentEncoding {field['contentEncoding']!r}")
        elif kind == "object":
            found.extend(problems(field, where))
        elif kind == "array":
            items = field.get("items")
            if not isinstance(items, dict):
                found.append(f"{where}: array without an items schema")
                continue
            item_kind = items.get("type")
            if item_kind in _SCALARS:
                pass
            elif item_kind == "string":
                if items.get("contentEncoding") is not None:
                    found.append(f"{where}[]: contentEncoding on array items")
            elif item_kind == "object":
                found.extend(problems(items, f"{where}[]"))
            else:
                found.append(f"{where}[]: unsupported array item type {item_kind!r}")
        else:
            found.append(f"{where}: unsupported type {kind!r}")
    return found
