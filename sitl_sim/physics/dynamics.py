"""6-DoF quadrotor dynamics in NED/FRD: the project's one physics.

State vector (17 floats, layout fixed by :data:`LAYOUT`, never sliced by bare numbers elsewhere):
``pos_ned_m`` (3), ``vel_ned_m_s`` (3), ``quat_wxyz`` (4, body FRD -> world NED), ``rate_frd_rad_s``
(3), ``rotor_thrust_n`` (4). The input is the commanded thrust of each rotor (N); each rotor follows
its command with a first-order lag, which is part of the integrated state.

Forces and torques:

* gravity ``(0, 0, m g)`` in NED;
* rotor thrust along body ``-z`` (up), summed;
* quadratic body drag ``F_i = -1/2 rho C_D A_i |v_i| v_i`` per body axis, with ``v`` the
  air-relative velocity in FRD (bluff-body drag; Beard & McLain, *Small Unmanned Aircraft*,
  2012, sec. 4.2; the per-axis form as in Bangura & Mahony, "Nonlinear dynamic modeling for
  high performance control of a quadrotor", ACRA 2012). ``v = v_ground - v_wind`` when a wind is
  given (as PX4's gazebo motor model and SIH form the apparent velocity), else the ground velocity
  itself (no wind: the arithmetic of the windless model, unchanged);
* roll/pitch torques from the rotors' lever arms (X configuration) and yaw torque from rotor
  drag, ``tau_z = k_m * sum(s_i T_i)`` with ``s_i = +1`` for CCW rotors;
* Euler's rigid-body equation ``J w' = tau - w x J w``; quaternion kinematics
  ``q' = q (x) (0, w) / 2``.

The ground is the plane ``down = 0``. :func:`step` integrates with classic RK4 and then resolves
contact so that the vehicle never goes below it.

The equations themselves are in :mod:`sitl_sim.physics.kernel` (compiled by numba where it is
installed, else plain Python, the same floats either way); this module is their typed face.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.contract.messages import quat_from_euler, quat_to_rotation
from sitl_sim.config import Planet, VehicleConfig
from sitl_sim.physics import kernel

__all__ = [
    "LAYOUT",
    "STATE_SIZE",
    "ContactEvent",
    "PadContact",
    "Physics",
    "StateLayout",
    "derivative",
    "euler_from_quat",
    "integrate",
    "make_state",
    "quat_from_euler",
    "quat_to_rotation",
    "rk4_step",
    "step",
    "tilt_of",
    "touchdown",
    "translational_accel_ned",
]


class StateLayout:
    """Named slices of the 17-float state vector."""

    pos_ned_m = slice(0, 3)
    vel_ned_m_s = slice(3, 6)
    quat_wxyz = slice(6, 10)
    rate_frd_rad_s = slice(10, 13)
    rotor_thrust_n = slice(13, 17)


LAYOUT = StateLayout()
STATE_SIZE = 17


class Physics:
    """Constants of one vehicle on one planet, precomputed once for the integrator.

    Rotor geometry (PX4 quad X): positions ``(x_i, y_i)`` in FRD at ``arm / sqrt(2)``, spin
    ``s_i`` (+1 CCW seen from above).
    """

    ROTOR_X = (1.0, -1.0, 1.0, -1.0)
    ROTOR_Y = (1.0, -1.0, -1.0, 1.0)
    ROTOR_SPIN = (1.0, 1.0, -1.0, -1.0)

    def __init__(self, vehicle: VehicleConfig, world: Planet) -> None:
        self.vehicle = vehicle
        self.world = world
        self.mass = vehicle.mass_kg
        self.g = world.gravity_m_s2
        self.ixx, self.iyy, self.izz = vehicle.inertia_diag_kg_m2
        d = vehicle.arm_length_m / math.sqrt(2.0)
        self.rx = tuple(d * s for s in self.ROTOR_X)
        self.ry = tuple(d * s for s in self.ROTOR_Y)
        self.km = vehicle.yaw_torque_per_thrust_m
        self.tau_motor = vehicle.motor_time_constant_s
        self.max_total_thrust_n = vehicle.max_total_thrust_n(world)  # T_max on this planet
        self.max_rotor_thrust = self.max_total_thrust_n / 4.0
        half_rho = 0.5 * world.air_density_kg_m3
        self.kdrag = tuple(half_rho * c for c in vehicle.drag_coefficient_area_m2)
        # Allocation: rotor thrusts (4) -> [collective N, tau_x, tau_y, tau_z] (N, N m).
        self.allocation = np.array(
            [
                [1.0, 1.0, 1.0, 1.0],
                [-y for y in self.ry],
                list(self.rx),
                [self.km * s for s in self.ROTOR_SPIN],
            ]
        )
        self.allocation_inv = np.linalg.inv(self.allocation)
        self.constants = kernel.plant_constants(self)
        """The kernel's plant constants (:func:`sitl_sim.physics.kernel.plant_constants`). A
        Physics is not changed once built."""

    @property
    def hover_rotor_thrust_n(self) -> float:
        return self.mass * self.g / 4.0


# --------------------------------------------------------------------------- rotations


def euler_from_quat(q: np.ndarray) -> np.ndarray:
    """ZYX Euler angles ``(roll, pitch, yaw)`` in rad, as MAVLink's ATTITUDE reports them."""
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.array([roll, pitch, yaw])


def make_state(
    pos_ned_m=(0.0, 0.0, 0.0),
    vel_ned_m_s=(0.0, 0.0, 0.0),
    quat_wxyz=(1.0, 0.0, 0.0, 0.0),
    rate_frd_rad_s=(0.0, 0.0, 0.0),
    rotor_thrust_n=(0.0, 0.0, 0.0, 0.0),
) -> np.ndarray:
    """Pack named quantities into a state vector (the only place the layout is filled)."""
    x = np.empty(STATE_SIZE)
    x[LAYOUT.pos_ned_m] = pos_ned_m
    x[LAYOUT.vel_ned_m_s] = vel_ned_m_s
    q = np.asarray(quat_wxyz, dtype=float)
    x[LAYOUT.quat_wxyz] = q / np.linalg.norm(q)
    x[LAYOUT.rate_frd_rad_s] = rate_frd_rad_s
    x[LAYOUT.rotor_thrust_n] = rotor_thrust_n
    return x


# --------------------------------------------------------------------------- equations of motion


def translational_accel_ned(
    quat_wxyz,
    vel_ned_m_s,
    collective_thrust_n: float,
    phys: Physics,
    wind_ned_m_s=None,
) -> tuple[float, float, float]:
    """Acceleration (NED, m/s^2) from gravity, collective thrust along body -z and body drag.

    The velocity rows of :func:`derivative` (the kernel's equations, so the same floats), as the
    MPC expert's linearisation asks for them. ``wind_ned_m_s`` (3, NED, m/s): drag then acts on
    the air-relative velocity ``v - wind``; None (the default) is still air.
    """
    qw, qx, qy, qz = (float(v) for v in quat_wxyz)
    vn, ve, vd = (float(v) for v in vel_ned_m_s)
    wn, we, wd = _wind(wind_ned_m_s)
    # The first three rows of the kernel's rates of change, the collective on one rotor: x + -0.0
    # is x for every float, so the rotors' sum is the collective itself, bit for bit.
    accel = kernel.rates(
        phys.constants, vn, ve, vd, qw, qx, qy, qz, 0.0, 0.0, 0.0, float(collective_thrust_n),
        -0.0, -0.0, -0.0, 0.0, 0.0, 0.0, 0.0, wn, we, wd,
    )  # fmt: skip
    return accel[0], accel[1], accel[2]


def _wind(wind_ned_m_s) -> tuple[float, float, float]:
    if wind_ned_m_s is None:
        return _STILL_AIR
    wn, we, wd = wind_ned_m_s
    return float(wn), float(we), float(wd)


_STILL_AIR = (0.0, 0.0, 0.0)


def derivative(x, rotor_cmd_n, phys: Physics, wind_ned_m_s=None) -> list[float]:
    """Time derivative of the 17-float state for commanded rotor thrusts ``rotor_cmd_n`` (4, N)
    in the wind ``wind_ned_m_s`` (3, NED; None: still air)."""
    x = [float(v) for v in x]
    c1, c2, c3, c4 = (float(v) for v in rotor_cmd_n)
    return [
        x[3],
        x[4],
        x[5],
        *kernel.rates(
            phys.constants, x[3], x[4], x[5], x[6], x[7], x[8], x[9], x[10], x[11], x[12],
            x[13], x[14], x[15], x[16], c1, c2, c3, c4, *_wind(wind_ned_m_s),
        ),
    ]  # fmt: skip


def rk4_step(x, rotor_cmd_n, dt: float, phys: Physics, wind_ned_m_s=None) -> list[float]:
    """One classic Runge-Kutta 4 step of :func:`derivative` (no ground, no renormalisation).

    The wind is held for the whole step (zero-order hold): all four stages see the same
    ``wind_ned_m_s``, as the commanded rotor thrusts are held.
    """
    c1, c2, c3, c4 = (float(v) for v in rotor_cmd_n)
    x = tuple(float(v) for v in x)
    return list(kernel.rk4(phys.constants, x, c1, c2, c3, c4, float(dt), *_wind(wind_ned_m_s)))


@dataclass(frozen=True)
class ContactEvent:
    """First ground contact of a flight, interpolated inside the physics step where it happened.

    Attributes:
        time_s: sim time of contact.
        pos_ned_m: (3,) position at contact (down = 0).
        vel_ned_m_s: (3,) velocity just before contact.
        tilt_rad: angle between body down and world down at contact.
        pad: on a site (:mod:`sitl_sim.site.contact`), the contact seen from the pad; None on
            the nominal flat ground with the still pad at the origin (whose frame is NED).
    """

    time_s: float
    pos_ned_m: np.ndarray
    vel_ned_m_s: np.ndarray
    tilt_rad: float
    pad: PadContact | None = None


@dataclass(frozen=True)
class PadContact:
    """A contact on a site, in the pad's frame (x forward, y right, z down along its normal).

    Attributes:
        pos_m: (3,) the vehicle centre relative to the pad's surface centre.
        vel_m_s: (3,) the vehicle's velocity relative to the pad's surface at that point.
        tilt_rad: angle between body down and the pad's down (its normal).
        touched_pad: the surface touched is the pad's own (within its extent, on its plane).
        tipped_over: the surface touched is steeper than the vehicle can stand on.
    """

    pos_m: np.ndarray
    vel_m_s: np.ndarray
    tilt_rad: float
    touched_pad: bool
    tipped_over: bool


def _tilt(qx: float, qy: float) -> float:
    # R[2][2] = cos(tilt) = 1 - 2 (qx^2 + qy^2)
    return math.acos(max(-1.0, min(1.0, 1.0 - 2.0 * (qx * qx + qy * qy))))


def touchdown(before, free, frac: float, t_prev: float, dt: float) -> ContactEvent:
    """The flat ground's :class:`ContactEvent` of a step that came down from the air: the point
    interpolated at ``frac`` of the step between the state ``before`` it and its free flight
    ``free`` (:func:`sitl_sim.physics.kernel.flat_contact`), the tilt of the free flight's."""
    lerp = [before[i] + frac * (free[i] - before[i]) for i in range(6)]
    return ContactEvent(
        time_s=t_prev + frac * dt,
        pos_ned_m=np.array([lerp[0], lerp[1], 0.0]),
        vel_ned_m_s=np.array(lerp[3:6]),
        tilt_rad=_tilt(free[7], free[8]),
    )


def integrate(x, rotor_cmd_n, dt: float, phys: Physics, wind_ned_m_s=None) -> list[float]:
    """RK4 over ``dt`` and the quaternion renormalised: the free flight of one step, no ground
    (:func:`step` adds the flat ground; :mod:`sitl_sim.site.contact` a site's surfaces)."""
    c1, c2, c3, c4 = (float(v) for v in rotor_cmd_n)
    x = tuple(float(v) for v in x)
    return list(
        kernel.integrate(phys.constants, x, c1, c2, c3, c4, float(dt), *_wind(wind_ned_m_s))
    )


def tilt_of(qx: float, qy: float) -> float:
    """The angle between body down and world down of a unit quaternion's x and y (rad)."""
    return _tilt(qx, qy)


def step(x, rotor_cmd_n, dt: float, phys: Physics, t_s: float = 0.0, wind_ned_m_s=None):
    """Advance the state by ``dt``: RK4, quaternion renormalisation, ground contact.

    Contact with the plane ``down = 0`` is fully inelastic with full friction
    (:func:`sitl_sim.physics.kernel.flat_contact`): the vehicle rests level with its heading kept
    and lifts off as soon as thrust exceeds weight.

    Args:
        x: state (17 floats, :data:`LAYOUT`).
        rotor_cmd_n: commanded thrust of each rotor, already within [0, max rotor thrust].
        dt: step length (s).
        phys: vehicle and planet constants.
        t_s: sim time at the start of the step (for the contact time stamp).
        wind_ned_m_s: (3,) wind held over the step (NED, m/s), or None for still air.

    Returns:
        ``(x_next, contact)``: the new state as a list, and a :class:`ContactEvent` if the vehicle
        came down onto the ground during this step, else ``None``.
    """
    before = tuple(float(v) for v in x)
    free = integrate(before, rotor_cmd_n, dt, phys, wind_ned_m_s)
    x_new, frac = kernel.flat_contact(phys.constants, before, tuple(free))
    event = touchdown(before, free, frac, t_s, dt) if frac >= 0.0 else None
    return list(x_new), event
