"""Shared fixtures: configs read from the repository's configs/, one pybullet scene per session."""

from __future__ import annotations

import pytest

from sitl_sim.config import SimConfig, VehicleConfig, load_sim, load_vehicle
from sitl_sim.scene import Scene


@pytest.fixture(scope="session")
def vehicle() -> VehicleConfig:
    return load_vehicle()


@pytest.fixture(scope="session")
def sim_cfg() -> SimConfig:
    return load_sim()


@pytest.fixture(scope="session")
def quiet_cfg(sim_cfg: SimConfig) -> SimConfig:
    """The default simulation with every sensor noise off (physics tests)."""
    return sim_cfg.noiseless()


@pytest.fixture(scope="session")
def scene():
    with Scene() as s:
        yield s
