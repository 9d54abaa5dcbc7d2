"""Airframe randomisation: a scenario's ``[vehicle]`` section scales the vehicle file per episode.

Each key is an optional ``[lo, hi]`` range of a factor on one quantity of ``configs/vehicle.toml``
(:class:`~sitl_sim.config.VehicleConfig`):

* ``mass_scale``: ``mass_kg``;
* ``inertia_scale``: all three of ``inertia_diag_kg_m2`` (one factor: the shape of the inertia
  ellipsoid is kept);
* ``thrust_scale``: T_max on every planet (``[vehicle.max_total_thrust_n]``);
* ``motor_time_constant_scale``: ``motor_time_constant_s`` (the rotor lag);
* ``drag_scale``: all three of ``drag_coefficient_area_m2``.

A key left out is the factor 1.0 exactly (not drawn), so a section with only ``mass_scale``
changes nothing but the mass. Each factor is drawn uniformly from its range, independently of
the others. In particular **inertia does not follow mass**: a payload changes the inertia by
where it sits (a battery at the centre adds mass and hardly any inertia, a gimbal on an arm adds
both), so a scenario states both ranges; give ``inertia_scale`` the range of ``mass_scale`` for
an airframe scaled as a whole (still two draws).

Randomness: :func:`draw_airframe` uses ``default_rng([seed, episode, AIRFRAME_STREAM])``, an
entropy no other stream of the project uses, and always draws the five factors in the order of
:data:`AIRFRAME_KEYS` (an absent key's draw is discarded), so adding a key never changes another
key's factor, and adding the section changes no other draw (initial state, wind, sensor noise).

The drawn :class:`AirframeScales` are stored, not the scaled vehicle (an
:class:`~sitl_sim.world.EpisodeWorld` does not depend on the vehicle file);
:meth:`AirframeScales.apply` makes the episode's vehicle from the file's. The autopilot is tuned
for the airframe it flies, as a tuned PX4 is: the rate loop turns its gains into torque with the
episode's inertia, and ``MPC_THR_HOVER`` is the episode's hover thrust. So ``inertia_scale``
changes the rotor effort a manoeuvre takes (and how soon the mixer saturates), not the rate
loop's bandwidth.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from companion.table import Bounded, Section, bounded, section_dict, section_keys, span
from sitl_sim.config import Planet, VehicleConfig
from sitl_sim.errors import ConfigError

__all__ = [
    "AIRFRAME_KEYS",
    "AIRFRAME_STREAM",
    "MAX_SCALE",
    "AirframeConfig",
    "AirframeScales",
    "airframe_config_from_table",
    "check_airframe_can_hover",
    "draw_airframe",
]

MAX_SCALE = 10.0
"""Largest factor a range may reach: beyond it the vehicle file no longer describes the craft
(a typo such as 13 for 1.3 is caught, a deliberately extreme airframe still fits)."""

AIRFRAME_STREAM = 0x5648434C
"""Third entropy word of the airframe's generator (ASCII "VHCL"); no other stream uses it, so
these draws are independent of the wind's, the sensors' and the sampler's."""


def _factor(doc: str) -> Any:
    return span(None, unit="1", lo=0.0, lo_open=True, hi=MAX_SCALE, noun="factors", doc=doc)


@dataclass(frozen=True)
class AirframeConfig(Section):
    """The ``[vehicle]`` section: a factor range ``(lo, hi)`` per key, None where absent (the
    factor 1.0 exactly, not drawn).

    Attributes:
        mass_scale: on ``mass_kg``.
        inertia_scale: on each of ``inertia_diag_kg_m2``.
        thrust_scale: on T_max (every planet).
        motor_time_constant_scale: on ``motor_time_constant_s``.
        drag_scale: on each of ``drag_coefficient_area_m2``.
        source: the file it came from (for error messages).
    """

    SECTION: ClassVar[str] = "vehicle"

    mass_scale: tuple[float, float] | None = _factor("factor on mass_kg (absent: 1)")
    inertia_scale: tuple[float, float] | None = _factor(
        "factor on all three of inertia_diag_kg_m2, drawn apart from mass_scale (absent: 1)"
    )
    thrust_scale: tuple[float, float] | None = _factor("factor on T_max, every planet (absent: 1)")
    motor_time_constant_scale: tuple[float, float] | None = _factor(
        "factor on motor_time_constant_s (absent: 1)"
    )
    drag_scale: tuple[float, float] | None = _factor(
        "factor on all three of drag_coefficient_area_m2 (absent: 1)"
    )

    def range(self, key: str) -> tuple[float, float] | None:
        return getattr(self, key)

    def to_dict(self) -> dict[str, list[float]]:
        """The ranges given (absent keys left out)."""
        return section_dict(self, drop_none=True)


AIRFRAME_KEYS = section_keys(AirframeConfig)
"""The ``[vehicle]`` keys, in the order their factors are drawn."""


@dataclass(frozen=True)
class AirframeScales(Bounded):
    """One episode's drawn factors on the vehicle file (1.0: that quantity as the file says)."""

    mass_scale: float = bounded(1.0, 0.0, lo_open=True)
    inertia_scale: float = bounded(1.0, 0.0, lo_open=True)
    thrust_scale: float = bounded(1.0, 0.0, lo_open=True)
    motor_time_constant_scale: float = bounded(1.0, 0.0, lo_open=True)
    drag_scale: float = bounded(1.0, 0.0, lo_open=True)

    def apply(self, vehicle: VehicleConfig) -> VehicleConfig:
        """``vehicle`` (the vehicle file) with these factors applied: the episode's vehicle."""
        return replace(
            vehicle,
            mass_kg=vehicle.mass_kg * self.mass_scale,
            inertia_diag_kg_m2=tuple(i * self.inertia_scale for i in vehicle.inertia_diag_kg_m2),  # type: ignore[arg-type]
            max_total_thrust_n_by_planet=tuple(
                (name, t * self.thrust_scale) for name, t in vehicle.max_total_thrust_n_by_planet
            ),
            motor_time_constant_s=vehicle.motor_time_constant_s * self.motor_time_constant_scale,
            drag_coefficient_area_m2=tuple(
                c * self.drag_scale for c in vehicle.drag_coefficient_area_m2
            ),  # type: ignore[arg-type]
        )

    def to_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in AIRFRAME_KEYS}

    @classmethod
    def from_dict(cls, data: Any, where: str) -> AirframeScales:
        """Read back :meth:`to_dict` (a flight log's record); ``where`` names it on error."""
        if not isinstance(data, dict) or set(data) != set(AIRFRAME_KEYS):
            raise ValueError(f"{where}: expected the factors {list(AIRFRAME_KEYS)}, got {data!r}")
        try:
            return cls(**{k: float(data[k]) for k in AIRFRAME_KEYS})
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None


def airframe_config_from_table(table: Any, where: str) -> AirframeConfig:
    """Check and type a scenario's ``[vehicle]`` table; ``where`` names the file."""
    return AirframeConfig.from_table(table, where)


def draw_airframe(config: AirframeConfig, seed: int, episode_index: int) -> AirframeScales:
    """Episode ``episode_index`` of ``seed``'s factors: a pure function of the three."""
    rng = np.random.default_rng([int(seed), int(episode_index), AIRFRAME_STREAM])
    unit = rng.random(len(AIRFRAME_KEYS))  # all five, always: a key's draw never moves
    factors: dict[str, float] = {}
    for key, u in zip(AIRFRAME_KEYS, unit, strict=True):
        rg = config.range(key)
        if rg is not None:
            factors[key] = rg[0] + (rg[1] - rg[0]) * float(u)
    return AirframeScales(**factors)


def check_airframe_can_hover(config: AirframeConfig, vehicle: VehicleConfig, world: Planet) -> None:
    """Refuse a ``[vehicle]`` section whose heaviest, weakest draw could not hover on ``world``
    (hover thrust >= T_max): its episodes would fall whatever the pilot did.

    Raises:
        ConfigError: naming the scenario file, the keys and the hover thrust fraction.
    """
    mass_hi = config.mass_scale[1] if config.mass_scale is not None else 1.0
    thrust_lo = config.thrust_scale[0] if config.thrust_scale is not None else 1.0
    worst = vehicle.hover_thrust_norm(world) * mass_hi / thrust_lo
    if worst >= 1.0:
        raise ConfigError(
            f"{config.source}: [vehicle] mass_scale up to {mass_hi} with thrust_scale down to "
            f"{thrust_lo} needs {worst:.2f} x T_max to hover on {world.name} "
            f"({vehicle.source}); expected < 1 (narrow the ranges)"
        )
