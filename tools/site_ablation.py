"""How the privileged expert must see a moving or tilted pad — the ablation behind the MPC's
pad-frame tracking (issue 32), re-runnable:

    python -m tools.site_ablation --episodes 10 --seed 500 rover_fast deck_moderate

Each site of ``configs/sites/`` is flown in process (no camera) by the expert given, in turn:
``full`` (the pad's position, velocity, attitude and acceleration: what it uses), ``no_accel``
(no acceleration feed-forward), ``position_only`` (where the pad is, not how it moves) and
``still_pad`` (no pad state: the expert of a still pad at the origin). Seed 500 is the
validation seed: it chooses, it is not the evaluation seed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from typing import Any

import numpy as np

from companion.contract import GroundTruth
from training.exec.rollout import fly_episode, make_policy

__all__ = ["VARIANTS", "ablate"]

VARIANTS = ("full", "no_accel", "position_only", "still_pad")


class _Seen:
    """The expert, given only part of the pad's state."""

    privileged = True

    def __init__(self, expert: Any, variant: str) -> None:
        self.expert, self.variant = expert, variant

    def initial_state(self) -> Any:
        return self.expert.initial_state()

    def act(self, obs: Any, gt: GroundTruth, state: Any):
        if gt.pad_pos_ned_m is not None and self.variant != "full":
            zero = np.zeros(3)
            if self.variant == "no_accel":
                gt = dataclasses.replace(gt, pad_accel_ned_m_s2=zero)
            elif self.variant == "position_only":
                gt = dataclasses.replace(gt, pad_vel_ned_m_s=zero, pad_accel_ned_m_s2=zero)
            else:
                gt = dataclasses.replace(
                    gt,
                    pad_pos_ned_m=None,
                    pad_vel_ned_m_s=None,
                    pad_quat_wxyz=None,
                    pad_accel_ned_m_s2=None,
                )
        return self.expert.act(obs, gt, state)


def ablate(sites: list[str], episodes: int = 10, seed: int = 500) -> list[dict[str, Any]]:
    """One row per (site, variant): successes, landing error mean/max, vertical speed max,
    touchdowns on the pad."""
    from sitl_sim.env import LandingEnv

    rows = []
    for site in sites:
        env = LandingEnv(scenario=f"configs/sites/{site}.toml", render_camera=False)
        try:
            for variant in VARIANTS:
                pilot = _Seen(make_policy("expert", env), variant)
                results = [fly_episode(env, pilot, seed, i).result for i in range(episodes)]
                landed = [r for r in results if r.landed]
                rows.append(
                    {
                        "site": site,
                        "variant": variant,
                        "episodes": episodes,
                        "success": sum(r.success for r in results),
                        "timeouts": len(results) - len(landed),
                        "on_pad": sum(r.touched_pad is True for r in results),
                        "error_mean_m": float(np.mean([r.landing_error_m for r in results])),
                        "error_max_m": float(max(r.landing_error_m for r in results)),
                        "vertical_speed_max_m_s": max(
                            (r.touchdown_vertical_speed_m_s for r in landed), default=None
                        ),
                    }
                )
        finally:
            env.close()
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.site_ablation", description=__doc__)
    p.add_argument("sites", nargs="+", help="names in configs/sites/ (e.g. rover_fast)")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--seed", type=int, default=500, help="default 500: the validation seed")
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    rows = ablate(args.sites, args.episodes, args.seed)
    if args.json:
        json.dump(rows, sys.stdout, indent=1)
        print()
        return 0
    for r in rows:
        vz = r["vertical_speed_max_m_s"]
        print(
            f"{r['site']:<14} {r['variant']:<13} success {r['success']}/{r['episodes']}  "
            f"timeouts {r['timeouts']}  on pad {r['on_pad']}  error mean "
            f"{r['error_mean_m']:.3f} m, max {r['error_max_m']:.3f} m  vertical speed max "
            + ("n/a" if vz is None else f"{vz:.3f} m/s")
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
