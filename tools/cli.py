"""``visland``: the one command-line entry point. Each subcommand is a thin shell over a
``run(config)``-style function that the tests call directly.

Errors a user can cause (bad config, bad file, bad value) end with one line on stderr naming
the problem and exit code 2; nothing prints a bare traceback.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path
from typing import Any

from training.seeds import EVAL_SEED
from training.transport import Transport

__all__ = ["main"]


_EVAL_EPISODES = 20
"""``visland eval``'s episodes without ``--suite``."""


def _print_json(obj: Any) -> None:
    """One JSON document on stdout; NaN (e.g. no touchdown) is null: "not defined"."""
    from companion.flightlog import jsonable

    print(json.dumps(jsonable(obj), indent=2))


def _cmd_demo(args: argparse.Namespace) -> int:
    from tools.demo import DemoConfig, run
    from training.fly import FlyError

    # With --json the narration goes to stderr so stdout is one JSON document.
    narration = sys.stderr if args.json else sys.stdout
    cfg = DemoConfig(
        policy=args.policy,
        episodes=args.episodes,
        seed=args.seed,
        scenario=args.scenario,
        out=args.out,
        progress=not args.json,
    )
    try:
        report = run(cfg, narration)
    except FlyError as exc:
        print(f"visland demo: failed: {exc}", file=sys.stderr)
        return 1
    if args.json:
        _print_json(report)
    return 0  # failed landings are results, reported above, not errors of the demo


def _cmd_sitl(args: argparse.Namespace) -> int:
    import logging

    from sitl_sim.mavlink_sitl import run_sitl
    from sitl_sim.sitl_config import sitl_config_from_args

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    return run_sitl(sitl_config_from_args(args))


def _cmd_companion(args: argparse.Namespace) -> int:
    import logging

    from companion.app import run_from_args
    from training.companion_process import resolve_policy

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    return run_from_args(args, resolve_policy, "visland companion")


def _cmd_fly(args: argparse.Namespace) -> int:
    from training.backend import backend_from_args
    from training.evaluate import format_table
    from training.fly import DEFAULT_VISION_POLICY, FlyConfig, FlyError, fly, fly_many

    link_args = _link_sitl_args(args)
    if link_args and not getattr(args, "realtime", False):
        print(
            f"visland {args.command}: --link-* impair a real-time link; add --realtime "
            "(in lockstep a delayed answer would stop the clock instead of arriving late)",
            file=sys.stderr,
        )
        return 2
    mode = getattr(args, "companion_mode", "offboard")
    policy = args.policy
    if policy is None:  # fly's default: the expert flies; in landing-target mode, the shipped net
        policy = DEFAULT_VISION_POLICY if mode == "landing-target" else "expert"
    cfg = FlyConfig(
        policy=policy,
        companion_mode=mode,
        episodes=args.episodes,
        seed=args.seed,
        scenario=str(args.scenario) if args.scenario else None,
        realtime=getattr(args, "realtime", False),
        out=str(args.out) if getattr(args, "out", None) else None,
        progress=not args.json,
        sitl_args=link_args,
        autopilot=getattr(args, "autopilot", "px4"),
        sitl_params=tuple(getattr(args, "sitl_param", None) or ()),
    )
    # eval --transport mavlink --workers N = fly --instances N
    instances = getattr(args, "instances", None) or getattr(args, "workers", 1)
    if instances < 1:
        print(f"visland {args.command}: --instances must be >= 1, got {instances}", file=sys.stderr)
        return 2
    try:
        if instances == 1 and args.ray is None:
            report = fly(cfg)
        else:
            with backend_from_args(args, instances) as backend:
                report = fly_many(cfg, list(range(args.episodes)), instances, backend=backend)
    except FlyError as exc:
        print(f"visland {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    if args.json:
        _print_json(report)
    else:
        format_table(report, sys.stdout)
        lat = report["latency_ms"]
        if lat.get("commands"):
            print(
                f"  frame receipt -> setpoint sent: median {lat['median_ms']:.2f} ms, "
                f"p99 {lat['p99_ms']:.2f} ms over {lat['commands']} commands; logs in "
                f"{report['out']}"
            )
    return 0


_LINK_FLAGS = {
    "link_loss": "--link-loss-prob",
    "link_delay_ms": "--link-delay-ms",
    "link_jitter_ms": "--link-jitter-ms",
    "link_duplicate": "--link-duplicate-prob",
    "link_reorder": "--link-reorder-prob",
    "link_cut_at_s": "--link-cut-at-s",
}
"""``visland fly``'s link flags -> the SITL's (``sitl_sim.sitl_config``), which impairs the link."""


def _link_sitl_args(args: argparse.Namespace) -> tuple[str, ...]:
    out: list[str] = []
    for name, flag in _LINK_FLAGS.items():
        value = getattr(args, name, None)
        if value is not None:
            out += [flag, repr(float(value))]
    return tuple(out)


def _cmd_eval_suite(args: argparse.Namespace) -> int:
    from training.backend import backend_from_args
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
        report = run_suite(
            suite,
            args.policy,
            episodes=args.episodes,
            seed=args.seed,
            render_camera=not args.no_camera,
            progress=not args.json,
            backend=backend,
        )
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
    if args.json:
        _print_json(report)
    else:
        format_suite_table(report, sys.stdout)
    return 0


def _cmd_pictures(args: argparse.Namespace) -> int:
    from tools.world_pictures import draw_visual_conditions, draw_wind_flight

    out = Path(args.out)
    print(draw_visual_conditions(out / "visual_conditions.png"))
    print(draw_wind_flight(out / "wind_flight.png"))
    return 0


def _cmd_eval(args: argparse.Namespace) -> int:
    from training.backend import backend_from_args
    from training.evaluate import EvalConfig, evaluate, format_table

    if args.suite is not None:
        return _cmd_eval_suite(args)
    if args.plot is not None or args.markdown is not None:
        print("visland eval: --plot and --markdown need --suite", file=sys.stderr)
        return 2
    # --episodes and --seed default to None so that a suite file's values stand unless given
    args.episodes = _EVAL_EPISODES if args.episodes is None else args.episodes
    args.seed = EVAL_SEED if args.seed is None else args.seed
    if args.transport == Transport.MAVLINK:  # SITL + companion processes over UDP: visland fly
        return _cmd_fly(args)
    with backend_from_args(args, args.workers) as backend:
        report = evaluate(
            EvalConfig(
                policy=args.policy,
                episodes=args.episodes,
                seed=args.seed,
                scenario=str(args.scenario) if args.scenario else None,
                render_camera=not args.no_camera,
                progress=not args.json,
                backend=backend,
            )
        )
    if args.json:
        _print_json(report)
    else:
        format_table(report, sys.stdout)
    return 0


def _cmd_collect(args: argparse.Namespace) -> int:
    from training.backend import backend_from_args
    from training.evaluate import CollectConfig, collect, format_table

    with backend_from_args(args, args.workers) as backend:
        summary = collect(
            CollectConfig(
                out=args.out,
                episodes=args.episodes,
                seed=args.seed,
                scenario=str(args.scenario) if args.scenario else None,
                progress=not args.json,
                backend=backend,
            )
        )
    if args.json:
        _print_json(summary)
    else:
        print(
            f"{summary['flown_now']} flown now, {summary['already_complete']} already complete; "
            f"logs in {summary['flights_dir']}"
        )
        if summary["flown_now"]:
            format_table({**summary, "episodes": summary["flown_now"]}, sys.stdout)
    failed = summary.get("policy_stats", {}).get("failed", 0)
    return 0 if summary["timeouts"] == 0 and not failed else 1


def _cmd_relabel(args: argparse.Namespace) -> int:
    import time

    from training.backend import backend_from_args

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
        _print_json(summary)
    else:
        print(
            f"labelled {steps} steps of {len(reports) - len(failed)}/{len(reports)} logs in "
            f"{wall:.1f} s ({summary['steps_per_s'] or 0:.0f} steps/s) -> {args.out}"
        )
    return 1 if failed else 0


def _cmd_log(args: argparse.Namespace) -> int:
    from tools.log_plots import plot_flight
    from tools.logtool import format_info, log_info

    if args.what == "info":
        info = log_info(args.file)
        if args.json:
            _print_json(info)
        else:
            print(format_info(info))
        return 0
    if args.what == "plot":
        report = plot_flight(args.file, args.out)
        print(f"wrote {report.out} ({report.kind} log)")
        for line in report.missing:
            print(f"  missing {line}")
        if report.truncated:
            print(f"  truncated log: plotted its readable prefix ({report.error})")
        return 0
    raise AssertionError(args.what)


def _cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "mpc":
        from expert.bench import bench_mpc

        res = bench_mpc()
        if args.json:
            _print_json(res)
        else:
            for k, v in res.items():
                print(f"{k:>28}: {v:.4g}" if isinstance(v, float) else f"{k:>28}: {v}")
        return 0
    if args.what == "policy":
        from tools.bench_companion import DEFAULT_CHECKPOINT
        from training.bench_policy import bench_policy

        res = bench_policy(
            args.checkpoint or DEFAULT_CHECKPOINT, steps=300, seed=args.seed, runtime=args.runtime
        )
        if args.json:
            _print_json(res)
            return 0
        if "shipped" in res:
            s, b = res["shipped"], res["paper_style"]
            print(
                f"policy step (one thread, batch 1, {res['kind']}): "
                f"median {s['median_ms']:.3f} ms, p99 {s['p99_ms']:.3f} ms, "
                f"{s['parameters']} parameters\n"
                f"paper-style CNN-MLP + LSTM-MLP, same run: median {b['median_ms']:.3f} ms "
                f"({b['parameters']} parameters) -> {res['speedup_vs_paper_style']:.1f}x faster\n"
                f"paper's reported policy step: {res['paper_reported_ms']} ms"
            )
        if "onnx" in res:
            o = res["onnx"]
            print(
                f"ONNX Runtime, interleaved with the torch nets: median {o['median_ms']:.3f} ms, "
                f"p99 {o['p99_ms']:.3f} ms ({res['onnx_vs_torch']:.2f}x torch)"
            )
        if "onnx_alone" in res:
            o = res["onnx_alone"]
            where = "" if "onnx" in res else " (no torch here: the export beside the checkpoint)"
            print(
                f"ONNX Runtime, alone{where}: median {o['median_ms']:.3f} ms, "
                f"p99 {o['p99_ms']:.3f} ms"
            )
        return 0
    if args.what == "companion":
        from tools.bench_companion import DEFAULT_CHECKPOINT, bench_companion, format_bench
        from training.fly import FlyError

        try:
            res = bench_companion(
                policy=args.checkpoint or DEFAULT_CHECKPOINT,
                episodes=args.episodes or 3,
                seed=args.seed,
                runtime=args.runtime,
            )
        except FlyError as exc:
            print(f"visland bench companion: failed: {exc}", file=sys.stderr)
            return 1
        if args.json:
            _print_json(res)
        elif not res.get("commands"):
            print("visland bench companion: no sent policy commands", file=sys.stderr)
            return 1
        else:
            print(format_bench(res))
        return 0
    if args.what == "rollouts":
        from tools.bench_rollouts import RolloutBenchConfig, bench_rollouts, format_rollout_bench
        from training.backend import check_ray_address
        from training.profiles import PROFILES

        if args.profile not in PROFILES:
            print(
                f"visland bench rollouts: unknown profile {args.profile!r}; expected one of "
                f"{sorted(PROFILES)}",
                file=sys.stderr,
            )
            return 2
        res = bench_rollouts(
            RolloutBenchConfig(
                episodes=args.episodes or 12,
                workers=args.workers,
                ray=check_ray_address(args.ray),
                seed=args.seed or 900,
                run=args.run,
                profile=args.profile,
            )
        )
        if args.json:
            _print_json(res)
        else:
            print(format_rollout_bench(res))
        return 0
    if args.what == "sim":
        from tools.bench import SimBenchConfig, bench_sim

        res = bench_sim(
            SimBenchConfig(
                sim_seconds=args.seconds,
                repeats=args.repeats,
                seed=args.seed,
                renderer=args.renderer,
                scenario=args.scenario,
            )
        )
        if args.json:
            _print_json(res)
        else:
            base = res["baseline"]
            print(
                f"simulator real-time factor (one core, physics {res['physics_rate_hz']} Hz + "
                f"sensors + {res['renderer']} camera {res['camera_rate_hz']} Hz, "
                f"{res['scenario']}): {res['realtime_factor']:.1f}x\n"
                f"  physics only: {res['realtime_factor_physics_only']:.1f}x "
                f"({res['physics_step_us']:.1f} us per RK4 step incl. rate loop)\n"
                f"  camera: {res['camera_frame_ms']:.2f} ms per frame "
                f"({100 * res['camera_share_of_wall']:.0f} % of the wall time)\n"
                f"  baseline, pybullet camera in the same run: {base['camera_frame_ms']:.2f} ms "
                f"per frame, {base['realtime_factor']:.1f}x real time -> camera "
                f"{res['camera_speedup_vs_baseline']:.1f}x faster, simulator "
                f"{res['realtime_speedup_vs_baseline']:.1f}x"
            )
        return 0
    raise AssertionError(args.what)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="visland",
        description="Vision-based drone landing: simulator, companion, imitation learning.",
    )
    sub = p.add_subparsers(dest="command", required=True)

    from training.provenance import SHIPPED_MODEL

    d = sub.add_parser(
        "demo",
        help="the shipped vision policy flies 3 landings: SITL + companion over MAVLink, "
        "results table, MCAP logs, PNG",
        description="Start the SITL and the companion as two processes over MAVLink/UDP, fly "
        "the shipped vision policy through N landings (lockstep), then print one row per "
        "landing, the MCAP flight logs of both processes and a PNG of all flights. Exit 0 when "
        "every episode was flown, whatever the landings scored (failures are reported); 1 when "
        "a process failed; 2 on bad input.",
    )
    d.add_argument(
        "--policy",
        default=str(SHIPPED_MODEL),
        help="checkpoint path, or expert | cascade (default: the shipped model, "
        "models/visland_vision.pt of this repository)",
    )
    d.add_argument("--episodes", type=int, default=3, help="landings to fly (default 3)")
    d.add_argument(
        "--seed",
        type=int,
        default=EVAL_SEED,
        help=f"scenario seed: episodes 0..N-1 of it are flown (default {EVAL_SEED}, the "
        "evaluation seed, disjoint from training)",
    )
    d.add_argument("--scenario", type=Path, default=None, help="scenario TOML")
    d.add_argument(
        "--out",
        type=Path,
        default=Path("runs/demo"),
        help="output folder: logs, flights.png, demo.json; a previous demo there is replaced "
        "(default runs/demo)",
    )
    d.add_argument("--json", action="store_true", help="print the report as JSON on stdout")
    d.set_defaults(func=_cmd_demo)

    pi = sub.add_parser(
        "pictures",
        help="draw the worlds: camera frames across the visual conditions, a wind flight (PNG)",
    )
    pi.add_argument("--out", default="docs/figures", help="folder for the PNGs")
    pi.set_defaults(func=_cmd_pictures)

    b = sub.add_parser("bench", help="benchmarks that print the project's speed figures")
    b.add_argument(
        "what",
        choices=["sim", "mpc", "policy", "companion", "rollouts"],
        help="sim: simulator real-time factor on one core; mpc: MPC solve time vs the paper's; "
        "policy: per-step inference of a checkpoint (default: the shipped model) vs a paper-style "
        "net; "
        "companion: frame receipt -> setpoint latency of the real companion process (SITL "
        "flights), and torch vs ONNX Runtime policy step on the same frames; "
        "rollouts: episodes per minute on the local backend vs Ray, and the projection of a "
        "training profile on a cluster",
    )
    b.add_argument(
        "--checkpoint",
        default=None,
        help="bench policy: checkpoint to time; bench companion: checkpoint to fly (default, "
        "both: models/visland_vision.pt)",
    )
    b.add_argument(
        "--runtime",
        choices=["torch", "onnx"],
        default="torch",
        help="bench companion: the companion's policy backend; bench policy: onnx times the "
        "checkpoint on ONNX Runtime too (exported to a temporary copy), beside torch",
    )
    b.add_argument(
        "--episodes",
        type=int,
        default=None,
        help="bench companion: flights (default 3); bench rollouts: episodes of each kind per "
        "backend (default 12)",
    )
    b.add_argument(
        "--ray",
        default="local",
        metavar="ADDRESS",
        help="bench rollouts: the Ray cluster to compare with (default: a local instance)",
    )
    b.add_argument(
        "--workers", type=int, default=0, help="bench rollouts: local processes (0: CPU count)"
    )
    b.add_argument(
        "--run",
        default="runs/robust",
        help="bench rollouts: run folder whose recorded training seconds the projection adds",
    )
    b.add_argument("--profile", default="robust", help="bench rollouts: the profile to project")
    b.add_argument(
        "--renderer",
        choices=["fast", "pybullet"],
        default="fast",
        help="bench sim: the camera renderer of the headline figures (pybullet is always timed "
        "too, as the baseline)",
    )
    b.add_argument(
        "--scenario", default=None, help="bench sim: scenario file (default: the nominal one)"
    )
    b.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per repeat")
    b.add_argument("--repeats", type=int, default=3, help="repeats (median reported)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--json", action="store_true", help="machine-readable output")
    b.set_defaults(func=_cmd_bench)

    from sitl_sim.sitl_config import add_sitl_arguments
    from training.backend import add_backend_arguments

    st = sub.add_parser(
        "sitl", help="the MAVLink 2 SITL: a PX4-like autopilot over UDP (lockstep or real time)"
    )
    add_sitl_arguments(st)
    st.set_defaults(func=_cmd_sitl)

    e = sub.add_parser(
        "eval",
        help="fly a policy over the scenario (or a benchmark suite) and print landing metrics",
    )
    e.add_argument("--policy", default="expert", help="expert | cascade | checkpoint path")
    e.add_argument(
        "--episodes",
        type=int,
        default=None,
        help=f"episodes (default {_EVAL_EPISODES}; with --suite: per condition, default the "
        "suite file's)",
    )
    e.add_argument(
        "--seed",
        type=int,
        default=None,
        help=f"disjoint from training seeds (default {EVAL_SEED}; with --suite: the suite file's)",
    )
    e.add_argument("--scenario", type=Path, default=None)
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
        "--workers",
        type=int,
        default=1,
        help="parallel processes (mavlink: SITL + companion pairs)",
    )
    e.add_argument(
        "--no-camera", action="store_true", help="skip rendering (privileged policies only)"
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
    add_backend_arguments(e)
    e.set_defaults(func=_cmd_eval)

    from companion.app import add_arguments as add_companion_arguments

    cp = sub.add_parser(
        "companion",
        help="the companion process: flies a policy through a PX4/ArduPilot autopilot",
    )
    add_companion_arguments(cp)
    cp.set_defaults(func=_cmd_companion)

    fl = sub.add_parser(
        "fly", help="SITL + companion as separate processes over UDP: N episodes, eval JSON"
    )
    fl.add_argument(
        "--policy",
        default=None,
        help="expert | cascade | checkpoint path (default: expert; with --companion-mode "
        "landing-target: models/visland_vision.pt)",
    )
    fl.add_argument(
        "--companion-mode",
        choices=("offboard", "landing-target"),
        default="offboard",
        help="offboard: the companion flies the policy; landing-target: it streams "
        "LANDING_TARGET from the policy's camera estimator and the SITL's AUTO.PRECLAND lands",
    )
    fl.add_argument(
        "--autopilot",
        choices=("px4", "ardupilot"),
        default="px4",
        help="autopilot profile of the SITL and the companion; ardupilot sets GUID_OPTIONS=8 "
        "(offboard) or PLND_ENABLED=1,PLND_TYPE=1 (landing-target) on the SITL first",
    )
    fl.add_argument(
        "--sitl-param",
        action="append",
        metavar="NAME=VALUE",
        help="a SITL parameter set at start, after the profile's setup (repeatable), e.g. "
        "GUID_OPTIONS=0 to see the companion refuse",
    )
    fl.add_argument("--episodes", type=int, default=20)
    fl.add_argument("--seed", type=int, default=EVAL_SEED, help="disjoint from training seeds")
    fl.add_argument("--scenario", type=Path, default=None)
    fl.add_argument("--realtime", action="store_true", help="real time instead of lockstep")
    link = fl.add_argument_group(
        "impaired link (--realtime only; over the scenario's [link]; seeded by --seed)"
    )
    link.add_argument("--link-loss", type=float, default=None, metavar="P", help="loss probability")
    link.add_argument(
        "--link-delay-ms", type=float, default=None, metavar="D", help="fixed one-way delay, ms"
    )
    link.add_argument(
        "--link-jitter-ms",
        type=float,
        default=None,
        metavar="J",
        help="extra delay uniform in [0, J] ms (each stream stays in order)",
    )
    link.add_argument(
        "--link-duplicate", type=float, default=None, metavar="P", help="duplicate probability"
    )
    link.add_argument(
        "--link-reorder",
        type=float,
        default=None,
        metavar="P",
        help="probability a datagram jumps the queue (needs a delay)",
    )
    link.add_argument(
        "--link-cut-at-s",
        type=float,
        default=None,
        metavar="T",
        help="the link dies for good T s into each flight (failsafe test)",
    )
    fl.add_argument(
        "--instances",
        type=int,
        default=1,
        help="SITL + companion pairs side by side, each on its own ports (default 1)",
    )
    fl.add_argument("--out", type=Path, default=None, help="run folder for both processes' logs")
    fl.add_argument("--json", action="store_true", help="print one JSON object")
    add_backend_arguments(fl)
    fl.set_defaults(func=_cmd_fly)

    c = sub.add_parser("collect", help="fly the expert and write one MCAP log per episode")
    c.add_argument("--episodes", type=int, default=300)
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--out", type=Path, required=True, help="run folder (logs in OUT/flights)")
    c.add_argument("--scenario", type=Path, default=None)
    c.add_argument("--workers", type=int, default=1)
    c.add_argument("--json", action="store_true")
    add_backend_arguments(c)
    c.set_defaults(func=_cmd_collect)

    r = sub.add_parser("relabel", help="expert labels for every control step of flight logs")
    r.add_argument("logs", nargs="+", type=Path, help="MCAP flight logs")
    r.add_argument("--out", type=Path, required=True, help="folder for the .labels.mcap files")
    r.add_argument("--workers", type=int, default=1)
    r.add_argument("--json", action="store_true")
    add_backend_arguments(r)
    r.set_defaults(func=_cmd_relabel)

    lg = sub.add_parser("log", help="look into an MCAP flight log: info, plot")
    lg_sub = lg.add_subparsers(dest="what", required=True)
    li = lg_sub.add_parser("info", help="topics, counts, schemas, duration, metadata, result")
    li.add_argument("file", type=Path, help="MCAP flight log (SITL, rollout or companion)")
    li.add_argument("--json", action="store_true", help="print one JSON object")
    li.set_defaults(func=_cmd_log)
    lp = lg_sub.add_parser(
        "plot", help="PNG: top view, altitude, attitude and commands vs time (matplotlib Agg)"
    )
    lp.add_argument("file", type=Path, help="MCAP flight log (SITL, rollout or companion)")
    lp.add_argument("--out", type=Path, default=None, help="PNG path (default: FILE's stem.png)")
    lp.set_defaults(func=_cmd_log)

    from tools.cli_train import register_training

    register_training(sub)

    from tools.export_onnx import register_export

    register_export(sub)
    return p


EXTRA_OF_MODULE = {
    "onnxruntime": "onnx",
    "torch": "torch",
    "cv2": "camera",
    "scipy": "sim",
    "pybullet": "sim",
    "gymnasium": "sim",
    "PIL": "sim",
    "cvxpy": "train",
    "osqp": "train",
    "clarabel": "train",
    "matplotlib": "train",
    "tqdm": "train",
    "tensorboard": "train",
    "tomli_w": "train",
    "onnx": "train",
    "ray": "ray",
    "mavsdk": "dev",
    "pytest": "dev",
}
"""Which ``pip install 'visland[EXTRA]'`` brings each optional module (pyproject.toml)."""


def missing_extra(exc: ImportError) -> str | None:
    """The line telling a user which extra a failed import needs; None for a module that no
    extra provides (a real bug, left to raise)."""
    top = (exc.name or "").split(".")[0]
    extra = EXTRA_OF_MODULE.get(top)
    if extra is None:
        return None
    return f"needs the '{extra}' extra (no module named {top!r}): pip install 'visland[{extra}]'"


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _run(args)
    except ImportError as exc:
        line = missing_extra(exc)
        if line is None:
            raise
        print(f"visland {args.command}: {line}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    from companion.contract import ContractError
    from companion.flightlog import FlightLogError
    from sitl_sim.errors import SimError
    from training.backend import BackendError

    try:
        return int(args.func(args))
    except (SimError, ContractError, FlightLogError, FileNotFoundError, ValueError) as exc:
        print(f"visland {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BackendError as exc:
        print(f"visland {args.command}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"visland {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
