"""Small stand-ins the unit tests share: decoded MAVLink messages without a link, one step of
a logged episode as the observation the companion built in flight, the CLI run as a user runs
it, the scenarios of the rendering, site and config tests (a high start, a rocky site), the
shipped config files edited for the bad-config tests, and camera frames (a short flight, one
frame from a hovering camera)."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from companion.contract import Command, Observation
from sitl_sim.config import CONFIG_DIR, load_sim, load_vehicle
from sitl_sim.scenario import InitialState, Scenario, scenario_from_dict
from sitl_sim.simulator import Simulator
from sitl_sim.site.site import Site
from sitl_sim.world import episode_world
from training.provenance import REPO

__all__ = [
    "HIGH_START",
    "NO_RETURN_CM",
    "FakeMsg",
    "attitude_msg",
    "config_plus",
    "edited_config",
    "episode_observation",
    "flight_frames",
    "hover_frame",
    "imu_msg",
    "range_msg",
    "rocky_site",
    "scenario_with",
    "visland",
]

NO_RETURN_CM = 65535
"""DISTANCE_SENSOR ``current_distance`` of a rangefinder with no return (UINT16_MAX)."""


def visland(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    """``visland ARGS`` as its own process from the repository root, output captured."""
    return subprocess.run(
        [sys.executable, "-m", "tools.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
    )


def edited_config(tmp_path: Path, name: str, old: str, new: str) -> Path:
    """The shipped ``configs/<name>`` with ``old`` (which must be in it) replaced by ``new``,
    written as ``tmp_path/<name>``."""
    text = (CONFIG_DIR / name).read_text()
    assert old in text
    out = tmp_path / name
    out.write_text(text.replace(old, new))
    return out


def config_plus(tmp_path: Path, extra: str, base: Path = CONFIG_DIR / "scenario.toml") -> Path:
    """``base`` (the shipped scenario) with ``extra`` appended, written as
    ``tmp_path/scenario.toml``."""
    out = tmp_path / "scenario.toml"
    out.write_text(base.read_text() + extra)
    return out


class FakeMsg(SimpleNamespace):
    """A stand-in for a decoded pymavlink message: its fields, ``get_type()`` and
    ``get_srcComponent()`` (the autopilot's component, 1)."""

    def get_type(self) -> str:
        return self.name

    def get_srcComponent(self) -> int:  # pymavlink's name
        return 1


def range_msg(time_boot_ms: int, range_cm: int, quality: int = 100, **fields: Any) -> FakeMsg:
    """DISTANCE_SENSOR of the downward rangefinder (orientation 25, 0-150 m) reading
    ``range_cm`` (:data:`NO_RETURN_CM`: no return) at signal ``quality``; ``fields`` replace
    any other."""
    values = dict(
        time_boot_ms=time_boot_ms,
        min_distance=0,
        max_distance=15000,
        current_distance=range_cm,
        orientation=25,
        signal_quality=quality,
    )
    return FakeMsg(name="DISTANCE_SENSOR", **{**values, **fields})


def attitude_msg(time_boot_ms: int, **fields: Any) -> FakeMsg:
    """ATTITUDE of a level vehicle, not rotating; ``fields`` replace any field."""
    values = dict(roll=0.0, pitch=0.0, yaw=0.0, rollspeed=0.0, pitchspeed=0.0, yawspeed=0.0)
    return FakeMsg(name="ATTITUDE", time_boot_ms=time_boot_ms, **{**values, **fields})


def imu_msg(time_usec: int, **fields: Any) -> FakeMsg:
    """HIGHRES_IMU of a level vehicle at rest (1 g up, no rotation, accel and gyro fields
    updated); ``fields`` replace any field."""
    values = dict(xacc=0.0, yacc=0.0, zacc=-9.81, xgyro=0.0, ygyro=0.0, zgyro=0.0)
    return FakeMsg(
        name="HIGHRES_IMU", time_usec=time_usec, fields_updated=0x3F, **{**values, **fields}
    )


def episode_observation(
    ep: Any, t: int, image_time_s: float, time_s: float, **fields: Any
) -> Observation:
    """Step ``t`` of a loaded episode (:class:`training.dataset.Episode` with images) as the
    companion's :class:`Observation`: the image stamped ``image_time_s``, attitude, range and
    IMU stamped ``time_s``; ``fields`` add the rest (``hover_thrust_norm``...)."""
    return Observation(
        image=np.ascontiguousarray(ep.images[t]),
        image_time_s=image_time_s,
        attitude_rad=ep.attitude_rad[t],
        rate_frd_rad_s=ep.rate_frd_rad_s[t],
        attitude_time_s=time_s,
        range_m=float(ep.range_m[t]),
        range_time_s=time_s,
        accel_frd_m_s2=ep.accel_frd_m_s2[t],
        imu_time_s=time_s,
        frame_id=int(ep.frame_id[t]),
        **fields,
    )


HIGH_START = {
    "initial_state": {
        "roll_pitch_deg": [-1.5, 1.5],
        "yaw_deg": [-180.0, 180.0],
        "north_east_m": [-5.0, 5.0],
        "altitude_m": [75.0, 100.0],
        "vel_north_east_m_s": [-1.0, 1.0],
        "vel_down_m_s": [0.0, 0.5],
        "rate_rad_s": [0.0, 0.0],
    }
}
"""An [initial_state] of the nominal high start (75-100 m over the pad): the rendering and
config tests' scenarios add their sections to it."""


def scenario_with(where: str = "test.toml", **sections: Any) -> Scenario:
    """The scenario :data:`HIGH_START` plus ``sections`` (``visual={...}``, ``pad={...}``...),
    read as if from the file ``where``."""
    return scenario_from_dict({**HIGH_START, **sections}, where)


def rocky_site(seed: int = 5, index: int = 1) -> tuple[Scenario, Site, int, tuple[float, float]]:
    """A scenario strewn with 0.3-0.6 m rocks (6 per 100 m²), the site it draws for episode
    ``(seed, index)``, and the index and (north, east) of that site's tallest rock."""
    sc = scenario_with(terrain={"rocks_per_100m2": 6.0, "rock_height_m": [0.3, 0.6]})
    site = episode_world(sc, seed, index).site
    rocks = site.terrain.rocks
    k = int(np.argmax(rocks.height))
    return sc, site, k, (float(rocks.north[k]), float(rocks.east[k]))


def _camera_sim(renderer: str | None, noiseless: bool) -> Simulator:
    cfg = load_sim()
    if noiseless:
        cfg = cfg.noiseless()
    if renderer is not None:
        cfg = replace(cfg, camera=replace(cfg.camera, renderer=renderer))
    return Simulator(load_vehicle(), cfg)


def flight_frames(
    scenario: Scenario, renderer: str, seed: int = 1, index: int = 0, n: int = 4
) -> list[np.ndarray]:
    """The first ``n`` camera frames (``renderer``, sensor noise on) of episode (``seed``,
    ``index``): a short flight from 12 m near the pad, a gentle roll/pitch manoeuvre."""
    sim = _camera_sim(renderer, noiseless=False)
    try:
        initial = InitialState((1.0, -2.0, -12.0), (0.2, 0.0, 0.3), (0.05, -0.02, 0.4), (0, 0, 0))
        world = episode_world(scenario, seed, index)
        sim.reset(initial, np.random.SeedSequence([seed, index]), world=world)
        out = []
        for k in range(n):
            out.append(sim.observe(frame_id=k).image)
            sim.step(Command.from_array([0.45, 0.3, -0.2, 0.0]))
        return out
    finally:
        sim.close()


def hover_frame(
    scenario: Scenario,
    pos_ned_m: tuple[float, float, float],
    renderer: str | None = None,
    seed: int = 0,
    index: int = 0,
    euler_rad: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> np.ndarray:
    """The first camera frame (noiseless; ``renderer``, None: the default one) of episode
    (``seed``, ``index``) from a vehicle at rest at ``pos_ned_m`` with attitude ``euler_rad``
    (roll, pitch, yaw)."""
    sim = _camera_sim(renderer, noiseless=True)
    try:
        initial = InitialState(pos_ned_m, (0.0, 0.0, 0.0), euler_rad, (0, 0, 0))
        world = episode_world(scenario, seed, index)
        sim.reset(initial, np.random.SeedSequence([seed, index]), world=world)
        return sim.observe().image
    finally:
        sim.close()
