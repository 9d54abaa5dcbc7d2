"""The MPC expert's prediction model: the vehicle's physics, linearised about hover.

State ``x`` (9, :class:`ModelState`): position NED (m), velocity NED (m/s), roll/pitch/yaw
(rad, ZYX). Input ``u`` (4, :class:`ModelInput`): ``thrust_norm`` and FRD body rates (rad/s) —
exactly the :class:`~companion.contract.Command` space, so expert labels are what the companion
sends. ``f(x, u)`` (:func:`model_derivative`) is evaluated through
``sitl_sim.physics.dynamics.derivative`` (gravity, collective thrust, body drag and quaternion
kinematics), so no physics constant is retyped here; the Jacobians about hover
(:func:`linearise_hover`) are central differences of it, discretised by zero-order hold
(``scipy.linalg.expm``) at the control period.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from scipy.linalg import expm

from sitl_sim.physics.dynamics import (
    Physics,
    derivative,
    euler_from_quat,
    make_state,
    quat_from_euler,
)

__all__ = [
    "NU",
    "NX",
    "VEL",
    "HoverModel",
    "ModelInput",
    "ModelState",
    "linearise_hover",
    "model_derivative",
]


class ModelState(IntEnum):
    """Indices of the MPC model state (NED position m, NED velocity m/s, ZYX Euler rad)."""

    N = 0
    E = 1
    D = 2
    VN = 3
    VE = 4
    VD = 5
    ROLL = 6
    PITCH = 7
    YAW = 8


class ModelInput(IntEnum):
    """Indices of the MPC model input: the Command (thrust_norm, FRD body rates rad/s)."""

    THRUST = 0
    P = 1
    Q = 2
    R = 3


NX = len(ModelState)
NU = len(ModelInput)
_EULER = slice(ModelState.ROLL, ModelState.YAW + 1)
VEL = slice(ModelState.VN, ModelState.VD + 1)
_QUAT_STEP = 1e-6  # s: central-difference step of the Euler angles along the quaternion rate


def model_derivative(phys: Physics, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """``f(x, u)``: time derivative (9,) of the MPC state for input ``u`` (4,).

    Everything comes from ``sitl_sim.physics.dynamics.derivative`` at rotor thrusts that give the
    collective ``thrust_norm * T_max`` with zero torque (equal rotors), body rates equal to the
    commanded ones (ideal rate loop): position and velocity rates directly, and the Euler-angle
    rates as the central difference of ``euler_from_quat`` along the quaternion rate.
    """
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    quat = quat_from_euler(*x[_EULER])
    rotor_n = (float(u[ModelInput.THRUST]) * phys.max_total_thrust_n / 4.0,) * 4
    x17 = make_state(
        pos_ned_m=x[ModelState.N : ModelState.D + 1],
        vel_ned_m_s=x[VEL],
        quat_wxyz=quat,
        rate_frd_rad_s=u[ModelInput.P : ModelInput.R + 1],
        rotor_thrust_n=rotor_n,
    )
    d = np.asarray(derivative(x17.tolist(), rotor_n, phys))
    qdot = d[6:10]
    plus = quat + _QUAT_STEP * qdot
    minus = quat - _QUAT_STEP * qdot
    euler_plus = euler_from_quat(plus / np.linalg.norm(plus))
    euler_minus = euler_from_quat(minus / np.linalg.norm(minus))
    euler_rate = (euler_plus - euler_minus) / (2.0 * _QUAT_STEP)
    return np.concatenate((d[0:6], euler_rate))


@dataclass(frozen=True)
class HoverModel:
    """The model linearised about hover and discretised by zero-order hold.

    Attributes:
        a: (9, 9) continuous ``df/dx`` at hover.
        b: (9, 4) continuous ``df/du`` at hover.
        a_d: (9, 9) discrete state matrix over ``dt_s``.
        b_d: (9, 4) discrete input matrix over ``dt_s`` (input held).
        gamma_d: (9, 9) ``int_0^dt expm(a s) ds``: maps a constant continuous residual
            (9,) to its effect over one step.
        u_hover: (4,) hover input (thrust_norm = m g / T_max, zero rates).
        dt_s: control period.
    """

    a: np.ndarray
    b: np.ndarray
    a_d: np.ndarray
    b_d: np.ndarray
    gamma_d: np.ndarray
    u_hover: np.ndarray
    dt_s: float


def linearise_hover(phys: Physics, dt_s: float, eps: float = 1e-4) -> HoverModel:
    """Central-difference Jacobians of :func:`model_derivative` at hover, then ZOH over ``dt_s``."""
    x0 = np.zeros(NX)
    u0 = np.zeros(NU)
    u0[ModelInput.THRUST] = phys.mass * phys.g / phys.max_total_thrust_n
    a = np.empty((NX, NX))
    b = np.empty((NX, NU))
    for i in range(NX):
        dx = np.zeros(NX)
        dx[i] = eps
        a[:, i] = (model_derivative(phys, x0 + dx, u0) - model_derivative(phys, x0 - dx, u0)) / (
            2.0 * eps
        )
    for j in range(NU):
        du = np.zeros(NU)
        du[j] = eps
        b[:, j] = (model_derivative(phys, x0, u0 + du) - model_derivative(phys, x0, u0 - du)) / (
            2.0 * eps
        )
    # One matrix exponential gives A_d, B_d and the residual map (Van Loan's block trick).
    m = np.zeros((NX + NU + NX, NX + NU + NX))
    m[:NX, :NX] = a
    m[:NX, NX : NX + NU] = b
    m[:NX, NX + NU :] = np.eye(NX)
    e = expm(m * dt_s)
    return HoverModel(
        a=a,
        b=b,
        a_d=e[:NX, :NX],
        b_d=e[:NX, NX : NX + NU],
        gamma_d=e[:NX, NX + NU :],
        u_hover=u0,
        dt_s=float(dt_s),
    )
