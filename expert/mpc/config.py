"""The MPC expert's tuning: :class:`MpcConfig`, its parameter checks and ``configs/expert.toml``.

Each field carries its TOML table, inclusive range, unit and help text (like PX4's
module.yaml); a config is checked on construction, so one built in code is validated the same
way as one read from disk by :func:`load_mpc_config`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from sitl_sim.config import CONFIG_DIR, load_toml
from sitl_sim.errors import ConfigError

__all__ = ["MpcConfig", "load_mpc_config"]


def _param(table: str, lo: float, hi: float, unit: str, doc: str, *, integer: bool = False) -> Any:
    """A config field: its TOML table, inclusive range, unit and help text (PX4 module.yaml)."""
    return field(
        metadata={"table": table, "lo": lo, "hi": hi, "unit": unit, "doc": doc, "int": integer}
    )


@dataclass(frozen=True)
class MpcConfig:
    """Tuning of the MPC expert, read from ``configs/expert.toml`` (every key required).

    Each field's metadata holds its TOML table, range, unit and help text; values are checked
    on construction, so a config built in code is validated the same way as one read from disk.
    """

    horizon_steps: int = _param("mpc", 5, 200, "steps", "prediction horizon", integer=True)
    near_distance_m: float = _param(
        "mpc", 0.0, 1e3, "m", "distance to the pad below which the near (tracking) cost is used"
    )
    max_descent_m_s: float = _param("descent", 0.05, 20.0, "m/s", "fastest reference descent")
    touchdown_descent_m_s: float = _param(
        "descent", 0.0, 2.0, "m/s", "reference descent speed at the ground"
    )
    descent_gain_1_s: float = _param(
        "descent", 0.0, 10.0, "1/s", "reference descent speed per metre of altitude"
    )
    descent_limit_at_ground_m_s: float = _param(
        "descent", 0.0, 5.0, "m/s", "soft limit on downward speed at the ground"
    )
    descent_limit_slope_1_s: float = _param(
        "descent", 0.0, 10.0, "1/s", "growth of that limit per metre of altitude"
    )
    approach_slope: float = _param(
        "descent", 0.0, 100.0, "m/m", "approach cone: altitude kept per metre off the pad"
    )
    approach_deadband_m: float = _param(
        "descent", 0.0, 100.0, "m", "horizontal distance within which the cone does not apply"
    )
    max_thrust_mg: float = _param("limits", 1.0, 10.0, "m g", "collective thrust limit")
    max_tilt_deg: float = _param("limits", 1.0, 80.0, "deg", "roll and pitch limit")
    touchdown_tilt_deg: float = _param(
        "limits", 1.0, 80.0, "deg", "roll and pitch limit of the plan's steps at the ground"
    )
    touchdown_tilt_height_m: float = _param(
        "limits", 0.0, 10.0, "m", "reference altitude below which the tilt limit closes (0: off)"
    )
    ground_margin_m: float = _param(
        "limits", 0.0, 1.0, "m", "predicted altitude may go this far below 0"
    )
    far_pos_ne: float = _param("weights", 0.0, 1e6, "1/m^2", "far: horizontal position")
    far_vel_ne: float = _param("weights", 0.0, 1e6, "s^2/m^2", "far: horizontal velocity")
    near_pos_ne: float = _param("weights", 0.0, 1e6, "1/m^2", "near: horizontal position")
    near_vel_ne: float = _param("weights", 0.0, 1e6, "s^2/m^2", "near: horizontal velocity")
    pos_d: float = _param("weights", 0.0, 1e6, "1/m^2", "altitude vs the descent profile")
    vel_d: float = _param("weights", 0.0, 1e6, "s^2/m^2", "downward speed vs the profile")
    tilt: float = _param("weights", 0.0, 1e6, "1/rad^2", "roll and pitch")
    yaw: float = _param("weights", 0.0, 1e6, "1/rad^2", "yaw error from the held heading")
    terminal_pos_ne: float = _param(
        "weights", 0.0, 1e6, "1/m^2", "terminal horizontal position (added at step N)"
    )
    terminal_vel_ne: float = _param(
        "weights", 0.0, 1e6, "s^2/m^2", "terminal horizontal velocity (added at step N)"
    )
    thrust_norm: float = _param("weights", 1e-6, 1e6, "1", "thrust_norm about hover")
    rate_roll_pitch: float = _param("weights", 1e-6, 1e6, "s^2/rad^2", "roll and pitch rates")
    rate_yaw: float = _param("weights", 1e-6, 1e6, "s^2/rad^2", "yaw rate")
    slack_linear: float = _param("weights", 0.0, 1e9, "1/unit", "safety slack, linear (exact)")
    slack_quadratic: float = _param("weights", 0.0, 1e9, "1/unit^2", "safety slack, quadratic")
    osqp_eps_abs: float = _param("solver", 1e-9, 1e-1, "1", "OSQP absolute tolerance")
    osqp_eps_rel: float = _param("solver", 1e-9, 1e-1, "1", "OSQP relative tolerance")
    osqp_max_iter: int = _param("solver", 1, 1_000_000, "1", "OSQP iterations", integer=True)
    clarabel_max_iter: int = _param(
        "solver", 1, 10_000, "1", "Clarabel (fallback) iterations", integer=True
    )

    def __post_init__(self) -> None:
        _check_config(self, "MpcConfig")

    def to_dict(self) -> dict[str, Any]:
        """The effective config, as saved with every artifact."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def _check_value(value: Any, meta: dict[str, Any], where: str) -> float | int:
    kind = "an integer" if meta["int"] else "a number"
    ok_type = isinstance(value, int) if meta["int"] else isinstance(value, int | float)
    if isinstance(value, bool) or not ok_type:
        raise ConfigError(f"{where} must be {kind} ({meta['unit']}), got {value!r}")
    if not math.isfinite(value) or not meta["lo"] <= value <= meta["hi"]:
        raise ConfigError(
            f"{where} = {value} is out of range; expected [{meta['lo']}, {meta['hi']}] "
            f"({meta['unit']}: {meta['doc']})"
        )
    return int(value) if meta["int"] else float(value)


def _check_config(cfg: MpcConfig, source: str) -> None:
    for f in fields(cfg):
        _check_value(getattr(cfg, f.name), dict(f.metadata), f"{source}: {f.name}")
    if cfg.touchdown_descent_m_s > cfg.max_descent_m_s:
        raise ConfigError(
            f"{source}: touchdown_descent_m_s = {cfg.touchdown_descent_m_s} exceeds "
            f"max_descent_m_s = {cfg.max_descent_m_s}; expected touchdown <= max"
        )
    if cfg.touchdown_tilt_deg > cfg.max_tilt_deg:
        raise ConfigError(
            f"{source}: touchdown_tilt_deg = {cfg.touchdown_tilt_deg} exceeds "
            f"max_tilt_deg = {cfg.max_tilt_deg}; expected touchdown <= max"
        )


def load_mpc_config(path: str | Path | None = None) -> MpcConfig:
    """Load and validate ``configs/expert.toml`` (or ``path``).

    Raises:
        ConfigError: naming the file, the table and the field that is missing, unknown,
            mistyped or out of range.
    """
    path = Path(path) if path is not None else CONFIG_DIR / "expert.toml"
    data = load_toml(path)
    values: dict[str, Any] = {}
    expected: dict[str, set[str]] = {}
    for f in fields(MpcConfig):
        expected.setdefault(f.metadata["table"], set()).add(f.name)
    for table, names in expected.items():
        tbl = data.get(table)
        if not isinstance(tbl, dict):
            raise ConfigError(f"{path}: missing table [{table}]")
        unknown = sorted(set(tbl) - names)
        if unknown:
            raise ConfigError(f"{path}: [{table}] unknown key(s) {unknown} (typo?)")
        for name in sorted(names):
            if name not in tbl:
                raise ConfigError(f"{path}: [{table}] missing key {name!r}")
    unknown_tables = sorted(set(data) - set(expected))
    if unknown_tables:
        raise ConfigError(f"{path}: unknown table(s) {unknown_tables}")
    for f in fields(MpcConfig):
        table = f.metadata["table"]
        values[f.name] = _check_value(
            data[table][f.name], dict(f.metadata), f"{path}: [{table}] {f.name}"
        )
    try:
        return MpcConfig(**values)
    except ConfigError as exc:  # cross-field checks: say which file
        raise ConfigError(f"{path}: {exc}") from None
