"""``visland pictures``: the worlds, drawn — camera frames across the visual conditions and a
flight through wind — so a reader (and the author) can check them with their own eyes.

- ``visual_conditions.png``: rows are visual conditions (the nominal ground, each procedural
  family, low sun, haze, blur + flicker, lens distortion, a small jittered pad), columns the
  camera at 80, 20, 5 and 1.5 m over the pad; every frame is what the policy gets (the simulator's
  ``observe()``: render, light, effects, sensor noise), from the fast renderer.
- ``wind_flight.png``: the MPC expert landing through severe turbulence and gusts: top view of
  the path with the wind at the vehicle drawn along it, and the wind's components and the
  altitude over time.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from sitl_sim.config import load_sim, load_vehicle
from sitl_sim.scenario import InitialState, InitialStateSampler, scenario_from_dict
from sitl_sim.simulator import Simulator
from sitl_sim.world import episode_world
from training.provenance import REPO
from training.seeds import EVAL_SEED

__all__ = ["VISUAL_ROWS", "draw_visual_conditions", "draw_wind_flight"]

ALTITUDES_M = (80.0, 20.0, 5.0, 1.5)
VISUAL_ROWS: list[tuple[str, dict]] = [
    ("nominal ground", {"terrain": ["nominal"]}),
    ("regolith", {"terrain": ["regolith"], "sun_elevation_deg": [50.0, 50.0]}),
    ("mars_rocks", {"terrain": ["mars_rocks"], "sun_elevation_deg": [35.0, 35.0]}),
    ("sand", {"terrain": ["sand"], "sun_elevation_deg": [30.0, 30.0]}),
    ("grass", {"terrain": ["grass"], "sun_elevation_deg": [60.0, 60.0]}),
    ("asphalt", {"terrain": ["asphalt"], "sun_elevation_deg": [70.0, 70.0]}),
    ("gravel", {"terrain": ["gravel"], "sun_elevation_deg": [40.0, 40.0]}),
    ("low sun 6 deg", {"terrain": ["mars_rocks"], "sun_elevation_deg": [6.0, 6.0]}),
    ("haze 0.6", {"terrain": ["sand"], "haze": [0.6, 0.6]}),
    (
        "blur 40 ms + flicker",
        {"terrain": ["regolith"], "motion_blur_ms": [40.0, 40.0], "exposure_noise": 0.2},
    ),
    ("lens k1 -0.3", {"terrain": ["gravel"], "lens_k1": [-0.3, -0.3]}),
    (
        "pad 0.7x, colours +-30 %",
        {"terrain": ["asphalt"], "pad_scale": [0.7, 0.7], "pad_colour_jitter": 0.3},
    ),
]
_INITIAL = {
    "roll_pitch_deg": [0.0, 0.0],
    "yaw_deg": [0.0, 0.0],
    "north_east_m": [0.0, 0.0],
    "altitude_m": [10.0, 10.0],
    "vel_north_east_m_s": [0.0, 0.0],
    "vel_down_m_s": [0.0, 0.0],
    "rate_rad_s": [0.0, 0.0],
}


def _frame(sim: Simulator, visual: dict, altitude: float, seed: int) -> np.ndarray:
    scenario = scenario_from_dict({"initial_state": _INITIAL, "visual": visual}, "pictures")
    # a little off the pad, yawed and rolling (the blur row shows the smear of the roll rate)
    offset = 0.12 * altitude
    initial = InitialState(
        (offset, -0.5 * offset, -altitude), (0, 0, 0), (0.05, 0.03, 0.6), (1.5, 0.4, 0.0)
    )
    sim.reset(initial, seed, world=episode_world(scenario, seed, 0))
    return sim.observe().image


def draw_visual_conditions(out_png: str | Path, seed: int = 3) -> Path:
    """The grid of camera frames (rows: :data:`VISUAL_ROWS`, columns: :data:`ALTITUDES_M`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sim_cfg = load_sim()
    sim_cfg = replace(sim_cfg, camera=replace(sim_cfg.camera, renderer="fast"))
    sim = Simulator(load_vehicle(), sim_cfg)
    try:
        frames = [[_frame(sim, v, a, seed) for a in ALTITUDES_M] for _, v in VISUAL_ROWS]
    finally:
        sim.close()
    rows, cols = len(VISUAL_ROWS), len(ALTITUDES_M)
    fig, axes = plt.subplots(rows, cols, figsize=(1.9 * cols + 1.6, 1.9 * rows))
    for r, (name, _) in enumerate(VISUAL_ROWS):
        for c, alt in enumerate(ALTITUDES_M):
            ax = axes[r][c]
            ax.imshow(frames[r][c], cmap="gray", vmin=0, vmax=255, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(f"{alt:g} m", fontsize=10)
            if c == 0:
                ax.set_ylabel(name, fontsize=9)
    fig.suptitle("Camera frames (128 x 128 mono, as the policy sees them) per [visual] condition")
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return out


def draw_wind_flight(out_png: str | Path, seed: int = EVAL_SEED, episode: int = 0) -> Path:
    """The expert's flight through episode ``episode`` of the standard suite's ``wind_severe``
    condition."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from expert.mpc import MpcExpert
    from training.suite import load_suite

    suite = load_suite(REPO / "configs/suites/standard.toml")
    scenario = next(c.scenario for c in suite.conditions if c.name == "wind_severe")
    vehicle, sim_cfg = load_vehicle(), load_sim()
    sim = Simulator(vehicle, sim_cfg, render=False)
    expert = MpcExpert(vehicle, sim_cfg)
    initial = InitialStateSampler(scenario, seed).sample(episode)
    sim.reset(
        initial,
        np.random.SeedSequence([seed, episode]),
        world=episode_world(scenario, seed, episode),
    )
    state = expert.initial_state()
    t, pos, wind = [], [], []
    steps = round(sim_cfg.episode_timeout_s * sim_cfg.control_rate_hz)
    for k in range(steps):
        gt = sim.ground_truth()
        t.append(gt.time_s)
        pos.append(gt.pos_ned_m)
        wind.append(gt.wind_ned_m_s)
        cmd, state = expert.act(sim.observe(k, gt), gt, state)
        if sim.step(cmd) is not None:
            break
    sim.close()
    t, pos, wind = np.array(t), np.array(pos), np.array(wind)
    err = float(np.hypot(*sim.ground_truth().pos_ned_m[:2]))
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(12, 5))
    ax0.plot(pos[:, 1], pos[:, 0], "k-", lw=1.2, label="path (expert MPC)")
    every = max(1, len(t) // 25)
    ax0.quiver(
        pos[::every, 1],
        pos[::every, 0],
        wind[::every, 1],
        wind[::every, 0],
        color="tab:blue",
        angles="xy",
        scale_units="xy",
        scale=4.0,
        width=0.004,
        label="wind at the vehicle (1 m of arrow = 4 m/s)",
    )
    ax0.plot([pos[0, 1]], [pos[0, 0]], "go", label="start")
    ax0.plot([pos[-1, 1]], [pos[-1, 0]], "rx", ms=10, label=f"touchdown, {err:.3f} m off")
    ax0.add_patch(plt.Rectangle((-2, -2), 4, 4, fill=False, ec="tab:green", lw=1.5))
    ax0.set_xlabel("east (m)")
    ax0.set_ylabel("north (m)")
    ax0.set_aspect("equal", adjustable="datalim")
    ax0.legend(fontsize=8, loc="best")
    ax0.set_title("Top view: path and wind vectors")
    for i, name in enumerate(("north", "east", "down")):
        ax1.plot(t, wind[:, i], lw=1, label=f"wind {name} (m/s)")
    ax1.set_xlabel("time (s)")
    ax1.set_ylabel("wind (m/s)")
    ax2 = ax1.twinx()
    ax2.plot(t, -pos[:, 2], "k--", lw=1, label="altitude (m)")
    ax2.set_ylabel("altitude (m)")
    lines = ax1.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    labels = ax1.get_legend_handles_labels()[1] + ax2.get_legend_handles_labels()[1]
    ax1.legend(lines, labels, fontsize=8, loc="upper right")
    ax1.set_title("Severe Dryden turbulence + 1-cosine gusts (6-10 m/s mean)")
    fig.suptitle(f"Wind flight: seed {seed}, episode {episode}")
    fig.tight_layout()
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out
