"""Load a protocol file: YAML -> :class:`~dentibot.protocol.schema.Protocol`, read strictly
(:mod:`dentibot.yamlfile`), with errors that name the file, the line, the field, the value
and the allowed range or choices.

Errors are collected (all of them, not only the first) into one :class:`ProtocolFileError`
before anything starts; the cross-field checks of the schema (working length against the
file, limits against the file's strength, step order, total duration) come with the line of
the field they name.
"""

from __future__ import annotations

from pathlib import Path

from dentibot.protocol.schema import Protocol
from dentibot.yamlfile import YamlFileError, describe_error, load, loads

__all__ = ["ProtocolFileError", "describe_error", "load_protocol", "parse_protocol"]


class ProtocolFileError(YamlFileError):
    """A protocol file is malformed or invalid; ``problems`` lists every (line, field, text)."""

    kind = "protocol"


def parse_protocol(text: str, path: str = "<protocol>") -> Protocol:
    """Validate protocol ``text``; raises :class:`ProtocolFileError`."""
    return loads(text, Protocol, path, ProtocolFileError)


def load_protocol(path: str | Path) -> Protocol:
    """Read and validate the protocol file ``path``; raises :class:`ProtocolFileError`."""
    return load(path, Protocol, ProtocolFileError)
