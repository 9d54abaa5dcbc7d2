"""The autopilot's AUTO.LAND controller: a cascaded PD lander on ground truth.

It is what PX4's multicopter position controller does, reduced to landing: position and velocity
errors give a desired acceleration, which gives a thrust vector (collective + desired body z
axis), and the attitude error gives body-rate setpoints. It reads ground truth, so it is a
*privileged* controller. It lives in ``sitl_sim`` because the SITL's LAND mode (and the
COM_OBL_RC_ACT failsafe) flies it, and ``sitl_sim`` may import only the companion contract;
:class:`expert.cascade.CascadeLander` wraps the same controller as a Policy (the scripted pilot
of the demo and the benchmarks, and the baseline the MPC expert must beat).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.contract import Command
from sitl_sim.config import Planet, VehicleConfig
from sitl_sim.physics.dynamics import quat_to_rotation

__all__ = ["CascadeGains", "CascadeLandController"]


@dataclass(frozen=True)
class CascadeGains:
    kp_pos: float = 0.6  # 1/s^2
    kd_pos: float = 1.4  # 1/s
    kp_vel_down: float = 2.0  # 1/s
    max_descent_m_s: float = 4.0
    min_descent_m_s: float = 0.35
    descent_per_altitude: float = 0.25  # descent speed = this * altitude, clamped
    kp_att: float = 6.0  # rad/s per rad
    kp_yaw: float = 1.0
    max_tilt_rad: float = math.radians(30.0)


class CascadeLandController:
    """Ground truth in, Command out: ``command(pos, vel, quat) -> Command`` (stateless).

    Satisfies :class:`sitl_sim.autopilot.px4.LandController`.
    """

    def __init__(self, vehicle: VehicleConfig, world: Planet, gains: CascadeGains | None = None):
        self.vehicle = vehicle
        self.world = world
        self.gains = gains or CascadeGains()
        self._max_total_thrust_n = vehicle.max_total_thrust_n(world)

    def for_vehicle(self, vehicle: VehicleConfig) -> CascadeLandController:
        """The same law (gains, planet) for ``vehicle``: this controller when it already flies
        it, else a new one (cheap: it keeps only the mass and T_max)."""
        if vehicle == self.vehicle:
            return self
        return type(self)(vehicle, self.world, self.gains)

    def command(self, pos_ned_m, vel_ned_m_s, quat_wxyz, v_down_m_s=None) -> Command:
        """``pos_ned_m`` is the position relative to the landing point (its down part the
        altitude); ``v_down_m_s`` replaces the land descent profile (e.g. an altitude hold)."""
        g = self.gains
        pos = np.asarray(pos_ned_m, dtype=float)
        vel = np.asarray(vel_ned_m_s, dtype=float)
        altitude = max(0.0, -pos[2])
        if v_down_m_s is None:
            v_down = min(
                g.max_descent_m_s, max(g.min_descent_m_s, g.descent_per_altitude * altitude)
            )
        else:
            v_down = float(v_down_m_s)
        acc = np.array(
            [
                -g.kp_pos * pos[0] - g.kd_pos * vel[0],
                -g.kp_pos * pos[1] - g.kd_pos * vel[1],
                g.kp_vel_down * (v_down - vel[2]),
            ]
        )
        # Thrust vector (NED) that produces acc against gravity, tilt-limited.
        force = self.vehicle.mass_kg * (acc - np.array([0.0, 0.0, self.world.gravity_m_s2]))
        horiz = math.hypot(force[0], force[1])
        max_h = abs(force[2]) * math.tan(g.max_tilt_rad)
        if horiz > max_h:
            force[:2] *= max_h / horiz
        rot = quat_to_rotation(quat_wxyz)
        z_des = -force / np.linalg.norm(force)  # desired body down axis
        thrust_n = float(-force @ rot[:, 2]) if force @ rot[:, 2] < 0 else 0.0
        thrust_norm = min(1.0, max(0.0, thrust_n / self._max_total_thrust_n))
        # Rate setpoint from the body-frame tilt error (small-angle, as PX4's attitude P loop)
        # and a yaw damper: only the tilt matters for landing.
        err_body = rot.T @ np.cross(rot[:, 2], z_des)
        rates = np.array([g.kp_att * err_body[0], g.kp_att * err_body[1], 0.0])
        return Command(thrust_norm=thrust_norm, rate_frd_rad_s=rates)
