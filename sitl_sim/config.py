"""Typed, validated configuration: the vehicle (paper Table 1), planets, and simulation settings.

Every number is read once, from TOML, into frozen dataclasses; every consumer (dynamics, rate
controller, sensors, camera, the MPC expert) takes these objects, never a loose dict.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from companion.files import read_toml
from companion.table import (
    Section,
    check_tables,
    choice,
    integer,
    number,
    read_values,
    section_dict,
    vector,
)
from sitl_sim.errors import ConfigError

__all__ = [
    "CONFIG_DIR",
    "CONFIG_SECTIONS",
    "PLANETS",
    "AttitudeConfig",
    "CameraConfig",
    "ImuConfig",
    "Planet",
    "RadarConfig",
    "RateControllerConfig",
    "SimConfig",
    "SimSection",
    "ThrustTable",
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


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file; a missing or malformed file is a ConfigError naming it."""
    return read_toml(path, ConfigError)


# --------------------------------------------------------------------------- vehicle


@dataclass(frozen=True)
class RateControllerConfig(Section):
    """``[rate_controller]``: body-rate PID gains (angular acceleration per rate error), per
    FRD axis, as PX4's MC_ROLLRATE_* / MC_PITCHRATE_* / MC_YAWRATE_*."""

    SECTION: ClassVar[str] = "rate_controller"

    kp: tuple[float, float, float] = vector(
        (25.0, 25.0, 8.0), size=3, unit="1/s", lo=0.0, hi=1e3, doc="proportional gain"
    )
    ki: tuple[float, float, float] = vector(
        (5.0, 5.0, 2.0), size=3, unit="1/s^2", lo=0.0, hi=1e3, doc="integral gain"
    )
    kd: tuple[float, float, float] = vector(
        (0.0, 0.0, 0.0), size=3, unit="1", lo=0.0, hi=1e2, doc="derivative gain"
    )
    integrator_limit_rad_s2: tuple[float, float, float] = vector(
        (5.0, 5.0, 2.0), size=3, unit="rad/s^2", lo=0.0, hi=1e3, doc="anti-windup clamp"
    )
    max_rate_rad_s: tuple[float, float, float] = vector(
        (3.5, 3.5, 1.5), size=3, unit="rad/s", lo=0.01, hi=20.0, doc="setpoints are clamped"
    )


@dataclass(frozen=True)
class ThrustTable(Section):
    """``[vehicle.max_total_thrust_n]``: T_max of all four rotors per planet the vehicle may
    fly (a rotor's thrust depends on the air density, so each is stated, never derived)."""

    SECTION: ClassVar[str] = "vehicle.max_total_thrust_n"

    earth: float | None = number(
        None, unit="N", lo=0.0, lo_open=True, hi=1e4, doc="T_max on Earth (absent: not flown)"
    )
    mars: float | None = number(
        None, unit="N", lo=0.0, lo_open=True, hi=1e4, doc="T_max on Mars (absent: not flown)"
    )


@dataclass(frozen=True)
class VehicleConfig(Section):
    """The quadrotor (paper Table 1) and its autopilot's rate-loop tuning: ``[vehicle]``
    (every key required: a vehicle's own physics has no nominal value), its
    ``[vehicle.max_total_thrust_n]`` and ``[rate_controller]``.

    Rotors are in X configuration, numbered as PX4's quad X: 1 front-right (CCW), 2 rear-left
    (CCW), 3 front-left (CW), 4 rear-right (CW).
    """

    SECTION: ClassVar[str] = "vehicle"

    mass_kg: float = number(unit="kg", lo=0.0, lo_open=True, hi=100.0, doc="take-off mass")
    arm_length_m: float = number(
        unit="m", lo=0.0, lo_open=True, hi=5.0, doc="motor to centre, X configuration"
    )
    inertia_diag_kg_m2: tuple[float, float, float] = vector(
        size=3, unit="kg m^2", lo=1e-6, hi=100.0, doc="Ixx, Iyy, Izz (FRD body axes)"
    )
    max_total_thrust_n_by_planet: tuple[tuple[str, float], ...]
    """T_max of all four rotors together per planet name, ``(("earth", 25.0), ...)`` (a tuple
    so the config stays hashable), from ``[vehicle.max_total_thrust_n]``. Read it through
    :meth:`max_total_thrust_n`."""
    motor_time_constant_s: float = number(
        unit="s", lo=0.0, hi=1.0, doc="first-order rotor thrust lag"
    )
    yaw_torque_per_thrust_m: float = number(
        unit="m", lo=0.0, hi=1.0, doc="rotor drag torque / rotor thrust (k_m / k_f)"
    )
    drag_coefficient_area_m2: tuple[float, float, float] = vector(
        size=3, unit="m^2", lo=0.0, hi=10.0, doc="C_D A along body F, R, D (quadratic drag)"
    )
    rate_controller: RateControllerConfig

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
        """Every field (where it was read from is not the vehicle: logs compare vehicles)."""
        d = _without_source(self)
        d["max_total_thrust_n_by_planet"] = dict(self.max_total_thrust_n_by_planet)
        return d


def _without_source(obj: Any) -> dict[str, Any]:
    """``asdict(obj)`` less every section's ``source`` (where it was read is not the value)."""

    def drop(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: drop(v) for k, v in value.items() if k != "source"}
        return value

    return drop(asdict(obj))


_THRUST = "max_total_thrust_n"


def load_vehicle(path: str | Path | None = None) -> VehicleConfig:
    """Load and validate ``configs/vehicle.toml`` (or ``path``)."""
    path = Path(path) if path is not None else CONFIG_DIR / "vehicle.toml"
    where = str(path)
    data = load_toml(path)
    check_tables(data, where, ("vehicle", "rate_controller"), required=("vehicle",))
    table = data["vehicle"]
    thrust = table.get(_THRUST)
    if thrust is None:
        raise ConfigError(
            f"{where}: missing table [vehicle.{_THRUST}] (T_max in N per planet, e.g. earth = 25.0)"
        )
    if not isinstance(thrust, dict) or not thrust:
        raise ConfigError(
            f"{where}: [vehicle] {_THRUST} = {thrust!r}; expected a table "
            f"[vehicle.{_THRUST}] with T_max (N) per planet, e.g. earth = 25.0 (known planets "
            f"{sorted(PLANETS)}): a rotor's thrust depends on the air density, so each "
            "planet's figure is stated"
        )
    stated = section_dict(ThrustTable.from_table(thrust, where), drop_none=True)
    return VehicleConfig(
        **read_values(VehicleConfig, {k: v for k, v in table.items() if k != _THRUST}, where),
        max_total_thrust_n_by_planet=tuple(stated.items()),
        rate_controller=RateControllerConfig.from_table(data.get("rate_controller", {}), where),
        source=where,
    )


# --------------------------------------------------------------------------- simulation


@dataclass(frozen=True)
class SimSection(Section):
    """``[sim]``: rates, timeout and planet (the scenario file may set another planet)."""

    SECTION: ClassVar[str] = "sim"

    physics_rate_hz: int = integer(
        250, unit="Hz", lo=250, hi=100_000, doc="RK4 rate (resolves the 20 ms motor lag)"
    )
    control_rate_hz: int = integer(
        10, unit="Hz", lo=1, hi=1000, doc="camera and control rate (paper Table 1)"
    )
    episode_timeout_s: float = number(
        90.0, unit="s", lo=0.0, lo_open=True, hi=3600.0, doc="an episode ends unlanded"
    )
    planet: str = choice("earth", PLANETS, doc="gravity and air of the world")


@dataclass(frozen=True)
class ImuConfig(Section):
    """``[imu]``: accelerometer and gyroscope noise and bias random walk."""

    SECTION: ClassVar[str] = "imu"

    accel_noise_std_m_s2: float = number(0.05, unit="m/s^2", lo=0.0, hi=10.0, doc="1-sigma")
    gyro_noise_std_rad_s: float = number(0.003, unit="rad/s", lo=0.0, hi=1.0, doc="1-sigma")
    accel_bias_walk_m_s2_sqrt_s: float = number(
        0.001, unit="m/s^2/sqrt(s)", lo=0.0, hi=1.0, doc="bias random walk"
    )
    gyro_bias_walk_rad_s_sqrt_s: float = number(
        0.0001, unit="rad/s/sqrt(s)", lo=0.0, hi=1.0, doc="bias random walk"
    )


@dataclass(frozen=True)
class AttitudeConfig(Section):
    """``[attitude]``: noise of the autopilot's attitude estimate (not a raw sensor)."""

    SECTION: ClassVar[str] = "attitude"

    angle_noise_std_rad: float = number(0.002, unit="rad", lo=0.0, hi=0.5, doc="1-sigma")
    rate_noise_std_rad_s: float = number(0.003, unit="rad/s", lo=0.0, hi=1.0, doc="1-sigma")


@dataclass(frozen=True)
class RadarConfig(Section):
    """``[radar]``: the radar altimeter (paper Table 1: 0-150 m)."""

    SECTION: ClassVar[str] = "radar"

    max_range_m: float = number(
        150.0, unit="m", lo=0.0, lo_open=True, hi=10_000.0, doc="no reading beyond"
    )
    noise_std_m: float = number(0.02, unit="m", lo=0.0, hi=10.0, doc="1-sigma, fixed part")
    noise_fraction: float = number(0.002, unit="1", lo=0.0, hi=0.5, doc="1-sigma per m of range")


@dataclass(frozen=True)
class CameraConfig(Section):
    """``[camera]``: the downward camera (paper Table 1: 128 x 128 px, 45 deg)."""

    SECTION: ClassVar[str] = "camera"

    width_px: int = integer(128, unit="px", lo=8, hi=4096, doc="image width")
    height_px: int = integer(128, unit="px", lo=8, hi=4096, doc="image height")
    fov_deg: float = number(45.0, unit="deg", lo=1.0, hi=170.0, doc="full field of view")
    noise_std_px: float = number(
        2.0, unit="grey levels", lo=0.0, hi=64.0, doc="additive pixel noise, 1-sigma"
    )
    renderer: str = choice(
        "pybullet",
        ("pybullet", "fast"),
        doc="pybullet (TinyRenderer, the reference) or fast (plane homographies, the same image)",
    )


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
        return _without_source(self)


_SIM_TABLES = (SimSection, ImuConfig, AttitudeConfig, RadarConfig, CameraConfig)


CONFIG_SECTIONS: dict[str, tuple[type, ...]] = {
    "vehicle.toml": (VehicleConfig, ThrustTable, RateControllerConfig),
    "sim.toml": _SIM_TABLES,
}
"""The sections of each file of ``configs/`` read here (for ``docs/config_keys.md``)."""


def load_sim(path: str | Path | None = None) -> SimConfig:
    """Load and validate ``configs/sim.toml`` (or ``path``); a table or key left out takes
    its nominal value (``docs/config_keys.md``)."""
    path = Path(path) if path is not None else CONFIG_DIR / "sim.toml"
    where = str(path)
    data = load_toml(path)
    check_tables(data, where, (cls.SECTION for cls in _SIM_TABLES))
    sim, imu, attitude, radar, camera = (
        cls.from_table(data.get(cls.SECTION, {}), where) for cls in _SIM_TABLES
    )
    try:
        return SimConfig(
            physics_rate_hz=sim.physics_rate_hz,
            control_rate_hz=sim.control_rate_hz,
            episode_timeout_s=sim.episode_timeout_s,
            planet=planet(sim.planet),
            imu=imu,
            attitude=attitude,
            radar=radar,
            camera=camera,
        )
    except ConfigError as exc:  # cross-field checks name the file too
        raise ConfigError(f"{where}: {exc}") from None
