"""``visland log info`` and ``visland log plot``: look into an MCAP flight log (SITL, rollout or
companion). Thin shells over :func:`tools.logtool.log_info` and
:func:`tools.log_plots.plot_flight`."""

from __future__ import annotations

import argparse
from pathlib import Path

from tools.cli_args import print_result

__all__ = ["register_log"]


def _cmd_log_info(args: argparse.Namespace) -> int:
    from tools.logtool import format_info, log_info

    info = log_info(args.file)
    print_result(info, args.json, lambda i, out: print(format_info(i), file=out))
    return 0


def _cmd_log_plot(args: argparse.Namespace) -> int:
    from tools.log_plots import plot_flight

    report = plot_flight(args.file, args.out)
    print(f"wrote {report.out} ({report.kind} log)")
    for line in report.missing:
        print(f"  missing {line}")
    if report.truncated:
        print(f"  truncated log: plotted its readable prefix ({report.error})")
    return 0


def register_log(sub: argparse._SubParsersAction) -> None:
    """Add ``log`` (``info``, ``plot``) to the ``visland`` subcommands."""
    lg = sub.add_parser("log", help="look into an MCAP flight log: info, plot")
    lg_sub = lg.add_subparsers(dest="what", required=True)
    li = lg_sub.add_parser("info", help="topics, counts, schemas, duration, metadata, result")
    li.add_argument("file", type=Path, help="MCAP flight log (SITL, rollout or companion)")
    li.add_argument("--json", action="store_true", help="print one JSON object")
    li.set_defaults(func=_cmd_log_info)
    lp = lg_sub.add_parser(
        "plot", help="PNG: top view, altitude, attitude and commands vs time (matplotlib Agg)"
    )
    lp.add_argument("file", type=Path, help="MCAP flight log (SITL, rollout or companion)")
    lp.add_argument("--out", type=Path, default=None, help="PNG path (default: FILE's stem.png)")
    lp.set_defaults(func=_cmd_log_plot)
