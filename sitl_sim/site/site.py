"""One episode's landing site: the ground (terrain or water), the pad's motion and its vehicle.

See :mod:`sitl_sim.site` for the API; this module composes :mod:`~sitl_sim.site.terrain`,
:mod:`~sitl_sim.site.pad_motion` and :mod:`~sitl_sim.site.vehicle`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sitl_sim.site.pad_motion import PadMotion, PadPose
from sitl_sim.site.terrain import Terrain
from sitl_sim.site.vehicle import Solid, hull, platform, rover

__all__ = ["Site"]

_NORMAL_EPS_M = 0.01


class Site:
    """One episode's landing site (drawn by :func:`sitl_sim.world.episode_world` into
    ``EpisodeWorld.site``; None there is the flat, still nominal site).

    Args:
        motion: the pad's motion (its kind picks the vehicle: a rover, a hull on water, a
            platform under a raised still pad, none under a pad on the ground).
        terrain: the ground's relief (None: the plane at height 0).
        pad_size_m: the pad's extent (along its forward axis, across it) in metres: the
            vehicle is sized to carry it.
    """

    def __init__(
        self,
        motion: PadMotion,
        terrain: Terrain | None = None,
        pad_size_m: tuple[float, float] = (4.0, 4.0),
    ) -> None:
        self.motion = motion
        self.terrain = terrain
        self.pad_size_m = (float(pad_size_m[0]), float(pad_size_m[1]))
        self.water = motion.kind == "deck"
        """The ground is the sea: flat at height 0 (its mean level)."""
        length, width = self.pad_size_m
        h = motion.height_m
        if motion.kind == "rover":
            self.vehicle: tuple[Solid, ...] = rover(length, width, h)
        elif motion.kind == "deck":
            self.vehicle = hull(length, width, h)
        elif h > 0.0:
            self.vehicle = platform(length, width, h)
        else:
            self.vehicle = ()

    @property
    def moves(self) -> bool:
        """Whether the pad (and its vehicle) move: renderers place them every frame."""
        return self.motion.moves

    # ------------------------------------------------------------------ the ground

    def ground_height(self, n: float, e: float) -> float:
        """The terrain's surface height (up positive, m) at (n, e): slope, relief, craters and
        rocks; on water the mean water level, 0."""
        if self.water or self.terrain is None:
            return 0.0
        return self.terrain.height(n, e)

    def ground_normal(self, n: float, e: float) -> tuple[float, float, float]:
        """The ground's upward unit normal (NED: its down component is negative) at (n, e)."""
        if self.water or self.terrain is None:
            return (0.0, 0.0, -1.0)
        k = _NORMAL_EPS_M
        dn = (self.ground_height(n + k, e) - self.ground_height(n - k, e)) / (2 * k)
        de = (self.ground_height(n, e + k) - self.ground_height(n, e - k)) / (2 * k)
        norm = math.sqrt(dn * dn + de * de + 1.0)
        return (-dn / norm, -de / norm, -1.0 / norm)

    # ------------------------------------------------------------------ the pad

    def pad_pose(self, t: float) -> PadPose:
        """The pad surface's centre at sim time ``t``: position, rotation pad->NED, velocity
        and angular velocity (NED)."""
        return self.motion.pose(t)

    def pad_accel(self, t: float) -> np.ndarray:
        """The pad surface centre's acceleration at ``t`` (NED, m/s^2; central difference of
        its velocity, 10 ms apart: the paths are smooth)."""
        if not self.moves:
            return np.zeros(3)
        h = 5e-3
        return (self.motion.pose(t + h).velocity_ned - self.motion.pose(t - h).velocity_ned) / (
            2 * h
        )

    def surface_height(self, n: float, e: float, t: float) -> float:
        """The highest surface at (n, e) at time ``t`` (up, m): the ground, a rock, the
        vehicle's roof or deck (the pad lies on it)."""
        return self.surface(n, e, t)[0]

    def surface(self, n: float, e: float, t: float) -> tuple[float, bool]:
        """``(height up (m), on_vehicle)``: the highest surface at (n, e) at time ``t``, and
        whether it is the carrying vehicle's (else the ground or a rock)."""
        top = self.ground_height(n, e)
        if not self.vehicle:
            return top, False
        p, r = self.motion.frame(t)
        start = max(top, -float(p[2])) + 50.0
        s = self._vehicle_ray(np.array([n, e, -start]), np.array([0.0, 0.0, 1.0]), p, r)
        if math.isfinite(s) and start - s > top:
            return start - s, True
        return top, False

    def base_ground_height(self, n: float, e: float) -> float:
        """The ground's height without rocks (up, m): a cheap bound's base (the terrain's
        bilinear relief; 0 on water or flat ground)."""
        if self.water or self.terrain is None:
            return 0.0
        return self.terrain.ground(n, e)[0]

    def clearance_bound_m(self) -> float:
        """How far above :meth:`base_ground_height` anything of the site can reach (m): a
        rock's top, or the vehicle's highest point however it moves (a bound, not tight)."""
        grad = self.terrain.max_gradient if self.terrain is not None else 0.0
        top = 0.0
        rocks = self.terrain.rocks if self.terrain is not None else None
        if rocks is not None and len(rocks):
            top = float(np.max(rocks.height)) + grad * float(np.max(rocks.extent))
        if self.vehicle:
            reach = max(float(np.max(np.abs(s.outline))) for s in self.vehicle) * math.sqrt(2)
            above = max(-s.z_top for s in self.vehicle)
            swell = getattr(self.motion, "heave_m", 0.0)
            top = max(top, self.motion.height_m + swell + above + reach * (0.5 + grad))
        return top

    # ------------------------------------------------------------------ ray cast

    def range_along(self, origin_ned, direction_ned, t: float, max_range: float) -> float:
        """Distance from ``origin_ned`` along ``direction_ned`` (normalised here) to the first
        surface — ground, rock, vehicle — at time ``t``; inf if none within ``max_range``
        (0 from inside one)."""
        o = np.asarray(origin_ned, dtype=float)
        d = np.asarray(direction_ned, dtype=float)
        d = d / np.linalg.norm(d)
        if self.water or self.terrain is None:
            if o[2] >= 0.0:
                best = 0.0
            else:
                best = -o[2] / d[2] if d[2] > 0.0 else math.inf
        else:
            best = self.terrain.ray(o, d, max_range)
        if self.vehicle:
            p, r = self.motion.frame(t)
            best = min(best, self._vehicle_ray(o, d, p, r))
        return best if best <= max_range else math.inf

    def _vehicle_ray(self, o: np.ndarray, d: np.ndarray, p: np.ndarray, r: np.ndarray) -> float:
        op, dp = r.T @ (o - p), r.T @ d
        return min(solid.ray(op, dp) for solid in self.vehicle)

    # ------------------------------------------------------------------ the log

    def record(self) -> dict[str, Any]:
        """What was drawn (the episode's log record ``site``)."""
        out: dict[str, Any] = {
            "pad": self.motion.record(),
            "ground": "water" if self.water else "land",
            "vehicle": [s.name for s in self.vehicle],
            "pad_size_m": list(self.pad_size_m),
        }
        if self.terrain is not None:
            out["terrain"] = self.terrain.record()
        return out
