"""The MPC expert's tuning: :class:`MpcConfig` and ``configs/expert.toml``.

Each key is declared once (:mod:`companion.table`, as PX4's module.yaml): its TOML table,
default, inclusive range, unit and meaning; a config is checked on construction, so one built
in code is validated the same way as one read from disk by :func:`load_mpc_config`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from companion.table import Section, integer, number, read_spread
from sitl_sim.config import CONFIG_DIR, load_toml
from sitl_sim.errors import ConfigError

__all__ = ["MpcConfig", "load_mpc_config"]


@dataclass(frozen=True)
class MpcConfig(Section):
    """Tuning of the MPC expert, read from ``configs/expert.toml``: each key is declared once
    with its table, default (the shipped tuning), range, unit and meaning; a key or table left
    out takes its default. Values are checked on construction, so a config built in code is
    validated the same way as one read from disk.
    """

    horizon_steps: int = integer(
        25, unit="steps", lo=5, hi=200, table="mpc", doc="prediction horizon"
    )
    near_distance_m: float = number(
        12.0,
        unit="m",
        lo=0.0,
        hi=1e3,
        table="mpc",
        doc="distance to the pad below which the near (tracking) cost is used",
    )
    max_descent_m_s: float = number(
        5.0, unit="m/s", lo=0.05, hi=20.0, table="descent", doc="fastest reference descent"
    )
    touchdown_descent_m_s: float = number(
        0.3,
        unit="m/s",
        lo=0.0,
        hi=2.0,
        table="descent",
        doc="reference descent speed at the ground",
    )
    descent_gain_1_s: float = number(
        0.5,
        unit="1/s",
        lo=0.0,
        hi=10.0,
        table="descent",
        doc="reference descent speed per metre of altitude",
    )
    descent_limit_at_ground_m_s: float = number(
        0.3,
        unit="m/s",
        lo=0.0,
        hi=5.0,
        table="descent",
        doc="soft limit on downward speed at the ground",
    )
    descent_limit_slope_1_s: float = number(
        0.8,
        unit="1/s",
        lo=0.0,
        hi=10.0,
        table="descent",
        doc="growth of that limit per metre of altitude",
    )
    approach_slope: float = number(
        1.0,
        unit="m/m",
        lo=0.0,
        hi=100.0,
        table="descent",
        doc="approach cone: altitude kept per metre off the pad",
    )
    approach_deadband_m: float = number(
        1.0,
        unit="m",
        lo=0.0,
        hi=100.0,
        table="descent",
        doc="horizontal distance within which the cone does not apply",
    )
    max_thrust_mg: float = number(
        2.5, unit="m g", lo=1.0, hi=10.0, table="limits", doc="collective thrust limit"
    )
    max_tilt_deg: float = number(
        30.0, unit="deg", lo=1.0, hi=80.0, table="limits", doc="roll and pitch limit"
    )
    touchdown_tilt_deg: float = number(
        16.0,
        unit="deg",
        lo=1.0,
        hi=80.0,
        table="limits",
        doc="roll and pitch limit of the plan's steps at the ground",
    )
    touchdown_tilt_height_m: float = number(
        0.4,
        unit="m",
        lo=0.0,
        hi=10.0,
        table="limits",
        doc="reference altitude below which the tilt limit closes (0: off)",
    )
    ground_margin_m: float = number(
        0.5,
        unit="m",
        lo=0.0,
        hi=1.0,
        table="limits",
        doc="predicted altitude may go this far below 0",
    )
    far_pos_ne: float = number(
        0.0, unit="1/m^2", lo=0.0, hi=1e6, table="weights", doc="far: horizontal position"
    )
    far_vel_ne: float = number(
        0.5, unit="s^2/m^2", lo=0.0, hi=1e6, table="weights", doc="far: horizontal velocity"
    )
    near_pos_ne: float = number(
        4.0, unit="1/m^2", lo=0.0, hi=1e6, table="weights", doc="near: horizontal position"
    )
    near_vel_ne: float = number(
        1.0, unit="s^2/m^2", lo=0.0, hi=1e6, table="weights", doc="near: horizontal velocity"
    )
    pos_d: float = number(
        0.05, unit="1/m^2", lo=0.0, hi=1e6, table="weights", doc="altitude vs the descent profile"
    )
    vel_d: float = number(
        4.0, unit="s^2/m^2", lo=0.0, hi=1e6, table="weights", doc="downward speed vs the profile"
    )
    tilt: float = number(1.0, unit="1/rad^2", lo=0.0, hi=1e6, table="weights", doc="roll and pitch")
    yaw: float = number(
        2.0, unit="1/rad^2", lo=0.0, hi=1e6, table="weights", doc="yaw error from the held heading"
    )
    terminal_pos_ne: float = number(
        20.0,
        unit="1/m^2",
        lo=0.0,
        hi=1e6,
        table="weights",
        doc="terminal horizontal position (added at step N)",
    )
    terminal_vel_ne: float = number(
        5.0,
        unit="s^2/m^2",
        lo=0.0,
        hi=1e6,
        table="weights",
        doc="terminal horizontal velocity (added at step N)",
    )
    thrust_norm: float = number(
        20.0, unit="1", lo=1e-6, hi=1e6, table="weights", doc="thrust_norm about hover"
    )
    rate_roll_pitch: float = number(
        0.5, unit="s^2/rad^2", lo=1e-6, hi=1e6, table="weights", doc="roll and pitch rates"
    )
    rate_yaw: float = number(
        1.0, unit="s^2/rad^2", lo=1e-6, hi=1e6, table="weights", doc="yaw rate"
    )
    slack_linear: float = number(
        1000.0, unit="1/unit", lo=0.0, hi=1e9, table="weights", doc="safety slack, linear (exact)"
    )
    slack_quadratic: float = number(
        100.0, unit="1/unit^2", lo=0.0, hi=1e9, table="weights", doc="safety slack, quadratic"
    )
    osqp_eps_abs: float = number(
        0.0001, unit="1", lo=1e-9, hi=1e-1, table="solver", doc="OSQP absolute tolerance"
    )
    osqp_eps_rel: float = number(
        0.0001, unit="1", lo=1e-9, hi=1e-1, table="solver", doc="OSQP relative tolerance"
    )
    osqp_max_iter: int = integer(
        4000, unit="1", lo=1, hi=1_000_000, table="solver", doc="OSQP iterations"
    )
    clarabel_max_iter: int = integer(
        200, unit="1", lo=1, hi=10_000, table="solver", doc="Clarabel (fallback) iterations"
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        for low, high in (
            ("touchdown_descent_m_s", "max_descent_m_s"),
            ("touchdown_tilt_deg", "max_tilt_deg"),
        ):
            if getattr(self, low) > getattr(self, high):
                raise ConfigError(
                    f"{self.source}: {low} = {getattr(self, low)} exceeds {high} = "
                    f"{getattr(self, high)}; expected touchdown <= max"
                )


def load_mpc_config(path: str | Path | None = None) -> MpcConfig:
    """Load and validate ``configs/expert.toml`` (or ``path``).

    Raises:
        ConfigError: naming the file, the table and the key that is unknown, mistyped or out
            of range (the keys and their defaults: ``docs/config_keys.md``).
    """
    path = Path(path) if path is not None else CONFIG_DIR / "expert.toml"
    return read_spread(MpcConfig, load_toml(path), str(path))
