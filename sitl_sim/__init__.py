"""The simulator: vehicle model, dynamics, rate loop, sensors, pybullet camera, gymnasium env.

Importing this package registers the gymnasium environment ``visland/Landing-v0``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from sitl_sim.errors import ConfigError, SimError, SimStateError

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

ENV_ID = "visland/Landing-v0"
"""The gymnasium id of :class:`sitl_sim.env.LandingEnv`."""

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


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


try:  # registered whenever gymnasium is installed (the [sim] extra); the entry point is lazy
    import gymnasium as _gym
except ImportError:  # pragma: no cover - a companion-only install
    _gym = None
if _gym is not None and ENV_ID not in _gym.registry:
    _gym.register(id=ENV_ID, entry_point="sitl_sim.env:LandingEnv", max_episode_steps=None)
