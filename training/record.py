"""Typed JSON records: frozen dataclasses that read and write one exact JSON layout.

A record class is a frozen dataclass deriving from :class:`Record`. Its fields, in declaration
order, are the keys of its JSON object; their annotations say what each key holds (``str``,
``int``, ``float``, ``bool``, ``X | None``, ``tuple[X, ...]`` for a JSON list, ``tuple[X, Y]``
for a fixed-length list, ``dict[str, X]``, another record, or ``Any`` for data kept verbatim).
``to_dict`` writes the object in field order; ``from_dict`` reads it back and raises
:class:`RecordError` naming the source, the field path, what was expected and what it got — for
a missing key, a wrong type and an unknown key alike (nothing is dropped silently).

Field metadata (``dataclasses.field(metadata=...)``):

- ``omit_none``: the key is absent when the value is None (a missing key reads as None);
- ``prefix``: a ``dict[str, X]`` field whose entries are spread into the object as
  ``<prefix><name>`` keys (the keys of the object starting with the prefix read back into it);
- ``inline``: a record field whose keys are spread into the object (its own keys, in its order,
  where the field stands), so records that share a group of keys declare it once;
- ``what``: how an error names the expected value (e.g. ``"[north, east] in m"``);
- ``added``: a key added after records were written; a missing one reads as the field's
  default, which must be the behaviour before the key existed (e.g. a profile key that is off
  by default).
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from collections.abc import Sequence
from typing import Any, TypeVar

__all__ = ["Record", "RecordError"]

R = TypeVar("R", bound="Record")
_Keys = tuple[str | int, ...]


class RecordError(ValueError):
    """A JSON record does not have its class's layout: names the source, field, expected, got."""


def where(source: str, keys: Sequence[str | int]) -> str:
    """``"<source>: field a.b[2].c"`` (just the source for the top level)."""
    if not keys:
        return str(source)
    name = "".join(f"[{k}]" if isinstance(k, int) else f".{k}" for k in keys).lstrip(".")
    return f"{source}: field {name}"


def _is_record(tp: Any) -> bool:
    return isinstance(tp, type) and issubclass(tp, Record)


def _optional(tp: Any) -> Any | None:
    """``X`` for ``X | None``, else None."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(tp)) == 2:
            return args[0]
    return None


def describe(tp: Any) -> str:
    """How an error names a value of type ``tp``."""
    inner = _optional(tp)
    if inner is not None:
        return f"{describe(inner)} or null"
    origin = typing.get_origin(tp)
    if tp is str:
        return "a string"
    if tp is bool:
        return "true or false"
    if tp is int:
        return "an integer"
    if tp is float:
        return "a number"
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_plural(args[0])}"
        return f"a list of {len(args)} values"
    if origin is dict or _is_record(tp):
        return "an object"
    return "a JSON value"


def _plural(tp: Any) -> str:
    d = describe(tp)
    for article in ("an ", "a "):
        if d.startswith(article):
            return d[len(article) :] + "s" if " or " not in d else d[len(article) :]
    return d


def _bad(source: str, keys: _Keys, what: str, value: Any) -> RecordError:
    return RecordError(f"{where(source, keys)}: expected {what}, got {value!r:.60}")


def _read(tp: Any, value: Any, source: str, keys: _Keys, what: str | None = None) -> Any:
    """``value`` read as ``tp``; ``what`` names it in an error at this level (default: the type)."""
    inner = _optional(tp)
    if inner is not None:
        return None if value is None else _read(inner, value, source, keys, what or describe(tp))
    if tp is Any:
        return value
    if _is_record(tp):
        return tp.from_dict(value, source, keys)
    origin = typing.get_origin(tp)
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list):
            raise _bad(source, keys, what or describe(tp), value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_read(args[0], v, source, (*keys, i)) for i, v in enumerate(value))
        if len(value) != len(args):
            raise _bad(source, keys, what or describe(tp), value)
        return tuple(
            _read(a, v, source, (*keys, i))
            for i, (a, v) in enumerate(zip(args, value, strict=True))
        )
    if origin is dict:
        _, item = typing.get_args(tp)
        if not isinstance(value, dict):
            raise _bad(source, keys, what or describe(tp), value)
        return {k: _read(item, v, source, (*keys, k)) for k, v in value.items()}
    ok = {
        str: lambda v: isinstance(v, str),
        bool: lambda v: isinstance(v, bool),
        int: lambda v: isinstance(v, int) and not isinstance(v, bool),
        float: lambda v: isinstance(v, int | float) and not isinstance(v, bool),
    }.get(tp)
    if ok is None:
        raise TypeError(f"record field type {tp!r} is not supported")
    if not ok(value):
        raise _bad(source, keys, what or describe(tp), value)
    return value  # as written: an integer stays an integer, so the JSON round-trips exactly


def _write(value: Any) -> Any:
    if isinstance(value, Record):
        return value.to_dict()
    if isinstance(value, tuple | list):
        return [_write(v) for v in value]
    if isinstance(value, dict):
        return {k: _write(v) for k, v in value.items()}
    return value


class Record:
    """Base of the typed records (a mixin for frozen dataclasses; see the module doc)."""

    @classmethod
    def _fields(cls) -> list[tuple[dataclasses.Field, Any]]:
        cache = cls.__dict__.get("_record_fields")
        if cache is None:
            hints = typing.get_type_hints(cls)
            cache = [(f, hints[f.name]) for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
            cls._record_fields = cache  # type: ignore[attr-defined]
        return cache

    def to_json(self, indent: int | None = 2) -> str:
        """The JSON document of :meth:`to_dict` (NaN and numpy values as ``jsonable`` writes
        them: NaN is null, "not defined")."""
        from companion.flightlog import jsonable

        return json.dumps(jsonable(self.to_dict()), indent=indent)

    def to_dict(self) -> dict[str, Any]:
        """The JSON object, keys in field order."""
        out: dict[str, Any] = {}
        for f, _ in self._fields():
            value = getattr(self, f.name)
            if f.metadata.get("prefix"):
                out.update({f"{f.metadata['prefix']}{k}": _write(v) for k, v in value.items()})
            elif f.metadata.get("inline"):
                out.update(value.to_dict())
            elif value is None and f.metadata.get("omit_none"):
                continue
            else:
                out[f.name] = _write(value)
        return out

    @classmethod
    def from_dict(cls: type[R], data: Any, source: str = "record", keys: _Keys = ()) -> R:
        """Read ``data`` (parsed JSON); :class:`RecordError` names ``source`` and the field."""
        if not isinstance(data, dict):
            what = f"a JSON object ({cls.__name__})"
            if not keys:
                raise RecordError(f"{source}: expected {what}, got {type(data).__name__}")
            raise _bad(source, keys, what, data)
        fields = cls._fields()
        inline = {
            f.name: {g.name for g, _ in tp._fields()}
            for f, tp in fields
            if f.metadata.get("inline")
        }
        names = {f.name for f, _ in fields if not f.metadata.get("prefix") and f.name not in inline}
        names.update(*inline.values())
        prefixes = [f.metadata["prefix"] for f, _ in fields if f.metadata.get("prefix")]
        unknown = [k for k in data if k not in names and not any(k.startswith(p) for p in prefixes)]
        if unknown:
            raise RecordError(
                f"{where(source, keys)}: unexpected field(s) {', '.join(map(repr, unknown))}; "
                f"a {cls.__name__} has {', '.join(sorted(names))}"
            )
        kwargs = {}
        for f, tp in fields:
            what = f.metadata.get("what")
            prefix = f.metadata.get("prefix")
            at = (*keys, f.name)
            if prefix:
                spread = {k[len(prefix) :]: v for k, v in data.items() if k.startswith(prefix)}
                kwargs[f.name] = _read(tp, spread, source, keys)
                continue
            if f.name in inline:
                own = {k: v for k, v in data.items() if k in inline[f.name]}
                kwargs[f.name] = tp.from_dict(own, source, keys)
                continue
            if f.name not in data:
                if f.metadata.get("omit_none"):
                    kwargs[f.name] = None
                    continue
                if f.metadata.get("added") and f.default is not dataclasses.MISSING:
                    kwargs[f.name] = f.default
                    continue
                raise RecordError(
                    f"{where(source, at)} is missing; expected {what or describe(tp)}"
                )
            try:
                kwargs[f.name] = _read(tp, data[f.name], source, at)
            except RecordError:
                if what is None:
                    raise
                raise _bad(source, at, what, data[f.name]) from None
        return cls(**kwargs)
