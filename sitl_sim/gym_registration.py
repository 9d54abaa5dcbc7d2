"""The gymnasium id of the landing task, registered whenever gymnasium is installed (the
``[sim]`` extra); the entry point is lazy, so registering imports nothing of the simulator."""

from __future__ import annotations

__all__ = ["ENV_ID"]

ENV_ID = "visland/Landing-v0"
"""The gymnasium id of :class:`sitl_sim.env.LandingEnv`."""

try:
    import gymnasium as _gym
except ImportError:  # pragma: no cover - a companion-only install
    _gym = None
if _gym is not None and ENV_ID not in _gym.registry:
    _gym.register(id=ENV_ID, entry_point="sitl_sim.env:LandingEnv", max_episode_steps=None)
