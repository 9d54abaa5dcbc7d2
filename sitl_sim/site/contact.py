"""Ground contact on a site: the heightfield, rocks, a sloped pad, a rover's roof, a moving deck.

The nominal site (flat ground, a still pad at the origin) keeps
:func:`sitl_sim.physics.dynamics.step` and its plane ``down = 0``; a
:class:`~sitl_sim.site.site.Site` uses :class:`SiteContact` instead, once per physics step after
the free flight's RK4 (:func:`~sitl_sim.physics.dynamics.integrate`).

The model, the flat ground's generalised:

* **Contact** when the vehicle centre reaches the highest surface under it
  (:meth:`Site.surface`: ground, rock, the vehicle's roof or deck at that time), interpolated
  inside the step on the gap ``altitude - surface height`` (which moves with a deck).
* **Fully inelastic, full friction, in the surface's frame**: the vehicle stops *relative to
  the surface it touched* and rests square to it (its landing gear on the plane) with its
  heading kept; on the carrying vehicle it is then carried, a fixed point of the pad frame,
  with the pad's velocity and angular velocity. It lifts off when the free flight of a step
  would take it above the surface's point (thrust beating weight *and* the surface's own
  acceleration: a deck heaving up holds a vehicle whose thrust only just beats gravity).
* **Tip-over**: a surface steeper than :data:`TIP_OVER_DEG` cannot be stood on. Why 25 deg:
  a quadrotor's skids sit under its motors, its mass a little above them (gear height about
  the arm's half length): ``atan(half track / centre-of-mass height)`` is 35-45 deg for
  common frames standing still, and rubber feet on rock or regolith slide at ``atan(0.6-0.7)``
  = 31-35 deg; a touchdown's momentum and one skid meeting the slope first take a margin off
  both. The contact then reports ``tipped_over`` (a failure); what the vehicle does after
  (rolling down the slope) is not simulated.
* A **hard landing on a rock** is a contact with the rock's top, in its facet's frame: the
  metrics (touchdown speed, the facet's steepness) say how hard.

:class:`~sitl_sim.physics.dynamics.PadContact` gives each contact in the pad's frame: the
metrics (:meth:`sitl_sim.metrics.EpisodeResult.from_contact`) score it there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sitl_sim.physics.dynamics import ContactEvent, PadContact, quat_to_rotation, tilt_of
from sitl_sim.site.pad_motion import frame_from_down
from sitl_sim.site.site import Site

__all__ = ["PAD_PLANE_TOL_M", "TIP_OVER_DEG", "SiteContact", "quat_from_rotation"]

TIP_OVER_DEG = 25.0
"""The steepest surface the vehicle stands on (see the module docstring)."""
PAD_PLANE_TOL_M = 0.05
"""A contact within this of the pad's plane (and inside its outline) is on the pad."""
_LIFT_OFF_M = 1e-9


def quat_from_rotation(r: np.ndarray) -> list[float]:
    """The unit quaternion ``(w, x, y, z)`` of a rotation matrix (body -> NED)."""
    m = np.asarray(r, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    n = math.sqrt(sum(v * v for v in q))
    sign = 1.0 if q[0] >= 0.0 else -1.0
    return [sign * v / n for v in q]


def _yaw(x: list[float]) -> float:
    qw, qx, qy, qz = x[6], x[7], x[8], x[9]
    return math.atan2(2 * qw * qz + 2 * qx * qy, 1 - 2 * (qy * qy + qz * qz))


@dataclass(frozen=True)
class _Rest:
    """Where a resting vehicle sits: on the carrying vehicle, a point and attitude fixed in the
    pad frame; on the ground, a point and attitude fixed in NED."""

    on_vehicle: bool
    pos: np.ndarray
    """Pad frame (on the vehicle) or NED (on the ground)."""
    rotation: np.ndarray
    """Body -> pad frame (on the vehicle) or body -> NED (on the ground)."""


class SiteContact:
    """The contact model of one episode's site (see the module docstring)."""

    def __init__(self, site: Site) -> None:
        self.site = site
        self._half = (0.5 * site.pad_size_m[0], 0.5 * site.pad_size_m[1])
        self._clear_m = site.clearance_bound_m() + 0.5
        self._rest: _Rest | None = None
        self.last: PadContact | None = None
        """The last contact's pad-frame view (None before the first)."""

    @property
    def resting(self) -> bool:
        """The vehicle rests on a surface (carried by it, if it moves)."""
        return self._rest is not None

    def height_above(self, x: list[float], t: float) -> float:
        """The vehicle centre's height above the surface under it (m; 0 at rest)."""
        if self._rest is not None:
            return 0.0
        h, _ = self.site.surface(x[0], x[1], t)
        return -x[2] - h

    def surface_accel(self, t: float) -> np.ndarray:
        """The acceleration of the point the vehicle rests on (NED; zero on the ground)."""
        if self._rest is None or not self._rest.on_vehicle:
            return np.zeros(3)
        return self.site.pad_accel(t)

    # ------------------------------------------------------------------ the step

    def resolve(
        self, x_prev: list[float], x_new: list[float], t_prev: float, dt: float
    ) -> tuple[list[float], ContactEvent | None]:
        """The step's end state after contact, and the touchdown if one happened in it.

        ``x_new`` is the free flight's state at ``t_prev + dt`` (RK4 from ``x_prev``)."""
        t_new = t_prev + dt
        if self._rest is not None:
            held = self._rest_state(self._rest, x_new, t_new)
            if -x_new[2] > -held[2] + _LIFT_OFF_M:
                self._rest = None  # lifted off: free flight again
                return x_new, None
            return held, None
        site = self.site
        alt = -x_new[2]
        if alt - site.base_ground_height(x_new[0], x_new[1]) > self._clear_m:
            return x_new, None
        h_new, _ = site.surface(x_new[0], x_new[1], t_new)
        if alt > h_new:
            return x_new, None
        h_prev, _ = site.surface(x_prev[0], x_prev[1], t_prev)
        g_prev, g_new = -x_prev[2] - h_prev, alt - h_new
        frac = g_prev / (g_prev - g_new) if g_prev > 0.0 and g_prev != g_new else 0.0
        lerp = [x_prev[i] + frac * (x_new[i] - x_prev[i]) for i in range(6)]
        t_c = t_prev + frac * dt
        h_c, on_vehicle = site.surface(lerp[0], lerp[1], t_c)
        pos_c = np.array([lerp[0], lerp[1], -h_c])
        vel_c = np.array(lerp[3:6])
        pose = site.pad_pose(t_c)
        r_pad = pose.R_pad_to_ned
        arm = pos_c - pose.position_ned
        pad_point_vel = pose.velocity_ned + np.cross(pose.omega_ned, arm)
        # the touched surface's down normal: the pad frame's on the vehicle, the ground's else
        if on_vehicle:
            down = r_pad[:, 2]
        else:
            down = -np.asarray(site.ground_normal(lerp[0], lerp[1]))
        steep = math.degrees(math.acos(max(-1.0, min(1.0, float(down[2])))))
        body = quat_to_rotation(x_new[6:10])
        rel = r_pad.T @ arm
        pad = PadContact(
            pos_m=rel,
            vel_m_s=r_pad.T @ (vel_c - pad_point_vel),
            tilt_rad=math.acos(max(-1.0, min(1.0, float(body[:, 2] @ r_pad[:, 2])))),
            touched_pad=bool(
                abs(rel[0]) <= self._half[0]
                and abs(rel[1]) <= self._half[1]
                and abs(rel[2]) <= PAD_PLANE_TOL_M
                and (on_vehicle or not site.vehicle)
            ),
            tipped_over=steep > TIP_OVER_DEG,
        )
        self.last = pad
        event = ContactEvent(
            time_s=t_c,
            pos_ned_m=pos_c,
            vel_ned_m_s=vel_c,
            tilt_rad=tilt_of(x_new[7], x_new[8]),
            pad=pad,
        )
        square = frame_from_down(down, _yaw(x_new))  # body -> NED resting square to the surface
        if on_vehicle:
            self._rest = _Rest(True, r_pad.T @ arm, r_pad.T @ square)
        else:
            self._rest = _Rest(False, pos_c, square)
        return self._rest_state(self._rest, x_new, t_new), event

    def _rest_state(self, rest: _Rest, x: list[float], t: float) -> list[float]:
        """The state of a vehicle resting at ``rest`` at time ``t`` (rotors from ``x``)."""
        out = list(x)
        if rest.on_vehicle:
            pose = self.site.pad_pose(t)
            r_pad = pose.R_pad_to_ned
            pos = pose.position_ned + r_pad @ rest.pos
            vel = pose.velocity_ned + np.cross(pose.omega_ned, pos - pose.position_ned)
            body = r_pad @ rest.rotation
            rates = body.T @ pose.omega_ned
        else:
            pos, vel, body, rates = rest.pos, np.zeros(3), rest.rotation, np.zeros(3)
        out[0:3] = [float(v) for v in pos]
        out[3:6] = [float(v) for v in vel]
        out[6:10] = quat_from_rotation(body)
        out[10:13] = [float(v) for v in rates]
        return out
