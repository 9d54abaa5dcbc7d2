"""Typed options: one frozen dataclass per entry point whose fields are its ``--flags`` (and,
for the companion, its TOML keys), each field's help becoming ``--help`` (as cleanrl's ``Args``
and PX4's ``module.yaml``).

A field is declared with :func:`option` (default, help, optional argparse type, choices and
range); it is also a key of the one table reader (:mod:`companion.table`), so a TOML table of
the same fields is read and checked by it (``read_values``; the companion's ``[companion]``), and
a record built from flags is range-checked the same way. :func:`add_arguments` makes one
``--flag`` per field (underscores become dashes, booleans get ``--flag/--no-flag``);
:func:`values_from_args` reads them back.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

from companion.table import Key, key_field

__all__ = ["add_arguments", "option", "redacted_dict", "values_from_args"]


def _options(cls_or_obj: Any) -> list[dataclasses.Field]:
    """The fields declared by :func:`option` (not a section's ``source``)."""
    return [f for f in dataclasses.fields(cls_or_obj) if "help" in f.metadata]


def redacted_dict(config: Any, secrets: tuple[str, ...] = ("signing_key",)) -> dict[str, Any]:
    """The options of ``config`` as a dict with each set secret field replaced by ``"<set>"`` (what
    flight logs and reports record of a config: never the key itself)."""
    d = {f.name: getattr(config, f.name) for f in _options(config)}
    for name in secrets:
        if d.get(name) is not None:
            d[name] = "<set>"
    return d


def option(
    default: Any,
    help: str,
    arg_type: type | None = None,
    choices: tuple[Any, ...] | None = None,
    *,
    repeatable: bool = False,
    unit: str = "",
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
) -> Any:
    """A dataclass field that is also a command-line flag and a table key (``arg_type`` where
    the default's type does not say it, e.g. ``None`` defaults; ``unit``, ``lo``, ``hi``,
    ``lo_open``: a number's unit and range, checked as a table key's). ``repeatable``: a string
    flag that may be given several times, its values joined by commas into the field (``--param
    A=1 --param B=2`` is ``"A=1,B=2"``, as ``--param A=1,B=2``)."""
    kind = arg_type or type(default)
    if kind is bool:
        key = Key("boolean", "", help)
    elif kind in (int, float):
        noun = "an integer" if kind is int else "a number"
        key = Key("integer" if kind is int else "number", unit, help, lo, hi, lo_open, noun=noun)
    elif choices:
        key = Key("choice", "", help, choices=tuple(choices))
    else:
        key = Key("text", "", help)
    return key_field(
        key, default, help=help, arg_type=arg_type, choices=choices, repeatable=repeatable
    )


def _arg_type(f: dataclasses.Field) -> type:
    return f.metadata.get("arg_type") or type(f.default)


def _help(f: dataclasses.Field, default: Any) -> str:
    """The field's help with its default said once: a help that names its own default
    (``"(default: centre)"``) keeps it; none (``None``) is not worth saying."""
    text = f.metadata["help"]
    if f.metadata.get("repeatable"):
        text += "; repeatable, each NAME=VALUE or NAME=VALUE,NAME=VALUE"
    if "default" in text or default is None:
        return text
    return f"{text} (default: {default})"


def add_arguments(
    parser: argparse.ArgumentParser,
    cls: type,
    *,
    unset_is_none: bool = False,
    defaults: dict[str, Any] | None = None,
) -> None:
    """One ``--flag`` per field of the dataclass ``cls``; its help says the default.

    ``unset_is_none``: a flag not given parses as ``None`` (so a config file may fill it in)
    instead of the field's default. ``defaults``: the command's own default of some fields
    (``visland sitl``'s seed is the evaluation seed), said in their help.
    """
    defaults = defaults or {}
    for f in _options(cls):
        flag = "--" + f.name.replace("_", "-")
        shown = defaults.get(f.name, f.default)
        help_text = _help(f, shown)
        default = None if unset_is_none else shown
        if isinstance(f.default, bool):
            parser.add_argument(
                flag, action=argparse.BooleanOptionalAction, default=default, help=help_text
            )
        elif f.metadata.get("repeatable"):
            parser.add_argument(flag, action="append", type=str, default=None, help=help_text)
        else:
            parser.add_argument(
                flag,
                type=_arg_type(f),
                default=default,
                help=help_text,
                choices=f.metadata.get("choices"),
            )


def values_from_args(args: argparse.Namespace, cls: type) -> dict[str, Any]:
    """The parsed value of each field of ``cls`` that was given (``None``: not given, when the
    flags were added with ``unset_is_none``)."""
    values = {f.name: getattr(args, f.name, None) for f in _options(cls)}
    for f in _options(cls):
        if f.metadata.get("repeatable") and values[f.name] is not None:
            values[f.name] = ",".join(values[f.name])  # a list of the flag's values
    return {k: v for k, v in values.items() if v is not None}
