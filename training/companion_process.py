"""``visland companion``: the companion process with the project's privileged pilots wired in.

``companion/`` may not import the simulator or the expert; this shell (tools may import
everything) turns ``--policy expert`` (the MPC, paper 3.2) and ``--policy cascade`` (the PD
baseline) into policy objects built from the same vehicle/sim configs as the SITL, and hands
them to :func:`companion.app.main`. Any other ``--policy`` is a learned checkpoint
(``untrained`` / ``untrained-privileged``: a randomly initialised network of the shipped size,
for latency benchmarks). Both privileged pilots read the companion's ODOMETRY record
(a ``companion.contract.GroundTruth``), so the SITL must run with ``--groundtruth``, and both
model the world they fly in: ``--planet NAME`` (this shell's own flag, default earth) is the
SITL scenario's planet — ``visland fly`` passes it; an Earth expert on Mars hovers until the
episode times out.
"""

from __future__ import annotations

import sys
from typing import Any

__all__ = ["main", "resolve_policy", "sim_companion_args"]


def sim_companion_args() -> tuple[str, ...]:
    """The flags every simulator launch of the companion gives (``visland fly``, ``visland
    demo``, DAgger's rollouts, the tests): the companion's defaults are the hardware
    template's (shadow, engage above 5 m, thrust ≤ 0.9, rates ≤ 2 / 1 rad/s), while a SITL
    flight flies with :class:`~companion.flight.OffboardConfig`'s and
    :class:`~companion.safety.SafetyConfig`'s own defaults — the settings of the in-process
    rollouts and of the SITL's own rate limits — so they are passed here, explicitly."""
    from companion.flight import OffboardConfig
    from companion.safety import SafetyConfig

    flight, safety = OffboardConfig(), SafetyConfig()
    rate_rp, _, rate_yaw = safety.max_rate_rad_s
    return (
        "--shadow" if flight.shadow else "--no-shadow",
        "--no-bench",
        "--engage-in-air",  # each episode starts in the air: the operator's word, given here
        *("--engage-min-range-m", repr(flight.engage_min_range_m)),
        *("--thrust-min", repr(safety.thrust_min)),
        *("--thrust-max", repr(safety.thrust_max)),
        *("--max-rate-rp-rad-s", repr(rate_rp)),
        *("--max-rate-yaw-rad-s", repr(rate_yaw)),
        *("--max-age-ms", repr(safety.max_age_s * 1000.0)),
        *("--near-ground-m", repr(safety.near_ground_m)),
    )


def resolve_policy(name: str, cfg: Any = None, planet: str = "earth") -> Any:
    """``expert`` | ``cascade`` | ``untrained`` | ``untrained-privileged`` | checkpoint path;
    the privileged pilots model ``planet``."""
    if name in ("expert", "cascade"):
        from sitl_sim.config import load_sim, load_vehicle
        from sitl_sim.config import planet as planet_named

        vehicle, sim = load_vehicle(), load_sim().with_planet(planet_named(planet))
        if name == "expert":
            from expert.mpc import MpcExpert

            return MpcExpert(vehicle, sim)
        from expert.cascade import CascadeLander

        return CascadeLander(vehicle, sim.planet)
    threads = getattr(cfg, "torch_threads", 1) if cfg is not None else 1
    runtime = getattr(cfg, "runtime", "auto") if cfg is not None else "auto"
    if name in ("untrained", "untrained-privileged"):
        if runtime == "onnx":
            raise ValueError(
                f"--policy {name} is built in torch; runtime {runtime!r} needs a checkpoint file "
                "(save it, then visland export-onnx)"
            )
        import torch

        from companion.policy_net import untrained_policy

        torch.set_num_threads(max(1, threads))
        return untrained_policy(seed=0, privileged=name.endswith("privileged"))
    from companion.runtime import load_policy_file

    return load_policy_file(name, threads, runtime)


def main(argv: list[str] | None = None) -> int:
    import argparse
    from functools import partial

    from companion.app import main as app_main
    from sitl_sim.config import PLANETS

    world = argparse.ArgumentParser(add_help=False)
    world.add_argument("--planet", choices=sorted(PLANETS), default="earth")
    known, rest = world.parse_known_args(sys.argv[1:] if argv is None else argv)
    resolve = partial(resolve_policy, planet=known.planet)
    return app_main(rest, resolve_policy=resolve, prog="visland companion")


if __name__ == "__main__":
    sys.exit(main())
