"""The simulator: vehicle model, dynamics, rate loop, sensors, pybullet camera, gymnasium env.

Importing this package registers the gymnasium environment ``visland/Landing-v0``.
"""

from __future__ import annotations

import gymnasium as gym

from sitl_sim.config import (
    PLANETS,
    Planet,
    SimConfig,
    VehicleConfig,
    load_sim,
    load_vehicle,
    planet,
)
from sitl_sim.env import ENV_ID, LandingEnv
from sitl_sim.errors import ConfigError, SimError, SimStateError
from sitl_sim.metrics import EpisodeResult, summarize
from sitl_sim.scenario import InitialState, InitialStateSampler, Scenario, load_scenario
from sitl_sim.simulator import Simulator

__all__ = [
    "ENV_ID",
    "PLANETS",
    "ConfigError",
    "EpisodeResult",
    "InitialState",
    "InitialStateSampler",
    "LandingEnv",
    "Planet",
    "Scenario",
    "SimConfig",
    "SimError",
    "SimStateError",
    "Simulator",
    "VehicleConfig",
    "load_scenario",
    "load_sim",
    "load_vehicle",
    "planet",
    "summarize",
]

if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point="sitl_sim.env:LandingEnv", max_episode_steps=None)
