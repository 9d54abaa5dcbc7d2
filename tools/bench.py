"""Benchmarks that print the figures the issues ask for (``visland bench ...``).

``bench sim``: the simulator's real-time factor on one core — physics (RK4 + rate loop), sensors
and the pybullet camera at 10 Hz — flown by the cascade controller; in the same run, physics
alone and the camera alone, so the split is visible whatever else the machine is doing.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from typing import Any

from expert.cascade import CascadeLander
from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.scenario import InitialStateSampler, load_scenario
from sitl_sim.simulator import Simulator

__all__ = ["SimBenchConfig", "bench_sim"]


@dataclass(frozen=True)
class SimBenchConfig:
    sim_seconds: float = 20.0
    """Simulated seconds per repeat."""
    repeats: int = 3
    """Repeats (the median is reported)."""
    seed: int = 0


def _fly(sim: Simulator, pilot: CascadeLander, seconds: float, render: bool) -> float:
    steps = round(seconds * sim.sim.control_rate_hz)
    t0 = time.perf_counter()
    for k in range(steps):
        gt = sim.ground_truth()
        if render:
            sim.observe(frame_id=k, truth=gt)
        sim.step(pilot.command(gt.pos_ned_m, gt.vel_ned_m_s, gt.quat_wxyz))
    return time.perf_counter() - t0


def bench_sim(cfg: SimBenchConfig) -> dict[str, Any]:
    vehicle, sim_cfg = load_vehicle(), load_sim()
    initial = InitialStateSampler(load_scenario(), cfg.seed).sample(0)
    full = Simulator(vehicle, sim_cfg, render=True)
    phys_only = Simulator(vehicle, sim_cfg, render=False)
    pilot = CascadeLander(vehicle, sim_cfg.planet)
    walls_full, walls_phys, walls_cam = [], [], []
    try:
        for _ in range(cfg.repeats):
            full.reset(initial, cfg.seed)
            walls_full.append(_fly(full, pilot, cfg.sim_seconds, render=True))
            phys_only.reset(initial, cfg.seed)
            walls_phys.append(_fly(phys_only, pilot, cfg.sim_seconds, render=False))
            full.reset(initial, cfg.seed)
            n = round(cfg.sim_seconds * sim_cfg.control_rate_hz)
            t0 = time.perf_counter()
            for k in range(n):
                full.observe(frame_id=k)
            walls_cam.append(time.perf_counter() - t0)
    finally:
        full.close()
    wall_full = statistics.median(walls_full)
    wall_phys = statistics.median(walls_phys)
    wall_cam = statistics.median(walls_cam)
    frames = cfg.sim_seconds * sim_cfg.control_rate_hz
    physics_steps = cfg.sim_seconds * sim_cfg.physics_rate_hz
    return {
        "benchmark": "sim",
        "sim_seconds": cfg.sim_seconds,
        "repeats": cfg.repeats,
        "physics_rate_hz": sim_cfg.physics_rate_hz,
        "camera_rate_hz": sim_cfg.control_rate_hz,
        "realtime_factor": cfg.sim_seconds / wall_full,
        "realtime_factor_physics_only": cfg.sim_seconds / wall_phys,
        "physics_step_us": 1e6 * wall_phys / physics_steps,
        "camera_frame_ms": 1e3 * wall_cam / frames,
        "camera_share_of_wall": wall_cam / wall_full,
    }
