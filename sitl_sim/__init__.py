"""The simulator: vehicle model, dynamics, rate loop, sensors, pybullet camera, gymnasium env.

Importing this package registers the gymnasium environment ``visland/Landing-v0``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from companion.lazy import lazy_exports
from sitl_sim.errors import ConfigError, SimError, SimStateError
from sitl_sim.gym_registration import ENV_ID

if TYPE_CHECKING:
    from sitl_sim.config import (
        PLANETS,
        Planet,
        SimConfig,
        VehicleConfig,
        load_sim,
        load_vehicle,
        planet,
    )
    from sitl_sim.env import LandingEnv
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

_LAZY = {
    "PLANETS": "config",
    "Planet": "config",
    "SimConfig": "config",
    "VehicleConfig": "config",
    "load_sim": "config",
    "load_vehicle": "config",
    "planet": "config",
    "LandingEnv": "env",
    "EpisodeResult": "metrics",
    "summarize": "metrics",
    "InitialState": "scenario",
    "InitialStateSampler": "scenario",
    "Scenario": "scenario",
    "load_scenario": "scenario",
    "Simulator": "simulator",
}
"""Public names imported on first access (PEP 562): the package itself imports nothing of the
``[sim]`` extra (numpy aside), so a light submodule (``sitl_sim.mavlink.endpoint``, the CLI's
flags) loads where pybullet, scipy and gymnasium are not installed."""


__getattr__, __dir__ = lazy_exports(__name__, _LAZY, __all__)
