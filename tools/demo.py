"""The demo flight: one simulated descent from the paper's distribution, narrated.

Until the companion and the shipped policy exist, the pilot is the privileged cascade
controller (``expert.cascade``); everything else — physics, rate loop, sensors, the pybullet
camera — is the real simulator.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from expert.cascade import CascadeLander
from sitl_sim.env import LandingEnv

__all__ = ["DemoConfig", "run"]


@dataclass(frozen=True)
class DemoConfig:
    """Options of ``visland demo``."""

    seed: int = 0
    """Scenario seed (the initial state is episode 0 of this seed)."""
    scenario: Path | None = None
    """Scenario TOML (default: configs/scenario.toml, the paper's distribution)."""
    report_every_s: float = 5.0
    """Print a state line every this many seconds of sim time."""


def run(cfg: DemoConfig, out: TextIO) -> dict[str, Any]:
    env = LandingEnv(scenario=cfg.scenario)
    try:
        pilot = CascadeLander(env.vehicle, env.sim_config.planet)
        obs, info = env.reset(seed=cfg.seed)
        st = env.initial_state
        out.write(
            f"visland demo — planet {env.sim_config.planet.name}, seed {cfg.seed}\n"
            f"start: N {st.pos_ned_m[0]:+.2f} m  E {st.pos_ned_m[1]:+.2f} m  "
            f"alt {-st.pos_ned_m[2]:.1f} m  yaw {math.degrees(st.euler_rad[2]):+.0f} deg\n"
            f"{'t [s]':>7} {'N [m]':>8} {'E [m]':>8} {'alt [m]':>8} {'v_down':>7} "
            f"{'radar [m]':>9} {'pad px':>7}\n"
        )
        wall0 = time.perf_counter()
        next_report = 0.0
        while True:
            gt = info["groundtruth"]
            if info["time_s"] >= next_report - 1e-9:
                pad_px = int(np.count_nonzero(obs["image"] > 140))
                out.write(
                    f"{info['time_s']:7.1f} {gt['pos_ned_m'][0]:8.2f} {gt['pos_ned_m'][1]:8.2f} "
                    f"{-gt['pos_ned_m'][2]:8.2f} {gt['vel_ned_m_s'][2]:7.2f} "
                    f"{float(obs['range_m'][0]):9.2f} {pad_px:7d}\n"
                )
                next_report += cfg.report_every_s
            cmd = pilot.command(gt["pos_ned_m"], gt["vel_ned_m_s"], gt["quat_wxyz"])
            obs, _, terminated, truncated, info = env.step(cmd.as_array())
            if terminated or truncated:
                break
        wall = time.perf_counter() - wall0
        result = info["result"]
        verdict = "LANDED" if result["landed"] else "TIMED OUT"
        out.write(
            f"{verdict} at t = {result['time_s']:.1f} s: landing error "
            f"{result['landing_error_m']:.3f} m, touchdown speed "
            f"{result['touchdown_speed_m_s']:.2f} m/s, tilt {result['tilt_deg']:.1f} deg, "
            f"success {result['success']}\n"
            f"simulated {result['time_s']:.1f} s in {wall:.1f} s wall "
            f"({result['time_s'] / wall:.0f}x real time, camera rendered at 10 Hz)\n"
        )
        return result
    finally:
        env.close()
