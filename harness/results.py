"""Typed results that are written as JSON: frozen dataclasses read by attribute, written and read back by one rule.

A gate command (compare, regress, replay) returns a frozen dataclass whose fields are its JSON file's keys, nested
dataclasses for nested objects. `Result.to_json()` gives the JSON-ready dict (`harness.files.atomic_write_json`
rounds and writes it, so the file is what the command always wrote); `Result.from_json(data)` builds the dataclass
again from such a dict (a stored compare.json, say), converting by the field types: nested dataclasses, `dict[str,
X]`, `tuple[X, ...]`, enums and optional values. A field whose key a file holds only sometimes defaults to `ABSENT`
and is left out of the dict while it is ABSENT (a key written as null is None, not ABSENT).
"""
from __future__ import annotations

import dataclasses
import enum
import types
import typing
from typing import Any


class _Absent:
    """The value of a field whose key the JSON file does not hold (falsy; left out by `to_json`)."""

    _instance = None

    def __new__(cls):
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __bool__(self) -> bool:
        return False

    def __repr__(self) -> str:
        return "ABSENT"


ABSENT: Any = _Absent()


def present(value) -> bool:
    """Whether a field's key is in the file (its value may still be None)."""
    return value is not ABSENT


def to_plain(value):
    """Dataclasses to dicts (ABSENT fields left out), enums to their values, tuples to lists; the rest as it is."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_plain(getattr(value, f.name)) for f in dataclasses.fields(value)
                if getattr(value, f.name) is not ABSENT}
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, dict):
        return {k: to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    return value


def from_plain(hint, value):
    """A JSON value converted to the type `hint` (see the module docstring); values of other types pass through."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None:
            return None
        for arg in args:
            if arg is type(None) or arg is _Absent:
                continue
            if dataclasses.is_dataclass(arg) and isinstance(value, dict):
                return build(arg, value)
            if isinstance(arg, type) and issubclass(arg, enum.Enum) and value in {m.value for m in arg}:
                return arg(value)
            if typing.get_origin(arg) in (dict, tuple, list) and isinstance(value, (dict, list)):
                return from_plain(arg, value)
        return value
    if dataclasses.is_dataclass(hint) and isinstance(value, dict):
        return build(hint, value)
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        return hint(value)
    if origin is dict and isinstance(value, dict):
        return {k: from_plain(args[1], v) for k, v in value.items()} if args else dict(value)
    if origin is tuple and isinstance(value, list):
        return tuple(from_plain(args[0], v) for v in value) if args else tuple(value)
    if origin is list and isinstance(value, list):
        return [from_plain(args[0], v) for v in value] if args else list(value)
    return value


def build(cls, data: dict):
    """An instance of the dataclass `cls` from a JSON object; a key the object lacks takes the field's default
    (ABSENT for keys a file holds only sometimes); unknown keys are refused (one line)."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown key(s) {', '.join(unknown)}")
    return cls(**{name: from_plain(hints[name], value) for name, value in data.items()})


class Result:
    """Mixin of a frozen dataclass written as JSON: `to_json()` and `from_json(data)`."""

    def to_json(self) -> dict:
        """The JSON-ready dict of this result (the file's schema: one key per field, ABSENT fields left out)."""
        return to_plain(self)

    @classmethod
    def from_json(cls, data: dict):
        """This result from a JSON object as `to_json` writes it (a file read back)."""
        return build(cls, data)
