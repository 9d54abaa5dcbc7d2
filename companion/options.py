"""Typed options: one frozen dataclass per entry point whose fields are its ``--flags`` (and,
for the companion, its TOML keys), each field's help becoming ``--help`` (as cleanrl's ``Args``
and PX4's ``module.yaml``).

A field is declared with :func:`option` (default, help, optional argparse type and choices);
:func:`add_arguments` makes one ``--flag`` per field (underscores become dashes, booleans get
``--flag/--no-flag``); :func:`values_from_args` reads them back; :func:`check_table` checks a TOML
table against the same fields (unknown key, wrong type, value not among the choices), naming the
file and key.
"""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

__all__ = ["add_arguments", "check_table", "option", "redacted_dict", "values_from_args"]


def redacted_dict(config: Any, secrets: tuple[str, ...] = ("signing_key",)) -> dict[str, Any]:
    """``dataclasses.asdict(config)`` with each set secret field replaced by ``"<set>"`` (what
    flight logs and reports record of a config: never the key itself)."""
    d = dataclasses.asdict(config)
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
) -> Any:
    """A dataclass field that is also a command-line flag (``arg_type`` where the default's
    type does not say it, e.g. ``None`` defaults). ``repeatable``: a string flag that may be
    given several times, its values joined by commas into the field (``--param A=1 --param
    B=2`` is ``"A=1,B=2"``, as ``--param A=1,B=2``)."""
    return dataclasses.field(
        default=default,
        metadata={
            "help": help,
            "arg_type": arg_type,
            "choices": choices,
            "repeatable": repeatable,
        },
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
    for f in dataclasses.fields(cls):
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
    values = {f.name: getattr(args, f.name, None) for f in dataclasses.fields(cls)}
    for f in dataclasses.fields(cls):
        if f.metadata.get("repeatable") and values[f.name] is not None:
            values[f.name] = ",".join(values[f.name])  # a list of the flag's values
    return {k: v for k, v in values.items() if v is not None}


def check_table(
    table: dict[str, Any], cls: type, where: str, error: type[Exception]
) -> dict[str, Any]:
    """``table`` (a TOML table) checked against the fields of ``cls``: every key a field, every
    value of the field's type (an integer is taken where a float is expected) and among its
    choices. Returns the table with those integers made floats.

    Raises:
        error: naming ``where`` (e.g. ``"companion.toml: [companion]"``), the key, the expected
            and the given value.
    """
    fields = {f.name: f for f in dataclasses.fields(cls)}
    out = dict(table)
    for key, value in table.items():
        f = fields.get(key)
        if f is None:
            raise error(f"{where} {key}: unknown key; known: {sorted(fields)}")
        expected = _arg_type(f)
        if expected is float and isinstance(value, int) and not isinstance(value, bool):
            out[key] = float(value)
        elif not isinstance(value, expected) or (expected is int and isinstance(value, bool)):
            raise error(f"{where} {key} = {value!r}; expected {expected.__name__}")
        choices = f.metadata.get("choices")
        if choices and value not in choices:
            raise error(f"{where} {key} = {value!r}; expected one of {choices}")
    return out
