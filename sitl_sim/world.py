"""One episode's world: everything a scenario file randomises, drawn once per (seed, episode).

A :class:`~sitl_sim.scenario.Scenario` holds *ranges* (wind speeds, airframe scale factors,
terrain families, sensor fault rates, ...); :func:`episode_world` draws the values for episode
``index`` of seed ``seed`` into an :class:`EpisodeWorld`, which :meth:`Simulator.reset
<sitl_sim.simulator.Simulator.reset>` takes. Every section draws from its own generator, keyed by
``(seed, index, SECTION_STREAM)`` (a distinct constant per section, e.g.
:data:`sitl_sim.wind.WIND_STREAM`, :data:`sitl_sim.sensor_faults.SENSORS_STREAM`), so adding a
section to a scenario never changes what another section draws, and the same (seed, episode) is
the same world in every process (the gymnasium env, the MAVLink SITL, parallel evaluation
workers, resumed runs).

A scenario without a section gets that section's "as the config files say" value (None below),
so the nominal scenario flies exactly the world it always did.
"""

from __future__ import annotations

from dataclasses import dataclass

from sitl_sim.scenario import Scenario
from sitl_sim.sensor_faults import SensorFaults
from sitl_sim.wind import WindModel

__all__ = ["EpisodeWorld", "episode_world"]


@dataclass(frozen=True)
class EpisodeWorld:
    """The drawn world of one episode (None fields: the section is absent, nominal world).

    ``wind`` is a fresh :class:`~sitl_sim.wind.WindModel` and ``sensors`` fresh
    :class:`~sitl_sim.sensor_faults.SensorFaults` (the drawn latency and IMU biases, and the
    generators of frame drops and radar faults), each carrying its own generator; they are
    stateful, so an EpisodeWorld is flown once (:func:`episode_world` again to re-fly).
    """

    wind: WindModel | None = None
    sensors: SensorFaults | None = None


def episode_world(scenario: Scenario, seed: int, index: int) -> EpisodeWorld:
    """Draw episode ``index`` of seed ``seed`` of ``scenario``'s world."""
    wind = WindModel.for_episode(scenario.wind, seed, index) if scenario.wind is not None else None
    sensors = (
        SensorFaults.for_episode(scenario.sensors, seed, index)
        if scenario.sensors is not None
        else None
    )
    return EpisodeWorld(wind=wind, sensors=sensors)
