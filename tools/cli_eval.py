"""``visland eval``, ``collect``, ``relabel`` and ``pictures``: fly policies over the scenario
in process and measure them (a benchmark suite included), record the expert's flights, label
flight logs with the expert, draw the worlds. Thin shells over :mod:`training.evaluate`,
:mod:`training.suite`, the backends' ``relabel`` and :mod:`tools.world_pictures`."""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tools.cli_args import (
    add_episode_arguments,
    add_parallel_arguments,
    config_from_args,
    print_json,
    print_result,
    scenario_arg,
)
from training.exec.transport import Transport
from training.seeds import EVAL_SEED

if TYPE_CHECKING:
    from training.exec.backend import Backend

__all__ = ["register_eval"]

_EVAL_EPISODES = 20
"""``visland eval``'s episodes without ``--suite``."""


def _flight_config(cls: type, args: argparse.Namespace, backend: Backend, **given: Any) -> Any:
    """``EvalConfig`` / ``CollectConfig`` from the command's flags, flown on ``backend``, with a
    progress bar unless ``--json``."""
    return config_from_args(
        cls, args, scenario=scenario_arg(args), progress=not args.json, backend=backend, **given
    )


def _cmd_eval_suite(args: argparse.Namespace) -> int:
    from training.evaluate import EvalConfig
    from training.exec.choose import backend_from_args
    from training.suite import (
        format_suite_table,
        load_suite,
        plot_suite,
        run_suite,
        suite_markdown,
    )

    clash = [
        flag
        for flag, given in (
            ("--scenario", args.scenario is not None),
            ("--transport mavlink", args.transport == Transport.MAVLINK),
        )
        if given
    ]
    if clash:
        print(
            f"visland eval: --suite cannot be combined with {' or '.join(clash)} (each suite "
            "condition names its own scenario; suites fly in process)",
            file=sys.stderr,
        )
        return 2
    suite = load_suite(args.suite)
    with backend_from_args(args, args.workers) as backend:
        # each condition replaces the scenario, episodes and seed
        flying = _flight_config(EvalConfig, args, backend, render_camera=not args.no_camera)
        report = run_suite(suite, flying, episodes=args.episodes, seed=args.seed)
    png = None
    if args.plot is not None:
        png = plot_suite(report, args.plot)
        print(f"plot: {png}", file=sys.stderr if args.json else sys.stdout)
    if args.markdown is not None:
        md = Path(args.markdown)
        md.parent.mkdir(parents=True, exist_ok=True)
        plot_rel = os.path.relpath(png, md.parent) if png is not None else None
        command = "visland " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        md.write_text(suite_markdown(report, command, plot_rel))
        print(f"markdown: {md}", file=sys.stderr if args.json else sys.stdout)
    print_result(report, args.json, format_suite_table)
    return 0


def _blind_vision_policy(args: argparse.Namespace) -> str | None:
    """Why ``--no-camera`` cannot fly ``--policy`` (a vision policy would fly on black frames,
    blind, and report it as its score), or None when it can."""
    if not args.no_camera:
        return None
    from training.exec.fly import policy_is_privileged

    if policy_is_privileged(args.policy):
        return None
    return (
        f"--no-camera skips rendering, but {args.policy!r} is a vision policy (camera, radar, "
        "IMU): it would fly blind on black frames. Drop --no-camera, or fly a privileged "
        "policy (expert, cascade, a privileged checkpoint) without the camera"
    )


def _settings(args: argparse.Namespace) -> tuple[tuple[str, Any], ...] | str:
    """``--estimator KEY=VALUE`` flags as (key, value) pairs, checked against the
    checkpoint's config fields (a bad one: the message why)."""
    given = args.estimator or []
    if not given:
        return ()
    from companion.policy_net.config import CheckpointError, NetConfig

    if args.policy in ("expert", "cascade"):
        return f"--estimator: {args.policy!r} has no estimator; it is for a checkpoint"
    try:
        pairs = dict(NetConfig.parse_setting(text) for text in given)
        NetConfig().with_settings(pairs)  # ranges and the checks between keys
    except CheckpointError as exc:
        return f"--estimator: {exc}"
    return tuple(pairs.items())


def _cmd_eval(args: argparse.Namespace) -> int:
    from tools.cli_sim import cmd_fly
    from training.evaluate import EvalConfig, evaluate, format_table
    from training.exec.choose import backend_from_args

    blind = _blind_vision_policy(args)
    if blind is not None:
        print(f"visland eval: error: {blind}", file=sys.stderr)
        return 2
    if args.scenario is not None:  # a bad file stops here, before anything flies
        from sitl_sim.scenario import load_scenario

        load_scenario(args.scenario)
    settings = _settings(args)
    if isinstance(settings, str):
        print(f"visland eval: error: {settings}", file=sys.stderr)
        return 2
    args.settings = settings
    if args.suite is not None:
        return _cmd_eval_suite(args)
    if args.plot is not None or args.markdown is not None:
        print("visland eval: --plot and --markdown need --suite", file=sys.stderr)
        return 2
    # --episodes and --seed default to None so that a suite file's values stand unless given
    args.episodes = _EVAL_EPISODES if args.episodes is None else args.episodes
    args.seed = EVAL_SEED if args.seed is None else args.seed
    if args.transport == Transport.MAVLINK:  # SITL + companion processes over UDP: visland fly
        if args.settings:
            print(
                "visland eval: --estimator is for in-process flights (the companion reads the "
                "checkpoint's own settings)",
                file=sys.stderr,
            )
            return 2
        if args.keep_logs is not None:
            print(
                "visland eval: --keep-logs is for in-process flights; --transport mavlink keeps "
                "every flight's SITL and companion logs in --out (visland fly)",
                file=sys.stderr,
            )
            return 2
        return cmd_fly(args)
    with backend_from_args(args, args.workers) as backend:
        report = evaluate(
            _flight_config(EvalConfig, args, backend, render_camera=not args.no_camera)
        )
    print_result(report, args.json, format_table)
    return 0


def _cmd_collect(args: argparse.Namespace) -> int:
    from training.evaluate import CollectConfig, collect, format_table
    from training.exec.choose import backend_from_args

    with backend_from_args(args, args.workers) as backend:
        report = collect(_flight_config(CollectConfig, args, backend))
    if args.json:
        print_json(report)
    else:
        print(
            f"{report.flown_now} flown now, {report.already_complete} already complete "
            f"(seed {report.seed}, scenario {report.scenario}); logs in {report.flights_dir}"
        )
        if report.flown_now:
            format_table(report, sys.stdout)
    failed = report.policy_stats.get("failed", 0)
    return 0 if report.summary.timeouts == 0 and not failed else 1


def _cmd_relabel(args: argparse.Namespace) -> int:
    import time

    from training.exec.choose import backend_from_args

    t0 = time.perf_counter()
    with backend_from_args(args, args.workers) as backend:
        reports = backend.relabel(list(args.logs), Path(args.out))
        described = backend.describe()
    wall = time.perf_counter() - t0
    steps = sum(r.steps for r in reports)
    failed = [r for r in reports if not r.ok]
    for r in reports:
        if not r.ok:
            print(f"visland relabel: {r.error}", file=sys.stderr)
        elif r.truncated:
            print(
                f"visland relabel: {r.log}: truncated log, labelled its readable prefix "
                f"({r.steps} steps)",
                file=sys.stderr,
            )
    summary = {
        "logs": len(reports),
        "failed": len(failed),
        "steps": steps,
        "wall_s": wall,
        "steps_per_s": steps / wall if wall > 0 else None,
        "labels_dir": str(args.out),
        "backend": described,
        "per_log": [r.__dict__ for r in reports],
    }
    if args.json:
        print_json(summary)
    else:
        print(
            f"labelled {steps} steps of {len(reports) - len(failed)}/{len(reports)} logs in "
            f"{wall:.1f} s ({summary['steps_per_s'] or 0:.0f} steps/s) -> {args.out}"
        )
    return 1 if failed else 0


def _cmd_pictures(args: argparse.Namespace) -> int:
    from tools.world_pictures import draw_visual_conditions, draw_wind_flight

    out = Path(args.out)
    print(draw_visual_conditions(out / "visual_conditions.png"))
    print(draw_wind_flight(out / "wind_flight.png"))
    return 0


def _register_eval(sub: argparse._SubParsersAction) -> None:
    e = sub.add_parser(
        "eval",
        help="fly a policy over the scenario (or a benchmark suite) and print landing metrics",
    )
    e.add_argument("--policy", default="expert", help="expert | cascade | checkpoint path")
    add_episode_arguments(
        e,
        episodes=None,
        seed=None,
        episodes_help=f"episodes (default {_EVAL_EPISODES}; with --suite: per condition, default "
        "the suite file's)",
        seed_help=f"disjoint from training seeds (default {EVAL_SEED}; with --suite: the suite "
        "file's)",
    )
    e.add_argument(
        "--suite",
        type=Path,
        default=None,
        help="benchmark suite TOML (e.g. configs/suites/standard.toml): every named condition "
        "is flown and reported; not with --scenario or --transport mavlink",
    )
    e.add_argument(
        "--plot",
        type=Path,
        default=None,
        help="with --suite: PNG of success rate and mean landing error per condition",
    )
    e.add_argument(
        "--markdown",
        type=Path,
        default=None,
        help="with --suite: write the results page (command, commit, table, plot) to this file, "
        "e.g. docs/suite_expert.md",
    )
    e.add_argument(
        "--no-camera", action="store_true", help="skip rendering (privileged policies only)"
    )
    e.add_argument(
        "--keep-logs",
        type=Path,
        default=None,
        metavar="DIR",
        help="keep the MCAP flight logs of --keep flights in DIR (camera, ground truth, "
        "observation, command, the policy's estimate), named <condition>_s<seed>_ep<i>.mcap; "
        "their paths in the table and in per_episode[i].log (default: none kept)",
    )
    e.add_argument(
        "--keep",
        choices=("failed", "all"),
        default="failed",
        help="with --keep-logs: the failed flights' logs (default) or all",
    )
    e.add_argument(
        "--estimator",
        action="append",
        metavar="KEY=VALUE",
        help="fly a checkpoint with one of its estimator or landing-guard settings changed "
        "(repeatable; e.g. land_floor_m=15, land_floor_m=none, unsure_threshold=0.6): the "
        "sweeps behind a choice as commands; the JSON records them under 'estimator'",
    )
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.add_argument(
        "--transport",
        type=Transport,
        choices=list(Transport),
        default=Transport.INPROCESS,
        help="inprocess: the simulator in this process; mavlink: SITL + companion processes "
        "over UDP (as visland fly)",
    )
    add_parallel_arguments(e, "parallel processes (mavlink: SITL + companion pairs)")
    e.set_defaults(func=_cmd_eval)


def register_eval(sub: argparse._SubParsersAction) -> None:
    """Add ``eval``, ``collect``, ``relabel`` and ``pictures`` to the ``visland``
    subcommands."""
    _register_eval(sub)

    c = sub.add_parser("collect", help="fly the expert and write one MCAP log per episode")
    add_episode_arguments(
        c,
        episodes=300,
        seed=0,
        episodes_help="expert flights to record (default 300)",
        seed_help=f"collection seed (default 0: a training seed, disjoint from the evaluation "
        f"seed {EVAL_SEED})",
    )
    c.add_argument("--out", type=Path, required=True, help="run folder (logs in OUT/flights)")
    c.add_argument("--json", action="store_true", help="print one JSON object")
    add_parallel_arguments(c, "parallel processes")
    c.set_defaults(func=_cmd_collect)

    r = sub.add_parser("relabel", help="expert labels for every control step of flight logs")
    r.add_argument("logs", nargs="+", type=Path, help="MCAP flight logs")
    r.add_argument("--out", type=Path, required=True, help="folder for the .labels.mcap files")
    r.add_argument("--json", action="store_true", help="print one JSON object")
    add_parallel_arguments(r, "parallel processes")
    r.set_defaults(func=_cmd_relabel)

    pi = sub.add_parser(
        "pictures",
        help="draw the worlds: camera frames across the visual conditions, a wind flight (PNG)",
    )
    pi.add_argument("--out", default="docs/figures", help="folder for the PNGs")
    pi.set_defaults(func=_cmd_pictures)
