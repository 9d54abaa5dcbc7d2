"""One episode's world: everything a scenario file randomises, drawn once per (seed, episode).

A :class:`~sitl_sim.scenario.Scenario` holds *ranges* (wind speeds, airframe scale factors,
terrain families, sensor fault rates, ...); :func:`episode_world` draws the values for episode
``index`` of seed ``seed`` into an :class:`EpisodeWorld`, which :meth:`Simulator.reset
<sitl_sim.simulator.Simulator.reset>` takes. Every section draws from its own generator, keyed by
``(seed, index, SECTION_STREAM)`` (a distinct constant per section:
:data:`sitl_sim.physics.wind.WIND_STREAM`, :data:`sitl_sim.physics.airframe.AIRFRAME_STREAM`,
:data:`sitl_sim.render.visual.VISUAL_STREAM`, :data:`sitl_sim.render.pad_section.PAD_STREAM`,
:data:`~sitl_sim.render.pad_section.PAD_MOTION_STREAM`,
:data:`sitl_sim.site.terrain.TERRAIN_STREAM`,
:data:`sitl_sim.physics.sensor_faults.SENSORS_STREAM`), so adding a section to a scenario never
changes what another section draws, and the same (seed, episode) is the same world in every
process (the gymnasium env, the MAVLink SITL, parallel evaluation workers, resumed runs).

A scenario without a section gets that section's "as the config files say" value (None below),
so the nominal scenario flies exactly the world it always did.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from sitl_sim.config import VehicleConfig
from sitl_sim.physics.airframe import AirframeScales, draw_airframe
from sitl_sim.physics.sensor_faults import SensorFaults
from sitl_sim.physics.wind import WindModel
from sitl_sim.render.ground import PadGeometry, PadLook, PadTexture
from sitl_sim.render.pad_section import PadConfig
from sitl_sim.render.pads import PadDesign
from sitl_sim.render.visual import VisualConfig, VisualSample
from sitl_sim.scenario import Scenario
from sitl_sim.site.site import Site
from sitl_sim.site.terrain import TerrainConfig

__all__ = ["EpisodeWorld", "episode_site", "episode_world"]


@dataclass(frozen=True)
class EpisodeWorld:
    """The drawn world of one episode (None fields: the section is absent, nominal world).

    ``wind`` and ``sensors`` carry their own generators and are stateful, so an EpisodeWorld is
    flown once (:func:`episode_world` again to re-fly).
    """

    wind: WindModel | None = None
    """``[wind]``: a fresh :class:`~sitl_sim.physics.wind.WindModel`."""
    airframe: AirframeScales | None = None
    """``[vehicle]``'s drawn factors, not a vehicle: the world does not depend on the vehicle
    file; :meth:`vehicle` applies them to one."""
    visual: VisualSample | None = None
    """``[visual]``'s look (and the pad design the renderers draw)."""
    sensors: SensorFaults | None = None
    """``[sensors]``: the drawn latency and IMU biases, the generators of frame drops and radar
    faults (:class:`~sitl_sim.physics.sensor_faults.SensorFaults`)."""
    pad: PadDesign | None = None
    """The design ``[pad]`` drew; the renderers get it through ``visual``
    (:meth:`VisualSample.pad <sitl_sim.render.visual.VisualSample.pad>`): with ``[pad]`` and no
    ``[visual]`` the nominal look carries it, unless it is the nominal pad itself."""
    site: Site | None = None
    """The landing site (:mod:`sitl_sim.site`: ``[terrain]``'s relief, ``[pad]``'s motion and
    vehicle); None when neither draws anything (flat ground, a still pad at height 0)."""

    def vehicle(self, base: VehicleConfig) -> VehicleConfig:
        """The episode's vehicle: ``base`` (the vehicle file) itself without ``[vehicle]``,
        else ``base`` scaled by the drawn factors."""
        return base if self.airframe is None else self.airframe.apply(base)

    def record(self) -> dict:
        """What was drawn, for the episode's log records and ``info`` (``airframe``,
        ``visual``, ``pad``, ``site``; absent sections left out, so nominal records are
        unchanged). The
        wind is logged as it blows, in the ground truth."""
        out: dict = {}
        if self.airframe is not None:
            out["airframe"] = self.airframe.to_dict()
        if self.visual is not None:
            out["visual"] = self.visual.to_dict()
        if self.pad is not None:
            out["pad"] = {
                "design": self.pad.name,
                "file": str(self.pad.path) if self.pad.path else None,
                "size_m": list(self.pad.size_m),
            }
        if self.site is not None:
            out["site"] = self.site.record()
        return out


def episode_world(scenario: Scenario, seed: int, index: int) -> EpisodeWorld:
    """Draw episode ``index`` of seed ``seed`` of ``scenario``'s world."""
    wind = WindModel.for_episode(scenario.wind, seed, index) if scenario.wind is not None else None
    airframe = (
        draw_airframe(scenario.vehicle, seed, index) if scenario.vehicle is not None else None
    )
    visual = scenario.visual.draw(seed, index) if scenario.visual is not None else None
    pad = scenario.pad.draw(seed, index) if scenario.pad is not None else None
    if pad is not None and (visual is not None or pad.scene_pad() != PadGeometry()):
        visual = replace(visual or VisualConfig().draw(seed, index), pad_design=pad)
    sensors = (
        SensorFaults.for_episode(scenario.sensors, seed, index)
        if scenario.sensors is not None
        else None
    )
    look = visual.pad() if visual is not None else PadGeometry()
    site = episode_site(scenario.terrain, scenario.pad, seed, index, look)
    return EpisodeWorld(
        wind=wind, airframe=airframe, visual=visual, sensors=sensors, pad=pad, site=site
    )


def episode_site(
    terrain_cfg: TerrainConfig | None,
    cfg: PadConfig | None,
    seed: int,
    index: int,
    pad: PadLook,
) -> Site | None:
    """Episode ``index``'s landing site from a scenario's ``[terrain]`` and ``[pad]`` sections
    (None: flat ground and a still pad at height 0, nominal): the terrain drawn first (a rover
    follows it, a still pad lies on its slope), then the motion; the vehicle is sized to the pad
    the renderers draw (``pad``)."""
    if terrain_cfg is None and (cfg is None or cfg.still_on_ground):
        return None
    if isinstance(pad, PadTexture):
        size = (pad.size_m[1], pad.size_m[0])  # (along north: forward, across)
    else:
        size = (pad.side_m, pad.side_m)
    clear_m = 0.5 * math.hypot(1.4 * size[0] + 0.6, size[1] + 0.6)
    terrain = terrain_cfg.draw(seed, index, clear_m) if terrain_cfg is not None else None
    motion = (cfg or PadConfig()).draw_motion(
        seed,
        index,
        ground=terrain.ground if terrain is not None else None,
        ground_gradient=terrain.gradient if terrain is not None else (0.0, 0.0),
    )
    return Site(motion, terrain, size)
