"""Physics with known answers: hover, free fall, rate step, RK4 order, energy, ground contact."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from companion.contract import Command
from sitl_sim.config import PLANETS
from sitl_sim.physics.dynamics import (
    LAYOUT,
    Physics,
    euler_from_quat,
    make_state,
    quat_from_euler,
    quat_to_rotation,
    rk4_step,
    step,
)
from sitl_sim.scenario import InitialState
from sitl_sim.simulator import Simulator

EARTH = PLANETS["earth"]


def _at(alt_m: float, **kw) -> InitialState:
    return InitialState(
        pos_ned_m=(0.0, 0.0, -alt_m),
        vel_ned_m_s=kw.get("vel", (0.0, 0.0, 0.0)),
        euler_rad=kw.get("euler", (0.0, 0.0, 0.0)),
        rate_frd_rad_s=(0.0, 0.0, 0.0),
    )


def test_hover_thrust_is_m_g(vehicle):
    assert vehicle.hover_thrust_norm(EARTH) == pytest.approx(1.0 * 9.81 / 25.0)
    phys = Physics(vehicle, EARTH)
    x = make_state(pos_ned_m=(0, 0, -10), rotor_thrust_n=(phys.hover_rotor_thrust_n,) * 4)
    d = np.asarray(rk4_step(x.tolist(), [phys.hover_rotor_thrust_n] * 4, 0.0, phys))
    np.testing.assert_allclose(d, x)  # zero-length step is the identity
    from sitl_sim.physics.dynamics import derivative

    deriv = np.asarray(derivative(x.tolist(), [phys.hover_rotor_thrust_n] * 4, phys))
    np.testing.assert_allclose(deriv, 0.0, atol=1e-12)  # hover is an equilibrium


def test_hover_holds_altitude_for_10_s(vehicle, quiet_cfg):
    sim = Simulator(vehicle, quiet_cfg, render=False)
    sim.reset(_at(50.0), seed=0)
    hover = Command(vehicle.hover_thrust_norm(quiet_cfg.planet), np.zeros(3))
    for _ in range(100):  # 10 s at 10 Hz
        sim.step(hover)
    gt = sim.ground_truth()
    assert abs(-gt.pos_ned_m[2] - 50.0) < 0.2
    assert np.linalg.norm(gt.pos_ned_m[:2]) < 0.2
    tilt = math.degrees(math.acos(quat_to_rotation(gt.quat_wxyz)[2, 2]))
    assert tilt < 1.0


def test_free_fall_matches_half_g_t_squared(vehicle):
    no_drag = replace(vehicle, drag_coefficient_area_m2=(0.0, 0.0, 0.0))
    phys = Physics(no_drag, EARTH)
    x = make_state(pos_ned_m=(0, 0, -200)).tolist()
    dt, t = 0.004, 0.0
    for _ in range(500):  # 2 s
        x, _ = step(x, [0.0] * 4, dt, phys, t)
        t += dt
    fallen = x[2] + 200.0
    expected = 0.5 * 9.81 * t**2
    assert fallen == pytest.approx(expected, rel=0.01)
    assert x[5] == pytest.approx(9.81 * t, rel=0.01)


def test_drag_slows_the_fall(vehicle):
    phys = Physics(vehicle, EARTH)
    x = make_state(pos_ned_m=(0, 0, -5000)).tolist()
    for k in range(2500):  # 10 s
        x, _ = step(x, [0.0] * 4, 0.004, phys, k * 0.004)
    assert x[5] < 9.81 * 10.0 * 0.9  # well below the vacuum speed
    # Terminal speed of quadratic drag: m g = 1/2 rho CdA v^2.
    v_term = math.sqrt(2 * 9.81 / (1.225 * vehicle.drag_coefficient_area_m2[2]))
    assert x[5] < v_term


def test_roll_rate_step_reaches_90_percent_within_150_ms(vehicle, quiet_cfg):
    sim = Simulator(vehicle, quiet_cfg, render=False)
    sim.reset(_at(50.0), seed=0)
    cmd = Command(vehicle.hover_thrust_norm(quiet_cfg.planet), np.array([1.0, 0.0, 0.0]))
    t90 = None
    for _ in range(round(0.3 / quiet_cfg.physics_dt_s)):
        sim.step_physics(cmd)
        if t90 is None and sim.ground_truth().rate_frd_rad_s[0] >= 0.9:
            t90 = sim.time_s
    assert t90 is not None and t90 <= 0.15
    # and it settles on the setpoint without large overshoot
    p = sim.ground_truth().rate_frd_rad_s[0]
    assert p == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_rate_commands_act_on_the_right_axis(vehicle, quiet_cfg, axis):
    sim = Simulator(vehicle, quiet_cfg, render=False)
    sim.reset(_at(50.0), seed=0)
    rate = np.zeros(3)
    rate[axis] = 0.5
    for _ in range(5):
        sim.step(Command(vehicle.hover_thrust_norm(quiet_cfg.planet), rate))
    euler = euler_from_quat(sim.ground_truth().quat_wxyz)
    assert euler[axis] > 0.1  # positive p -> roll grows, q -> pitch grows, r -> yaw grows
    others = [i for i in range(3) if i != axis]
    assert np.all(np.abs(euler[others]) < 0.02)


def test_rk4_is_fourth_order(vehicle):
    # Drag off: |v| v is not twice differentiable where a velocity component crosses zero, which
    # would (correctly) cap the observed order below 4.
    phys = Physics(replace(vehicle, drag_coefficient_area_m2=(0.0, 0.0, 0.0)), EARTH)
    x0 = make_state(
        pos_ned_m=(1.0, -2.0, -30.0),
        vel_ned_m_s=(2.0, 1.0, -0.5),
        quat_wxyz=quat_from_euler(0.2, -0.1, 0.5),
        rate_frd_rad_s=(0.8, -0.6, 0.3),
        rotor_thrust_n=(2.0, 3.0, 2.5, 2.8),
    ).tolist()
    cmd = [4.0, 1.0, 3.0, 2.0]
    horizon = 0.4

    def integrate(dt: float) -> np.ndarray:
        x = x0
        for _ in range(round(horizon / dt)):
            x = rk4_step(x, cmd, dt, phys)
        return np.asarray(x)

    ref = integrate(horizon / 2048)
    # Step sizes in RK4's asymptotic range (dt well below the 20 ms motor lag).
    errs = [np.linalg.norm(integrate(horizon / n) - ref) for n in (20, 40, 80)]
    orders = [math.log2(errs[i] / errs[i + 1]) for i in range(2)]
    assert all(3.6 < o < 4.4 for o in orders), orders


def test_energy_is_conserved_without_drag_and_lost_with_it(vehicle):
    def energy(x) -> float:
        v = np.asarray(x[3:6])
        return 0.5 * vehicle.mass_kg * v @ v + vehicle.mass_kg * 9.81 * (-x[2])  # KE + PE

    x0 = make_state(pos_ned_m=(0, 0, -500), vel_ned_m_s=(5.0, -3.0, -4.0)).tolist()
    for drag, check in (
        ((0.0, 0.0, 0.0), lambda e0, e1: e1 == pytest.approx(e0, rel=1e-9, abs=1e-6)),
        (vehicle.drag_coefficient_area_m2, lambda e0, e1: e1 < e0 - 1.0),
    ):
        phys = Physics(replace(vehicle, drag_coefficient_area_m2=drag), EARTH)
        x = x0
        for k in range(1000):
            x, _ = step(x, [0.0] * 4, 0.004, phys, k * 0.004)
        assert check(energy(x0), energy(x))


def test_ground_is_never_penetrated_and_touchdown_is_reported(vehicle, quiet_cfg):
    sim = Simulator(vehicle, quiet_cfg, render=False)
    sim.reset(_at(3.0, vel=(1.0, 0.0, 2.0), euler=(0.1, 0.0, 0.3)), seed=0)
    contact = None
    for _ in range(round(3.0 / quiet_cfg.physics_dt_s)):
        ev = sim.step_physics(Command(0.0, np.zeros(3)))
        contact = contact or ev
        assert sim.ground_truth().pos_ned_m[2] <= 0.0
    assert contact is not None and sim.contact is contact
    # fell ~3 m starting at 2 m/s down (drag is small at these speeds)
    v_expected = math.sqrt(2.0**2 + 2 * 9.81 * 3.0)
    assert contact.vel_ned_m_s[2] == pytest.approx(v_expected, rel=0.05)
    assert contact.pos_ned_m[2] == 0.0
    assert math.degrees(contact.tilt_rad) == pytest.approx(math.degrees(0.1), abs=1.0)
    gt = sim.ground_truth()  # at rest, level, same heading
    np.testing.assert_allclose(gt.vel_ned_m_s, 0.0)
    assert euler_from_quat(gt.quat_wxyz)[2] == pytest.approx(0.3, abs=1e-6)


def test_vehicle_lifts_off_again_with_thrust(vehicle, quiet_cfg):
    sim = Simulator(vehicle, quiet_cfg, render=False)
    sim.reset(_at(0.0), seed=0)
    for _ in range(10):
        sim.step(Command(0.6, np.zeros(3)))
    assert sim.ground_truth().pos_ned_m[2] < -0.5
    assert sim.contact is None  # starting on the ground is not a touchdown


def test_rotor_thrust_limits_and_lag(vehicle):
    phys = Physics(vehicle, EARTH)
    x = make_state(pos_ned_m=(0, 0, -50)).tolist()
    n = 50
    for _ in range(n):  # one time constant, in small steps
        x, _ = step(x, [6.25] * 4, vehicle.motor_time_constant_s / n, phys)
    frac = np.asarray(x)[LAYOUT.rotor_thrust_n] / 6.25
    np.testing.assert_allclose(frac, 1 - math.exp(-1), rtol=1e-3)  # first-order lag, one tau


def test_mixer_saturates_without_exceeding_rotor_limits(vehicle, quiet_cfg):
    sim = Simulator(vehicle, quiet_cfg, render=False)
    sim.reset(_at(50.0), seed=0)
    for _ in range(20):
        sim.step_physics(Command(1.0, np.array([3.5, -3.5, 1.5])))
        thrust = sim.ground_truth().rotor_thrust_n
        assert np.all(thrust >= -1e-9) and np.all(thrust <= sim.phys.max_rotor_thrust + 1e-9)
    assert sim.rate_controller.saturated


def test_mars_gravity(vehicle):
    phys = Physics(vehicle, PLANETS["mars"])
    x = make_state(pos_ned_m=(0, 0, -100)).tolist()
    for k in range(250):
        x, _ = step(x, [0.0] * 4, 0.004, phys, k * 0.004)
    assert x[5] == pytest.approx(3.71, rel=0.01)  # thin air: almost no drag


# --------------------------------------------------------------------------- the kernels


def _reference_derivative(x, cmd, phys: Physics, wind=None) -> list[float]:
    """The state derivative as written before the kernels (translational_accel_ned, then the
    rotation, quaternion and rotor rows one by one): the kernels must give the same floats."""
    from sitl_sim.physics.dynamics import translational_accel_ned

    qw, qx, qy, qz = x[6:10]
    p, q, r = x[10:13]
    t1, t2, t3, t4 = x[13:17]
    an, ae, ad = translational_accel_ned((qw, qx, qy, qz), x[3:6], t1 + t2 + t3 + t4, phys, wind)
    rx, ry = phys.rx, phys.ry
    tau_x = -(ry[0] * t1 + ry[1] * t2 + ry[2] * t3 + ry[3] * t4)
    tau_y = rx[0] * t1 + rx[1] * t2 + rx[2] * t3 + rx[3] * t4
    tau_z = phys.km * (t1 + t2 - t3 - t4)
    ixx, iyy, izz = phys.ixx, phys.iyy, phys.izz
    rates = [
        (tau_x + (iyy - izz) * q * r) / ixx,
        (tau_y + (izz - ixx) * r * p) / iyy,
        (tau_z + (ixx - iyy) * p * q) / izz,
    ]
    dquat = [
        0.5 * (-qx * p - qy * q - qz * r),
        0.5 * (qw * p + qy * r - qz * q),
        0.5 * (qw * q - qx * r + qz * p),
        0.5 * (qw * r + qx * q - qy * p),
    ]
    lag = phys.tau_motor
    rotors = [
        (c - t) * (1.0 / lag) if lag > 0.0 else 0.0 for c, t in zip(cmd, x[13:17], strict=True)
    ]
    return [*x[3:6], an, ae, ad, *dquat, *rates, *rotors]


def _reference_rk4(x, cmd, dt, phys, wind=None) -> list[float]:
    k1 = _reference_derivative(x, cmd, phys, wind)
    k2 = _reference_derivative(
        [a + 0.5 * dt * k for a, k in zip(x, k1, strict=True)], cmd, phys, wind
    )
    k3 = _reference_derivative(
        [a + 0.5 * dt * k for a, k in zip(x, k2, strict=True)], cmd, phys, wind
    )
    k4 = _reference_derivative([a + dt * k for a, k in zip(x, k3, strict=True)], cmd, phys, wind)
    s = dt / 6.0
    return [
        a + s * (b + 2.0 * c + 2.0 * d + e) for a, b, c, d, e in zip(x, k1, k2, k3, k4, strict=True)
    ]


@pytest.mark.parametrize(
    "change",
    [{}, {"motor_time_constant_s": 0.0}, {"drag_coefficient_area_m2": (0.0, 0.0, 0.0)}],
)
def test_kernels_give_the_reference_floats_exactly(vehicle, change):
    """The fused RK4 (stages in locals, one rates-of-change kernel) is the reference RK4 of the
    reference equations, bit for bit: the same flights, only faster."""
    from sitl_sim.physics.dynamics import derivative

    rng = np.random.default_rng(5)
    for planet in ("earth", "mars"):
        phys = Physics(replace(vehicle, **change), PLANETS[planet])
        for k in range(300):
            x = make_state(
                pos_ned_m=rng.uniform(-50, 1, 3),
                vel_ned_m_s=rng.normal(0, 5, 3),
                quat_wxyz=rng.normal(0, 1, 4),
                rate_frd_rad_s=rng.normal(0, 2, 3),
                rotor_thrust_n=rng.uniform(0, 6, 4),
            ).tolist()
            cmd = rng.uniform(0, 6, 4).tolist()
            wind = None if k % 2 else tuple(rng.normal(0, 5, 3).tolist())
            dt = (0.004, 0.0, 0.02)[k % 3]
            assert derivative(x, cmd, phys, wind) == _reference_derivative(x, cmd, phys, wind)
            assert rk4_step(x, cmd, dt, phys, wind) == _reference_rk4(x, cmd, dt, phys, wind)
