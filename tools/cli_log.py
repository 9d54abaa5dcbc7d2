"""``visland log info`` and ``visland log plot``: look into an MCAP flight log (SITL, rollout or
companion). Thin shells over :func:`tools.logtool.log_info` and
:func:`tools.log_plots.plot_flight`."""

from __future__ import annotations

import argparse
from pathlib import Path

from tools.cli_args import add_live_argument, json_command, print_result

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


def _cmd_log_replay(args: argparse.Namespace) -> int:
    from tools.cli_args import config_from_args, print_json
    from tools.log_replay import ReplayConfig, replay_live

    cfg = config_from_args(ReplayConfig, args)
    print(f"visland log replay: {args.file} on ws://{args.live} (Foxglove: Open connection)")
    report = replay_live(cfg)
    if args.json:
        print_json(report.to_dict())
    else:
        print(
            f"replayed {report.frames} frames and {report.events} events, {report.sim_s:.1f} s "
            f"of flight in {report.wall_s:.1f} s"
            + ("" if report.watched else " (no client subscribed)")
        )
    return 0


def _cmd_log_scene(args: argparse.Namespace) -> int:
    from companion.live.scene_log import add_scene
    from tools.cli_args import print_json

    if args.out is not None and len(args.file) > 1:
        raise SystemExit("visland log scene: --out takes one FILE; got several")
    reports = [add_scene(f, args.out, args.policy) for f in args.file]
    if args.json:
        print_json([r.to_dict() for r in reports])
    for r in reports if not args.json else ():
        print(
            f"wrote {r.file}: {r.messages} messages of the live view's scene for {r.frames} "
            f"frames and {r.events} events"
            + (f" (policy {r.policy} run again)" if r.policy else "")
            + (" (a truncated log: its readable part)" if r.truncated else "")
        )
    return 0


def _cmd_log_frame(args: argparse.Namespace) -> int:
    from tools.cli_args import print_json
    from tools.log_frame import plot_frame

    r = plot_frame(args.file, args.out, args.time, args.policy)
    if args.json:
        print_json(r.to_dict())
        return 0
    print(
        f"wrote {r.out}: frame {r.frame} of {r.frames} at t = {r.time_s:.1f} s ({r.why})"
        + ("" if r.estimate_error_m is None else f"; estimate {r.estimate_error_m:.1f} m off")
        + ("" if r.pad_probability is None else f"; pad p = {r.pad_probability:.2f}")
    )
    return 0


def register_log(sub: argparse._SubParsersAction) -> None:
    """Add ``log`` (``info``, ``plot``, ``frame``, ``replay``, ``scene``) to the ``visland``
    subcommands."""
    lg = sub.add_parser(
        "log", help="look into an MCAP flight log: info, plot, frame, replay, scene"
    )
    lg_sub = lg.add_subparsers(dest="what", required=True)
    li = lg_sub.add_parser("info", help="topics, counts, schemas, duration, metadata, result")
    li.add_argument("file", type=Path, help="MCAP flight log (SITL, rollout or companion)")
    json_command(li, _cmd_log_info)
    lp = lg_sub.add_parser(
        "plot", help="PNG: top view, altitude, attitude and commands vs time (matplotlib Agg)"
    )
    lp.add_argument("file", type=Path, help="MCAP flight log (SITL, rollout or companion)")
    lp.add_argument("--out", type=Path, default=None, help="PNG path (default: FILE's stem.png)")
    lp.set_defaults(func=_cmd_log_plot)
    lr = lg_sub.add_parser(
        "replay",
        help="play a recorded flight live in Foxglove: camera, scene, transforms, time series",
    )
    lr.add_argument("file", type=Path, help="MCAP flight log (SITL, rollout or companion)")
    add_live_argument(lr, "the replay serves it")
    lr.set_defaults(live="8765")
    lr.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="times the flight's own pace; 0: no pauses (default 1)",
    )
    lr.add_argument(
        "--policy",
        default=None,
        help="a vision checkpoint run again on the logged observations to draw its CNN bearing "
        "and estimate (default: a companion log's own policy, if it is a file; else none)",
    )
    lr.add_argument(
        "--wait-s",
        type=float,
        default=10.0,
        help="wait this long for a Foxglove client before playing (default 10; 0: at once)",
    )
    json_command(lr, _cmd_log_replay)
    ls = lg_sub.add_parser(
        "scene",
        help="add the live view's channels to a flight log (camera annotations, 3D scene, "
        "transforms, time series, events as foxglove.Log), so it opens in Foxglove with "
        "docs/foxglove/visland.json as a live flight does",
    )
    ls.add_argument("file", type=Path, nargs="+", help="MCAP flight log(s), rewritten in place")
    ls.add_argument("--out", type=Path, default=None, help="write here instead (one FILE)")
    ls.add_argument(
        "--policy",
        default=None,
        help="a vision checkpoint run again on the logged observations to draw its CNN bearing "
        "and estimate (default: the log's own /policy/estimate, or a companion log's policy)",
    )
    json_command(ls, _cmd_log_scene)
    lf = lg_sub.add_parser(
        "frame",
        help="PNG of one moment: the camera frame with the live view's annotations, and the "
        "scene from above (default: where the estimate was furthest from the truth)",
    )
    lf.add_argument("file", type=Path, help="MCAP flight log (SITL, rollout or companion)")
    lf.add_argument("--time", type=float, default=None, help="the frame nearest this time (s)")
    lf.add_argument(
        "--out", type=Path, default=None, help="PNG path (default: FILE's stem_frame.png)"
    )
    lf.add_argument(
        "--policy", default=None, help="a vision checkpoint run again (as for log scene)"
    )
    json_command(lf, _cmd_log_frame)
