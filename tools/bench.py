"""Benchmarks that print the figures the issues ask for (``visland bench ...``).

``bench sim``: the simulator's real-time factor on one core — physics (RK4 + rate loop), sensors
and the camera at 10 Hz — flown by the cascade controller; in the same run, physics alone and the
camera alone, so the split is visible whatever else the machine is doing. ``physics_step_us`` is
the physics-only flight's wall time per physics step (the cascade's command and the ground truth
at 10 Hz included); ``kernel`` says whether the physics kernel ran compiled (numba) or as
Python. The camera is timed with both renderers in the same run: the headline figures are the
chosen one's (default ``fast``), and ``baseline`` holds pybullet's (the reference renderer), with
the speed-up as a ratio. ``--scenario`` benches a scenario's first episode world (e.g.
``[visual]`` effects).
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, replace
from typing import Any

from expert.cascade import CascadeLander
from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.physics import kernel
from sitl_sim.scenario import InitialStateSampler, load_scenario
from sitl_sim.simulator import Simulator
from sitl_sim.world import episode_world

__all__ = ["SimBenchConfig", "bench_sim"]


@dataclass(frozen=True)
class SimBenchConfig:
    sim_seconds: float = 20.0
    """Simulated seconds per repeat."""
    repeats: int = 3
    """Repeats (the median is reported)."""
    seed: int = 0
    renderer: str = "fast"
    """The renderer of the headline figures; pybullet is always timed too, as the baseline."""
    scenario: str | None = None
    """A scenario file (default: configs/scenario.toml, the nominal world)."""


def _fly(
    sim: Simulator, pilot: CascadeLander, seconds: float, render: bool, stepwise: bool = False
) -> float:
    """Wall time of a flight; ``stepwise``: one physics step per call (the SITL's path)."""
    steps = round(seconds * sim.sim.control_rate_hz)
    substeps = sim.sim.substeps
    t0 = time.perf_counter()
    for k in range(steps):
        gt = sim.ground_truth()
        if render:
            sim.observe(frame_id=k, truth=gt)
        cmd = pilot.command(gt.pos_ned_m, gt.vel_ned_m_s, gt.quat_wxyz)
        if stepwise:
            for _ in range(substeps):
                sim.step_physics(cmd)
        else:
            sim.step(cmd)
    return time.perf_counter() - t0


def _bench_renderer(cfg: SimBenchConfig, renderer: str) -> dict[str, Any]:
    vehicle, sim_cfg = load_vehicle(), load_sim()
    sim_cfg = replace(sim_cfg, camera=replace(sim_cfg.camera, renderer=renderer))
    scenario = load_scenario(cfg.scenario)
    if scenario.world != sim_cfg.planet:
        sim_cfg = sim_cfg.with_planet(scenario.world)
    initial = InitialStateSampler(scenario, cfg.seed).sample(0)
    full = Simulator(vehicle, sim_cfg, render=True)
    phys_only = Simulator(vehicle, sim_cfg, render=False)
    pilot = CascadeLander(vehicle, sim_cfg.planet)
    walls_full, walls_phys, walls_stepwise, walls_cam = [], [], [], []

    def world():
        return episode_world(scenario, cfg.seed, 0)

    try:
        for _ in range(cfg.repeats):
            full.reset(initial, cfg.seed, world())
            walls_full.append(_fly(full, pilot, cfg.sim_seconds, render=True))
            phys_only.reset(initial, cfg.seed, world())
            walls_phys.append(_fly(phys_only, pilot, cfg.sim_seconds, render=False))
            phys_only.reset(initial, cfg.seed, world())
            walls_stepwise.append(
                _fly(phys_only, pilot, cfg.sim_seconds, render=False, stepwise=True)
            )
            full.reset(initial, cfg.seed, world())
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
        "renderer": renderer,
        "kernel": kernel.KERNEL,
        "physics_rate_hz": sim_cfg.physics_rate_hz,
        "camera_rate_hz": sim_cfg.control_rate_hz,
        "realtime_factor": cfg.sim_seconds / wall_full,
        "realtime_factor_physics_only": cfg.sim_seconds / wall_phys,
        "physics_step_us": 1e6 * wall_phys / physics_steps,
        "physics_step_us_stepwise": 1e6 * statistics.median(walls_stepwise) / physics_steps,
        "camera_frame_ms": 1e3 * wall_cam / frames,
        "camera_share_of_wall": wall_cam / wall_full,
    }


def bench_sim(cfg: SimBenchConfig) -> dict[str, Any]:
    """The chosen renderer's figures, then pybullet's in the same run as ``baseline``."""
    head = _bench_renderer(cfg, cfg.renderer)
    base = head if cfg.renderer == "pybullet" else _bench_renderer(cfg, "pybullet")
    return {
        "benchmark": "sim",
        "scenario": cfg.scenario or "configs/scenario.toml",
        "sim_seconds": cfg.sim_seconds,
        "repeats": cfg.repeats,
        **head,
        "baseline": {
            k: v for k, v in base.items() if k not in ("physics_rate_hz", "camera_rate_hz")
        },
        "camera_speedup_vs_baseline": base["camera_frame_ms"] / head["camera_frame_ms"],
        "realtime_speedup_vs_baseline": head["realtime_factor"] / base["realtime_factor"],
    }
