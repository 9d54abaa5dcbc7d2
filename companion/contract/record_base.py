"""The machinery of the flight-log records (:mod:`companion.contract.records`): a frozen
dataclass base whose fields are a message's JSON keys, in order, and the JSON schema derived
from those fields.

A record's field is written as its key in declaration order, so the dataclass *is* the message
layout (mcap's ``records.py`` is the model). A field whose default is :data:`ABSENT` is left out
of the message while it holds ``ABSENT`` ("not in this message", as in logs written before the
field existed); ``None`` is written as ``null`` ("in the message, not defined"). A float that is
not finite is written as ``null`` too (JSON has no NaN): float fields are ``number | null`` in
the schema. Every message also carries :data:`TIME_S`, the sim-time stamp the log writer puts
first; it is no record's field unless the record has its own ``time_s``.

The schema (:meth:`LogRecord.json_schema`) is what the log writer puts in the MCAP schema
record: jsonschema, ``title`` = the schema name, one property per field, ``required`` = the
fields that are never left out.
"""

from __future__ import annotations

import enum
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import MISSING, dataclass, fields
from typing import Any, ClassVar, Final, TypeVar

import numpy as np

__all__ = [
    "ABSENT",
    "RECORD",
    "TIME_S",
    "Absent",
    "LogRecord",
    "RecordError",
    "Vector",
]

TIME_S: Final = "time_s"
"""The key of every message's sim-time stamp (seconds), written first by the log writer."""


class Absent:
    """The type of :data:`ABSENT`: a field left out of the message."""

    _instance: ClassVar[Absent | None] = None

    def __new__(cls) -> Absent:
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __repr__(self) -> str:
        return "ABSENT"

    def __reduce__(self) -> str:
        return "ABSENT"


ABSENT: Final = Absent()
"""A field's value meaning "not in this message" (its key is left out; ``None`` is ``null``)."""


Vector = np.ndarray | Sequence[float]
"""A vector field: a numpy array (or list) when written, a list of numbers (null = NaN) read."""

RECORD: Final = types.MappingProxyType({"frozen": True, "kw_only": True, "slots": True})
"""The dataclass options of every record: ``@dataclass(**RECORD)``."""


class RecordError(ValueError):
    """A message that does not match its record (a required key missing, a bad nested value)."""


R = TypeVar("R", bound="LogRecord")

_Layout = tuple[tuple[str, "type[LogRecord] | None", bool], ...]
_LAYOUTS: dict[type, _Layout] = {}


def _record_type(hint: Any) -> type[LogRecord] | None:
    """The LogRecord class a field holds (alone or in a union with None/Absent), else None."""
    for arg in typing.get_args(hint) or (hint,):
        if isinstance(arg, type) and issubclass(arg, LogRecord):
            return arg
    return None


def _layout(cls: type[LogRecord]) -> _Layout:
    """``(name, nested record class or None, required)`` per field, in order (cached)."""
    layout = _LAYOUTS.get(cls)
    if layout is None:
        hints = typing.get_type_hints(cls)
        layout = tuple(
            (
                f.name,
                _record_type(hints[f.name]),
                f.default is MISSING and f.default_factory is MISSING,
            )
            for f in fields(cls)
        )
        _LAYOUTS[cls] = layout
    return layout


@dataclass(frozen=True, kw_only=True, slots=True)
class LogRecord:
    """One flight-log message: its fields are the message's keys, in order.

    Subclasses are ``@dataclass(frozen=True, kw_only=True, slots=True)`` and set ``SCHEMA``
    (the MCAP schema name; nested parts such as a timestamp set none).
    """

    SCHEMA: ClassVar[str] = ""

    def to_dict(self) -> dict[str, Any]:
        """The message body: every field not :data:`ABSENT`, nested records as dicts (values
        as given: the log writer makes them JSON, numpy and NaN included)."""
        out: dict[str, Any] = {}
        for name, nested, _ in _layout(type(self)):
            value = getattr(self, name)
            if value is ABSENT:
                continue
            out[name] = value.to_dict() if nested is not None and value is not None else value
        return out

    @classmethod
    def from_dict(cls: type[R], data: Mapping[str, Any]) -> R:
        """The record of a logged message (values as JSON gave them: lists, not arrays; a
        key the record does not declare, such as :data:`TIME_S`, is ignored).

        Raises:
            RecordError: a required key is missing, or a nested part is not an object.
        """
        kwargs: dict[str, Any] = {}
        for name, nested, required in _layout(cls):
            if name not in data:
                if required:
                    raise RecordError(
                        f"{cls.SCHEMA or cls.__name__}: message has no {name!r} "
                        f"(keys: {sorted(data)})"
                    )
                continue
            value = data[name]
            if nested is not None and value is not None:
                if not isinstance(value, Mapping):
                    raise RecordError(
                        f"{cls.SCHEMA or cls.__name__}.{name}: expected an object, got {value!r}"
                    )
                value = nested.from_dict(value)
            kwargs[name] = value
        return cls(**kwargs)

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """The message's keys, in order (those left out when ABSENT included)."""
        return tuple(name for name, _, _ in _layout(cls))

    @classmethod
    def required_field_names(cls) -> tuple[str, ...]:
        """The keys every message has (no default), in order."""
        return tuple(name for name, _, required in _layout(cls) if required)

    @classmethod
    def json_schema(cls) -> dict[str, Any]:
        """The jsonschema of this record's messages, derived from its fields."""
        hints = typing.get_type_hints(cls)
        props: dict[str, Any] = {}
        required: list[str] = []
        for f in fields(cls):
            prop = _schema_of(hints[f.name])
            prop.update(f.metadata.get("schema", {}))
            props[f.name] = prop
            if f.default is MISSING and f.default_factory is MISSING:
                required.append(f.name)
        if cls.SCHEMA and TIME_S not in props:  # a message's stamp, which the writer adds
            props = {TIME_S: {"type": "number"}, **props}
            required.insert(0, TIME_S)
        schema: dict[str, Any] = {"type": "object", "properties": props}
        if cls.SCHEMA:
            schema = {"title": cls.SCHEMA, **schema}
        if required:
            schema["required"] = required
        return schema


_ANY_NUMBER = {"type": ["number", "null"]}  # a non-finite float is written as null


def _schema_of(hint: Any) -> dict[str, Any]:
    """The jsonschema of one field's type annotation."""
    origin = typing.get_origin(hint)
    if origin is typing.Union or origin is types.UnionType:
        args = [a for a in typing.get_args(hint) if a is not Absent]
        nullable = type(None) in args
        args = [a for a in args if a is not type(None)]
        if np.ndarray in args:  # a vector given as an array or a sequence of floats
            args = [np.ndarray]
        if len(args) != 1:
            return {}
        inner = _schema_of(args[0])
        if nullable and isinstance(inner.get("type"), str):
            inner["type"] = [inner["type"], "null"]
        elif nullable and "type" not in inner:
            inner = {"anyOf": [inner, {"type": "null"}]}
        return inner
    if hint is np.ndarray:
        return {"type": "array", "items": dict(_ANY_NUMBER)}
    if isinstance(hint, type) and issubclass(hint, LogRecord):
        return hint.json_schema()
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        return {"type": "string", "enum": [m.value for m in hint]}
    if hint is bool:
        return {"type": "boolean"}
    if hint is int:
        return {"type": "integer"}
    if hint is float:
        return dict(_ANY_NUMBER)
    if hint is str:
        return {"type": "string"}
    if origin in (list, tuple, Sequence) or hint in (list, tuple):
        args = [a for a in typing.get_args(hint) if a is not Ellipsis]
        return {"type": "array", "items": _schema_of(args[0]) if args else {}}
    if origin in (dict, Mapping) or hint in (dict, Mapping):
        return {"type": "object"}
    return {}
