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
contact so that the vehicle never goes below it (see :func:`_resolve_ground_contact`).

The functions take plain floats internally: at 17 states, Python scalars are several times faster
than small numpy arrays, and the simulator has to run tens of times faster than real time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.contract.messages import quat_from_euler, quat_to_rotation
from sitl_sim.config import Planet, VehicleConfig

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
        self.rates_of_change, self.rk4 = _kernels(self)
        """The integrator's kernels for these constants (:func:`_kernels`): ``rates_of_change``
        is :func:`derivative` less the position rows, ``rk4`` is :func:`rk4_step`. A Physics
        is not changed once built (the kernels hold its constants)."""

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
    the air-relative velocity ``v - wind``; None (the default) is still air, computed exactly as
    before wind existed (not ``v - 0``).
    """
    qw, qx, qy, qz = quat_wxyz
    vn, ve, vd = vel_ned_m_s
    # The first three rows of the kernel's rates of change, the collective on one rotor: x + -0.0
    # is x for every float, so the rotors' sum is the collective itself, bit for bit.
    accel = phys.rates_of_change(
        vn, ve, vd, qw, qx, qy, qz, 0.0, 0.0, 0.0, collective_thrust_n, -0.0, -0.0, -0.0,
        0.0, 0.0, 0.0, 0.0, wind_ned_m_s,
    )  # fmt: skip
    return accel[0], accel[1], accel[2]


def derivative(x, rotor_cmd_n, phys: Physics, wind_ned_m_s=None) -> list[float]:
    """Time derivative of the 17-float state for commanded rotor thrusts ``rotor_cmd_n`` (4, N)
    in the wind ``wind_ned_m_s`` (3, NED; None: still air, see :func:`translational_accel_ned`)."""
    c1, c2, c3, c4 = rotor_cmd_n
    return [
        x[3],
        x[4],
        x[5],
        *phys.rates_of_change(
            x[3], x[4], x[5], x[6], x[7], x[8], x[9], x[10], x[11], x[12],
            x[13], x[14], x[15], x[16], c1, c2, c3, c4, wind_ned_m_s,
        ),
    ]  # fmt: skip


def rk4_step(x, rotor_cmd_n, dt: float, phys: Physics, wind_ned_m_s=None) -> list[float]:
    """One classic Runge-Kutta 4 step of :func:`derivative` (no ground, no renormalisation).

    The wind is held for the whole step (zero-order hold): all four stages see the same
    ``wind_ned_m_s``, as the commanded rotor thrusts are held.
    """
    return phys.rk4(x, rotor_cmd_n, dt, wind_ned_m_s)


def _kernels(phys: Physics):
    """``(rates_of_change, rk4)`` for ``phys``'s constants, in plain Python floats.

    ``rates_of_change(vn, ve, vd, qw, qx, qy, qz, p, q, r, t1, t2, t3, t4, c1, c2, c3, c4,
    wind)`` is the state derivative but for the position rows (which are the velocity): the
    equations of the module docstring (:func:`translational_accel_ned` reads its first three
    rows). ``rk4(x, rotor_cmd_n, dt, wind)`` is the classic RK4 step of it with each stage's
    rows unpacked into locals: ~2x faster than stage lists of 17, and the SITL steps its physics
    250 times a simulated second.
    """
    kx, ky, kz = phys.kdrag
    mass, g, km = phys.mass, phys.g, phys.km
    ixx, iyy, izz = phys.ixx, phys.iyy, phys.izz
    rx0, rx1, rx2, rx3 = phys.rx
    ry0, ry1, ry2, ry3 = phys.ry
    i_p, i_q, i_r = iyy - izz, izz - ixx, ixx - iyy  # Euler's coupling terms
    lag = phys.tau_motor > 0.0
    inv_tau = 1.0 / phys.tau_motor if lag else 0.0
    inv_m = 1.0 / mass

    def rates_of_change(vn, ve, vd, qw, qx, qy, qz, p, q, r, t1, t2, t3, t4, c1, c2, c3, c4, wind):
        if wind is not None:
            wn, we, wd = wind
            vn, ve, vd = vn - wn, ve - we, vd - wd
        # translation: rotation body -> NED, drag on the air-relative body velocity
        r00 = 1 - 2 * (qy * qy + qz * qz)
        r01 = 2 * (qx * qy - qw * qz)
        r02 = 2 * (qx * qz + qw * qy)
        r10 = 2 * (qx * qy + qw * qz)
        r11 = 1 - 2 * (qx * qx + qz * qz)
        r12 = 2 * (qy * qz - qw * qx)
        r20 = 2 * (qx * qz - qw * qy)
        r21 = 2 * (qy * qz + qw * qx)
        r22 = 1 - 2 * (qx * qx + qy * qy)
        vbx = r00 * vn + r10 * ve + r20 * vd
        vby = r01 * vn + r11 * ve + r21 * vd
        vbz = r02 * vn + r12 * ve + r22 * vd
        fbx = -kx * abs(vbx) * vbx
        fby = -ky * abs(vby) * vby
        fbz = -kz * abs(vbz) * vbz - (t1 + t2 + t3 + t4)
        # Euler: J w' = tau - w x (J w), J diagonal; q' = 1/2 q (x) (0, w); the rotor lag
        if lag:
            dt1, dt2 = (c1 - t1) * inv_tau, (c2 - t2) * inv_tau
            dt3, dt4 = (c3 - t3) * inv_tau, (c4 - t4) * inv_tau
        else:
            dt1 = dt2 = dt3 = dt4 = 0.0
        return (
            (r00 * fbx + r01 * fby + r02 * fbz) * inv_m,
            (r10 * fbx + r11 * fby + r12 * fbz) * inv_m,
            (r20 * fbx + r21 * fby + r22 * fbz) * inv_m + g,
            0.5 * (-qx * p - qy * q - qz * r),
            0.5 * (qw * p + qy * r - qz * q),
            0.5 * (qw * q - qx * r + qz * p),
            0.5 * (qw * r + qx * q - qy * p),
            (-(ry0 * t1 + ry1 * t2 + ry2 * t3 + ry3 * t4) + i_p * q * r) / ixx,
            (rx0 * t1 + rx1 * t2 + rx2 * t3 + rx3 * t4 + i_q * r * p) / iyy,
            (km * (t1 + t2 - t3 - t4) + i_r * p * q) / izz,
            dt1,
            dt2,
            dt3,
            dt4,
        )

    f = rates_of_change

    def rk4(x, rotor_cmd_n, dt, wind=None):
        pn, pe, pd, vn, ve, vd, qw, qx, qy, qz, p, q, r, t1, t2, t3, t4 = x
        c1, c2, c3, c4 = rotor_cmd_n
        h = 0.5 * dt
        # k1 at x; k2 at x + h k1; k3 at x + h k2; k4 at x + dt k3 (the position rows' k is
        # the stage's velocity)
        a = f(vn, ve, vd, qw, qx, qy, qz, p, q, r, t1, t2, t3, t4, c1, c2, c3, c4, wind)
        stages, vel = [a], []
        for k in (h, h, dt):
            an, ae, ad, dqw, dqx, dqy, dqz, dp, dq, dr, d1, d2, d3, d4 = a
            vnk, vek, vdk = vn + k * an, ve + k * ae, vd + k * ad
            a = f(
                vnk, vek, vdk, qw + k * dqw, qx + k * dqx, qy + k * dqy, qz + k * dqz,
                p + k * dp, q + k * dq, r + k * dr, t1 + k * d1, t2 + k * d2, t3 + k * d3,
                t4 + k * d4, c1, c2, c3, c4, wind,
            )  # fmt: skip
            stages.append(a)
            vel.append((vnk, vek, vdk))
        (vn2, ve2, vd2), (vn3, ve3, vd3), (vn4, ve4, vd4) = vel
        s = dt / 6.0  # x + dt/6 (k1 + 2 k2 + 2 k3 + k4), row by row
        e, b, c, d = stages
        return [
            pn + s * (vn + 2.0 * vn2 + 2.0 * vn3 + vn4),
            pe + s * (ve + 2.0 * ve2 + 2.0 * ve3 + ve4),
            pd + s * (vd + 2.0 * vd2 + 2.0 * vd3 + vd4),
            vn + s * (e[0] + 2.0 * b[0] + 2.0 * c[0] + d[0]),
            ve + s * (e[1] + 2.0 * b[1] + 2.0 * c[1] + d[1]),
            vd + s * (e[2] + 2.0 * b[2] + 2.0 * c[2] + d[2]),
            qw + s * (e[3] + 2.0 * b[3] + 2.0 * c[3] + d[3]),
            qx + s * (e[4] + 2.0 * b[4] + 2.0 * c[4] + d[4]),
            qy + s * (e[5] + 2.0 * b[5] + 2.0 * c[5] + d[5]),
            qz + s * (e[6] + 2.0 * b[6] + 2.0 * c[6] + d[6]),
            p + s * (e[7] + 2.0 * b[7] + 2.0 * c[7] + d[7]),
            q + s * (e[8] + 2.0 * b[8] + 2.0 * c[8] + d[8]),
            r + s * (e[9] + 2.0 * b[9] + 2.0 * c[9] + d[9]),
            t1 + s * (e[10] + 2.0 * b[10] + 2.0 * c[10] + d[10]),
            t2 + s * (e[11] + 2.0 * b[11] + 2.0 * c[11] + d[11]),
            t3 + s * (e[12] + 2.0 * b[12] + 2.0 * c[12] + d[12]),
            t4 + s * (e[13] + 2.0 * b[13] + 2.0 * c[13] + d[13]),
        ]

    return rates_of_change, rk4


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


def _resolve_ground_contact(x_prev, x_new: list[float], t_prev: float, dt: float):
    """Keep the vehicle on or above ``down = 0``; report a contact that happened in this step.

    Contact is fully inelastic with full friction (skids on flat ground): the vehicle stops, its
    roll and pitch settle level (the landing gear rests on the plane) and its yaw is kept. It
    lifts off again as soon as thrust exceeds weight (then ``down`` decreases in the next step).
    """
    if x_new[2] < 0.0:
        return x_new, None
    d_prev, d_new = x_prev[2], x_new[2]
    event = None
    if d_prev < 0.0:
        frac = d_prev / (d_prev - d_new) if d_new != d_prev else 1.0
        lerp = [x_prev[i] + frac * (x_new[i] - x_prev[i]) for i in range(6)]
        event = ContactEvent(
            time_s=t_prev + frac * dt,
            pos_ned_m=np.array([lerp[0], lerp[1], 0.0]),
            vel_ned_m_s=np.array(lerp[3:6]),
            tilt_rad=_tilt(x_new[7], x_new[8]),
        )
    # Resting on the ground: level attitude with the same heading, no motion.
    qw, qz = x_new[6], x_new[9]
    yaw = math.atan2(2 * qw * qz + 2 * x_new[7] * x_new[8], 1 - 2 * (x_new[8] ** 2 + qz * qz))
    out = list(x_new)
    out[2] = 0.0
    out[3] = out[4] = out[5] = 0.0
    out[6], out[7], out[8], out[9] = math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)
    out[10] = out[11] = out[12] = 0.0
    return out, event


def integrate(x, rotor_cmd_n, dt: float, phys: Physics, wind_ned_m_s=None) -> list[float]:
    """RK4 over ``dt`` and the quaternion renormalised: the free flight of one step, no ground
    (:func:`step` adds the flat ground; :mod:`sitl_sim.site.contact` a site's surfaces)."""
    x_new = phys.rk4(x, rotor_cmd_n, dt, wind_ned_m_s)
    n = math.sqrt(x_new[6] ** 2 + x_new[7] ** 2 + x_new[8] ** 2 + x_new[9] ** 2)
    x_new[6] /= n
    x_new[7] /= n
    x_new[8] /= n
    x_new[9] /= n
    return x_new


def tilt_of(qx: float, qy: float) -> float:
    """The angle between body down and world down of a unit quaternion's x and y (rad)."""
    return _tilt(qx, qy)


def step(x, rotor_cmd_n, dt: float, phys: Physics, t_s: float = 0.0, wind_ned_m_s=None):
    """Advance the state by ``dt``: RK4, quaternion renormalisation, ground contact.

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
    on_ground = x[2] >= 0.0
    x_new = integrate(x, rotor_cmd_n, dt, phys, wind_ned_m_s)
    x_new, event = _resolve_ground_contact(x, x_new, t_s, dt)
    if on_ground:
        event = None  # still resting: not a new touchdown
    return x_new, event
