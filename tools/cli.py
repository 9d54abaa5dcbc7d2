"""``visland``: the one command-line entry point. Each subcommand is a thin shell over a
``run(config)``-style function that the tests call directly.

Errors a user can cause (bad config, bad file, bad value) end with one line on stderr naming
the problem and exit code 2; nothing prints a bare traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

__all__ = ["main"]


def _json_default(obj: Any) -> Any:
    import numpy as np

    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def _print_json(obj: Any) -> None:
    def clean(v: Any) -> Any:
        if isinstance(v, float) and not math.isfinite(v):
            return None  # JSON has no NaN: null means "not defined" (e.g. no touchdown)
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list | tuple):
            return [clean(x) for x in v]
        return v

    print(json.dumps(clean(json.loads(json.dumps(obj, default=_json_default))), indent=2))


def _cmd_demo(args: argparse.Namespace) -> int:
    from tools.demo import DemoConfig, run

    # With --json the narration goes to stderr so stdout is one JSON document.
    narration = sys.stderr if args.json else sys.stdout
    result = run(DemoConfig(seed=args.seed, scenario=args.scenario), narration)
    if args.json:
        _print_json(result)
    return 0 if result["landed"] else 1


def _cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "sim":
        from tools.bench import SimBenchConfig, bench_sim

        res = bench_sim(
            SimBenchConfig(sim_seconds=args.seconds, repeats=args.repeats, seed=args.seed)
        )
        if args.json:
            _print_json(res)
        else:
            print(
                f"simulator real-time factor (one core, physics {res['physics_rate_hz']} Hz + "
                f"sensors + pybullet camera {res['camera_rate_hz']} Hz): "
                f"{res['realtime_factor']:.1f}x\n"
                f"  physics only: {res['realtime_factor_physics_only']:.1f}x "
                f"({res['physics_step_us']:.1f} us per RK4 step incl. rate loop)\n"
                f"  camera: {res['camera_frame_ms']:.2f} ms per frame "
                f"({100 * res['camera_share_of_wall']:.0f} % of the wall time)"
            )
        return 0
    raise AssertionError(args.what)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="visland",
        description="Vision-based drone landing: simulator, companion, imitation learning.",
    )
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="fly one simulated descent and print what happened")
    d.add_argument("--seed", type=int, default=0, help="scenario seed (default 0)")
    d.add_argument("--scenario", type=Path, default=None, help="scenario TOML")
    d.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    d.set_defaults(func=_cmd_demo)

    b = sub.add_parser("bench", help="benchmarks that print the project's speed figures")
    b.add_argument("what", choices=["sim"], help="sim: simulator real-time factor on one core")
    b.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per repeat")
    b.add_argument("--repeats", type=int, default=3, help="repeats (median reported)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--json", action="store_true", help="machine-readable output")
    b.set_defaults(func=_cmd_bench)
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from companion.contract import ContractError
    from sitl_sim.errors import SimError

    try:
        return int(args.func(args))
    except (SimError, ContractError) as exc:
        print(f"visland {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"visland {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
