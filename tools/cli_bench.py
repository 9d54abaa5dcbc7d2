"""``visland bench sim|mpc|policy|companion|sitl|rollouts``: the benchmarks that print the
project's speed figures, one function each. Thin shells over :func:`tools.bench.bench_sim`,
:func:`expert.bench.bench_mpc`, :func:`training.bench_policy.bench_policy`,
:func:`tools.bench_companion.bench_companion`, :func:`tools.bench_sitl.bench_sitl` and
:func:`tools.bench_rollouts.bench_rollouts`."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from tools.cli_args import config_from_args, json_command, print_json, print_result

__all__ = ["register_bench"]


def _bench_mpc(args: argparse.Namespace) -> int:
    from expert.bench import bench_mpc

    res = bench_mpc()
    if args.json:
        print_json(res)
    else:
        for k, v in res.items():
            print(f"{k:>28}: {v:.4g}" if isinstance(v, float) else f"{k:>28}: {v}")
    return 0


def _bench_policy(args: argparse.Namespace) -> int:
    from training.bench_policy import bench_policy
    from training.provenance import SHIPPED_MODEL

    res = bench_policy(
        args.checkpoint or str(SHIPPED_MODEL),
        steps=300,
        seed=args.seed,
        runtime=args.runtime or "torch",
    )
    if args.json:
        print_json(res)
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
            f"ONNX Runtime, alone{where}: median {o['median_ms']:.3f} ms, p99 {o['p99_ms']:.3f} ms"
        )
    return 0


def _bench_companion(args: argparse.Namespace) -> int:
    from tools.bench_companion import bench_companion, print_bench
    from training.exec.fly import FlyError
    from training.provenance import SHIPPED_MODEL

    try:
        res = bench_companion(
            policy=args.checkpoint or str(SHIPPED_MODEL),
            episodes=args.episodes or 3,
            seed=args.seed,
            runtime=args.runtime or "torch",
            live=args.live_client,
            scene_baseline=args.scene_baseline,
        )
    except FlyError as exc:
        print(f"visland bench companion: failed: {exc}", file=sys.stderr)
        return 1
    return print_bench(res, args.json, "visland bench companion")


def _bench_rollouts(args: argparse.Namespace) -> int:
    from tools.bench_rollouts import RolloutBenchConfig, bench_rollouts, format_rollout_bench
    from training.exec.choose import check_ray_address
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
    print_result(res, args.json, lambda r, out: print(format_rollout_bench(r), file=out))
    return 0


def _bench_sim(args: argparse.Namespace) -> int:
    from tools.bench import SimBenchConfig, bench_sim

    res = bench_sim(config_from_args(SimBenchConfig, args, sim_seconds=args.seconds))
    if args.json:
        print_json(res)
        return 0
    base = res["baseline"]
    print(
        f"simulator real-time factor (one core, physics {res['physics_rate_hz']} Hz + "
        f"sensors + {res['renderer']} camera {res['camera_rate_hz']} Hz, "
        f"{res['scenario']}): {res['realtime_factor']:.1f}x\n"
        f"  physics only: {res['realtime_factor_physics_only']:.1f}x "
        f"({res['physics_step_us']:.1f} us per RK4 step incl. rate loop; "
        f"{res['physics_step_us_stepwise']:.1f} us one step per call, as the SITL steps; "
        f"{res['kernel']} kernel)\n"
        f"  camera: {res['camera_frame_ms']:.2f} ms per frame "
        f"({100 * res['camera_share_of_wall']:.0f} % of the wall time)\n"
        f"  baseline, pybullet camera in the same run: {base['camera_frame_ms']:.2f} ms "
        f"per frame, {base['realtime_factor']:.1f}x real time -> camera "
        f"{res['camera_speedup_vs_baseline']:.1f}x faster, simulator "
        f"{res['realtime_speedup_vs_baseline']:.1f}x"
    )
    return 0


def _bench_sitl(args: argparse.Namespace) -> int:
    from tools.bench_sitl import SitlBenchConfig, bench_sitl, format_sitl_bench
    from training.exec.fly import FlyError
    from training.provenance import SHIPPED_MODEL

    try:
        res = bench_sitl(
            SitlBenchConfig(
                policy=args.checkpoint or str(SHIPPED_MODEL),
                runtime=args.runtime or "auto",
                episodes=args.episodes or 2,
                seed=args.seed,
                scenario=args.scenario,
                repeats=args.repeats,
            )
        )
    except FlyError as exc:
        print(f"visland bench sitl: failed: {exc}", file=sys.stderr)
        return 1
    print_result(res, args.json, lambda r, out: print(format_sitl_bench(r), file=out))
    return 0


_BENCHES: dict[str, Callable[[argparse.Namespace], int]] = {
    "sim": _bench_sim,
    "mpc": _bench_mpc,
    "policy": _bench_policy,
    "companion": _bench_companion,
    "sitl": _bench_sitl,
    "rollouts": _bench_rollouts,
}
"""``visland bench WHAT`` -> the function that runs and prints it (the choices, in order)."""


def _cmd_bench(args: argparse.Namespace) -> int:
    return _BENCHES[args.what](args)


def register_bench(sub: argparse._SubParsersAction) -> None:
    """Add ``bench`` to the ``visland`` subcommands."""
    b = sub.add_parser("bench", help="benchmarks that print the project's speed figures")
    b.add_argument(
        "what",
        choices=list(_BENCHES),
        help="sim: simulator real-time factor on one core; mpc: MPC solve time vs the paper's; "
        "policy: per-step inference of a checkpoint (default: the shipped model) vs a paper-style "
        "net; "
        "companion: frame receipt -> setpoint latency of the real companion process (SITL "
        "flights), and torch vs ONNX Runtime policy step on the same frames; "
        "sitl: real-time factor of a SITL + companion pair in lockstep and where both "
        "processes' wall time goes, beside the in-process simulator in the same run; "
        "rollouts: episodes per minute on the local backend vs Ray, and the projection of a "
        "training profile on a cluster",
    )
    b.add_argument(
        "--checkpoint",
        default=None,
        help="bench policy: checkpoint to time; bench companion: checkpoint to fly; bench sitl: "
        "what the companion flies, a checkpoint or expert (default, all: "
        "models/visland_vision.pt)",
    )
    b.add_argument(
        "--live",
        dest="live_client",
        action="store_true",
        help="bench companion: fly the same episodes again with the live view on and a "
        "Foxglove-protocol client subscribed to every channel, and report both latencies and "
        "their ratio (default: off)",
    )
    b.add_argument(
        "--scene-baseline",
        action="store_true",
        help="bench companion: fly the same episodes again with --log-scene off, and report "
        "what writing the live view's picture into each log costs (latency, log size; "
        "default: off)",
    )
    b.add_argument(
        "--runtime",
        choices=["auto", "torch", "onnx"],
        default=None,
        help="bench companion (default torch) and sitl (default auto, as the demo: onnx where "
        "the export is beside the checkpoint): the companion's policy backend; bench policy: "
        "onnx times the checkpoint on ONNX Runtime too (exported to a temporary copy), beside "
        "torch",
    )
    b.add_argument(
        "--episodes",
        type=int,
        default=None,
        help="bench companion: flights (default 3); bench sitl: flights (default 2); bench "
        "rollouts: episodes of each kind per backend (default 12)",
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
        "--scenario", default=None, help="bench sim, sitl: scenario file (default: the nominal one)"
    )
    b.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per repeat")
    b.add_argument("--repeats", type=int, default=3, help="repeats (median reported)")
    b.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the benchmark's episodes (default 0; bench rollouts: 0 stands for 900)",
    )
    json_command(b, _cmd_bench, "machine-readable output")
