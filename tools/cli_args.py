"""What ``visland``'s commands share: the flags several of them take, written once, and how a
command prints its result (one JSON document, or the human-readable table)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

__all__ = [
    "HelpFormatter",
    "add_deprecated_alias",
    "add_episode_arguments",
    "add_parallel_arguments",
    "config_from_args",
    "json_command",
    "print_json",
    "print_result",
    "scenario_arg",
]


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Every option's help says its default once: argparse's "(default: X)" where the help does
    not already name its default, and nothing for a flag (off) or an unset (None) default."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text or action.default in (None, False) or action.nargs == 0:
            return text
        return super()._get_help_string(action)


class _DeprecatedAlias(argparse.Action):
    """A hidden old spelling of a flag: it still works (same ``dest``), and warns on stderr
    with the new spelling."""

    def __init__(self, option_strings, dest, new: str, append: bool = False, **kwargs) -> None:
        super().__init__(option_strings, dest, help=argparse.SUPPRESS, **kwargs)
        self.new = new
        self.append = append

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        print(
            f"{parser.prog}: warning: {option_string} is deprecated; use {self.new}",
            file=sys.stderr,
        )
        if self.append:
            values = [*(getattr(namespace, self.dest, None) or []), values]
        setattr(namespace, self.dest, values)


def add_deprecated_alias(
    p: argparse.ArgumentParser | Any,
    old: str,
    new: str,
    dest: str,
    *,
    type: Callable[[str], Any] = str,
    append: bool = False,
) -> None:
    """``old`` as a hidden, warning alias of the flag ``new`` (whose value lands in ``dest``;
    ``append``: a repeatable flag)."""
    p.add_argument(old, dest=dest, type=type, new=new, append=append, action=_DeprecatedAlias)


def json_command(
    p: argparse.ArgumentParser,
    func: Callable[[argparse.Namespace], int],
    help: str = "print one JSON object",
) -> None:
    """A command's last flag and its action: ``--json`` (``help``), and ``p`` runs ``func``."""
    p.add_argument("--json", action="store_true", help=help)
    p.set_defaults(func=func)


def print_json(obj: Any) -> None:
    """One JSON document on stdout (a typed report's :meth:`~training.record.Record.to_json`);
    NaN (e.g. no touchdown) is null: "not defined"."""
    from companion.flightlog import jsonable
    from training.record import Record

    print(obj.to_json() if isinstance(obj, Record) else json.dumps(jsonable(obj), indent=2))


def print_result(result: Any, as_json: bool, table: Callable[[Any, TextIO], None]) -> None:
    """``result`` as one JSON document (``--json``), else written by ``table`` to stdout."""
    if as_json:
        print_json(result)
    else:
        table(result, sys.stdout)


def add_episode_arguments(
    p: argparse.ArgumentParser,
    *,
    episodes: int | None,
    seed: int | None,
    episodes_help: str | None = None,
    seed_help: str | None = None,
) -> None:
    """``--episodes``, ``--seed``, ``--scenario``: which episodes of which scenario fly
    (episodes ``0..N-1`` of the seed's initial states)."""
    p.add_argument("--episodes", type=int, default=episodes, help=episodes_help)
    p.add_argument("--seed", type=int, default=seed, help=seed_help)
    p.add_argument(
        "--scenario", type=Path, default=None, help="scenario TOML (default configs/scenario.toml)"
    )


def add_parallel_arguments(p: argparse.ArgumentParser, workers_help: str | None = None) -> None:
    """``--workers N`` (local processes) and the backend's ``--ray`` / ``--shared-dir``."""
    from training.exec.choose import add_backend_arguments

    p.add_argument("--workers", type=int, default=1, help=workers_help)
    add_backend_arguments(p)


def add_live_argument(p: argparse.ArgumentParser, who: str) -> None:
    """``--live [HOST:]PORT``: a live view in Foxglove (:mod:`companion.live`)."""
    p.add_argument(
        "--live",
        metavar="[HOST:]PORT",
        default="",
        type=_live,
        help=f"serve a live view of the flight in Foxglove ({who}) on PORT (default host "
        "127.0.0.1; 8765 is Foxglove's port): open Foxglove, Open connection, ws://HOST:PORT, "
        "and load docs/foxglove/visland.json (needs 'visland[live]'; default: off)",
    )


def _live(text: str) -> str:
    from companion.live import parse_live

    if not text:  # the default: off
        return text
    try:
        parse_live(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def scenario_arg(args: argparse.Namespace) -> str | None:
    """``--scenario`` as the configs take it: a path string, None for the default."""
    return str(args.scenario) if args.scenario else None


def config_from_args(cls: type, args: argparse.Namespace | Any, **given: Any) -> Any:
    """The config dataclass ``cls`` from the flags named as its fields; ``given`` over them
    (the fields whose flag differs in name or type). ``args`` may also be another config: its
    fields named as ``cls``'s carry over."""
    names = [f.name for f in dataclasses.fields(cls) if f.name not in given]
    return cls(**{n: getattr(args, n) for n in names if hasattr(args, n)}, **given)
