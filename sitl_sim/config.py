"""Typed, validated configuration: the vehicle (paper Table 1), planets, and simulation settings.

Every number is read once, from TOML, into frozen dataclasses; every consumer (dynamics, rate
controller, sensors, camera, the MPC expert) takes these objects, never a loose dict.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.files import read_toml
from sitl_sim.errors import ConfigError

__all__ = [
    "CONFIG_DIR",
    "PLANETS",
    "AttitudeConfig",
    "CameraConfig",
    "ImuConfig",
    "Planet",
    "RadarConfig",
    "RateControllerConfig",
    "SimConfig",
    "VehicleConfig",
    "load_sim",
    "load_toml",
    "load_vehicle",
    "planet",
]

CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
"""The repository's ``configs/`` folder (the defaults every command starts from)."""


@dataclass(frozen=True)
class Planet:
    """Gravity and air density of a world."""

    name: str
    gravity_m_s2: float
    air_density_kg_m3: float


PLANETS: dict[str, Planet] = {
    "earth": Planet("earth", 9.81, 1.225),
    "mars": Planet("mars", 3.71, 0.020),
}


def planet(name: str) -> Planet:
    """The planet profile called ``name``; a ConfigError lists the known ones."""
    try:
        return PLANETS[name]
    except KeyError:
        raise ConfigError(
            f"planet: unknown planet {name!r}; expected one of {sorted(PLANETS)}"
        ) from None


# --------------------------------------------------------------------------- field readers


class _Fields:
    """Reads typed, range-checked fields out of one TOML table, naming file and key on error."""

    def __init__(self, data: dict[str, Any], where: str) -> None:
        self._data = data
        self._where = where
        self.used: set[str] = set()

    def table(self, key: str) -> _Fields:
        value = self._data.get(key)
        if not isinstance(value, dict):
            raise ConfigError(f"{self._where}: missing table [{key}]")
        self.used.add(key)
        return _Fields(value, f"{self._where} [{key}]")

    def value(self, key: str) -> Any:
        """The raw value of ``key`` (None when absent), for a field with checks of its own."""
        if key in self._data:
            self.used.add(key)
        return self._data.get(key)

    def _raw(self, key: str, default: Any) -> Any:
        if key not in self._data:
            if default is None:
                raise ConfigError(f"{self._where}: missing key {key!r}")
            return default
        self.used.add(key)
        return self._data[key]

    def number(
        self, key: str, lo: float, hi: float, default: float | None = None, *, lo_open=False
    ) -> float:
        value = self._raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{self._where}: {key} must be a number, got {value!r}")
        value = float(value)
        below = value <= lo if lo_open else value < lo
        if not math.isfinite(value) or below or value > hi:
            bracket = "(" if lo_open else "["
            raise ConfigError(
                f"{self._where}: {key} = {value} is out of range; expected {bracket}{lo}, {hi}]"
            )
        return value

    def integer(self, key: str, lo: int, hi: int, default: int | None = None) -> int:
        value = self._raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{self._where}: {key} must be an integer, got {value!r}")
        if not lo <= value <= hi:
            raise ConfigError(
                f"{self._where}: {key} = {value}; expected an integer in [{lo}, {hi}]"
            )
        return value

    def vector(
        self, key: str, n: int, lo: float, hi: float, default: list[float] | None = None
    ) -> tuple[float, ...]:
        value = self._raw(key, default)
        if not isinstance(value, list) or len(value) != n:
            raise ConfigError(f"{self._where}: {key} must be a list of {n} numbers, got {value!r}")
        out = []
        for i, item in enumerate(value):
            if isinstance(item, bool) or not isinstance(item, int | float):
                raise ConfigError(f"{self._where}: {key}[{i}] must be a number, got {item!r}")
            if not math.isfinite(item) or not lo <= item <= hi:
                raise ConfigError(
                    f"{self._where}: {key}[{i}] = {item} is out of range; expected [{lo}, {hi}]"
                )
            out.append(float(item))
        return tuple(out)

    def string(self, key: str, choices: tuple[str, ...], default: str | None = None) -> str:
        value = self._raw(key, default)
        if not isinstance(value, str) or value not in choices:
            raise ConfigError(f"{self._where}: {key} = {value!r}; expected one of {list(choices)}")
        return value

    def check_unknown(self) -> None:
        unknown = sorted(set(self._data) - self.used)
        if unknown:
            raise ConfigError(f"{self._where}: unknown key(s) {unknown} (typo?)")


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; a missing or malformed file is a ConfigError naming it."""
    return read_toml(path, ConfigError)


# --------------------------------------------------------------------------- vehicle


@dataclass(frozen=True)
class RateControllerConfig:
    """Body-rate PID gains (angular acceleration per rate error), per FRD axis."""

    kp: tuple[float, float, float]
    ki: tuple[float, float, float]
    kd: tuple[float, float, float]
    integrator_limit_rad_s2: tuple[float, float, float]
    max_rate_rad_s: tuple[float, float, float]


@dataclass(frozen=True)
class VehicleConfig:
    """The quadrotor (paper Table 1) and its autopilot's rate-loop tuning.

    Rotors are in X configuration, numbered as PX4's quad X: 1 front-right (CCW), 2 rear-left
    (CCW), 3 front-left (CW), 4 rear-right (CW).
    """

    mass_kg: float
    arm_length_m: float
    inertia_diag_kg_m2: tuple[float, float, float]
    max_total_thrust_n_by_planet: tuple[tuple[str, float], ...]
    """T_max of all four rotors together per planet name, ``(("earth", 25.0), ...)`` (a tuple
    so the config stays hashable). Stated per planet in the file, never derived: a rotor's
    thrust depends on the air density. Read it through :meth:`max_total_thrust_n`."""
    motor_time_constant_s: float
    yaw_torque_per_thrust_m: float
    drag_coefficient_area_m2: tuple[float, float, float]
    rate_controller: RateControllerConfig
    source: str = field(default="<memory>", compare=False)
    """The file it came from (for error messages; not part of the vehicle)."""

    def max_total_thrust_n(self, world: Planet) -> float:
        """T_max of all four rotors on ``world``, N.

        Raises:
            ConfigError: the vehicle file states no T_max for that planet (naming the file
                and the planet): thrust must never silently follow another planet's air.
        """
        for name, thrust_n in self.max_total_thrust_n_by_planet:
            if name == world.name:
                return thrust_n
        stated = [name for name, _ in self.max_total_thrust_n_by_planet]
        raise ConfigError(
            f"{self.source}: [vehicle.max_total_thrust_n] has no T_max for planet "
            f"{world.name!r} (stated: {stated}); add '{world.name} = <N>' for the rotors "
            "this vehicle flies there (thrust depends on the air density, so it is not derived "
            "from another planet's figure)"
        )

    @property
    def inertia_kg_m2(self) -> np.ndarray:
        return np.diag(self.inertia_diag_kg_m2)

    def hover_thrust_norm(self, world: Planet) -> float:
        """Collective thrust fraction that balances gravity on ``world`` (PX4's
        MPC_THR_HOVER): ``m g / T_max(world)``."""
        return self.mass_kg * world.gravity_m_s2 / self.max_total_thrust_n(world)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        del d["source"]  # where it was read from is not the vehicle (logs compare vehicles)
        d["max_total_thrust_n_by_planet"] = dict(self.max_total_thrust_n_by_planet)
        return d


def load_vehicle(path: str | Path | None = None) -> VehicleConfig:
    """Load and validate ``configs/vehicle.toml`` (or ``path``)."""
    path = Path(path) if path is not None else CONFIG_DIR / "vehicle.toml"
    root = _Fields(load_toml(path), str(path))
    v = root.table("vehicle")
    rc = root.table("rate_controller")
    rate = RateControllerConfig(
        kp=rc.vector("kp", 3, 0.0, 1e3),  # type: ignore[arg-type]
        ki=rc.vector("ki", 3, 0.0, 1e3),  # type: ignore[arg-type]
        kd=rc.vector("kd", 3, 0.0, 1e2),  # type: ignore[arg-type]
        integrator_limit_rad_s2=rc.vector("integrator_limit_rad_s2", 3, 0.0, 1e3),  # type: ignore[arg-type]
        max_rate_rad_s=rc.vector("max_rate_rad_s", 3, 0.01, 20.0),  # type: ignore[arg-type]
    )
    cfg = VehicleConfig(
        mass_kg=v.number("mass_kg", 0.0, 100.0, lo_open=True),
        arm_length_m=v.number("arm_length_m", 0.0, 5.0, lo_open=True),
        inertia_diag_kg_m2=v.vector("inertia_diag_kg_m2", 3, 1e-6, 100.0),  # type: ignore[arg-type]
        max_total_thrust_n_by_planet=_thrust_by_planet(v, str(path)),
        motor_time_constant_s=v.number("motor_time_constant_s", 0.0, 1.0),
        yaw_torque_per_thrust_m=v.number("yaw_torque_per_thrust_m", 0.0, 1.0),
        drag_coefficient_area_m2=v.vector("drag_coefficient_area_m2", 3, 0.0, 10.0),  # type: ignore[arg-type]
        rate_controller=rate,
        source=str(path),
    )
    for section in (root, v, rc):
        section.check_unknown()
    return cfg


def _thrust_by_planet(v: _Fields, where: str) -> tuple[tuple[str, float], ...]:
    """``[vehicle.max_total_thrust_n]``: one T_max per planet the vehicle may fly."""
    table = v.value("max_total_thrust_n")
    key = "[vehicle.max_total_thrust_n]"
    if table is None:
        raise ConfigError(
            f"{where}: missing table {key} (T_max in N per planet, e.g. earth = 25.0)"
        )
    if not isinstance(table, dict) or not table:
        raise ConfigError(
            f"{where}: [vehicle] max_total_thrust_n = {table!r}; expected a table {key} with "
            f"T_max (N) per planet, e.g. earth = 25.0 (known planets {sorted(PLANETS)}): a "
            "rotor's thrust depends on the air density, so each planet's figure is stated"
        )
    unknown = sorted(set(table) - set(PLANETS))
    if unknown:
        raise ConfigError(
            f"{where}: {key} unknown planet(s) {unknown}; expected some of {sorted(PLANETS)}"
        )
    thrust = _Fields(table, f"{where} {key}")
    return tuple(
        (name, thrust.number(name, 0.0, 1e4, lo_open=True)) for name in PLANETS if name in table
    )


# --------------------------------------------------------------------------- simulation


@dataclass(frozen=True)
class ImuConfig:
    accel_noise_std_m_s2: float
    gyro_noise_std_rad_s: float
    accel_bias_walk_m_s2_sqrt_s: float
    gyro_bias_walk_rad_s_sqrt_s: float


@dataclass(frozen=True)
class AttitudeConfig:
    angle_noise_std_rad: float
    rate_noise_std_rad_s: float


@dataclass(frozen=True)
class RadarConfig:
    max_range_m: float
    noise_std_m: float
    noise_fraction: float


@dataclass(frozen=True)
class CameraConfig:
    width_px: int
    height_px: int
    fov_deg: float
    noise_std_px: float
    renderer: str = "pybullet"
    """``"pybullet"`` (TinyRenderer, the reference) or ``"fast"`` (plane homographies, the same
    image: :mod:`sitl_sim.render.render_fast`)."""


@dataclass(frozen=True)
class SimConfig:
    """Rates, timeout, planet and sensor models of one simulation."""

    physics_rate_hz: int
    control_rate_hz: int
    episode_timeout_s: float
    planet: Planet
    imu: ImuConfig
    attitude: AttitudeConfig
    radar: RadarConfig
    camera: CameraConfig

    def __post_init__(self) -> None:
        if self.physics_rate_hz % self.control_rate_hz != 0:
            raise ConfigError(
                f"[sim] physics_rate_hz = {self.physics_rate_hz} must be an integer multiple of "
                f"control_rate_hz = {self.control_rate_hz}"
            )
        if self.physics_rate_hz < 250:
            raise ConfigError(
                f"[sim] physics_rate_hz = {self.physics_rate_hz}; expected >= 250 "
                "(RK4 must resolve the 20 ms motor lag)"
            )

    @property
    def physics_dt_s(self) -> float:
        return 1.0 / self.physics_rate_hz

    @property
    def control_dt_s(self) -> float:
        return 1.0 / self.control_rate_hz

    @property
    def substeps(self) -> int:
        """Physics steps per control/camera step."""
        return self.physics_rate_hz // self.control_rate_hz

    def with_planet(self, world: Planet) -> SimConfig:
        from dataclasses import replace

        return replace(self, planet=world)

    def noiseless(self) -> SimConfig:
        """The same configuration with every sensor noise and bias walk set to zero."""
        from dataclasses import replace

        return replace(
            self,
            imu=ImuConfig(0.0, 0.0, 0.0, 0.0),
            attitude=AttitudeConfig(0.0, 0.0),
            radar=replace(self.radar, noise_std_m=0.0, noise_fraction=0.0),
            camera=replace(self.camera, noise_std_px=0.0),
        )

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def load_sim(path: str | Path | None = None) -> SimConfig:
    """Load and validate ``configs/sim.toml`` (or ``path``)."""
    path = Path(path) if path is not None else CONFIG_DIR / "sim.toml"
    root = _Fields(load_toml(path), str(path))
    s, i, a, r, c = (root.table(k) for k in ("sim", "imu", "attitude", "radar", "camera"))
    try:
        cfg = _build_sim(s, i, a, r, c)
    except ConfigError as exc:
        if str(exc).startswith(str(path)):
            raise
        raise ConfigError(f"{path}: {exc}") from None  # cross-field checks name the file too
    for section in (root, s, i, a, r, c):
        section.check_unknown()
    return cfg


def _build_sim(s: _Fields, i: _Fields, a: _Fields, r: _Fields, c: _Fields) -> SimConfig:
    return SimConfig(
        physics_rate_hz=s.integer("physics_rate_hz", 1, 100_000),
        control_rate_hz=s.integer("control_rate_hz", 1, 1000),
        episode_timeout_s=s.number("episode_timeout_s", 0.0, 3600.0, lo_open=True),
        planet=planet(s.string("planet", tuple(PLANETS))),
        imu=ImuConfig(
            accel_noise_std_m_s2=i.number("accel_noise_std_m_s2", 0.0, 10.0),
            gyro_noise_std_rad_s=i.number("gyro_noise_std_rad_s", 0.0, 1.0),
            accel_bias_walk_m_s2_sqrt_s=i.number("accel_bias_walk_m_s2_sqrt_s", 0.0, 1.0),
            gyro_bias_walk_rad_s_sqrt_s=i.number("gyro_bias_walk_rad_s_sqrt_s", 0.0, 1.0),
        ),
        attitude=AttitudeConfig(
            angle_noise_std_rad=a.number("angle_noise_std_rad", 0.0, 0.5),
            rate_noise_std_rad_s=a.number("rate_noise_std_rad_s", 0.0, 1.0),
        ),
        radar=RadarConfig(
            max_range_m=r.number("max_range_m", 0.0, 10_000.0, lo_open=True),
            noise_std_m=r.number("noise_std_m", 0.0, 10.0),
            noise_fraction=r.number("noise_fraction", 0.0, 0.5),
        ),
        camera=CameraConfig(
            width_px=c.integer("width_px", 8, 4096),
            height_px=c.integer("height_px", 8, 4096),
            fov_deg=c.number("fov_deg", 1.0, 170.0),
            noise_std_px=c.number("noise_std_px", 0.0, 64.0),
            renderer=c.string("renderer", ("pybullet", "fast"), "pybullet"),
        ),
    )
