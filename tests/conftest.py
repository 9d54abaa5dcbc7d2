"""Shared fixtures: configs read from the repository's configs/, one pybullet scene per session,
a test's subprocesses, in-process SITL configs on free loopback ports."""

from __future__ import annotations

import os

# Before numpy loads: one OpenBLAS kernel for every machine the suite runs on. The bit-for-bit
# digests of nominal flights (test_airframe, test_sensor_faults) were recorded with OpenBLAS's
# Haswell (AVX2) kernels; an AVX-512 machine picks SkylakeX kernels by default, whose small
# matrix products round differently in the last bit, and every flight drifts from the record.
# Flights are bit-identical per (seed, episode) on one machine and kernel (docs/DESIGN.md).
os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

from collections.abc import Iterator
from pathlib import Path

import pytest
from flights import LOW_INITIAL_STATE, Ports, Processes, free_ports

from sitl_sim.config import SimConfig, VehicleConfig, load_sim, load_vehicle
from sitl_sim.mavlink.config import SitlConfig
from sitl_sim.render.scene import Scene


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


@pytest.fixture
def procs(tmp_path) -> Iterator[Processes]:
    """The test's subprocesses (:class:`flights.Processes`), stopped by PID at teardown."""
    p = Processes(tmp_path)
    yield p
    p.stop_all()


@pytest.fixture(scope="session")
def scene():
    with Scene() as s:
        yield s


LOW_SCENARIO = f"""
[initial_state]{LOW_INITIAL_STATE}sampler = "uniform"
[world]
planet = "earth"
"""
"""Short flights from 5-6 m over the pad (SITL, companion and log tests)."""


@pytest.fixture(scope="session")
def low_scenario(tmp_path_factory) -> str:
    """Path of a scenario file with :data:`LOW_SCENARIO`."""
    path = tmp_path_factory.mktemp("scenario") / "low.toml"
    path.write_text(LOW_SCENARIO)
    return str(path)


@pytest.fixture
def loopback_sitl():
    """A factory: ``make(scenario, log_dir, **overrides) -> (ports, SitlConfig)`` — fresh
    loopback UDP ports (``ports.mavlink``, ``.remote``, ``.camera``) and an in-process SITL
    config on them without GCS link or rendering, stopping after 60 s of wall time at most."""

    def make(scenario, log_dir, **overrides) -> tuple[Ports, SitlConfig]:
        ports = free_ports()
        values = dict(
            mavlink_port=ports.mavlink,
            remote_port=ports.remote,
            camera_port=ports.camera,
            gcs=False,
            scenario=str(scenario),
            log_dir=str(Path(log_dir)),
            render=False,
            max_wall_s=60.0,
        )
        values.update(overrides)
        return ports, SitlConfig(**values)

    return make
