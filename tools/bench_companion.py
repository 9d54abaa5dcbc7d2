"""Companion latency: frame receipt -> setpoint handed to the OS, read from companion logs.

``python -m tools.bench_companion LOG...`` reads existing companion logs;
without logs it first flies (``visland fly``: SITL + companion processes, lockstep, camera
rendered) a policy — by default ``untrained``, a randomly initialised network of the shipped
size, which is what the latency depends on — and reads the logs of that run. Prints median /
p90 / p99 / max of the latency and of the policy's share of it.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from companion.record import latency_stats

__all__ = ["bench_companion", "main"]


def bench_companion(
    logs: list[Path] | None = None,
    policy: str = "untrained",
    episodes: int = 3,
    seed: int = 0,
    scenario: str | None = None,
) -> dict[str, Any]:
    """Latency figures from ``logs``, or from a fresh ``fly`` run of ``policy``."""
    source: dict[str, Any]
    if not logs:
        from tools.fly import FlyConfig, fly

        report = fly(
            FlyConfig(
                policy=policy,
                episodes=episodes,
                seed=seed,
                scenario=scenario,
                render=True,
                progress=False,
            )
        )
        logs = sorted((Path(report["out"]) / "companion").glob("*.mcap"))
        source = {"policy": policy, "episodes": episodes, "seed": seed, "run": report["out"]}
    else:
        source = {"logs": [str(p) for p in logs]}
    return {**source, **latency_stats(list(logs))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.bench_companion", description=__doc__)
    p.add_argument("logs", nargs="*", type=Path, help="companion MCAP logs (none: fly first)")
    p.add_argument("--policy", default="untrained", help="untrained | expert | checkpoint")
    p.add_argument("--episodes", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--scenario", default=None)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    res = bench_companion(args.logs, args.policy, args.episodes, args.seed, args.scenario)
    if args.json:
        print(json.dumps(res, indent=2))
    elif not res.get("commands"):
        print("no sent policy commands in those logs", file=sys.stderr)
        return 1
    else:
        print(
            f"frame receipt -> setpoint sent over {res['commands']} commands: median "
            f"{res['median_ms']:.2f} ms, p90 {res['p90_ms']:.2f} ms, p99 {res['p99_ms']:.2f} ms, "
            f"max {res['max_ms']:.2f} ms (policy: median {res['policy_median_ms']:.2f} ms, "
            f"p99 {res['policy_p99_ms']:.2f} ms)"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
