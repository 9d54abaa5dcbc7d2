"""Scenarios: the initial-state distribution of paper section 4.1, read from a TOML file.

``sampler = "sobol+uniform"`` (the paper's hybrid): a scrambled Sobol sequence covers the six
dimensions that shape a landing (north, east, altitude, and the three velocities) evenly; roll,
pitch, yaw and rates are drawn uniformly. ``sampler = "uniform"`` draws everything uniformly.
An optional ``[wind]`` section (:mod:`sitl_sim.physics.wind`) adds wind, turbulence and gusts; an
optional ``[vehicle]`` section (:mod:`sitl_sim.physics.airframe`) scales the vehicle file per
episode;
``[visual]`` (:mod:`sitl_sim.render.visual`) draws ground families or ground pictures, sun, pad
size and colour and camera effects; ``[pad]`` (:mod:`sitl_sim.render.pad_section`) picks the pad
design and how it moves (on a rover, on a ship's deck); ``[terrain]``
(:mod:`sitl_sim.site.terrain`) tilts the ground and adds relief, rocks and craters;
``[sensors]`` (:mod:`sitl_sim.physics.sensor_faults`) adds sensor faults; ``[link]``
(:mod:`sitl_sim.mavlink.link_impairment`) impairs the MAVLink SITL's real-time link (loss, delay,
jitter, duplicates, reordering, outages).

Episode ``i`` of seed ``s`` always gets the same initial state, whichever process asks for it, so
parallel workers and resumed runs agree.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from scipy.stats import qmc

from companion.table import Section, check_section, check_tables, choice, read_values, span
from sitl_sim.config import CONFIG_DIR, PLANETS, Planet, load_toml, planet
from sitl_sim.errors import ConfigError
from sitl_sim.mavlink.link_impairment import LinkConfig
from sitl_sim.physics.airframe import AirframeConfig
from sitl_sim.physics.dynamics import quat_from_euler
from sitl_sim.physics.sensor_faults import SensorFaultsConfig
from sitl_sim.physics.wind import WindConfig
from sitl_sim.render.pad_section import PadConfig
from sitl_sim.render.visual import VisualConfig
from sitl_sim.site.terrain import TerrainConfig

__all__ = [
    "SECTIONS",
    "InitialState",
    "InitialStateSampler",
    "Scenario",
    "WorldSection",
    "load_scenario",
    "scenario_from_dict",
    "scenario_tables",
]

_SAMPLERS = ("sobol+uniform", "uniform")


def _range(unit: str, doc: str, **bounds: Any) -> Any:
    return span(unit=unit, doc=doc, **bounds)


@dataclass(frozen=True)
class WorldSection(Section):
    """The ``[world]`` section: the planet flown (gravity, air density: :data:`PLANETS`)."""

    SECTION: ClassVar[str] = "world"

    planet: str = choice("earth", PLANETS, doc="gravity and air density of the world flown")


@dataclass(frozen=True)
class Scenario:
    """Ranges ``(lo, hi)`` of the initial state (the ``[initial_state]`` keys), the sampler,
    the planet, and the optional sections: the wind (None: still air), the airframe factors of
    ``[vehicle]`` (None: the vehicle file as is), the look of ``[visual]`` (None: the nominal
    ground and camera), the pad of ``[pad]`` (None: the paper's pad, still), the ground's relief
    of ``[terrain]`` (None: flat), the sensor faults (None:
    the sensors of the sim config, no faults) and the link impairment (None: a perfect link;
    only the real-time MAVLink SITL has a link to impair)."""

    SECTION: ClassVar[str] = "initial_state"

    roll_pitch_deg: tuple[float, float] = _range(
        "deg", "roll and pitch, each drawn uniformly (beyond 90: upside down)", lo=-90.0, hi=90.0
    )
    yaw_deg: tuple[float, float] = _range("deg", "yaw, drawn uniformly", lo=-360.0, hi=360.0)
    north_east_m: tuple[float, float] = _range(
        "m", "north and east of the pad (Sobol)", lo=-500.0, hi=500.0
    )
    altitude_m: tuple[float, float] = _range(
        "m",
        "altitude above the pad (Sobol); starts in the air, within reach of a landing (the "
        "radar sees 150 m, an episode lasts 90 s)",
        lo=0.0,
        lo_open=True,
        hi=300.0,
    )
    vel_north_east_m_s: tuple[float, float] = _range(
        "m/s", "north and east velocity (Sobol)", lo=-30.0, hi=30.0
    )
    vel_down_m_s: tuple[float, float] = _range(
        "m/s", "downward velocity (Sobol)", lo=-30.0, hi=30.0
    )
    rate_rad_s: tuple[float, float] = _range(
        "rad/s", "each body rate, drawn uniformly", lo=-20.0, hi=20.0
    )
    sampler: str = choice(
        "sobol+uniform",
        _SAMPLERS,
        doc="Sobol for position and velocity, uniform for the rest; or uniform for all",
    )
    world: Planet = PLANETS["earth"]
    """``[world] planet``: gravity, air density and the vehicle's T_max there."""
    source: str = "<memory>"
    """The file it was read from (named in every error)."""
    # The optional sections: None = the section is absent, the nominal world bit for bit.
    wind: WindConfig | None = None
    """``[wind]``: mean wind, Dryden turbulence, gusts (:mod:`sitl_sim.physics.wind`)."""
    visual: VisualConfig | None = None
    """``[visual]``: ground, light and camera effects (:mod:`sitl_sim.render.visual`)."""
    pad: PadConfig | None = None
    """``[pad]``: which pad and how it moves (:mod:`sitl_sim.render.pad_section`)."""
    terrain: TerrainConfig | None = None
    """``[terrain]``: slope, relief, rocks, craters (:mod:`sitl_sim.site.terrain`)."""
    vehicle: AirframeConfig | None = None
    """``[vehicle]``: the airframe's spread (:mod:`sitl_sim.physics.airframe`)."""
    sensors: SensorFaultsConfig | None = None
    """``[sensors]``: camera, radar and IMU faults (:mod:`sitl_sim.physics.sensor_faults`)."""
    link: LinkConfig | None = None
    """``[link]``: MAVLink impairment, real time only (:mod:`sitl_sim.mavlink.link_impairment`)."""

    def __post_init__(self) -> None:
        if math.isfinite(self.altitude_m[0]) and self.altitude_m[0] <= 0.0:
            raise ConfigError(
                f"{self.source}: [initial_state] altitude_m starts at {self.altitude_m[0]}; "
                "expected > 0 (the vehicle starts in the air)"
            )
        check_section(self)
        if self.terrain is not None and self.pad is not None and self.pad.motion == "deck":
            raise ConfigError(
                f"{self.source}: [terrain] with [pad] motion = 'deck'; expected one of them (a "
                "deck floats on water: the ground is the sea, flat at its mean level)"
            )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["world"] = self.world.name
        # an absent section is left out: a nominal scenario's record (in every log) is unchanged
        for key in _OPTIONAL:
            section = getattr(self, key)
            if section is None:
                del d[key]
            else:
                d[key] = section.to_dict()
        return d


_OPTIONAL: dict[str, type[Section]] = {
    "wind": WindConfig,
    "vehicle": AirframeConfig,
    "visual": VisualConfig,
    "pad": PadConfig,
    "terrain": TerrainConfig,
    "sensors": SensorFaultsConfig,
    "link": LinkConfig,
}
"""The optional sections, each a :class:`companion.table.Section` (absent: None)."""

SECTIONS = ("initial_state", "world", *_OPTIONAL)
"""The tables a scenario file may hold; any other is refused (a misspelt section would
otherwise fly the nominal world without a word)."""


def scenario_tables() -> tuple[tuple[str, type], ...]:
    """Each scenario section's name and declaring class, in file order (for
    ``docs/config_keys.md``)."""
    classes = {"initial_state": Scenario, "world": WorldSection, **_OPTIONAL}
    return tuple((name, classes[name]) for name in SECTIONS)


def load_scenario(path: str | Path | None = None) -> Scenario:
    """Read a scenario TOML (default ``configs/scenario.toml``) with the keys of
    ``docs/config_keys.md``."""
    path = Path(path) if path is not None else CONFIG_DIR / "scenario.toml"
    return scenario_from_dict(load_toml(path), str(path))


def scenario_from_dict(data: Any, where: str) -> Scenario:
    """Check and type a scenario table (the parsed contents of a scenario file, or a table
    inline in another file); ``where`` starts every ConfigError message (the file, or e.g.
    ``suite.toml: [conditions.windy]``) and becomes the scenario's ``source``."""
    check_tables(data, where, SECTIONS, required=("initial_state",))
    initial = read_values(Scenario, data["initial_state"], where)
    world = WorldSection.from_table(data.get("world", {}), where)
    optional = {
        name: cls.from_table(data[name], where) if name in data else None
        for name, cls in _OPTIONAL.items()
    }
    return Scenario(**initial, world=planet(world.planet), source=where, **optional)


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
