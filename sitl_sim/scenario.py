"""Scenarios: the initial-state distribution of paper section 4.1, read from a TOML file.

``sampler = "sobol+uniform"`` (the paper's hybrid): a scrambled Sobol sequence covers the six
dimensions that shape a landing (north, east, altitude, and the three velocities) evenly; roll,
pitch, yaw and rates are drawn uniformly. ``sampler = "uniform"`` draws everything uniformly.
An optional ``[wind]`` section (:mod:`sitl_sim.wind`) adds wind, turbulence and gusts; an
optional ``[vehicle]`` section (:mod:`sitl_sim.airframe`) scales the vehicle file per episode;
``[visual]`` (:mod:`sitl_sim.visual`) draws ground families, sun, pad and camera effects;
``[sensors]`` (:mod:`sitl_sim.sensor_faults`) adds sensor faults; ``[link]``
(:mod:`sitl_sim.link_impairment`) impairs the MAVLink SITL's real-time link (loss, delay,
jitter, duplicates, reordering, outages).

Episode ``i`` of seed ``s`` always gets the same initial state, whichever process asks for it, so
parallel workers and resumed runs agree.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import qmc

from sitl_sim.airframe import AirframeConfig, airframe_config_from_table
from sitl_sim.config import CONFIG_DIR, PLANETS, Planet, load_toml, number_pair, planet
from sitl_sim.dynamics import quat_from_euler
from sitl_sim.errors import ConfigError
from sitl_sim.link_impairment import LinkConfig, link_config_from_table
from sitl_sim.sensor_faults import SensorFaultsConfig, sensor_faults_config_from_table
from sitl_sim.visual import VisualConfig, visual_config_from_table
from sitl_sim.wind import WindConfig, wind_config_from_table

__all__ = [
    "SECTIONS",
    "InitialState",
    "InitialStateSampler",
    "Scenario",
    "load_scenario",
    "scenario_from_dict",
]

_RANGE_KEYS = (
    "roll_pitch_deg",
    "yaw_deg",
    "north_east_m",
    "altitude_m",
    "vel_north_east_m_s",
    "vel_down_m_s",
    "rate_rad_s",
)
_SAMPLERS = ("sobol+uniform", "uniform")


@dataclass(frozen=True)
class Scenario:
    """Ranges ``(lo, hi)`` of the initial state, the sampler, the planet, and the optional
    sections: the wind (None: still air), the airframe factors of ``[vehicle]`` (None: the
    vehicle file as is), the look of ``[visual]`` (None: the nominal ground and camera) and the
    sensor faults (None: the sensors of the sim config, no faults) and the link impairment
    (None: a perfect link; only the real-time MAVLink SITL has a link to impair)."""

    roll_pitch_deg: tuple[float, float]
    yaw_deg: tuple[float, float]
    north_east_m: tuple[float, float]
    altitude_m: tuple[float, float]
    vel_north_east_m_s: tuple[float, float]
    vel_down_m_s: tuple[float, float]
    rate_rad_s: tuple[float, float]
    sampler: str
    world: Planet
    source: str = "<memory>"
    wind: WindConfig | None = None
    visual: VisualConfig | None = None
    vehicle: AirframeConfig | None = None
    sensors: SensorFaultsConfig | None = None
    link: LinkConfig | None = None

    def __post_init__(self) -> None:
        for key in _RANGE_KEYS:
            lo, hi = getattr(self, key)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi):
                raise ConfigError(
                    f"{self.source}: [initial_state] {key} = [{lo}, {hi}]; expected finite [lo, hi]"
                    " with lo <= hi"
                )
        if self.altitude_m[0] <= 0.0:
            raise ConfigError(
                f"{self.source}: [initial_state] altitude_m starts at {self.altitude_m[0]}; "
                "expected > 0 (the vehicle starts in the air)"
            )
        if self.sampler not in _SAMPLERS:
            raise ConfigError(
                f"{self.source}: [initial_state] sampler = {self.sampler!r}; expected one of "
                f"{list(_SAMPLERS)}"
            )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["world"] = self.world.name
        # an absent section is left out: a nominal scenario's record (in every log) is unchanged
        for key in ("wind", "vehicle", "visual", "sensors", "link"):
            section = getattr(self, key)
            if section is None:
                del d[key]
            else:
                d[key] = section.to_dict()
        return d


SECTIONS = ("initial_state", "world", "wind", "vehicle", "visual", "sensors", "link")
"""The tables a scenario file may hold; any other is refused (a misspelt section would
otherwise fly the nominal world without a word)."""


def load_scenario(path: str | Path | None = None) -> Scenario:
    """Read a scenario TOML (default ``configs/scenario.toml``) with the keys of DESIGN.md."""
    path = Path(path) if path is not None else CONFIG_DIR / "scenario.toml"
    return scenario_from_dict(load_toml(path), str(path))


def scenario_from_dict(data: Any, where: str) -> Scenario:
    """Check and type a scenario table (the parsed contents of a scenario file, or a table
    inline in another file); ``where`` starts every ConfigError message (the file, or e.g.
    ``suite.toml: [conditions.windy]``) and becomes the scenario's ``source``."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a table of scenario sections, got {data!r}")
    unknown_sections = sorted(set(data) - set(SECTIONS))
    if unknown_sections:
        raise ConfigError(
            f"{where}: unknown section(s) {['[' + s + ']' for s in unknown_sections]}; "
            f"expected {['[' + s + ']' for s in SECTIONS]} (typo?)"
        )
    init = data.get("initial_state")
    if not isinstance(init, dict):
        raise ConfigError(f"{where}: missing table [initial_state]")
    unknown = sorted(set(init) - {*_RANGE_KEYS, "sampler"})
    if unknown:
        raise ConfigError(f"{where}: [initial_state] unknown key(s) {unknown}")
    ranges: dict[str, tuple[float, float]] = {}
    for key in _RANGE_KEYS:
        if key not in init:
            raise ConfigError(f"{where}: [initial_state] missing key {key!r}")
        value = init[key]
        pair = number_pair(value)
        if pair is None:
            raise ConfigError(
                f"{where}: [initial_state] {key} = {value!r}; expected [lo, hi] (two numbers)"
            )
        ranges[key] = pair
    sampler = init.get("sampler", "sobol+uniform")
    world_tbl = data.get("world", {})
    if not isinstance(world_tbl, dict):
        raise ConfigError(f"{where}: [world] must be a table")
    unknown = sorted(set(world_tbl) - {"planet"})
    if unknown:
        raise ConfigError(f"{where}: [world] unknown key(s) {unknown}; expected ['planet']")
    name = world_tbl.get("planet", "earth")
    if name not in PLANETS:
        raise ConfigError(f"{where}: [world] planet = {name!r}; expected one of {sorted(PLANETS)}")
    wind = wind_config_from_table(data["wind"], where) if "wind" in data else None
    airframe = airframe_config_from_table(data["vehicle"], where) if "vehicle" in data else None
    visual = visual_config_from_table(data["visual"], where) if "visual" in data else None
    sensors = sensor_faults_config_from_table(data["sensors"], where) if "sensors" in data else None
    link = link_config_from_table(data["link"], where) if "link" in data else None
    return Scenario(
        **ranges,
        sampler=str(sampler),
        world=planet(name),
        source=where,
        wind=wind,
        vehicle=airframe,
        visual=visual,
        sensors=sensors,
        link=link,
    )


@dataclass(frozen=True)
class InitialState:
    """One sampled initial state (NED/FRD)."""

    pos_ned_m: tuple[float, float, float]
    vel_ned_m_s: tuple[float, float, float]
    euler_rad: tuple[float, float, float]
    rate_frd_rad_s: tuple[float, float, float]

    @property
    def quat_wxyz(self) -> np.ndarray:
        return quat_from_euler(*self.euler_rad)

    def to_dict(self) -> dict[str, list[float]]:
        return {k: list(v) for k, v in asdict(self).items()}


class InitialStateSampler:
    """Deterministic initial states for episode indices 0, 1, 2, ... of one seed."""

    _SOBOL_DIMS = 6  # north, east, altitude, vel north, vel east, vel down

    def __init__(self, scenario: Scenario, seed: int) -> None:
        self.scenario = scenario
        self.seed = int(seed)
        self._sobol = np.empty((0, self._SOBOL_DIMS))

    def _sobol_point(self, index: int) -> np.ndarray:
        if index >= len(self._sobol):
            m = max(6, math.ceil(math.log2(index + 1)))
            engine = qmc.Sobol(d=self._SOBOL_DIMS, scramble=True, seed=self.seed)
            self._sobol = engine.random_base2(m)
        return self._sobol[index]

    def sample(self, index: int) -> InitialState:
        if index < 0:
            raise ValueError(f"episode index must be >= 0, got {index}")
        sc = self.scenario
        rng = np.random.default_rng([self.seed, index])
        unit_uniform = rng.random(10)
        if sc.sampler == "sobol+uniform":
            unit = self._sobol_point(index)
        else:
            unit = unit_uniform[:6]

        def lerp(rg: tuple[float, float], u: float) -> float:
            return rg[0] + (rg[1] - rg[0]) * float(u)

        north = lerp(sc.north_east_m, unit[0])
        east = lerp(sc.north_east_m, unit[1])
        alt = lerp(sc.altitude_m, unit[2])
        vel = (
            lerp(sc.vel_north_east_m_s, unit[3]),
            lerp(sc.vel_north_east_m_s, unit[4]),
            lerp(sc.vel_down_m_s, unit[5]),
        )
        roll = math.radians(lerp(sc.roll_pitch_deg, unit_uniform[6]))
        pitch = math.radians(lerp(sc.roll_pitch_deg, unit_uniform[7]))
        yaw = math.radians(lerp(sc.yaw_deg, unit_uniform[8]))
        rates = tuple(lerp(sc.rate_rad_s, u) for u in rng.random(3))
        return InitialState(
            pos_ned_m=(north, east, -alt),
            vel_ned_m_s=vel,
            euler_rad=(roll, pitch, yaw),
            rate_frd_rad_s=rates,  # type: ignore[arg-type]
        )
